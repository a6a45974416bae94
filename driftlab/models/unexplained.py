"""The honest remainder of a diagnosis (spec section 4, ``unexplained``).

Every (axis, term) whose training residual, after the accepted effects, stays above
``RATIO`` (1.5) x the measurement noise is listed, with hints: the residual's signature in
words and figures. Each hint is a plain statistic of the training residual (no held-out row):

- follows a stage's heat source: correlation with a first-order lag of the source's on/off
  schedule (``physics.lag``, the one lag filter; 0.5-8 h), or of a conditions.csv column;
- depends on the approach direction: mean difference of the two directions against its
  standard error; and whether that difference follows a model channel's dT;
- steps at a time: the largest jump of the sweep means against the sweep-to-sweep changes;
- grows with time: slope against time and its correlation;
- correlates with a channel outside the model.

An effect outside the catalogue ends here, named by its signature, instead of as a wrong
catalogue kind.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from driftlab.models.effects import source_schedules
from driftlab.models.standard_model import PreparedBundle, TermData, robust_sigma
from driftlab.physics.lag import first_order_lag_even

#: a term is unexplained when its training residual RMS exceeds this multiple of the noise
RATIO = 1.5
#: ... or, once every decision is made, when its held-out residual RMS exceeds this multiple (issue 33.5:
#: the held-out part shows what training did not; reported, it changes no decision)
HOLDOUT_RATIO = 2.0
#: the hint that says so
HELD_OUT_HINT = "held out shows what training did not"
#: correlations below this are not worth a hint
MIN_R = 0.3
#: lag time constants tried for the heat-source hint (s)
HINT_TAUS = (1800.0, 3600.0, 7200.0, 14400.0, 28800.0)


@dataclass
class Unexplained:
    """One (axis, term) whose residual stays above the noise after the accepted effects, with hints."""

    axis: str
    term: str
    residual_over_noise: float
    rmse_train: float
    noise: float
    hints: list[str] = field(default_factory=list)
    figures: dict[str, float] = field(default_factory=dict)
    #: the held-out residual after the final model (scored once, after every decision)
    rmse_holdout: float = float("nan")
    #: which part shows the remainder: "training" (and maybe held out too) or "held out" alone
    part: str = "training"

    @property
    def holdout_over_noise(self) -> float:
        """Return the held-out residual RMS over the noise (NaN without held-out rows)."""
        return self.rmse_holdout / self.noise if self.noise > 0 else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """Return the spec's ``unexplained[]`` entry (with figures, RMSEs, noise and the part that shows it)."""
        return {
            "axis": self.axis,
            "term": self.term,
            "residual_over_noise": self.residual_over_noise,
            "hints": list(self.hints),
            "figures": dict(self.figures),
            "rmse_train": self.rmse_train,
            "rmse_holdout": self.rmse_holdout if np.isfinite(self.rmse_holdout) else None,
            "holdout_over_noise": self.holdout_over_noise if np.isfinite(self.rmse_holdout) else None,
            "noise": self.noise,
            "part": self.part,
        }


def _fmt(value: float, unit: str) -> str:
    """Return a value in display units: um for mm, urad for rad."""
    return f"{value * 1e6:.3g} urad" if unit == "rad" else f"{value * 1e3:.3g} um"


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    """Return Pearson's r of two series (0 when either is constant)."""
    if a.size < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


@dataclass
class _Residual:
    """A term's training residual and what its hints are read against, with the hints found so far."""

    td: TermData
    prep: PreparedBundle
    model_channels: list[str]
    noise: float
    rt: np.ndarray  # the residual on the training rows
    tt: np.ndarray  # their times
    hints: list[tuple[float, str]] = field(default_factory=list)  # (strength for the order, sentence)
    fig: dict[str, float] = field(default_factory=dict)

    @property
    def u(self) -> str:
        """Return the unit of the term's values."""
        return self.td.unit


def _hint_source(res: _Residual) -> None:
    """Hint at a stage's heat source or a machine-state column, through a first-order lag."""
    prep = res.prep
    if prep.grid_t.size <= 2:
        return
    step = float(prep.grid_t[1] - prep.grid_t[0])
    best: tuple[float, str, float] | None = None
    for name, x in source_schedules(prep).items():
        for tau in HINT_TAUS:
            lag = np.interp(res.tt, prep.grid_t, first_order_lag_even(x, step, tau))
            c = _corr(res.rt, lag)
            if best is None or abs(c) > abs(best[0]):
                best = (c, name, tau)
    if best is None or abs(best[0]) < MIN_R:
        return
    c, name, tau = best
    what = name.split(":", 1)[1]
    kind = "heat source" if name.startswith("stage:") else "machine-state column"
    res.fig["source_r"] = c
    res.fig["source_tau_s"] = tau
    res.hints.append(
        (abs(c), f"follows a {tau / 3600:.1f} h lag of the {what} {kind} (r = {c:.2f}): heat no model sensor reads")
    )


def _hint_direction(res: _Residual) -> None:
    """Hint at a difference between the approach directions, and whether it follows a model channel."""
    td, rt, tr = res.td, res.rt, res.td.train
    dt_ = td.direction[tr].astype(float)
    if np.unique(dt_).size <= 1:
        return
    a, b = rt[dt_ > 0], rt[dt_ < 0]
    diff = float(np.mean(a) - np.mean(b))
    se = float(np.sqrt(np.var(a) / max(a.size, 1) + np.var(b) / max(b.size, 1)))
    z = abs(diff) / max(se, 1e-300)
    if z > 5 and abs(diff) > 0.5 * res.noise:
        res.fig["direction_difference"] = diff
        res.hints.append(
            (min(1.0, z / 20), f"depends on the approach direction ({_fmt(abs(diff), res.u)} between them)")
        )
    # does the direction difference follow a temperature?
    prep = res.prep
    cols = {ch: td.temps[tr, prep.channel_index(ch)] for ch in res.model_channels if ch in prep.channels}
    best_c: tuple[float, str] | None = None
    for ch, col in cols.items():
        if not np.all(np.isfinite(col)):
            continue
        c = _corr(rt * dt_, col - col[0])
        if best_c is None or abs(c) > abs(best_c[0]):
            best_c = (c, ch)
    if best_c is not None and abs(best_c[0]) >= MIN_R:
        res.fig["direction_temperature_r"] = best_c[0]
        res.hints.append((abs(best_c[0]), f"the direction difference grows with {best_c[1]} (r = {best_c[0]:.2f})"))


def _hint_step(res: _Residual) -> None:
    """Hint at a step between sweeps: the largest jump of the sweep means against their robust scatter."""
    sw, rt, tt = res.td.sweep[res.td.train], res.rt, res.tt
    ids, first = np.unique(sw, return_index=True)
    if ids.size < 8:
        return
    order = np.argsort(tt[first])
    means = np.array([float(np.mean(rt[sw == i])) for i in ids[order]])
    starts = tt[first][order]
    d = np.diff(means)
    s = max(robust_sigma(d), 1e-300)
    k = int(np.argmax(np.abs(d)))
    z = abs(d[k]) / s
    if z > 8 and abs(d[k]) > res.noise:
        res.fig["step"] = float(d[k])
        res.fig["step_time_s"] = float(starts[k + 1])
        res.hints.append(
            (min(1.0, z / 30), f"steps by {_fmt(d[k], res.u)} at t = {starts[k + 1] / 3600:.2f} h ({z:.0f} sigma)")
        )


def _hint_time(res: _Residual) -> None:
    """Hint at a residual that grows with time."""
    days = (res.tt - res.tt[0]) / 86400.0
    c = _corr(res.rt, days)
    if abs(c) >= MIN_R:
        slope = float(np.polyfit(days, res.rt, 1)[0])
        res.fig["time_r"] = c
        res.fig["rate_per_day"] = slope
        res.hints.append((abs(c), f"grows with time ({_fmt(slope, res.u)} per day, r = {c:.2f})"))


def _hint_outside(res: _Residual) -> None:
    """Hint at the channel outside the model the residual correlates with most."""
    best_o: tuple[float, str] | None = None
    for j, ch in enumerate(res.prep.channels):
        if ch in res.model_channels:
            continue
        col = res.td.temps[res.td.train, j]
        if not np.all(np.isfinite(col)):
            continue
        c = _corr(res.rt, col - col[0])
        if best_o is None or abs(c) > abs(best_o[0]):
            best_o = (c, ch)
    if best_o is not None and abs(best_o[0]) >= MIN_R:
        res.fig["outside_channel_r"] = best_o[0]
        res.hints.append(
            (abs(best_o[0]), f"correlates with {best_o[1]}, a channel outside the model (r = {best_o[0]:.2f})")
        )


def describe_residual(
    td: TermData, r: np.ndarray, prep: PreparedBundle, model_channels: list[str], noise: float
) -> tuple[list[str], dict[str, float]]:
    """Return hints (sentences) and figures on the training residual ``r`` of one term."""
    tr = td.train
    res = _Residual(td, prep, model_channels, noise, r[tr], td.t[tr])
    for hint in (_hint_source, _hint_direction, _hint_step, _hint_time, _hint_outside):
        hint(res)
    res.hints.sort(key=lambda h: -h[0])
    words = [h[1] for h in res.hints]
    if not words:
        words = ["no simple signature: noise larger than stated, or an effect outside the catalogue"]
    return words, res.fig


def unexplained_term(
    td: TermData, r: np.ndarray, prep: PreparedBundle, model_channels: list[str], noise: float
) -> Unexplained | None:
    """Return the :class:`Unexplained` entry of a term whose residual stays above its noise, else None.

    The training residual above ``RATIO`` x noise, or the held-out residual (of the final model,
    after every decision) above ``HOLDOUT_RATIO`` x noise: the held-out part then shows what training
    did not, and the entry says so. The hints read the training residual alone.
    """
    tr = td.train
    if noise <= 0 or tr.sum() < 3:
        return None
    rms = float(np.sqrt(np.mean(r[tr] ** 2)))
    ho = ~tr
    rms_ho = float(np.sqrt(np.mean(r[ho] ** 2))) if ho.any() else float("nan")
    ratio = rms / noise
    held = bool(np.isfinite(rms_ho) and rms_ho > HOLDOUT_RATIO * noise)
    if ratio <= RATIO and not held:
        return None
    hints, fig = describe_residual(td, r, prep, model_channels, noise)
    part = "training" if ratio > RATIO else "held out"
    if held:
        hints.insert(
            0 if part == "held out" else len(hints),
            f"{HELD_OUT_HINT}: the held-out residual is {rms_ho / noise:.1f}x the noise ({_fmt(rms_ho, td.unit)})"
            f" against {ratio:.1f}x in training",
        )
    return Unexplained(td.axis, td.term, ratio, rms, noise, hints, fig, rms_ho, part)
