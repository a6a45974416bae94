"""Thermocouples whose calibration drifts: decided on the temperatures alone (spec section 3, ``sensor_drift``).

An ageing junction or a creeping mount makes a reading depart from what its structure does,
slowly and steadily (thesis 6.4.2 and appendix B: a thermocouple's calibration is not forever).
Seen from the errors alone, such a channel looks like a machine drift on every term whose model
reads it; seen from the temperatures it is plain: the channel departs from its virtual sensor
(thesis 6.6: the channel predicted from the others on its structure and the room air) along a
ramp in time, from some moment on, while its neighbours agree with one another.

``scan_sensor_drifts`` fits, per channel, the virtual sensor jointly with a hinge
``max(t - t0, 0)`` in days for every candidate start ``t0`` (one projection for all starts),
and keeps the start that explains most of the departure. The virtual sensor is dynamic: the
neighbours' readings, their first-order lags (15 and 45 min) and the lags (15 min to 2 h) of the
heat inputs the bundle states (stage schedules, conditions columns), none longer than an eighth of
the campaign, with the temperature coefficients summing to one (unit steady gain). A drift is
plausible when the ramp explains most of the departure (RSS ratio), is large against the departure
that is left, keeps its direction over its span (both halves' rates share its sign),
lasts at least a quarter of the campaign (a short ramp is a transient, not an ageing junction), and
stands out among all channels' ratios (a peer test, as for sensor faults). The repair subtracts
the ramp from the reading; the result has the same form as a sensor fault's scan
(:class:`~driftlab.models.effects.FaultScan` with ``mode="drift"``) so the diagnosis repairs
the terms that read it the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from driftlab.models.effects import FaultScan, _neighbours, source_schedules
from driftlab.models.standard_model import PreparedBundle, robust_sigma
from driftlab.physics.lag import first_order_lag

#: the ramp must explain this share of the departure from the virtual sensor: RSS without / with it
MIN_RATIO = 4.0
#: ... counted on means over this many seconds, so the bar means the same at every scan rate: the bar was
#: set on 60-120 s scans, where a block holds one or two readings; a logger scanning every 10 s puts twelve
#: readings of independent thermocouple noise in the same time, which the ramp (a slow law) cannot explain
#: and which made a real drift's ratio 2.3 instead of 13 (issue 22, open world seeds 901 and 905)
RATIO_BLOCK_S = 120.0
#: ... and reach this many sigmas of what is left of the departure at the end of the campaign
MIN_SIZE_SIGMA = 10.0
#: ... and this much in degC (a thermocouple's stated tolerance is 0.5-1 degC; a drift below 0.05 degC
#: over a campaign is no finding about the sensor)
MIN_SIZE_DEGC = 0.05
#: the ramp must last at least this share of the campaign
MIN_SPAN_FRACTION = 0.25
#: floor of the peers' spread of log ratios (healthy channels can agree to a few percent)
PEER_MAD_FLOOR = 0.25
#: time constants (s) of the neighbours' first-order lags in the dynamic virtual sensor: a thermocouple
#: site follows its heat inputs as a first-order lag of tens of minutes to hours (thesis 2.4.2; 5.3, Fig.
#: 5.4), so one site is a lagged mix of another's reading (see ``scan_sensor_drifts``)
VS_TAUS_S = (900.0, 2700.0)
#: time constants (s) of the stated heat inputs' lags in the virtual sensor (a site's own response to a source)
SCHED_TAUS_S = (900.0, 2700.0, 7200.0)
#: no lag of the virtual sensor is longer than this share of the campaign: none can build a ramp that lasts
#: a quarter of it or more (a lag of a third of the campaign can mimic a trend)
VS_TAU_MAX_FRACTION = 0.125


def _block_means(r: np.ndarray, t: np.ndarray, block_s: float) -> np.ndarray:
    """Return the means of ``r`` over consecutive blocks of ``block_s`` seconds of ``t``."""
    k = np.floor((t - t[0]) / block_s).astype(int)
    sums = np.bincount(k, weights=r)
    cnt = np.bincount(k)
    ok = cnt > 0
    return sums[ok] / cnt[ok]


def _hinge_bank(t: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Return the (n, k) hinges max(t - t0, 0) in days for every start ``t0``."""
    return np.maximum(t[:, None] - starts[None, :], 0.0) / 86400.0


@dataclass
class _DriftGrid:
    """What every channel's drift scan shares: the grid, the hinge bank and the dynamic virtual sensor's inputs."""

    prep: PreparedBundle
    D: np.ndarray  # dT of every channel on the grid
    finite: np.ndarray  # usable channels
    corr: np.ndarray  # correlations of the channels' dT
    starts: np.ndarray  # candidate starts of the ramp
    H: np.ndarray  # the hinges max(t - t0, 0) in days, one per start
    lagged: list[np.ndarray]  # every channel's dT through the neighbours' lags
    heat: list[np.ndarray]  # the stated heat inputs through their lags


def _drift_grid(prep: PreparedBundle) -> _DriftGrid:
    """Return the shared inputs of the drift scans (see ``scan_sensor_drifts``)."""
    T, t = prep.grid_T, prep.grid_t
    finite = np.all(np.isfinite(T), axis=0) & (np.ptp(np.nan_to_num(T), axis=0) > 0)
    span = float(t[-1] - t[0])
    # candidate starts every ~1/48 of the campaign, up to where a quarter of it is left
    starts = np.linspace(t[0], t[0] + (1.0 - MIN_SPAN_FRACTION) * span, 37)
    D = T - T[0]
    with np.errstate(all="ignore"):
        corr = np.nan_to_num(np.corrcoef(np.where(finite, D, 0.0).T))
    # the dynamic virtual sensor (thesis 6.6 with the first-order site response of 2.4.2 and 5.3): two sites
    # that follow the same heat input f with their own time constants, T_j = L_tj(f) and T_k = L_tk(f)
    # (L: the lag filter, tau dL/dt = u - L), are related by T_j = L_tj(T_k + t_k dT_k/dt), which lies in
    # the span of T_k and L_tj(T_k). A static regression on T_k leaves every stage's transient as a
    # departure as large as a slow calibration drift; the lagged neighbours take it
    dt_med = float(np.median(np.diff(t)))
    lim = VS_TAU_MAX_FRACTION * span
    D0 = np.where(finite, D, 0.0)
    lagged = [first_order_lag(D0, t, tau) for tau in VS_TAUS_S if 3.0 * dt_med <= tau <= lim]
    # the heat inputs the campaign states (stage schedules, conditions columns) through the same lags: a site
    # that sees a source its neighbours barely see (5.3, Fig. 5.4: sites near a source change most) departs
    # from them at every stage of that source, and that is no drift
    sched = list(source_schedules(prep).values())
    heat = [first_order_lag(np.column_stack(sched), t, tau) for tau in SCHED_TAUS_S if tau <= lim] if sched else []
    return _DriftGrid(prep, D, finite, corr, starts, _hinge_bank(t, starts), lagged, heat)


def _virtual_sensor_basis(g: _DriftGrid, j: int, nb: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Return an orthonormal basis of channel ``j``'s dynamic virtual sensor and its departure to explain.

    Unit steady gain: a uniform change of the machine and its room moves every reading alike (a uniform
    field solves the heat equation without sources; each lag has unit steady gain), so the temperature
    coefficients sum to one - written against a reference, the room air when the bundle names it.
    """
    prep, D = g.prep, g.D
    room = [k for k in nb if prep.channels[k] in prep.room_channels]
    ref = room[0] if room else nb[0]
    temps = np.column_stack([D[:, nb], *[L[:, nb] for L in g.lagged]]) - D[:, [ref]]
    A = np.column_stack([np.ones(D.shape[0]), temps, *g.heat])
    s = np.sqrt(np.mean(A * A, axis=0))
    Q, R = np.linalg.qr(A / np.where(s > 0, s, 1.0))
    keep = np.abs(np.diag(R)) > 1e-10 * np.abs(np.diag(R)).max()
    return Q[:, keep], D[:, j] - D[:, ref]


def _scan_drift_channel(g: _DriftGrid, j: int, skip: set[int]) -> FaultScan | None:
    """Return the best ramp of channel ``j``'s departure from its dynamic virtual sensor (``skip``: not neighbours)."""
    prep, t, n = g.prep, g.prep.grid_t, g.D.shape[0]
    order = [k for k in np.argsort(-np.abs(g.corr[j])) if k != j and g.finite[k] and k not in skip]
    nb = _neighbours(prep, j, order, 16)
    if not nb:
        return None
    Q, y = _virtual_sensor_basis(g, j, nb)
    ry = y - Q @ (Q.T @ y)
    rss0 = float(ry @ ry)
    RH = g.H - Q @ (Q.T @ g.H)
    nh = np.sum(RH * RH, axis=0)
    ok = nh > 1e-12
    drops = np.where(ok, (RH.T @ ry) ** 2 / np.where(ok, nh, 1.0), -1.0)
    i = int(np.argmax(drops))
    if drops[i] <= 0 or rss0 <= 0:
        return None
    b = float((RH[:, i] @ ry) / nh[i])  # degC per day: the ramp's own coefficient (FWL)
    r1 = ry - b * RH[:, i]
    rss1 = max(float(r1 @ r1), 1e-300)
    # the share of the departure the ramp explains, on means over RATIO_BLOCK_S: a thermocouple's noise is
    # independent from reading to reading, and reading by reading a 10 s logger's ratio measures its noise
    m0, m1 = _block_means(ry, t, RATIO_BLOCK_S), _block_means(r1, t, RATIO_BLOCK_S)
    ratio = float(m0 @ m0) / max(float(m1 @ m1), 1e-300)
    size = abs(b) * (t[-1] - g.starts[i]) / 86400.0
    sigma = max(robust_sigma(np.diff(r1)) / np.sqrt(2.0), float(np.sqrt(rss1 / n)), 1e-6)
    plausible = bool(
        ratio > MIN_RATIO
        and size > MIN_SIZE_SIGMA * sigma
        and size > MIN_SIZE_DEGC
        and _steady(t, Q, ry, float(g.starts[i]), b)
    )
    return FaultScan(
        prep.channels[j],
        float(g.starts[i]),
        size,
        1.0,
        "drift",
        1.0,
        prep.grid_T[:, j] - b * g.H[:, i],
        plausible,
        [prep.channels[k] for k in nb],
        ratio,
        float("nan"),
        float("nan"),
        rate_degC_per_day=b,
    )


def _steady(t: np.ndarray, Q: np.ndarray, ry: np.ndarray, t0: float, b: float) -> bool:
    """Return whether the ramp keeps its direction: fitted on each half of its span, both rates share its sign.

    An ageing junction departs steadily one way; a virtual sensor's misfit of one stage's transient
    (a fast site after the last heating, a neighbour's slow response) that a hinge happens to fit
    rises and falls back. The halves' sizes are not compared: each half is pinned far less well than
    the whole (a real 0.5 degC/day drift came out as 0.95 and 0.18 on the open world).
    """
    tm = 0.5 * (t0 + t[-1])
    h = np.column_stack([np.clip(t - t0, 0.0, tm - t0), np.maximum(t - tm, 0.0)]) / 86400.0
    Rh = h - Q @ (Q.T @ h)
    ab = np.linalg.lstsq(Rh, ry, rcond=None)[0]
    return bool(np.all(ab * b > 0))


def _resolve_mates(g: _DriftGrid, out: dict[str, FaultScan], ex_idx: set[int]) -> None:
    """Keep, of two flagged junctions that read one another, the one whose ramp survives without the other.

    Each departs from a virtual sensor built on the other by the same ramp of opposite sign. The one that
    drifts keeps its ramp when the other flagged channels leave its neighbours (it departs from the rest of
    its structure and the room air too); the healthy one loses it.
    """
    flagged = [c for c, f in out.items() if f.plausible]
    if len(flagged) < 2:
        return
    idx = {c: g.prep.channel_index(c) for c in flagged}
    again: dict[str, float] = {}
    for c in flagged:
        f = _scan_drift_channel(g, idx[c], ex_idx | {idx[o] for o in flagged if o != c})
        again[c] = f.break_ratio if f is not None else 0.0
    for c in flagged:
        mates = [o for o in flagged if o != c and (o in out[c].neighbours or c in out[o].neighbours)]
        out[c].partners = mates
        if mates and again[c] < max(again[o] for o in mates):
            out[c].plausible = False  # its partner drifts, not it (the diagnosis may overrule on the errors)


def scan_sensor_drifts(prep: PreparedBundle, exclude: set[str] | None = None) -> dict[str, FaultScan]:
    """Return a :class:`FaultScan` (``mode="drift"``) per channel: the best ramp of its virtual-sensor departure.

    ``start_s`` is where the ramp begins, ``strength`` the ramp's size at the end in degC,
    ``break_ratio`` the RSS of the virtual sensor without the ramp over the RSS with it,
    ``replaced`` the reading with the ramp removed, ``p_value`` the peer test's one-sided normal
    p-value of the log ratio among all channels. Channels in ``exclude`` (faults already found)
    are neither scanned nor used as neighbours.
    """
    exclude = exclude or set()
    n, m = prep.grid_T.shape
    if m < 3 or n < 60:
        return {}
    g = _drift_grid(prep)
    ex_idx = {prep.channel_index(c) for c in exclude if c in prep.channels}
    out: dict[str, FaultScan] = {}
    for j in range(m):
        if g.finite[j] and j not in ex_idx:
            f = _scan_drift_channel(g, j, ex_idx)
            if f is not None:
                out[prep.channels[j]] = f
    _resolve_mates(g, out, ex_idx)
    _peer_test(out)
    return out


def _peer_test(scans: dict[str, FaultScan]) -> None:
    """Set every scan's p-value: the one-sided normal p of its log ratio's robust z among all channels."""
    ratios = np.array([f.break_ratio for f in scans.values() if np.isfinite(f.break_ratio) and f.break_ratio > 0])
    if ratios.size < 5:
        return
    logs = np.log(ratios)
    med = float(np.median(logs))
    mad = max(1.4826 * float(np.median(np.abs(logs - med))), PEER_MAD_FLOOR)
    for f in scans.values():
        z = (np.log(max(f.break_ratio, 1e-300)) - med) / mad
        f.p_value = float(stats.norm.sf(z))
