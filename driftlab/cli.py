"""The single ``driftlab`` entry point: discovers subcommands in ``driftlab.commands``."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path

from driftlab import __version__
from driftlab import commands as commands_pkg
from driftlab.errors import DriftlabError, environment_error
from driftlab.logs import setup_logging

#: exit status of a database, file or permission failure (2 is bad input or usage, 3 a stopped campaign)
ENVIRONMENT_EXIT = 1


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line on stderr, exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        """Print a one-line usage error and exit with status 2."""
        sys.stderr.write(f"driftlab: error: {message}\n")
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    """Return the top-level parser with every discovered subcommand registered."""
    parser = _Parser(
        prog="driftlab",
        description="Measure, learn and cancel the thermal drift of a five-axis machine tool.",
    )
    parser.add_argument("--version", action="version", version=f"driftlab {__version__}")
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="log progress at INFO level (-vv: DEBUG, with the libraries' own lines)",
    )
    parser.add_argument(
        "--log-file",
        type=Path,
        default=None,
        metavar="PATH",
        help="also append timestamped log lines (INFO and worse) to this file",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for info in sorted(pkgutil.iter_modules(commands_pkg.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands_pkg.__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI and return its exit status; user errors become one line on stderr."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        setup_logging(args.verbose, args.log_file)
    except OSError as exc:
        sys.stderr.write(f"driftlab: error: --log-file {args.log_file}: {exc.strerror or exc}\n")
        return 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except DriftlabError as exc:
        if args.verbose:
            traceback.print_exc()
        sys.stderr.write(f"driftlab: error: {exc.one_line()}\n")
        return exc.exit_code
    except KeyboardInterrupt:
        sys.stderr.write("driftlab: interrupted\n")
        return 130
    except Exception as exc:
        # a database, file or permission failure: one line (the traceback with -v); a bug still raises
        line = environment_error(exc)
        if line is None:
            raise
        if args.verbose:
            traceback.print_exc()
        sys.stderr.write(f"driftlab: error: {line}\n")
        return ENVIRONMENT_EXIT


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
