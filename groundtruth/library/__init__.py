"""Shipped material descriptions (``<name>.toml``); load them by name with `find_description`."""
