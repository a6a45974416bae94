"""The effect catalogue of spec section 3: candidate regressors, their screening and parameters.

Each catalogue kind becomes one or more candidate regressors (columns added to
the current model of an (axis, term)):

- ``reversal``: the approach direction (+1/-1); magnitude = full span = 2 x coefficient (3.3, 5.5).
- ``screw_expansion``: position x dT_k (eq. 3.2 with a uniform shaft temperature; Fig. 5.14),
  plus dT_k itself when k is not in the model (so the candidate nests the model).
- ``unmapped_channel``: dT_k for a channel outside the model (4.3).
- ``thermal_lag``: a first-order lag of dT_k, L' = (dT_k - L) / tau, on a log grid of tau
  within the resolvable range; the best tau is refined by a bounded 1-D search (2.4.2, 8.3).
- ``sensor_fault``: the channel's departure from its virtual sensor (a regression on the
  other thermocouples, ch. 6.4.2/6.6) after a change point found on the temperatures alone.
- ``drift``: time in days (3.2, 6.4.3).
- ``quadratic``: dT_k^2 (6.4.2).
- ``operating_condition``: a conditions.csv column (spindle_rpm, feed_mm_min) to the power 1 or 2,
  entering the error directly (6.4.3: centrifugal spindle growth with rpm^2, feed-dependent errors).

A ``sensor_fault`` is not a candidate regressor: it is decided on the temperatures alone
(``scan_sensor_faults``) and its repair applied before the search (diagnosis.py).

Screening is one QR of the current training design and a projection of all
candidate columns at once (numpy); statsmodels is used only for the final
statistics of the candidates that pass.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from driftlab.models.standard_model import PreparedBundle, TermData, lstsq, robust_sigma
from driftlab.physics.lag import first_order_lag_even
from driftlab.vocabulary import EFFECT_KINDS

KINDS = EFFECT_KINDS  # the catalogue (driftlab.vocabulary)

#: number of log-spaced time constants screened per channel for thermal_lag
N_TAU = 16
#: candidate kinds screened as a bank of columns (one per tau or per cut), the best column kept
BANK_KINDS = frozenset({"thermal_lag", "unsensed_source", "datum_shift"})
#: at most this many cuts are screened for a datum step per term (sweep starts, evenly thinned)
MAX_CUTS = 160


# ---------------------------------------------------------------------------------------------
# first-order lag: physics.lag (the thermal network's own element, dL/dt = (T - L) / tau)


def tau_bounds(prep: PreparedBundle, td: TermData) -> tuple[float, float]:
    """Return the resolvable range of a lag time constant for ``td`` (seconds).

    Lower: a lag shorter than half the spacing of error sweeps (or 3 scans)
    cannot be told from no lag; upper: a third of the training span, beyond
    which a lag cannot be told from a drift.
    """
    dt_scan = float(prep.grid_t[1] - prep.grid_t[0]) if prep.grid_t.size > 1 else 60.0
    st = np.unique(td.t[td.train])
    spacing = float(np.median(np.diff(st))) if st.size > 2 else dt_scan
    sweeps = td.sweep[td.train]
    if sweeps.max() > 2:
        starts = np.array([td.t[td.train][sweeps == s][0] for s in np.unique(sweeps)])
        spacing = max(spacing, float(np.median(np.diff(starts))))
    lo = max(3.0 * dt_scan, 0.5 * spacing)
    span = float(td.t[td.train][-1] - td.t[0])
    return lo, max(lo * 1.5, span / 3.0)


# ---------------------------------------------------------------------------------------------
# sensor faults: virtual sensor + change point on the temperatures alone


@dataclass
class FaultScan:
    """One channel compared with its virtual sensor (the channel predicted from the others)."""

    channel: str
    start_s: float
    strength: float  # RMS departure after start_s in units of the pre-fault sigma
    persistence: float  # fraction of post-start samples beyond 3 sigma
    mode: str  # "detached" or "open"
    p_value: float  # block-mean Welch test of the departure (temperatures only)
    replaced: np.ndarray  # the channel on the grid: readings before start_s, virtual sensor after
    plausible: bool
    neighbours: list[str] = field(default_factory=list)
    break_ratio: float = float("nan")  # RSS of one virtual-sensor fit / RSS of the fits split at start_s
    toward_air: float = float("nan")  # share of the early departure pointing toward the room air
    gap_left: float = float("nan")  # |reading - air| / |virtual sensor - air| once settled (0: reads the air)
    rate_degC_per_day: float = float("nan")  # mode "drift" (sensor_drift): the reading's ramp from start_s
    partners: list[str] = field(default_factory=list)  # drift: flagged channels that read one another

    @property
    def kind(self) -> str:
        """Return the catalogue kind of this sensor finding: ``sensor_drift`` or ``sensor_fault``."""
        return "sensor_drift" if self.mode == "drift" else "sensor_fault"


def _trimmed_fit(A: np.ndarray, y: np.ndarray, rows: np.ndarray, rounds: int = 3) -> np.ndarray:
    """Return least-squares coefficients refitted after trimming >4-sigma residuals (``rounds`` times)."""
    use = rows.copy()
    beta = lstsq(A[use], y[use])
    for _ in range(rounds):
        r = y - A @ beta
        s = robust_sigma(r[use])
        if s == 0:
            break
        new = rows & (np.abs(r - np.median(r[use])) < 4.0 * s)
        if new.sum() < max(20, A.shape[1] * 3) or np.array_equal(new, use):
            break
        use = new
        beta = lstsq(A[use], y[use])
    return beta


def _cusum_start(r: np.ndarray, sigma: float, kappa: float = 4.0) -> int:
    """Return the change point of a departure from zero: argmin of cumsum(r^2 - kappa sigma^2)."""
    c = np.cumsum(r * r - kappa * sigma * sigma)
    return int(np.argmin(np.concatenate([[0.0], c])))


def _dead_tail(raw: np.ndarray, min_len: int) -> int | None:
    """Return the first index of a missing or stuck run of readings that lasts to the end, if long enough."""
    n = raw.size
    ok = np.isfinite(raw)
    if not ok.any():
        return None
    last = int(np.flatnonzero(ok)[-1])
    if n - 1 - last >= min_len:
        return last + 1
    d = np.diff(raw[ok])
    if d.size and d[-1] == 0:
        changed = np.flatnonzero(d != 0)
        first_flat = int(np.flatnonzero(ok)[changed[-1] + 1]) if changed.size else 0
        if n - first_flat >= min_len and first_flat > 0:
            return first_flat
    return None


def best_break(
    A: np.ndarray, y: np.ndarray, lo: int, hi: int, step: int, A_post: np.ndarray | None = None
) -> tuple[int, float]:
    """Return the cut k in [lo, hi] minimising RSS([0, k)) + RSS([k, n)) of ``y ~ A``, and the ratio
    RSS(one fit) / that minimum (a least-squares structural-break estimate).

    Sums of outer products are accumulated per block of ``step`` rows, so the
    coarse search over block boundaries costs one pass; the best boundary is then
    refined row by row within one block on either side. With ``A_post`` the rows
    after the cut are fitted on those regressors instead (a detached sensor after
    it reads the air: room channels only); the ratio's one fit stays ``y ~ A``.
    """
    if A_post is not None:
        lo_k, r_pre = _break_costs(A, y, lo, hi, step)
        _, r_post = _break_costs(A_post, y, lo, hi, step)
        cost = r_pre[0] + r_post[1]
        i = int(np.argmin(cost))
        one = _break_costs(A, y, y.size, y.size, 1)[1][0][0]
        return int(lo_k[i]), one / max(float(cost[i]), 1e-300)
    return _best_break_same(A, y, lo, hi, step)


def _break_costs(
    A: np.ndarray, y: np.ndarray, lo: int, hi: int, step: int
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Return every cut in [lo, hi] (row by row) with the RSS of ``y ~ A`` before and after it (prefix sums)."""
    s = np.sqrt(np.mean(A * A, axis=0))
    A = A / np.where(s > 0, s, 1.0)
    n, p = A.shape
    ridge = 1e-9 * n * np.eye(p)
    cxx = np.concatenate([np.zeros((1, p, p)), np.cumsum(np.einsum("ni,nj->nij", A, A), axis=0)])
    cxy = np.concatenate([np.zeros((1, p)), np.cumsum(A * y[:, None], axis=0)])
    cyy = np.concatenate([[0.0], np.cumsum(y * y)])
    ks = np.arange(lo, hi + 1)

    def rss(xx: np.ndarray, xy: np.ndarray, yy: np.ndarray) -> np.ndarray:
        beta = np.linalg.solve(xx + ridge, xy[..., None])[..., 0]
        return np.maximum(yy - np.einsum("ki,ki->k", beta, xy), 0.0)

    pre = rss(cxx[ks], cxy[ks], cyy[ks])
    post = rss(cxx[-1] - cxx[ks], cxy[-1] - cxy[ks], cyy[-1] - cyy[ks])
    return ks, (pre, post)


def _best_break_same(A: np.ndarray, y: np.ndarray, lo: int, hi: int, step: int) -> tuple[int, float]:
    """Return the best cut and RSS ratio with the same regressors on both sides (block prefix sums)."""
    s = np.sqrt(np.mean(A * A, axis=0))
    A = A / np.where(s > 0, s, 1.0)
    n, p = A.shape
    ridge = 1e-9 * n * np.eye(p)
    nblk = n // step
    Ab = A[: nblk * step].reshape(nblk, step, p)
    yb = y[: nblk * step].reshape(nblk, step)
    bxx = np.concatenate([np.zeros((1, p, p)), np.cumsum(np.einsum("bsi,bsj->bij", Ab, Ab), axis=0)])
    bxy = np.concatenate([np.zeros((1, p)), np.cumsum(np.einsum("bsi,bs->bi", Ab, yb), axis=0)])
    byy = np.concatenate([[0.0], np.cumsum(np.einsum("bs,bs->b", yb, yb))])
    txx, txy, tyy = A.T @ A, A.T @ y, float(y @ y)

    def rss(xx: np.ndarray, xy: np.ndarray, yy: np.ndarray) -> np.ndarray:
        beta = np.linalg.solve(xx + ridge, xy[..., None])[..., 0]
        return np.maximum(yy - np.einsum("ki,ki->k", beta, xy), 0.0)

    def total(xx: np.ndarray, xy: np.ndarray, yy: np.ndarray) -> np.ndarray:
        return rss(xx, xy, yy) + rss(txx - xx, txy - xy, tyy - yy)

    kb = np.arange(1, nblk + 1)
    cuts = kb * step
    ok = (cuts >= lo) & (cuts <= hi)
    if not ok.any():
        return lo, 1.0
    costs = total(bxx[kb[ok]], bxy[kb[ok]], byy[kb[ok]])
    k0 = int(cuts[ok][int(np.argmin(costs))])
    a0 = max(lo, k0 - step)
    b0 = min(hi, k0 + step)
    base_b = a0 // step  # prefix sums up to the block boundary at or below a0, then row by row
    rows = A[base_b * step : b0]
    outer = np.cumsum(np.einsum("ni,nj->nij", rows, rows), axis=0)
    xy = np.cumsum(rows * y[base_b * step : b0, None], axis=0)
    yy = np.cumsum(y[base_b * step : b0] ** 2)
    ks = np.arange(a0, b0 + 1)
    off = ks - base_b * step  # number of rows past the block boundary
    pre_xx = bxx[base_b] + np.where(off[:, None, None] > 0, outer[np.maximum(off - 1, 0)], 0.0)
    pre_xy = bxy[base_b] + np.where(off[:, None] > 0, xy[np.maximum(off - 1, 0)], 0.0)
    pre_yy = byy[base_b] + np.where(off > 0, yy[np.maximum(off - 1, 0)], 0.0)
    fine = total(pre_xx, pre_xy, pre_yy)
    i = int(np.argmin(fine))
    one = float(rss(txx[None], txy[None], np.array([tyy]))[0])
    return int(ks[i]), one / max(float(fine[i]), 1e-300)


def _neighbours(prep: PreparedBundle, j: int, order: list[int], n_max: int) -> list[int]:
    """Return the channels a virtual sensor of channel j is built from (ch. 6.6: "surrounding" ones).

    The other thermocouples on the same structure and the room air when the
    bundle names structures (few regressors that share the physics extrapolate
    well); topped up with the most correlated channels to at least 4; without
    structure information, the ``n_max`` most correlated channels.
    """
    ch = prep.channels[j]
    struct = prep.structures.get(ch, "")
    if not struct:
        return order[:n_max]
    room = {prep.channel_index(c) for c in prep.room_channels}
    same = [k for k in order if prep.structures.get(prep.channels[k], "") == struct or k in room]
    extra = [k for k in order if k not in same]
    return (same + extra[: max(0, 4 - len(same))])[:n_max]


@dataclass
class _FaultGrid:
    """What every channel's fault scan shares: the temperature grid and the scan's limits (in scans)."""

    prep: PreparedBundle
    D: np.ndarray  # dT of every channel on the grid
    dt: float
    min_len: int  # a fault lasts at least 30 min
    min_pre: int  # and starts after 5 % of the campaign (at least 30 scans)
    step: int  # candidate cuts every 5 min, then refined to the scan
    room_cols: list[int]
    smooth_T: np.ndarray | None

    @property
    def n(self) -> int:
        """Return the number of grid scans."""
        return int(self.D.shape[0])


def _fault_break(g: _FaultGrid, j: int, A: np.ndarray, dead: int | None) -> tuple[int, float]:
    """Return the scan where channel ``j``'s relation to its neighbours ``A`` breaks, and the RSS ratio of the split.

    A run of missing or stuck readings to the end (``dead``) fixes the start exactly; otherwise the
    least-squares break, also with room air alone after the cut (a detached junction becomes an air
    thermometer).
    """
    n, y = g.n, g.D[:, j]
    if dead is not None:
        return dead, float("inf")
    start, ratio = best_break(A, y, g.min_pre, n - g.min_len, g.step)
    if g.room_cols and j not in g.room_cols:
        A_air = np.column_stack([np.ones(n), g.D[:, g.room_cols]])
        k_air, r_air = best_break(A, y, g.min_pre, n - g.min_len, g.step, A_post=A_air)
        if r_air > ratio:
            start, ratio = k_air, r_air
    return start, ratio


def _toward_air(g: _FaultGrid, j: int, est: np.ndarray, start: int, m_early: int) -> tuple[float, float]:
    """Return the share of the early window that departs toward the room air, and the gap left to it once settled.

    A junction that came loose reads the air: its departure from the virtual sensor ``est`` points
    toward the room temperature, and once settled it has closed at least half the gap between its
    structure (the virtual sensor) and the air (judged on the early window after 30 min; a healthy site
    whose relation to its neighbours changes at a stage change moves with its structure instead).
    """
    T = g.prep.grid_T
    air = np.mean(T[:, g.room_cols], axis=1)
    w = slice(start, start + m_early)
    toward = np.sign(T[w, j] - est[w]) == np.sign(air[w] - est[w])
    toward_air = float(np.mean(toward)) if m_early else 0.0
    if not m_early:
        return toward_air, float("inf")
    settled = slice(start + min(max(1, int(1800.0 / g.dt)), m_early // 2), start + m_early)
    gap_est = float(np.median(np.abs(est[settled] - air[settled])))
    return toward_air, float(np.median(np.abs(T[settled, j] - air[settled]))) / max(gap_est, 1e-9)


def _departure_p(g: _FaultGrid, r: np.ndarray, start: int, dead: int | None) -> float:
    """Return the p-value that the departure grows after ``start`` (0 for a dead card: an observation).

    One-sided Welch test on the log mean square of the departure in 30-min blocks (blocks tame the
    autocorrelation of temperatures; the square catches a departure of either sign, e.g. a held reading
    the structure warms past and cools back through, whose mean can be near zero).
    """
    if dead is not None:
        # no reading, or one stuck value, from start to the end for at least 30 min: the card says
        # so itself; this is an observation, not a statistical inference on the departure
        return 0.0
    blk = max(1, int(1800.0 / g.dt))
    pre_b = np.log(_block_means(r[:start] ** 2, blk) + 1e-12)
    post_b = np.log(_block_means(r[start:] ** 2, blk) + 1e-12)
    if pre_b.size >= 2 and post_b.size >= 2 and np.ptp(np.concatenate([pre_b, post_b])) > 0:
        p = float(stats.ttest_ind(post_b, pre_b, equal_var=False, alternative="greater").pvalue)
        return p if np.isfinite(p) else 1.0
    return 1.0


def _scan_fault_channel(g: _FaultGrid, j: int, nb: list[int]) -> FaultScan:
    """Return the fault scan of channel ``j`` against its virtual sensor on the neighbours ``nb``."""
    prep, n, dt, T = g.prep, g.n, g.dt, g.prep.grid_T
    A = np.column_stack([np.ones(n), g.D[:, nb]])
    y = g.D[:, j]
    dead = _dead_tail(prep.raw_grid_T[:, j], g.min_len)
    start, ratio = _fault_break(g, j, A, dead)
    rows = np.arange(n) < start
    beta = _trimmed_fit(A, y, rows)
    r = y - A @ beta
    sigma = max(robust_sigma(r[:start]), 1e-6)
    if dead is None:
        # a detached sensor departs gradually: the break lands where the departure is already
        # large, so walk back to where it began (last sample within 2 sigma of the sensor)
        k = start
        while k > g.min_pre and abs(r[k - 1]) > 2.0 * sigma and np.sign(r[k - 1]) == np.sign(r[start]):
            k -= 1
        start = k
    rpost = r[start:]
    strength = float(np.sqrt(np.mean(rpost * rpost)) / sigma) if rpost.size else 0.0
    # persistence is judged on the first hours after the start: a detached junction reads the
    # air, and agrees with its structure again whenever the structure cools to the air (a night)
    early = rpost[: max(g.min_len, int(7200.0 / dt))]
    persistence = float(np.mean(np.abs(early) > 3 * sigma)) if early.size else 0.0
    toward_air, gap_left = 1.0, 0.0
    if dead is None and g.room_cols and j not in g.room_cols:
        toward_air, gap_left = _toward_air(g, j, T[0, j] + A @ beta, start, early.size)
    plausible = (
        rpost.size >= g.min_len
        and start >= g.min_pre
        and (
            dead is not None
            or (ratio > 10.0 and strength > 5.0 and persistence > 0.6 and toward_air > 0.6 and gap_left < 0.5)
        )
    )
    if g.smooth_T is not None:
        Ds = g.smooth_T - g.smooth_T[0]
        A_s = np.column_stack([np.ones(n), Ds[:, nb]])
        virtual = T[0, j] + A_s @ _trimmed_fit(A_s, Ds[:, j], rows)
    else:
        virtual = T[0, j] + A @ beta
    replaced = T[:, j].copy()
    replaced[start:] = virtual[start:]
    return FaultScan(
        prep.channels[j],
        float(prep.grid_t[min(start, n - 1)]),
        strength,
        persistence,
        "open" if dead is not None else "detached",
        _departure_p(g, r, start, dead),
        replaced,
        bool(plausible),
        [prep.channels[k] for k in nb],
        ratio,
        toward_air,
        gap_left,
    )


def scan_sensor_faults(
    prep: PreparedBundle, n_neighbours: int = 16, smooth_T: np.ndarray | None = None
) -> dict[str, FaultScan]:
    """Return a :class:`FaultScan` for every channel (two passes: faulty channels leave the neighbourhoods).

    The virtual sensor of channel j is a least-squares fit of its dT on the dT of
    its surrounding channels (``_neighbours``, ch. 6.6). A loose or broken
    thermocouple is a structural break in that relation, so the change point is
    the cut that minimises the summed RSS of separate fits before and after it
    (a least-squares break estimate, evaluated for every cut at once with prefix
    sums). A run of missing or stuck readings to the end fixes the start
    exactly (mode ``open``: a broken lead); otherwise the mode is ``detached``.
    The virtual sensor is then learnt on the readings before the start and
    replaces the channel after it. Plausible faults last at least 30 min, split
    the relation decisively (single-fit RSS > 10x the split RSS), and depart from
    the virtual sensor by more than 5 sigma RMS, beyond 3 sigma for 60 % of the first
    2 h after the start (a detached junction agrees with its structure again whenever the
    structure cools to the air). With ``smooth_T`` (the denoised readings on the same
    grid) the replacement is the virtual sensor learnt and evaluated on denoised
    neighbours: a regression on 16 noisy channels would add their scan noise to it.
    """
    T = prep.grid_T
    t = prep.grid_t
    n, m = T.shape
    finite = np.all(np.isfinite(T), axis=0) & (np.ptp(np.nan_to_num(T), axis=0) > 0)
    if m < 3 or n < 60:
        return {}
    dt = float(t[1] - t[0])
    D = T - T[0]
    room_cols = [prep.channel_index(c) for c in prep.room_channels if finite[prep.channel_index(c)]]
    g = _FaultGrid(
        prep, D, dt, max(10, int(1800.0 / dt)), max(30, int(0.05 * n)), max(1, int(300.0 / dt)), room_cols, smooth_T
    )
    with np.errstate(all="ignore"):  # channels without readings have no correlation (NaN -> 0)
        corr = np.nan_to_num(np.corrcoef(np.where(finite, D, 0.0).T))
    excluded: set[int] = set()
    out: dict[str, FaultScan] = {}
    for _pass in range(2):
        for j in range(m):
            if not finite[j]:
                continue
            order = [k for k in np.argsort(-np.abs(corr[j])) if k != j and finite[k] and k not in excluded]
            nb = _neighbours(prep, j, order, n_neighbours)
            if not nb or n - g.min_len <= g.min_pre:
                continue
            out[prep.channels[j]] = _scan_fault_channel(g, j, nb)
        excluded = {prep.channel_index(c) for c, f in out.items() if f.plausible}
        if not excluded:
            break
    _peer_test(out)
    return out


def _peer_test(scans: dict[str, FaultScan]) -> None:
    """Hold every detached-fault candidate to its peers: its break must stand out among all channels'.

    Every channel's virtual-sensor relation, split at its own best break, fits better on the two
    sides (the relation between sites changes with the heat sources, and the break is chosen to
    make the most of it), so the break ratio of a healthy channel is not 1 and the block test on
    the departure, taken after choosing the cut, is optimistic. A loose thermocouple breaks its
    relation far more than its peers do: the robust z of its log break ratio among all channels
    (median, 1.4826 MAD) gives a one-sided normal p-value, and the fault's temperature p-value
    becomes the larger of that and the block test. A dead tail (no or stuck readings to the
    end) is its own evidence and is left as it is.
    """
    ratios = np.array([f.break_ratio for f in scans.values() if np.isfinite(f.break_ratio) and f.break_ratio > 0])
    if ratios.size < 5:
        return
    logs = np.log(ratios)
    med = float(np.median(logs))
    mad = max(1.4826 * float(np.median(np.abs(logs - med))), 1e-6)
    for f in scans.values():
        if f.mode == "detached":
            z = (np.log(max(f.break_ratio, 1e-300)) - med) / mad if np.isfinite(f.break_ratio) else -np.inf
            f.p_value = max(f.p_value, float(stats.norm.sf(z)))


def _block_means(x: np.ndarray, blk: int) -> np.ndarray:
    """Return the means of consecutive blocks of ``blk`` samples (last partial block dropped)."""
    nb = x.size // blk
    return x[: nb * blk].reshape(nb, blk).mean(axis=1) if nb else np.empty(0)


# ---------------------------------------------------------------------------------------------
# candidates


@dataclass
class Candidate:
    """One regressor set that an effect of the catalogue would add to an (axis, term) model."""

    kind: str
    channels: list[str]
    cols: np.ndarray  # (n, k) added columns in physical units
    names: list[str]
    hint: dict[str, Any] = field(default_factory=dict)  # tau_s, start_s, mode ...
    replace: list[tuple[str, np.ndarray]] | None = None  # sensor_fault: (channel, replacement dT column)
    family_size: int = 1  # hypotheses this candidate stands for (tau grid points)
    label: str = ""  # what tells apart candidates of one kind without channels (operating_condition)

    @property
    def key(self) -> tuple[str, tuple[str, ...]]:
        """Return (kind, channels) - or (kind, (label,)) - : what makes two candidates the same effect."""
        return self.kind, (self.label,) if self.label else tuple(self.channels)


@dataclass
class TermContext:
    """What the candidate builders need about one (axis, term): data, lags and the current model."""

    prep: PreparedBundle
    td: TermData
    model_channels: list[str]  # channels whose dT is in the current design
    chan_cols: dict[str, np.ndarray]  # dT column of every usable channel at the error times
    lag_cache: dict[str, tuple[np.ndarray, np.ndarray]]  # channel -> (taus, (n, n_tau) lagged dT)
    faults: dict[str, FaultScan]
    taken: set[tuple[str, tuple[str, ...]]]
    sources: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    # unsensed heat inputs: source -> (taus, (n, n_tau) lagged schedule at the error times, schedule on the grid)


def build_context(
    prep: PreparedBundle,
    td: TermData,
    model_channels: list[str],
    faults: dict[str, FaultScan],
    lag_bank: dict[str, np.ndarray] | None,
    taus: np.ndarray | None,
) -> TermContext:
    """Return the :class:`TermContext` of ``td`` with dT columns and lag banks at its error times."""
    chan_cols: dict[str, np.ndarray] = {}
    for j, ch in enumerate(prep.channels):
        col = td.temps[:, j]
        if np.all(np.isfinite(col)) and np.ptp(col) > 0:
            chan_cols[ch] = col - col[0]
    lag_cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if lag_bank is not None and taus is not None and taus.size:
        # the points of a sweep share their time: interpolate at the distinct times only
        ut, inverse = np.unique(td.t, return_inverse=True)
        g = prep.grid_t
        hi = np.clip(np.searchsorted(g, ut), 1, g.size - 1)  # linear interpolation weights, shared by all banks
        lo = hi - 1
        w = np.clip((ut - g[lo]) / np.where(g[hi] > g[lo], g[hi] - g[lo], 1.0), 0.0, 1.0)[:, None]
        for ch, bank in lag_bank.items():
            if ch not in chan_cols:
                continue
            at = (bank[lo] * (1.0 - w) + bank[hi] * w)[inverse]
            lag_cache[ch] = (taus, at - at[0])
    sources: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    if taus is not None and taus.size and lag_bank is not None:
        for name, (sched, sbank) in source_banks(prep, taus).items():
            at = np.column_stack([np.interp(td.t, prep.grid_t, sbank[:, i]) for i in range(taus.size)])
            if np.ptp(at[td.train]) > 0:
                sources[name] = (taus, at, sched)
    return TermContext(prep, td, list(model_channels), chan_cols, lag_cache, faults, set(), sources)


_SOURCE_CACHE: dict[int, tuple[Any, np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]] = {}


def source_schedules(prep: PreparedBundle) -> dict[str, np.ndarray]:
    """Return the heat inputs no thermocouple need read, on the temperature grid (spec 3, ``unsensed_source``).

    Each distinct ``heat_source`` of the campaign's stages (other than none/off) as its on/off
    schedule (1 while a stage of that source runs), and each conditions.csv column (spindle_rpm,
    feed_mm_min) scaled to its largest value (a state log: held between rows).
    """
    g = prep.grid_t
    out: dict[str, np.ndarray] = {}
    for st in prep.stages:
        src = str(st.get("heat_source") or "").strip()
        if not src or src.lower() in ("none", "off", "rest"):
            continue
        x = out.setdefault(f"stage:{src}", np.zeros(g.size))
        x[(g >= float(st.get("start_s", 0.0))) & (g < float(st.get("end_s", 0.0)))] = 1.0
    for name, v in prep.conditions_grid.items():
        top = float(np.nanmax(np.abs(v))) if v.size else 0.0
        if top > 0 and np.all(np.isfinite(v)):
            out[f"conditions:{name}"] = v / top
    return {k: v for k, v in out.items() if np.ptp(v) > 0}


def source_banks(prep: PreparedBundle, taus: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Return, per heat input of ``source_schedules``, (schedule, (n_grid, n_tau) first-order lags of it)."""
    key = id(prep)
    hit = _SOURCE_CACHE.get(key)
    if hit is not None and hit[0] is prep and np.array_equal(hit[1], taus):
        return hit[2]
    dt = float(prep.grid_t[1] - prep.grid_t[0]) if prep.grid_t.size > 1 else 60.0
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, x in source_schedules(prep).items():
        bank = np.column_stack([first_order_lag_even(x, dt, float(tau)) for tau in taus])
        out[name] = (x, bank)
    _SOURCE_CACHE.clear()
    _SOURCE_CACHE[key] = (prep, taus.copy(), out)
    return out


def lag_bank_for(prep: PreparedBundle, channels: list[str], taus: np.ndarray) -> dict[str, np.ndarray]:
    """Return, per channel, the (n_grid, n_tau) lagged temperatures on the uniform grid (one pass per tau)."""
    if not channels or taus.size == 0 or prep.grid_t.size < 3:
        return {}
    dt = float(prep.grid_t[1] - prep.grid_t[0])
    idx = [prep.channel_index(c) for c in channels]
    X = prep.grid_T[:, idx]
    bank = np.empty((X.shape[0], len(idx), taus.size))
    for i, tau in enumerate(taus):
        bank[:, :, i] = first_order_lag_even(X, dt, float(tau))
    return {c: bank[:, k, :] for k, c in enumerate(channels)}


def _fault_candidate(ctx: TermContext, scans: list[FaultScan]) -> Candidate:
    """Return the sensor_fault candidate of one or more faulty channels (earliest start first)."""
    td = ctx.td
    scans = sorted(scans, key=lambda f: f.start_s)
    cols, names, reps = [], [], []
    for fs in scans:
        rep = np.interp(td.t, ctx.prep.grid_t, fs.replaced)
        rep = rep - rep[0]
        cols.append(rep - ctx.chan_cols[fs.channel])
        names.append(f"fault_{fs.channel}")
        reps.append((fs.channel, rep))
    hint: dict[str, Any] = {
        "start_s": scans[0].start_s,
        "mode": scans[0].mode,
        "rate_degC_per_day": scans[0].rate_degC_per_day,
        "p_temp": min(1.0, min(f.p_value for f in scans) * len(scans)),
    }
    if len(scans) > 1:
        hint["start_s_by_channel"] = {f.channel: f.start_s for f in scans}
        hint["mode_by_channel"] = {f.channel: f.mode for f in scans}
    if len(scans) > 1 and scans[0].mode == "drift":
        hint["rate_degC_per_day_by_channel"] = {f.channel: f.rate_degC_per_day for f in scans}
    return Candidate(scans[0].kind, [f.channel for f in scans], np.column_stack(cols), names, hint, replace=reps)


#: the power of a machine-state column's direct effect in the catalogue's physical story (spec section 3,
#: ``operating_condition``: centrifugal spindle growth with rpm^2, a feed-dependent following error)
PHYSICAL_POWER = {"spindle_rpm": 2, "feed_mm_min": 1}


def _plain_candidates(ctx: TermContext, n_dirs: int) -> list[Candidate]:
    """Return the candidates that hold no temperature: reversal, drift, stated re-zeros and the step bank."""
    td = ctx.td
    out: list[Candidate] = []
    if n_dirs > 1 and ("reversal", ()) not in ctx.taken:
        out.append(Candidate("reversal", [], td.direction[:, None].astype(float), ["direction"]))
    if ("drift", ()) not in ctx.taken:
        days = (td.t - td.t[0]) / 86400.0
        out.append(Candidate("drift", [], days[:, None], ["time_days"]))
    # the re-zero moments a bundle v2 states (a new session of a setup zeroed when mounted): one hypothesis each
    tr_t = td.t[td.train]
    for t0 in td.datum_times:
        label = f"stated@{t0:.0f}"
        n_before = int(np.sum(tr_t < t0))
        if ("datum_shift", (label,)) in ctx.taken or n_before < 3 or tr_t.size - n_before < 3:
            continue
        col = (td.t >= t0).astype(float)[:, None]
        out.append(
            Candidate("datum_shift", [], col, ["datum_step"], {"time_s": float(t0), "stated": True}, label=label)
        )
    steps = step_bank(td)
    if steps is not None and ("datum_shift", ()) not in ctx.taken:
        cuts, bank = steps
        out.append(Candidate("datum_shift", [], bank, ["datum_step"], {"cuts": cuts}, family_size=int(cuts.size)))
    return out


def _channel_candidates(ctx: TermContext, n_dirs: int, n_pos: int) -> list[Candidate]:
    """Return the candidates built from each channel's dT: screw, unmapped channel, square, direction x dT."""
    td = ctx.td
    out: list[Candidate] = []
    for ch, col in ctx.chan_cols.items():
        in_model = ch in ctx.model_channels
        if n_pos > 1 and ("screw_expansion", (ch,)) not in ctx.taken:
            cols = [td.pos * col] + ([] if in_model else [col])
            names = [f"position*dT_{ch}"] + ([] if in_model else [f"dT_{ch}"])
            out.append(Candidate("screw_expansion", [ch], np.column_stack(cols), names))
        if not in_model and ("unmapped_channel", (ch,)) not in ctx.taken:
            out.append(Candidate("unmapped_channel", [ch], col[:, None], [f"dT_{ch}"]))
        if in_model and ("quadratic", (ch,)) not in ctx.taken:
            out.append(Candidate("quadratic", [ch], (col * col)[:, None], [f"dT_{ch}^2"]))
        if n_dirs > 1 and in_model and ("direction_thermal", (ch,)) not in ctx.taken:
            # a reversal that opens as a nut or guide warms (3.3 with 3.5): direction x dT, with the plain
            # direction when no reversal is in the model yet (the candidate nests it)
            d = td.direction.astype(float)
            plain = ("reversal", ()) not in ctx.taken
            cols_dt = [d * col] + ([d] if plain else [])
            names_dt = [f"direction*dT_{ch}"] + (["direction"] if plain else [])
            out.append(Candidate("direction_thermal", [ch], np.column_stack(cols_dt), names_dt))
    return out


def _condition_candidates(ctx: TermContext) -> list[Candidate]:
    """Return the machine state, directly: a column of conditions.csv to the power 1 or 2 (6.4.3)."""
    td = ctx.td
    out: list[Candidate] = []
    for name, v in td.conditions.items():
        # a column with two values in the training rows (off and one speed) gives rpm^2 = c rpm: one law, whose
        # power the data cannot tell; the catalogue's physical story names it (spec 3: centrifugal growth with
        # rpm^2, a following error with the feed)
        two_valued = np.unique(v[td.train][np.isfinite(v[td.train])]).size <= 2
        for power in (1, 2):
            if two_valued and power != PHYSICAL_POWER.get(name, 1):
                continue
            label = f"{name}^{power}"
            x = v**power
            if ("operating_condition", (label,)) in ctx.taken or np.ptp(x[td.train]) == 0:
                continue
            hint = {"column": name, "power": power}
            out.append(Candidate("operating_condition", [], x[:, None].astype(float), [label], hint, label=label))
    return out


def _lag_candidates(ctx: TermContext) -> list[Candidate]:
    """Return the lag banks: each stated heat input's (unsensed_source) and each channel's (thermal_lag)."""
    out: list[Candidate] = []
    for name, (taus, at, _sched) in ctx.sources.items():
        if ("unsensed_source", (name,)) in ctx.taken:
            continue
        hint_s = {"taus": taus, "source": name}
        out.append(
            Candidate(
                "unsensed_source", [], at - at[0], [f"lag_{name}"], hint_s, family_size=int(taus.size), label=name
            )
        )
    for ch, (taus, at) in ctx.lag_cache.items():
        if ("thermal_lag", (ch,)) in ctx.taken:
            continue
        hint: dict[str, Any] = {"taus": taus}
        if ch not in ctx.model_channels and ch in ctx.chan_cols:
            hint["with"] = ctx.chan_cols[ch]  # scored together with the channel's own dT
        out.append(Candidate("thermal_lag", [ch], at, [f"lag_{ch}"], hint, family_size=int(taus.size)))
    return out


def build_candidates(ctx: TermContext) -> list[Candidate]:
    """Return every catalogue candidate for the current model of ``ctx`` (kinds not yet taken)."""
    td = ctx.td
    n_dirs = np.unique(td.direction[td.train]).size
    n_pos = np.unique(np.round(td.pos[td.train], 9)).size
    return [
        *_plain_candidates(ctx, n_dirs),
        *_channel_candidates(ctx, n_dirs, n_pos),
        *_condition_candidates(ctx),
        *_lag_candidates(ctx),
    ]


# ---------------------------------------------------------------------------------------------
# screening


@dataclass
class Scored:
    """A candidate with its naive nested-model F test on the training rows."""

    cand: Candidate
    F: float
    p_value: float
    df_num: int
    df_den: int
    rss_drop: float
    col_index: int = 0  # which column of a bank (thermal_lag: the best tau on the grid)


@dataclass
class _Bank:
    """Every candidate column of a term at once, projected on the current model (``screen``).

    ``big``: the training rows of the columns, side by side (``edges`` per candidate); ``scale``: 1 / their
    RMS; ``G``: Q'C and ``big_y``: C'ry of the unit-RMS columns; ``big_n2``: |C - Q Q'C|^2.
    """

    cands: list[Candidate]
    edges: np.ndarray
    big: np.ndarray
    scale: np.ndarray
    G: np.ndarray
    big_y: np.ndarray
    big_n2: np.ndarray


def _finite_bank(cands: list[Candidate], rows: slice | np.ndarray) -> tuple[list[Candidate], np.ndarray, np.ndarray]:
    """Return the candidates whose columns are finite on the training rows, their columns and column edges."""
    widths = [c.cols.shape[1] for c in cands]
    edges = np.concatenate([[0], np.cumsum(widths)])
    big = np.concatenate([c.cols[rows] for c in cands], axis=1)
    col_ok = np.all(np.isfinite(big), axis=0)
    finite = [c for ci, c in enumerate(cands) if col_ok[edges[ci] : edges[ci + 1]].all()]
    if len(finite) < len(cands):
        keep_cols = np.concatenate(
            [
                np.arange(edges[ci], edges[ci + 1])
                for ci, c in enumerate(cands)
                if col_ok[edges[ci] : edges[ci + 1]].all()
            ]
            or [np.zeros(0, dtype=int)]
        )
        big = big[:, keep_cols]
        widths = [c.cols.shape[1] for c in finite]
        edges = np.concatenate([[0], np.cumsum(widths)])
    return finite, big, edges


def _bank_drop(
    bk: _Bank, ci: int, Q: np.ndarray, ry: np.ndarray, with_col: np.ndarray | None
) -> tuple[float, int, int] | None:
    """Return the best RSS drop of a bank candidate (one column per tau or cut), its column and its width.

    With ``with_col`` (a channel outside the model, scored with its own dT) two columns per tau,
    [lag_tau, dT]: closed-form 2x2 least squares for every tau. None: no column adds anything.
    """
    sl = slice(bk.edges[ci], bk.edges[ci + 1])
    norm2 = bk.big_n2[sl]
    ok = norm2 > 1e-10 * bk.big.shape[0]
    if with_col is None:
        drops = np.where(ok, bk.big_y[sl] ** 2 / np.maximum(norm2, 1e-300), -1.0)
        k = 1
    else:
        w = with_col / max(float(np.sqrt(np.mean(with_col * with_col))), 1e-300)
        rw = w - Q @ (Q.T @ w)
        ww, wy = float(rw @ rw), float(rw @ ry)
        bw = (bk.big[:, sl].T @ rw) * bk.scale[sl]
        by = bk.big_y[sl]
        det = norm2 * ww - bw * bw
        good = ok & (det > 1e-10 * np.maximum(norm2 * ww, 1e-300))
        drops = np.where(good, (ww * by * by - 2 * bw * by * wy + norm2 * wy * wy) / np.where(good, det, 1.0), -1.0)
        k = 2
    i = int(np.argmax(drops))
    return None if drops[i] <= 0 else (float(drops[i]), i, k)


def _set_drop(bk: _Bank, ci: int, Q: np.ndarray, ry: np.ndarray) -> tuple[float, int, int] | None:
    """Return the RSS drop of a candidate's columns together, 0, and its width (None: collinear with the model)."""
    sl = slice(bk.edges[ci], bk.edges[ci + 1])
    norm2 = bk.big_n2[sl]
    if np.any(norm2 <= 1e-10 * bk.big.shape[0]):
        return None  # collinear with the model: nothing new
    width = bk.edges[ci + 1] - bk.edges[ci]
    if width == 1:
        return float(bk.big_y[sl][0] ** 2 / norm2[0]), 0, 1
    RC = bk.big[:, sl] * bk.scale[sl] - Q @ bk.G[sl].T
    b, *_ = np.linalg.lstsq(RC, ry, rcond=None)
    fitted = RC @ b
    return float(fitted @ fitted), 0, width


def screen(X: np.ndarray, y: np.ndarray, train: np.ndarray, cands: list[Candidate]) -> list[Scored]:
    """Return the nested F test of every candidate against ``y ~ X`` on the training rows (one QR)."""
    Xt = X[train]
    s = np.sqrt(np.mean(Xt * Xt, axis=0))
    s = np.where(s > 0, s, 1.0)
    Q, R = np.linalg.qr(Xt / s)
    keep = np.abs(np.diag(R)) > 1e-10 * np.abs(np.diag(R)).max()
    Q = Q[:, keep]
    yt = y[train]
    ry = yt - Q @ (Q.T @ yt)
    rss = float(ry @ ry)
    n, p = yt.size, Q.shape[1]
    out: list[Scored] = []
    # every candidate column at once: one projection for the whole catalogue of this term
    n_tr = int(train.sum())
    rows = slice(0, n_tr) if train[:n_tr].all() else train  # training rows are the first ones: views
    if not cands:
        return out
    finite, big, edges = _finite_bank(cands, rows)
    if not finite:
        return out
    # the columns' parts outside the model, without forming them (the candidate bank is the largest array
    # here): with unit-RMS columns C and ry, rw orthogonal to Q, (C - Q Q'C)' ry = C' ry and
    # |C - Q Q'C|^2 = |C|^2 - |Q'C|^2 - one pass over the bank for its squares, one product with [Q, ry]
    nrow = big.shape[0]
    scale = 1.0 / np.maximum(np.sqrt(np.einsum("ij,ij->j", big, big) / nrow), 1e-300)
    prod = (big.T @ np.column_stack([Q, ry])) * scale[:, None]  # rows: columns of the bank, unit RMS
    G = prod[:, :-1]
    big_n2 = np.maximum(nrow - np.einsum("ij,ij->i", G, G), 0.0) * (np.isfinite(scale) & (scale < 1e300))
    bk = _Bank(finite, edges, big, scale, G, prod[:, -1], big_n2)
    for ci, c in enumerate(finite):
        if c.kind in BANK_KINDS:  # a bank: one column per tau (or cut), score each, keep the best
            with_col = c.hint.get("with")
            got = _bank_drop(bk, ci, Q, ry, None if with_col is None else with_col[train])
        else:
            got = _set_drop(bk, ci, Q, ry)
        if got is None:
            continue
        drop, col_index, k = got
        dof = n - p - k
        if dof <= 0 or rss <= 0:
            continue
        F = (drop / k) / max((rss - drop) / dof, 1e-300)
        out.append(Scored(c, float(F), float(stats.f.sf(F, k, dof)), k, dof, drop, col_index))
    return out


def step_bank(td: TermData) -> tuple[np.ndarray, np.ndarray] | None:
    """Return the candidate cuts of a datum step (sweep starts inside the training part) and their step columns.

    A step between two sweeps: 0 before the cut, 1 from it on. Cuts leave at least two sweeps and
    8 readings on either side inside the training part; at most ``MAX_CUTS``, evenly thinned.
    """
    tr = td.train
    sw = td.sweep[tr]
    t = td.t[tr]
    _, first = np.unique(sw, return_index=True)
    starts = np.sort(t[first])
    if starts.size < 6:
        return None
    cand = starts[2:-2]
    n_before = np.searchsorted(t, cand, side="left")
    ok = (n_before >= 8) & (t.size - n_before >= 8)
    cand = cand[ok]
    if cand.size == 0:
        return None
    if cand.size > MAX_CUTS:
        cand = cand[np.unique(np.linspace(0, cand.size - 1, MAX_CUTS).round().astype(int))]
    bank = (td.t[:, None] >= cand[None, :]).astype(float)
    return cand, bank


def _search_tau(
    td: TermData, X: np.ndarray, taus: np.ndarray, i_best: int, column: Callable[[float], np.ndarray]
) -> tuple[float, np.ndarray]:
    """Return the tau (s) minimising the training RSS of ``X`` + ``column(log tau)``, and its columns.

    A bounded 1-D search (scipy) on log tau between the grid neighbours of the best grid point,
    kept only where it beats that grid point.
    """
    tr = td.train

    def rss(log_tau: float) -> float:
        A = np.column_stack([X, column(log_tau)])
        b = lstsq(A[tr], td.y[tr])
        r = td.y[tr] - A[tr] @ b
        return float(r @ r)

    lo = np.log(taus[max(i_best - 1, 0)])
    hi = np.log(taus[min(i_best + 1, taus.size - 1)])
    if hi <= lo:
        return float(taus[i_best]), column(np.log(taus[i_best]))
    res = optimize.minimize_scalar(rss, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3})
    best = float(res.x) if rss(float(res.x)) <= rss(np.log(taus[i_best])) else float(np.log(taus[i_best]))
    return float(np.exp(best)), column(best)


def refine_source_tau(ctx: TermContext, name: str, i_best: int, X: np.ndarray) -> tuple[float, np.ndarray]:
    """Return the tau (s) minimising the training RSS of ``X`` + lag(source schedule, tau), and its column."""
    td, prep = ctx.td, ctx.prep
    taus, _, sched = ctx.sources[name]
    dt = float(prep.grid_t[1] - prep.grid_t[0])

    def column(log_tau: float) -> np.ndarray:
        g = first_order_lag_even(sched, dt, float(np.exp(log_tau)))
        at = np.interp(td.t, prep.grid_t, g)
        return (at - at[0])[:, None]

    return _search_tau(td, X, taus, i_best, column)


def refine_tau(
    ctx: TermContext, channel: str, i_best: int, X: np.ndarray, extra: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """Return the tau (s) minimising the training RSS of ``X`` + lag(dT_channel, tau) and its columns.

    The columns are the lag of dT started at rest on the first scan and
    exp(-(t - t_first scan) / tau): the body's unknown initial departure from its
    thermocouple decays with the same time constant (a machine is rarely at
    rest when a campaign starts). A bounded 1-D search (scipy) on log tau
    between the grid neighbours of the best grid point.
    """
    td, prep = ctx.td, ctx.prep
    taus, _ = ctx.lag_cache[channel]
    j = prep.channel_index(channel)
    dt = float(prep.grid_t[1] - prep.grid_t[0])
    x = prep.grid_T[:, j]

    def column(log_tau: float) -> np.ndarray:
        tau = float(np.exp(log_tau))
        g = first_order_lag_even(x, dt, tau)
        at = np.interp(td.t, prep.grid_t, g)
        return np.column_stack([at - at[0], np.exp(-(td.t - prep.grid_t[0]) / tau)])

    base = X if extra is None else np.column_stack([X, extra])  # ``extra`` enters every fit of the search

    return _search_tau(td, base, taus, i_best, column)


def lag_columns(ctx: TermContext, channel: str, tau_s: float) -> np.ndarray:
    """Return the two thermal_lag columns of ``channel`` at ``tau_s``: lag of dT and exp(-(t - t_0)/tau)."""
    td, prep = ctx.td, ctx.prep
    j = prep.channel_index(channel)
    dt = float(prep.grid_t[1] - prep.grid_t[0])
    g = first_order_lag_even(prep.grid_T[:, j], dt, float(tau_s))
    at = np.interp(td.t, prep.grid_t, g)
    return np.column_stack([at - at[0], np.exp(-(td.t - prep.grid_t[0]) / float(tau_s))])


def columns_like(cand: Candidate, hint: dict[str, Any], ctx: TermContext) -> np.ndarray | None:
    """Return the columns ``cand`` (found in another view of the same term) adds in ``ctx``'s view.

    Used to hold a candidate found on the readings to the denoised readings too;
    ``None`` for a sensor fault (a repair, tested on the readings) or an unusable channel.
    """
    td = ctx.td
    k = cand.kind
    if k in ("reversal", "drift", "operating_condition"):
        return cand.cols
    if k == "sensor_fault" or not cand.channels:
        return None
    ch = cand.channels[0]
    col = ctx.chan_cols.get(ch)
    if col is None:
        return None
    in_model = ch in ctx.model_channels
    if k == "screw_expansion":
        return np.column_stack([td.pos * col] + ([] if in_model else [col]))
    if k == "unmapped_channel":
        return col[:, None]
    if k == "quadratic":
        return (col * col)[:, None]
    if k == "thermal_lag":
        cols = lag_columns(ctx, ch, float(hint["tau_s"]))
        return cols if in_model else np.column_stack([cols, col])
    if k == "direction_thermal":
        d = td.direction.astype(float)
        return np.column_stack([d * col] + ([d] if cand.cols.shape[1] > 1 else []))
    return None
