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


def timeit_best(fn: Callable[[], Any], repeat: int = 3) -> float:
    """Return the best wall time in seconds of ``repeat`` calls of ``fn``."""
    best = float("inf")
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def emit(figures: dict[str, Any]) -> None:
    """Print the figures as one JSON line on stdout."""
    sys.stdout.write(json.dumps(figures) + "\n")
    sys.stdout.flush()


single_core()
