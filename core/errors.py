"""The root of neumip's user-facing errors.

Every error that reports a user's mistake or an unusable input (bad queries, a corrupt model or
checkpoint, an incomplete data set, an unreachable server, a missing LLVM) derives from
:class:`NeumipError`, so the CLI turns each into one line and exit status 2 instead of a traceback.
"""


class NeumipError(Exception):
    """An error whose message alone tells the user what went wrong and what to do."""


class CommandError(NeumipError):
    """An error a command reports to the user as one line, exit status 2."""
