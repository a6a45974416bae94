"""Strict JSON: what driftlab stores and serves has no NaN or Infinity and no numpy scalars.

Python's ``json`` writes NaN and Infinity, which strict JSON (browsers, PostgreSQL's jsonb) refuses.
Every document, report and job result goes through :func:`strict_json` before it is written;
values coming in go through :func:`check_json`, which refuses rather than repairs.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from driftlab.errors import ValidationError


def finite_or_none(v: Any) -> float | None:
    """Return ``v`` as a finite float, or None when it is missing, NaN or infinite."""
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def strict_json(obj: Any) -> Any:
    """Return ``obj`` with numpy scalars and arrays made plain, non-finite floats None and keys text."""
    if isinstance(obj, dict):
        return {str(k): strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return strict_json(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        return finite_or_none(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def check_json(obj: Any, where: str = "document") -> None:
    """Refuse non-finite numbers and NUL characters anywhere in a JSON value (ValidationError).

    Python's JSON parser accepts NaN and Infinity, which strict JSON (and PostgreSQL's jsonb) does
    not; PostgreSQL text cannot hold NUL either.
    """
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise ValidationError(f"{where}: numbers must be finite")
    elif isinstance(obj, str):
        if "\x00" in obj:
            raise ValidationError(f"{where}: text must not contain NUL characters")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            check_json(k, where)
            check_json(v, f"{where}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            check_json(v, f"{where}[{i}]")
