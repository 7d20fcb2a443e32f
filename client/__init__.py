"""neumip.client: the query contract, in-process and HTTP evaluators, the CLI and the Mitsuba plugin.

Importing this package never imports torch or mitsuba.
"""
