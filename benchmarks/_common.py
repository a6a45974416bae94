"""Tiny shared helpers for the benchmark scripts: one core, best-of timing, one JSON line.

Import this module before numpy so that ``single_core()`` (run at import) takes effect on the
BLAS/OpenMP thread pools. Running this file on its own does nothing (``make bench`` runs every
``benchmarks/*.py``).
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from typing import Any

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def single_core() -> None:
    """Pin the numeric thread pools to one thread (effective when run before numpy is imported)."""
    for var in _THREAD_VARS:
        os.environ[var] = "1"


def timeit_best(fn: Callable[[], Any], repeat: int = 3, clock: Callable[[], float] = time.perf_counter) -> float:
    """Return the best time in seconds of ``repeat`` calls of ``fn`` (wall clock unless told).

    Pass ``clock=time.process_time`` for the CPU time of this process: on a machine shared with
    other work it measures what one core does, where wall time also counts the waiting.
    """
    best = float("inf")
    for _ in range(max(1, repeat)):
        start = clock()
        fn()
        best = min(best, clock() - start)
    return best


def load_average() -> float | None:
    """Return the 1-minute load average (None where the OS does not report it)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def emit(figures: dict[str, Any]) -> None:
    """Print the figures as one JSON line on stdout."""
    sys.stdout.write(json.dumps(figures) + "\n")
    sys.stdout.flush()


single_core()
