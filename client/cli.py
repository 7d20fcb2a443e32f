"""The `neumip` command line. Each area registers its own subcommands; heavy imports stay lazy."""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import logging
import sys

from neumip.core.errors import CommandError, NeumipError  # noqa: F401  (CommandError: re-exported)

AREAS = (
    "neumip.client.commands",
    "neumip.client.mitsuba.commands",
    "neumip.training.commands",
    "neumip.training.fit_command",
    "neumip.training.trim_command",
    "neumip.training.calibrate_command",
    "neumip.groundtruth.commands",
    "neumip.report.commands",
    "neumip.server.commands",
)
"""Modules with a `register(subparsers)` function adding that area's subcommands."""


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """`--help` shows each option's default, "(default: X)", unless it has none (None, False, [], "")
    or its help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        no_default = any(default is none for none in (None, False, argparse.SUPPRESS)) or default in ([], "")
        if no_default or "default" in text:
            return text
        return super()._get_help_string(action)


def version() -> str:
    """The installed neumip's version (from the package metadata)."""
    try:
        return importlib.metadata.version("neumip")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="neumip", description="Multi-resolution neural materials.")
    parser.add_argument("--version", action="version", version=f"neumip {version()}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for area in AREAS:
        importlib.import_module(area).register(sub)
    for command in sub.choices.values():  # -v also after the subcommand: `neumip train ... -v`
        command.formatter_class = HelpFormatter
        command.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                             help="log debug messages")
    return parser


QUIET_LOGGERS = ("httpx", "httpcore")
"""Libraries that log every HTTP request at INFO: their lines show with -v only."""


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    if not (sys.argv[1:] if argv is None else argv):  # bare `neumip`: what it can do, not a usage error
        parser.print_help()
        return 0
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    for name in QUIET_LOGGERS:
        logging.getLogger(name).setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    from tqdm.contrib.logging import logging_redirect_tqdm

    try:
        with logging_redirect_tqdm():  # log lines print above the progress bars, never inside them
            return int(args.func(args) or 0)
    except (NeumipError, FileNotFoundError) as exc:
        print(f"neumip {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"neumip {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
