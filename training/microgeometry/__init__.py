"""Tiled microgeometry and path-traced MBTF ground truth with Mitsuba 3 (needs neumip[render])."""
