"""A lag's time constant pinned or not by the training rows, and the mean over the taus they do not tell apart.

The generated terms are not shaped like the fit's own model: the body follows a *distributed* lag of
its site (the mean of four first-order lags, 5 min to 5.3 h: a body with several thermal masses),
under random heating stages and AR(1) noise with rho 0.8; the fit has one first-order lag. The last test runs
the whole search on a closed-world bundle whose body follows four lags of one channel.
"""

from __future__ import annotations

import numpy as np
import pytest

from driftlab.models import diagnosis
from driftlab.models.diagnosis import diagnose_bundle
from driftlab.models.lag_pinning import FLAT_SPAN, averaged_lag, profile_tau
from driftlab.models.standard_model import OutlierFlags, TermData, lstsq
from driftlab.physics.lag import first_order_lag_even
from tests import effects_generator as gen

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


def _held_out_garbage(bundle):
    """Return the bundle with every held-out error value (last 25 % of each term's rows) replaced by noise."""
    errs = bundle.errors.copy()
    rng = np.random.default_rng(0)
    for _, g in errs.groupby(["axis", "term"]):
        ts = np.sort(g["time_s"].to_numpy())
        idx = g.index[g["time_s"].to_numpy() >= ts[int(np.floor(0.75 * ts.size))]]
        errs.loc[idx, "value"] = rng.normal(0.0, 0.05, idx.size)
    return type(bundle)(
        name=bundle.name, meta=bundle.meta, temperatures=bundle.temperatures, conditions=bundle.conditions, errors=errs
    )


def test_the_search_averages_an_unpinned_lag_on_the_training_rows_alone(monkeypatch):
    # a closed-world term whose body follows four lags of T3 (10 min to 4.5 h): the search takes T3's lag and then
    # a lag of T1 for what is left; in the final model T1's tau is flat over more than two octaves and enters as
    # the mean of its lags there. Decided on the training rows: garbage in the held-out values changes nothing
    pl = [gen.Planted("thermal_lag", "X", "dx", ["T3"], {"tau_s": t}) for t in (600.0, 1800.0, 5400.0, 16200.0)]
    case = gen.make_case(pl, seed=1, model_channels={"X": ["T1", "T2", "T3", "T9"]})
    res = diagnose_bundle(case.bundle)
    averaged = [e for e in res.effects if "tau_range_s" in e.params]
    assert [(e.kind, e.channels) for e in averaged] == [("thermal_lag", ["T1"])]
    lo, hi = averaged[0].params["tau_range_s"]
    assert lo <= averaged[0].params["tau_s"] <= hi and hi / lo >= 4.0 * (1 - 1e-9)
    term = res.terms[0]
    assert term.effects[-1].rmse_holdout_after == pytest.approx(term.extended.rmse_holdout)
    again = diagnose_bundle(_held_out_garbage(case.bundle))
    assert [(e.kind, e.channels, e.params) for e in again.effects] == [
        (e.kind, e.channels, e.params) for e in res.effects
    ]
    monkeypatch.setattr(diagnosis, "AVERAGE_UNPINNED_LAGS", False)
    assert not any("tau_range_s" in e.params for e in diagnose_bundle(case.bundle).effects)
