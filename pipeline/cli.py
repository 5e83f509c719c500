"""The ``flexdof`` command: sub-commands are discovered in :mod:`pipeline.commands`."""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from pipeline import __version__, commands
from pipeline.errors import FlexdofError


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every sub-command of :mod:`pipeline.commands`."""
    parser = argparse.ArgumentParser(
        prog="flexdof",
        description="Flexible depth-of-field photography (Kuthirummal et al., TPAMI 2011).",
    )
    parser.add_argument("--version", action="version", version=f"flexdof {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-q", "--quiet", action="store_true", help="only errors")
    verbosity.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue  # helpers shared by commands (e.g. the progress display)
        importlib.import_module(f"{commands.__name__}.{info.name}").register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; user errors are printed as one line and give exit code 2."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.ERROR if args.quiet else logging.DEBUG if args.verbose else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # output piped into e.g. `head`
        return 0
    except (FlexdofError, ValueError, OSError) as err:
        print(f"flexdof {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"flexdof {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
