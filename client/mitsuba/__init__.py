"""Mitsuba 3 plugins: the `neumip` BSDF and the buffered-evaluation integrator (needs neumip[render])."""
