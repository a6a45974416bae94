"""The one root-mean-square error every report, fit and benchmark quotes (thesis ch. 6: RMSE)."""

from __future__ import annotations

from typing import Any

import numpy as np


def rmse(residual: Any) -> float:
    """Return the root mean square of the finite values of ``residual`` (NaN when there are none).

    Missing values (NaN, a dropped reading) are left out, not counted as zero.
    """
    r = np.asarray(residual, dtype=float).ravel()
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")
