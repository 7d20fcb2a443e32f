"""Tiled microgeometry and path-traced MBTF ground truth with Mitsuba 3 (needs neumip[render]).

See README.md in this folder: material descriptions, `neumip generate`, external data, conventions.
"""
