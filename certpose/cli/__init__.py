"""Command-line interface: a thin layer over the library (owns argument parsing, printing, exit codes).

Each sub-command lives in its own module exposing ``add_parser(subparsers)``; heavy imports
happen inside the command functions so ``certpose --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from certpose._version import __version__

_COMMANDS = ("certpose.cli.register", "certpose.cli.bench", "certpose.cli.pose", "certpose.cli.object")


class CLIError(Exception):
    """An error reported to the user as one line, with a non-zero exit code."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="certpose",
        description="Certifiable robust registration and probabilistic object pose estimation.",
    )
    parser.add_argument("--version", action="version", version=f"certpose {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (CLIError, ValueError, TypeError, OSError, ImportError, MemoryError) as exc:
        print(f"certpose {args.command}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
