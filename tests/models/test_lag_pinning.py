"""A lag's time constant pinned or not by the training rows, and the mean over the taus they do not tell apart.

The generated terms are not shaped like the fit's own model: the body follows a *distributed* lag of
its site (the mean of four first-order lags, 5 min to 5.3 h: a body with several thermal masses),
under random heating stages and AR(1) noise with rho 0.8; the fit has one first-order lag.
"""

from __future__ import annotations

import numpy as np
import pytest

from driftlab.models.lag_pinning import FLAT_SPAN, averaged_lag, profile_tau
from driftlab.models.standard_model import OutlierFlags, TermData, lstsq
from driftlab.physics.lag import first_order_lag_even

DT = 60.0
NOISE = 5e-4


def _term(seed: int, taus_true: list[float], size: float) -> tuple[TermData, np.ndarray, np.ndarray]:
    """Return a 30 h term whose body follows the mean of lags at ``taus_true`` of its site, ``size`` x noise."""
    rng = np.random.default_rng(seed)
    n = int(30 * 3600 / DT)
    t = np.arange(n) * DT
    u = np.zeros(n)
    k = 0
    while k < n:  # random heating stages: 1-5 h on at a random power, 0.5-3 h off
        on, off = int(rng.uniform(1, 5) * 60), int(rng.uniform(0.5, 3) * 60)
        u[k : k + on] = rng.uniform(0.5, 1.5)
        k += on + off
    x = first_order_lag_even(8.0 * u, DT, 2400.0)  # the site's temperature rise
    body = np.mean([first_order_lag_even(x, DT, tau) for tau in taus_true], axis=0)
    sig = body - x  # what the body's lag adds to the site's own dT
    beyond = sig - np.polyval(np.polyfit(x, sig, 1), x)
    e = np.zeros(n)
    w = rng.normal(0.0, 1.0, n)
    for i in range(1, n):
        e[i] = 0.8 * e[i - 1] + 0.6 * w[i]
    y = size * NOISE / np.std(beyond) * sig + 0.01 * x + NOISE * e
    flags = OutlierFlags("Z/dz", 0)
    td = TermData("Z", "dz", t, np.zeros(n), np.ones(n), y, x[:, None], int(0.75 * n), np.arange(n), flags)
    return td, np.column_stack([np.ones(n), x]), x


def _column(x: np.ndarray, t: np.ndarray):
    def column(tau: float) -> np.ndarray:
        g = first_order_lag_even(x, DT, tau)
        return np.column_stack([g - g[0], np.exp(-t / tau)])

    return column


def _best_tau(td: TermData, X: np.ndarray, column) -> float:
    tr = td.train
    grid = np.exp(np.linspace(np.log(180.0), np.log(30000.0), 60))

    def rss(tau: float) -> float:
        A = np.column_stack([X, column(tau)])[tr]
        r = td.y[tr] - A @ lstsq(A, td.y[tr])
        return float(r @ r)

    return float(grid[int(np.argmin([rss(g) for g in grid]))])


def _held_out(td: TermData, X: np.ndarray, cols: np.ndarray) -> float:
    A = np.column_stack([X, cols])
    tr = td.train
    r = td.y[~tr] - A[~tr] @ lstsq(A[tr], td.y[tr])
    return float(np.sqrt(np.mean(r * r)))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_lag_the_training_rows_tell_apart_is_pinned(seed):
    td, X, x = _term(seed, [1800.0], 6.0)
    column = _column(x, td.t)
    tau = _best_tau(td, X, column)
    prof = profile_tau(td, X, column, tau, (180.0, 30000.0), NOISE)
    assert prof.pinned and prof.span < 2.0
    assert tau == pytest.approx(1800.0, rel=0.15)


def test_a_distributed_lag_is_not_pinned_and_its_mean_over_the_flat_set_predicts_better():
    unpinned = 0
    for seed in range(4):
        td, X, x = _term(seed, [300.0, 1200.0, 4800.0, 19200.0], 2.0)
        column = _column(x, td.t)
        tau = _best_tau(td, X, column)
        prof = profile_tau(td, X, column, tau, (180.0, 30000.0), NOISE)
        lo, hi = prof.flat_range
        assert lo <= tau <= hi
        if prof.pinned:
            continue
        unpinned += 1
        assert prof.span >= FLAT_SPAN * (1 - 1e-9)
        # the fit at the point tau extrapolates worse to the rows after the training part than the mean
        assert _held_out(td, X, averaged_lag(column, prof)) < _held_out(td, X, column(tau))
    assert unpinned >= 3
