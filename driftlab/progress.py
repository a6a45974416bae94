"""The one progress helper: a rich progress bar on a terminal, silent otherwise; log lines print above it.

Every bar and every log line on a terminal goes through one stderr ``Console`` (``console()``),
so a log record emitted while a bar is drawn is printed above the bar instead of breaking it.
``stages()`` is a bar over named steps whose total is the list of steps: it can never run past
its end, and it shows the step in progress.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from functools import lru_cache
from typing import Any, TypeVar

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

T = TypeVar("T")


@lru_cache(maxsize=1)
def console() -> Console:
    """Return the stderr console shared by progress bars and terminal log lines."""
    return Console(stderr=True)


def _attached() -> bool:
    """Return True when stderr is a terminal (progress is shown only then)."""
    return sys.stderr.isatty()


def _columns(total: float | None) -> list[Any]:
    """Return the bar's columns: a count and time left when the total is known, a spinner otherwise."""
    if total is None:
        return [SpinnerColumn(), TextColumn("[bold]{task.description}"), TimeElapsedColumn()]
    return [
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    ]


@contextmanager
def progress(description: str, total: float | None = None) -> Iterator[_Task]:
    """Yield a task whose ``advance(n)`` moves a bar on a terminal and does nothing elsewhere.

    Without ``total`` the bar is a spinner with the elapsed time (nothing claims a fraction it
    does not know).
    """
    if not _attached():
        yield _Task(None, None)
        return
    with Progress(*_columns(total), console=console(), transient=True) as bar:
        yield _Task(bar, bar.add_task(description, total=total))


class _Task:
    """A handle on one progress task (a no-op when not attached to a terminal)."""

    def __init__(self, bar: Progress | None, task_id: Any) -> None:
        self._bar = bar
        self._id = task_id

    def advance(self, n: float = 1.0) -> None:
        """Advance the bar by ``n`` units."""
        if self._bar is not None:
            self._bar.advance(self._id, n)

    def update(
        self, *, description: str | None = None, total: float | None = None, completed: float | None = None
    ) -> None:
        """Change the description, total or position of the bar."""
        if self._bar is not None:
            kw: dict[str, Any] = {}
            if description is not None:
                kw["description"] = description
            if total is not None:
                kw["total"] = total
            if completed is not None:
                kw["completed"] = completed
            self._bar.update(self._id, **kw)


class Stages:
    """Progress over named steps: ``done(name)`` marks a step finished and names the next one."""

    def __init__(self, task: _Task, label: str, steps: Sequence[str]) -> None:
        self.task, self.label, self.steps = task, label, list(steps)
        self.finished: list[str] = []
        self._show()

    def _show(self) -> None:
        """Redraw the description (the step in progress) and the count."""
        left = [s for s in self.steps if s not in self.finished]
        now = left[0].replace("_", " ") if left else "done"
        self.task.update(description=f"{self.label}: {now}", total=len(self.steps), completed=len(self.finished))

    def done(self, step: str) -> None:
        """Mark ``step`` finished; an unexpected step extends the list (the bar never runs past its end)."""
        if step not in self.steps:
            self.steps.insert(len(self.finished), step)
        if step not in self.finished:
            self.finished.append(step)
        self._show()


@contextmanager
def stages(label: str, steps: Sequence[str]) -> Iterator[Stages]:
    """Yield a :class:`Stages` bar over ``steps`` (silent when not on a terminal)."""
    with progress(label, total=len(steps)) as task:
        yield Stages(task, label, steps)


def track(items: Iterable[T], description: str, total: float | None = None) -> Iterator[T]:
    """Yield from ``items`` while advancing a progress bar on a terminal."""
    with progress(description, total) as task:
        for item in items:
            yield item
            task.advance()


def stdout_console() -> Console:
    """Return a console for tables on stdout: the terminal's width, or when piped ``COLUMNS`` (else 120, so piped
    tables do not wrap)."""
    if sys.stdout.isatty():
        return Console()
    try:
        width = int(os.environ.get("COLUMNS", ""))
    except ValueError:
        width = 0
    return Console(width=width if width >= 40 else 120, no_color=True)
