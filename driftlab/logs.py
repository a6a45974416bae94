"""Logging of the command line: timestamped lines on stderr (above any progress bar), an optional log file.

Verbosity: default WARNING; ``-v`` INFO (migrations then say only which revisions they apply);
``-vv`` DEBUG with every library's chatter. ``--log-file PATH`` appends every INFO-or-worse line
(DEBUG with ``-vv``), with the date and milliseconds, whatever the terminal shows.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

CONSOLE_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
FILE_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
DATE = "%Y-%m-%d %H:%M:%S"
#: libraries whose INFO lines say nothing a user of driftlab needs, unless -vv
CHATTY = ("alembic", "httpx", "httpcore", "matplotlib", "urllib3", "asyncio", "multipart", "PIL")


class _QuietLibraries(logging.Filter):
    """Let through a chatty library's warnings, and of Alembic's INFO only the revisions it runs."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Return False for a library's routine INFO or DEBUG line."""
        if record.levelno >= logging.WARNING or not record.name.startswith(CHATTY):
            return True
        return record.name.startswith("alembic.runtime.migration") and record.getMessage().startswith(
            ("Running upgrade", "Running downgrade")
        )


class _CurrentStderr(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is when a record is emitted."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> object:
        """Return the current standard error."""
        return sys.stderr

    @stream.setter
    def stream(self, _value: object) -> None:
        """Ignore: the stream is always the current standard error."""


def setup_logging(verbosity: int = 0, log_file: Path | None = None) -> None:
    """Configure the root logger for a CLI run (replacing any handlers a previous run installed)."""
    # lazy: logs is on the `driftlab --help` path; rich adds 0.07 s there (measured)
    from driftlab.progress import console

    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    root = logging.getLogger()
    for h in list(root.handlers):
        if getattr(h, "_driftlab", False):
            root.removeHandler(h)
            h.close()
    handlers: list[logging.Handler] = []
    if sys.stderr.isatty():
        # lazy: logs is on the `driftlab --help` path; rich adds 0.07 s there (measured)
        from rich.logging import RichHandler

        term: logging.Handler = RichHandler(
            console=console(), show_path=False, markup=False, rich_tracebacks=False, log_time_format="[%H:%M:%S]"
        )
        term.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    else:
        term = _CurrentStderr()
        term.setFormatter(logging.Formatter(CONSOLE_FORMAT, DATE))
    term.setLevel(level)
    handlers.append(term)
    file_level = min(level, logging.INFO)
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(log_file, encoding="utf-8")
        fh.setFormatter(logging.Formatter(FILE_FORMAT, DATE))
        fh.setLevel(file_level)
        handlers.append(fh)
    for h in handlers:
        h._driftlab = True  # type: ignore[attr-defined]
        if verbosity < 2:
            h.addFilter(_QuietLibraries())
        root.addHandler(h)
    root.setLevel(min(h.level for h in handlers))
