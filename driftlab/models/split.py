"""The held-out split by time: one rule for the fit, the diagnosis and every figure they state (issue 33).

Per measured line (axis, term) of one campaign, the split is the time of its row at
``1 - holdout_fraction`` of its rows (rows with a time and a position, whatever their value, so that
nothing in the values can move it); rows before it train, the rest is held out. The held-out part
is the end of the record: the model is scored on what comes after everything it was fitted on, as
the compensator uses it (the thesis' validation on later, unseen runs, ch. 6.5).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

#: the held-out split's name in reports (``holdout.method`` of the diagnosis report, ``split`` of the fit's)
TIME_SPLIT = "time"
#: the fit's older split: the last part of every training stage (interpolation within each stage)
STAGE_SPLIT = "stage"
SPLITS = (TIME_SPLIT, STAGE_SPLIT)


def split_time(times: np.ndarray, holdout_fraction: float) -> float:
    """Return the first held-out time of one line's row times (inf: nothing held out)."""
    t = np.sort(np.asarray(times, dtype=float))
    if t.size == 0 or holdout_fraction <= 0:
        return math.inf
    return float(t[min(int(math.floor((1.0 - holdout_fraction) * t.size)), t.size - 1)])


def split_times(errors: pd.DataFrame, holdout_fraction: float) -> dict[tuple[str, str], float]:
    """Return the first held-out time of every (axis, term) of one campaign's errors frame."""
    errs = errors.dropna(subset=["time_s", "position"])
    return {
        (str(axis), str(term)): split_time(g["time_s"].to_numpy(float), holdout_fraction)
        for (axis, term), g in errs.groupby(["axis", "term"], sort=True)
    }


def held_out_rows(errors: pd.DataFrame, holdout_fraction: float) -> np.ndarray:
    """Return the boolean mask of the rows of an errors frame that the time split holds out."""
    cuts = split_times(errors, holdout_fraction)
    if errors.empty:
        return np.zeros(0, dtype=bool)
    key = list(zip(errors["axis"].astype(str), errors["term"].astype(str)))
    cut = np.array([cuts.get(k, math.inf) for k in key], dtype=float)
    return errors["time_s"].to_numpy(float) >= cut
