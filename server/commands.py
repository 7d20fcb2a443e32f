"""Server subcommands (`serve` arrives with the server)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """No server subcommands yet."""
