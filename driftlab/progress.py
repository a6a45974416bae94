"""The one progress helper: a rich progress bar on a terminal, silent otherwise."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import TypeVar

from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

T = TypeVar("T")


def _attached() -> bool:
    """Return True when stderr is a terminal (progress is shown only then)."""
    return sys.stderr.isatty()


@contextmanager
def progress(description: str, total: float | None = None) -> Iterator["_Task"]:
    """Yield a task whose ``advance(n)`` moves a bar on a terminal and does nothing elsewhere."""
    if not _attached():
        yield _Task(None, None)
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        transient=True,
    ) as bar:
        yield _Task(bar, bar.add_task(description, total=total))


class _Task:
    """A handle on one progress task (a no-op when not attached to a terminal)."""

    def __init__(self, bar: Progress | None, task_id: object) -> None:
        self._bar = bar
        self._id = task_id

    def advance(self, n: float = 1.0) -> None:
        """Advance the bar by ``n`` units."""
        if self._bar is not None:
            self._bar.advance(self._id, n)  # type: ignore[arg-type]


def track(items: Iterable[T], description: str, total: float | None = None) -> Iterator[T]:
    """Yield from ``items`` while advancing a progress bar on a terminal."""
    with progress(description, total) as task:
        for item in items:
            yield item
            task.advance()
