"""A lag's time constant, pinned or not by the training rows (issue 22: "shrinkage where a lag's time
constant is poorly pinned").

A first-order lag (thesis 2.4.2, 8.3: the deforming body follows its thermocouple through its thermal
mass, dL/dt = (T - L) / tau) enters the diagnosis with the tau that minimises the training RSS
(``effects.refine_tau``), given the model at the time it enters. Once the set of effects is final, the
training rows may no longer tell its tau from values far away: another lag taken later carries what
set it (FL_THERMAL dx, t16: the final model's training RMSE moves 7 % over 0.25-4 x tau). A point tau
chosen there by the noise, with its coefficient fitted to whatever that tau happens to carry, is a
guess presented as a fact, and it extrapolates as one.

``profile_tau`` evaluates the training fit over tau on a log grid around the optimum (0.25-4 x, inside
the resolvable range), every other column fixed. Its **flat set** is the interval of taus whose fit
explains less than ``PIN_NOISE`` x noise less than the best (in quadrature: the bar an effect must
reach on the training rows to be taken at all, ``SearchConfig.min_explained_train``): values the
training rows cannot tell apart. A lag whose flat set spans at least ``FLAT_SPAN`` (two octaves: its
tau unknown to within a factor of two either way) is **poorly pinned**; ``averaged_lag`` then stands
the mean of its lag responses over the flat set in for the point tau (equal weights on log tau: a
flat profile gives every value in it the same support, so the model average over them is the plain
mean). A mean of first-order lags is a smoother kernel than any one of them: the coefficient fitted
to it is shrunk towards what every plausible tau agrees on, and the lag's part no tau in the set
pins is averaged out. Training rows only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from driftlab.models.standard_model import TermData, lstsq

#: taus whose training fit explains less than this many noise RMS (in quadrature) less than the best are
#: not told apart by the training rows (the training effect-size bar of an effect, ``min_explained_train``)
PIN_NOISE = 0.5
#: a lag whose flat set spans at least this factor in tau is poorly pinned (its responses averaged over the set)
FLAT_SPAN = 4.0
#: the profile's grid: tau x 2^(k/2), k = -4..4 (0.25-4 x the optimum), inside the resolvable range
PROFILE_STEPS = np.arange(-4, 5) / 2.0


@dataclass(frozen=True)
class TauProfile:
    """The training fit of a lag over tau (every other column fixed) and its flat set."""

    taus: np.ndarray  # the profile's grid (s), increasing, the optimum included
    rmse_train: np.ndarray  # training RMSE of the current design + the lag at each tau
    flat: np.ndarray  # bool: taus the training rows do not tell from the optimum
    tau: float  # the in-sample optimum

    @property
    def span(self) -> float:
        """Return the factor the flat set spans in tau (1 when only the optimum)."""
        flat = self.taus[self.flat]
        return float(flat.max() / flat.min()) if flat.size else 1.0

    @property
    def flat_range(self) -> tuple[float, float]:
        """Return the smallest and largest tau of the flat set (s)."""
        flat = self.taus[self.flat]
        return float(flat.min()), float(flat.max())

    @property
    def pinned(self) -> bool:
        """Return whether the training rows pin the lag's tau (its flat set spans less than ``FLAT_SPAN``)."""
        return self.span < FLAT_SPAN * (1.0 - 1e-9)


def _rmse_train(X: np.ndarray, y: np.ndarray, train: np.ndarray) -> float:
    """Return the training RMSE of ``y ~ X``."""
    b = lstsq(X[train], y[train])
    r = y[train] - X[train] @ b
    return float(np.sqrt(np.mean(r * r)))


def _contiguous(mask: np.ndarray, i: int) -> np.ndarray:
    """Return the run of True in ``mask`` that holds index ``i`` (a flat set is one interval of tau)."""
    out = np.zeros_like(mask)
    lo = i
    while lo > 0 and mask[lo - 1]:
        lo -= 1
    hi = i
    while hi < mask.size - 1 and mask[hi + 1]:
        hi += 1
    out[lo : hi + 1] = True
    return out


def profile_tau(
    td: TermData,
    X: np.ndarray,
    column: Callable[[float], np.ndarray],
    tau: float,
    bounds: tuple[float, float],
    noise: float,
) -> TauProfile:
    """Return the training profile of a lag over tau around its optimum ``tau`` and its flat set.

    ``X``: every other column of the model (a channel's own dT included when the lag brought it);
    ``column(tau)``: the lag's columns at ``tau``; ``bounds``: the resolvable range of tau; ``noise``:
    the term's repeatability. Training rows only (``td.train``).
    """
    lo, hi = bounds
    grid = tau * 2.0**PROFILE_STEPS
    grid = grid[(grid > lo * 1.02) & (grid < hi * 0.98)]
    taus = np.unique(np.append(grid, tau))
    rm = np.array([_rmse_train(np.column_stack([X, column(float(t))]), td.y, td.train) for t in taus])
    i0 = int(np.argmin(np.abs(taus - tau)))
    close = rm**2 - float(rm.min()) ** 2 <= (PIN_NOISE * noise) ** 2
    flat = _contiguous(close, i0) if close[i0] else np.arange(taus.size) == i0
    return TauProfile(taus, rm, flat, float(tau))


def averaged_lag(column: Callable[[float], np.ndarray], prof: TauProfile) -> np.ndarray:
    """Return the lag's columns averaged over the flat set of ``prof`` (equal weights on its log-spaced taus)."""
    return np.mean([column(float(t)) for t in prof.taus[prof.flat]], axis=0)
