"""The standard model of bundle v1 (spec section 2) and the metrology-grade data preparation under it.

Data preparation (done once per bundle, shared by every (axis, term)):

- temperatures: readings outside a physical range are treated as missing
  (an open thermocouple card reports a rail value); isolated spikes are
  rejected with a rolling-median / MAD test; gaps up to ``max_gap_s`` are
  interpolated linearly; longer gaps hold the last valid reading (what a
  controller does with a dead channel) and are counted in the flags;
  everything is put once on a uniform scan grid;
- errors: NaN rows are dropped; spikes are rejected per (axis, term,
  position, direction) series with the same rolling-median / MAD test;
- the temperature matrix is interpolated once to every error sample time.

The standard model itself (spec section 2) is OLS per (axis, term) on
intercept, position, position^2, position^3 and dT_k = T_k(t) - T_k(t_first)
for the model channels of the axis, with regressors centred and scaled
(position^3 of 254 mm is 1.6e7) and coefficients reported in physical units.
Train = the rows before the time of the term's row at ``1 - holdout_fraction`` of its rows (the
split depends on the rows' times only, never on their values), score = the rest.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, TypedDict

import numpy as np
import pandas as pd
from scipy import stats
from scipy.signal import savgol_filter

from driftlab.errors import ValidationError
from driftlab.metrics import rmse
from driftlab.models.split import split_time
from driftlab.vocabulary import term_unit

#: physically possible thermocouple readings on a machine tool (degC); outside = card error value
TEMP_RANGE_C = (-40.0, 250.0)
#: robust z beyond which an isolated sample is a spike (8 MAD-sigma: ~1e-15 for Gaussian noise)
SPIKE_Z = 8.0


def meta_get(meta: object, key: str, default: Any = None) -> Any:
    """Return ``meta[key]`` whether the campaign metadata is a dict or a pydantic model."""
    if meta is None:
        return default
    if isinstance(meta, dict):
        return meta.get(key, default)
    value = getattr(meta, key, default)
    return default if value is None else value


def _as_plain(obj: Any) -> Any:
    """Return pydantic models / nested objects as plain dicts and lists."""
    if hasattr(obj, "model_dump"):
        return obj.model_dump()
    if isinstance(obj, dict):
        return {k: _as_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_as_plain(v) for v in obj]
    return obj


class OutlierFlagsRecord(TypedDict):
    """The JSON form of :class:`OutlierFlags`."""

    series: str
    spikes: int
    out_of_range: int
    held_scans: int
    first_times_s: list[float]


@dataclass(frozen=True)
class OutlierFlags:
    """What the cleaning did to one series (a channel or an (axis, term))."""

    series: str
    spikes: int
    out_of_range: int = 0
    held_scans: int = 0
    first_times_s: tuple[float, ...] = ()

    def to_dict(self) -> OutlierFlagsRecord:
        """Return the JSON form of the flags."""
        return {
            "series": self.series,
            "spikes": self.spikes,
            "out_of_range": self.out_of_range,
            "held_scans": self.held_scans,
            "first_times_s": list(self.first_times_s),
        }


def robust_sigma(x: np.ndarray) -> float:
    """Return 1.4826 MAD of ``x`` (falls back to the nonzero deviations for quantised data)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return 0.0
    dev = np.abs(x - np.median(x))
    s = 1.4826 * float(np.median(dev))
    if s == 0.0:
        nz = dev[dev > 0]
        s = 1.4826 * float(np.median(nz)) if nz.size else 0.0
    return s


def spike_mask(x: np.ndarray, z: float = SPIKE_Z) -> np.ndarray:
    """Return True where a sample is an isolated excursion: beyond ``z`` robust sigmas of both sides.

    A sample is a spike when it departs, in the same direction, from the mean of
    the two readings before it and from the mean of the two after it by more
    than ``z`` sigma, sigma being the robust scale of first differences / sqrt(2)
    (the noise of one reading). A step or a fast but lasting transient is never a
    spike (the readings after it agree with it), and the first and last two
    readings are never flagged (one side is unknown). NaNs are skipped.
    """
    x = np.asarray(x, dtype=float)
    out = np.zeros(x.shape, dtype=bool)
    idx = np.flatnonzero(np.isfinite(x))
    if idx.size < 10:
        return out
    v = x[idx]
    s = robust_sigma(np.diff(v)) / np.sqrt(2.0)
    if s == 0.0:
        return out
    left = 0.5 * (v[:-4] + v[1:-3])
    mid = v[2:-2]
    right = 0.5 * (v[3:-1] + v[4:])
    dl, dr = mid - left, mid - right
    spike = (np.sign(dl) == np.sign(dr)) & (np.abs(dl) > z * s) & (np.abs(dr) > z * s)
    out[idx[2:-2][spike]] = True
    return out


def _fill_gaps(t: np.ndarray, x: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, int]:
    """Interpolate runs of missing readings up to ``max_gap_s`` long linearly, hold the last reading across
    longer ones (the run's length counts the channel's missing scans, not time the logger wrote nothing)."""
    ok = np.isfinite(x)
    if ok.all():
        return x, 0
    if not ok.any():
        return x, 0
    tv, xv = t[ok], x[ok]
    lin = np.interp(t, tv, xv)
    idx = np.searchsorted(tv, t, side="right")
    prev_i = np.clip(idx - 1, 0, tv.size - 1)
    inside = (idx > 0) & (idx < tv.size)
    # the length of a run of missing readings is the time from its first to its last missing scan
    # (one scan interval for a single one): a scan the logger never wrote is no missing reading
    run = np.concatenate([[0], np.cumsum(np.diff(ok.astype(int)) != 0)])
    miss = ~ok
    first_t = pd.Series(np.where(miss, t, np.nan)).groupby(run).transform("min").to_numpy()
    last_t = pd.Series(np.where(miss, t, np.nan)).groupby(run).transform("max").to_numpy()
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    length = last_t - first_t + step
    short = inside & (length <= max_gap_s)
    del prev_i
    held = np.where(idx > 0, xv[np.clip(idx - 1, 0, tv.size - 1)], xv[0])  # leading gap: first valid reading
    out = np.where(ok, x, np.where(short, lin, held))
    return out, int((~ok & ~short).sum())


@dataclass
class TermData:
    """The rows of one (axis, term), sorted by time, with temperatures at the error times."""

    axis: str
    term: str
    t: np.ndarray
    pos: np.ndarray
    direction: np.ndarray
    y: np.ndarray
    temps: np.ndarray  # (n, n_channels) at the error times
    n_train: int
    sweep: np.ndarray  # sweep index of each row (consecutive rows closer than the sweep gap)
    flags: OutlierFlags
    conditions: dict[str, np.ndarray] = field(default_factory=dict)  # machine-state columns at the error times
    datum_times: np.ndarray = field(default_factory=lambda: np.empty(0))  # bundle v2: stated re-zero moments

    @property
    def unit(self) -> str:
        """Return the unit of the term's values."""
        return term_unit(self.term)

    @property
    def n(self) -> int:
        """Return the number of usable rows."""
        return int(self.t.size)

    @property
    def train(self) -> np.ndarray:
        """Return the boolean mask of the training rows (first part in time)."""
        m = np.zeros(self.n, dtype=bool)
        m[: self.n_train] = True
        return m

    @property
    def holdout_start_s(self) -> float:
        """Return the time of the first held-out row."""
        return float(self.t[self.n_train]) if self.n_train < self.n else float("nan")

    def dT(self, col: np.ndarray) -> np.ndarray:
        """Return ``col - col[first row]`` (dT relative to the first error sample, spec section 2)."""
        return col - col[0]


@dataclass
class PreparedBundle:
    """A bundle after cleaning: uniform temperature grid, per-term rows, flags and metadata."""

    name: str
    channels: list[str]
    room_channels: list[str]
    model_channels: dict[str, list[str]]
    stages: list[dict[str, Any]]
    noise: dict[str, float]
    grid_t: np.ndarray
    grid_T: np.ndarray  # (n_grid, n_channels) cleaned temperatures on the uniform grid
    raw_grid_T: np.ndarray  # readings before cleaning, nearest scan on the grid (NaN = missing)
    terms: list[TermData]
    flags: list[OutlierFlags] = field(default_factory=list)
    holdout_fraction: float = 0.25
    locations: dict[str, str] = field(default_factory=dict)  # channel -> stated location ('' = unknown)
    structures: dict[str, str] = field(default_factory=dict)  # channel -> structure ('' = unknown)
    conditions_grid: dict[str, np.ndarray] = field(default_factory=dict)  # operating column -> value on grid_t

    def channel_index(self, name: str) -> int:
        """Return the column of channel ``name``."""
        return self.channels.index(name)


def _sweep_ids(t: np.ndarray) -> np.ndarray:
    """Return sweep indices of time-sorted rows.

    Rows that share their time stamp (a sweep stamped once, or read at once) form
    one sweep each distinct time; otherwise a new sweep starts where the time gap
    exceeds 3x the median positive gap, and a series without such gaps (one
    reading at a time) has one sweep per reading.
    """
    if t.size < 2:
        return np.zeros(t.size, dtype=int)
    d = np.diff(t)
    pos = d[d > 0]
    if pos.size == 0:
        return np.zeros(t.size, dtype=int)
    if np.mean(d == 0) >= 0.5:  # most rows share a time stamp with the row before: a stamp per sweep
        return np.concatenate([[0], np.cumsum(d > 0)]).astype(int)
    gap = 3.0 * float(np.median(pos))
    new = d > gap
    if not new.any():
        return np.arange(t.size, dtype=int)
    return np.concatenate([[0], np.cumsum(new)]).astype(int)


#: conditions.csv columns that describe how the machine is run (the pose columns x..b are where it is)
OPERATING_COLUMNS = ("spindle_rpm", "feed_mm_min")


def _conditions_source(bundle: object) -> dict[str, Callable[[np.ndarray], np.ndarray]]:
    """Return, per operating column of conditions.csv, a function giving its value at error times.

    The state log is a log of set points: a value holds until the next row (zero-order hold);
    unknown cells hold the last known value. Columns that never change are left out.
    """
    cond = getattr(bundle, "conditions", None)
    out: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
    if cond is None or len(cond) == 0 or "time_s" not in cond:
        return out
    c = cond.sort_values("time_s", kind="stable")
    tc = c["time_s"].to_numpy(dtype=float)
    for col in OPERATING_COLUMNS:
        if col not in c:
            continue
        v = pd.to_numeric(c[col], errors="coerce").ffill().bfill().to_numpy(dtype=float)
        if not np.isfinite(v).all() or np.ptp(v) == 0:
            continue

        def at(t: np.ndarray, tc: np.ndarray = tc, v: np.ndarray = v) -> np.ndarray:
            i = np.clip(np.searchsorted(tc, t, side="right") - 1, 0, tc.size - 1)
            return v[i]

        out[col] = at
    return out


def _session_labels(errs: pd.DataFrame, setups: Any) -> pd.Series:
    """Return each error row's instrument session ('' for readings against a stable artefact, and bundle v1).

    Bundle v2 ``datum: session``: a laser is zeroed when it is set up, so its readings are relative
    to that moment; a session is a maximal run, in time order over all readings, of one such setup
    (the same definition as the fit's).
    """
    out = pd.Series("", index=errs.index, dtype=object)
    if not setups or "setup" not in errs.columns:
        return out
    order = np.argsort(errs["time_s"].to_numpy(dtype=float), kind="stable")
    sid = errs["setup"].astype(str).to_numpy(dtype=object)[order]
    run = np.concatenate([[0], np.cumsum(sid[1:] != sid[:-1])]) if sid.size else np.zeros(0, dtype=int)
    labels = np.full(sid.size, "", dtype=object)
    for k, (s, r) in enumerate(zip(sid, run)):
        entry = setups.get(s) if isinstance(setups, dict) else getattr(setups, s, None)
        if entry is not None and str(meta_get(entry, "datum", "session")) == "session":
            labels[k] = f"{s}.{r}"
    out.iloc[order] = labels
    return out


class BundleLike(Protocol):
    """What the models read of a campaign bundle (``driftlab.campaigns.bundle.Bundle`` has it; the
    preparation reads ``conditions`` when present)."""

    @property
    def name(self) -> str: ...
    @property
    def meta(self) -> Any: ...  # the campaign metadata: a dict or a pydantic model (``meta_get`` reads both)
    @property
    def temperatures(self) -> pd.DataFrame: ...
    @property
    def errors(self) -> pd.DataFrame: ...


@dataclass(frozen=True)
class _TemperatureGrid:
    """The temperatures after cleaning, on a uniform scan grid, and what the cleaning did."""

    #: the scan times, sorted
    ts: np.ndarray
    grid_t: np.ndarray
    grid_T: np.ndarray
    raw_grid: np.ndarray
    flags: list[OutlierFlags]
    max_gap_s: float


def _clean_temperatures(temps: pd.DataFrame, channels: list[str], max_gap_s: float | None) -> _TemperatureGrid:
    """Return the temperatures cleaned channel by channel (range, spikes, gaps) and put on a uniform grid."""
    ts = temps["time_s"].to_numpy(dtype=float)
    order = np.argsort(ts, kind="stable")
    ts = ts[order]
    raw = temps[channels].to_numpy(dtype=float)[order]
    dts = np.diff(ts)
    dt = float(np.median(dts[dts > 0])) if (dts > 0).any() else 1.0
    if max_gap_s is None:
        max_gap_s = max(5.0 * dt, 600.0)
    grid_t = np.arange(ts[0], ts[-1] + 0.5 * dt, dt)
    grid_T = np.empty((grid_t.size, len(channels)))
    raw_grid = np.empty_like(grid_T)
    nearest = np.clip(np.searchsorted(ts, grid_t), 0, ts.size - 1)
    flags: list[OutlierFlags] = []
    lo, hi = TEMP_RANGE_C
    for j, ch in enumerate(channels):
        x = raw[:, j].copy()
        raw_grid[:, j] = x[nearest]
        oor = np.isfinite(x) & ((x < lo) | (x > hi))
        x[oor] = np.nan
        sp = spike_mask(x)
        x[sp] = np.nan
        x, held = _fill_gaps(ts, x, max_gap_s)
        if np.isfinite(x).any():
            xv = np.isfinite(x)
            grid_T[:, j] = np.interp(grid_t, ts[xv], x[xv])
        else:
            grid_T[:, j] = np.nan
        if sp.any() or oor.any() or held:
            bad = ts[sp | oor]
            flags.append(OutlierFlags(ch, int(sp.sum()), int(oor.sum()), held, tuple(float(v) for v in bad[:5])))
    return _TemperatureGrid(ts, grid_t, grid_T, raw_grid, flags, max_gap_s)


def _error_spikes(t: np.ndarray, pos: np.ndarray, direction: np.ndarray, y: np.ndarray, hold_t: float) -> np.ndarray:
    """Return the spikes of one (axis, term) per (position, direction) series, training and held-out rows apart."""
    bad = np.zeros(y.size, dtype=bool)
    keys = np.round(pos, 9) * 10 + direction
    is_train = t < hold_t
    for key in np.unique(keys):
        for part in (is_train, ~is_train):
            idx = np.flatnonzero((keys == key) & part)
            if idx.size >= 10:
                bad[idx] = spike_mask(y[idx])
    return bad


def _in_scan_gaps(t: np.ndarray, ts: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Return True for an error sample inside a gap of the scans (nothing written for longer than ``max_gap_s``)."""
    nxt = np.clip(np.searchsorted(ts, t, side="left"), 0, ts.size - 1)
    prv = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 1)
    return (ts[nxt] - ts[prv] > max_gap_s) | (t < ts[0]) | (t > ts[-1])


@dataclass(frozen=True)
class _TermContext:
    """What every (axis, term) of one bundle is prepared with."""

    grid: _TemperatureGrid
    #: each error row's instrument session ('' for none)
    session: pd.Series
    #: operating column -> its value at given times (``_conditions_source``)
    cond_at: dict[str, Callable[[np.ndarray], np.ndarray]]
    holdout_fraction: float


def _term_data(axis: str, term: str, g: pd.DataFrame, ctx: _TermContext, flags: list[OutlierFlags]) -> TermData | None:
    """Return the cleaned rows of one (axis, term) (None: too few left); append what the cleaning did to ``flags``."""
    grid = ctx.grid
    g = g.sort_values("time_s", kind="stable")
    t_all = g["time_s"].to_numpy(dtype=float)
    hold_t = split_time(t_all, ctx.holdout_fraction)  # the one split of the fit and the diagnosis
    g = g[np.isfinite(g["value"].to_numpy(dtype=float))]
    sess_g = ctx.session.loc[g.index].to_numpy(dtype=object)
    y = g["value"].to_numpy(dtype=float)
    t = g["time_s"].to_numpy(dtype=float)
    pos = g["position"].to_numpy(dtype=float)
    direction = g["direction"].to_numpy(dtype=float) if "direction" in g else np.ones_like(y)
    direction = np.where(np.isfinite(direction), direction, 1.0)
    bad = _error_spikes(t, pos, direction, y, hold_t)
    fl = OutlierFlags(f"{axis}/{term}", int(bad.sum()), 0, 0, tuple(float(v) for v in t[bad][:5]))
    if bad.any():
        flags.append(fl)
    # an error sample inside a gap of the scans has no temperatures: it is left out and counted
    in_gap = _in_scan_gaps(t, grid.ts, grid.max_gap_s)
    if in_gap.any():
        first = tuple(float(v) for v in t[in_gap][:5])
        flags.append(OutlierFlags(f"{axis}/{term}: {int(in_gap.sum())} samples in scan gaps left out", 0, 0, 0, first))
    keep = ~bad & ~in_gap
    t, pos, direction, y = t[keep], pos[keep], direction[keep], y[keep]
    sess_g = sess_g[keep]
    # a new session of a setup zeroed at its mounting (bundle v2 datum: session): a stated re-zero
    new = np.flatnonzero((sess_g[1:] != sess_g[:-1]) & (sess_g[1:] != "")) + 1
    datum_times = np.unique(t[new]) if new.size else np.empty(0)
    if y.size < 12:  # too few to fit a cubic and temperatures and to hold a quarter out
        flags.append(OutlierFlags(f"{axis}/{term}: {y.size} samples, too few to diagnose", 0))
        return None
    T_at = np.empty((t.size, grid.grid_T.shape[1]))
    for j in range(grid.grid_T.shape[1]):
        T_at[:, j] = np.interp(t, grid.grid_t, grid.grid_T[:, j])
    n_train = int(np.sum(t < hold_t))
    conds = {c: f(t) for c, f in ctx.cond_at.items()}
    # sweeps of the training rows from their own times (which held-out rows survive cleaning depends on
    # their values), the held-out rows' numbered after them
    sw_train = _sweep_ids(t[:n_train])
    sw_hold = _sweep_ids(t[n_train:]) + (int(sw_train.max()) + 1 if n_train else 0)
    sweep = np.concatenate([sw_train, sw_hold]).astype(int)
    return TermData(str(axis), str(term), t, pos, direction, y, T_at, n_train, sweep, fl, conds, datum_times)


@dataclass(frozen=True)
class _MetaView:
    """What the preparation reads of the campaign metadata, as plain values."""

    model_channels: dict[str, list[str]]
    stages: list[dict[str, Any]]
    noise: dict[str, float]
    room: list[str]
    locations: dict[str, str]
    structures: dict[str, str]


def _meta_view(meta: Any, channels: list[str]) -> _MetaView:
    """Return the metadata the preparation keeps (channels it does not know are left out; 'unknown' is '')."""
    mc_raw = _as_plain(meta_get(meta, "model_channels", None)) or {}
    model_channels = {str(a): [c for c in v if c in channels] for a, v in mc_raw.items()}
    stages = [_as_plain(s) for s in (meta_get(meta, "stages", []) or [])]
    noise = _as_plain(meta_get(meta, "noise", None)) or {}
    room = [c for c in (meta_get(meta, "room_channels", []) or []) if c in channels]
    unknown = {"", "unspecified", "unknown", "none"}
    info = meta_get(meta, "channels", {}) or {}
    locations = {ch: str(meta_get(v, "location", "") or "") for ch, v in info.items()}
    structures = {ch: str(meta_get(v, "structure", "") or "") for ch, v in info.items()}
    return _MetaView(
        model_channels,
        stages,
        {k: float(v) for k, v in noise.items() if v is not None},
        room,
        {k: ("" if v.strip().lower() in unknown else v) for k, v in locations.items()},
        {k: ("" if v.strip().lower() in unknown else v) for k, v in structures.items()},
    )


def prepare_bundle(
    bundle: BundleLike, holdout_fraction: float = 0.25, max_gap_s: float | None = None
) -> PreparedBundle:
    """Return the cleaned, grid-aligned :class:`PreparedBundle` of a bundle (one pass, vectorised)."""
    if not 0.0 < holdout_fraction < 0.9:
        raise ValidationError(f"--holdout-fraction must be in (0, 0.9), got {holdout_fraction}")
    temps: pd.DataFrame = bundle.temperatures
    errors: pd.DataFrame = bundle.errors
    channels = [c for c in temps.columns if c != "time_s"]
    if not channels:
        raise ValidationError("temperatures.csv: no thermocouple channels")
    if errors is None or len(errors) == 0:
        raise ValidationError("errors.csv: no error samples")
    grid = _clean_temperatures(temps, channels, max_gap_s)
    flags = list(grid.flags)
    # the held-out split is fixed on the rows' times alone (never their values), and the training and
    # held-out rows are cleaned apart: nothing in the held-out values can change a training decision
    errs = errors.dropna(subset=["time_s", "position"])
    cond_at = _conditions_source(bundle)
    ctx = _TermContext(grid, _session_labels(errs, meta_get(bundle.meta, "setups", None)), cond_at, holdout_fraction)
    terms: list[TermData] = []
    for (axis, term), g in errs.groupby(["axis", "term"], sort=True):
        td = _term_data(str(axis), str(term), g, ctx, flags)
        if td is not None:
            terms.append(td)
    mv = _meta_view(bundle.meta, channels)
    return PreparedBundle(
        str(getattr(bundle, "name", "bundle")),
        channels,
        mv.room,
        mv.model_channels,
        mv.stages,
        mv.noise,
        grid.grid_t,
        grid.grid_T,
        grid.raw_grid,
        terms,
        flags,
        holdout_fraction,
        mv.locations,
        mv.structures,
        {name: np.asarray(at(grid.grid_t), dtype=float) for name, at in cond_at.items()},
    )


# ---------------------------------------------------------------------------------------------
# least squares core


def _normalise(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``X`` with unit-RMS columns and the scales used (zero columns keep scale 1)."""
    s = np.sqrt(np.mean(X * X, axis=0))
    s = np.where(s > 0, s, 1.0)
    return X / s, s


def lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Return the least-squares coefficients of ``y ~ X`` with column scaling for conditioning."""
    Xn, s = _normalise(X)
    beta, *_ = np.linalg.lstsq(Xn, y, rcond=None)
    return beta / s


def position_basis(pos: np.ndarray, ref: np.ndarray | None = None) -> tuple[np.ndarray, list[str]]:
    """Return the centred/scaled cubic position basis (intercept, u, u^2, u^3) and its names.

    ``ref`` (the training positions) fixes the centre, scale and the number of
    identifiable powers (at most unique positions - 1).
    """
    ref = pos if ref is None else ref
    lo, hi = float(np.min(ref)), float(np.max(ref))
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    n_unique = np.unique(np.round(ref, 9)).size
    degree = min(3, n_unique - 1)
    u = (pos - c) / h if h > 0 else np.zeros_like(pos)
    cols = [np.ones_like(pos)] + [u**k for k in range(1, degree + 1)]
    names = ["intercept", "position", "position^2", "position^3"][: degree + 1]
    return np.column_stack(cols), names


@dataclass
class LinearFit:
    """An OLS fit on the training rows scored on the held-out rows (coefficients in physical units)."""

    names: list[str]
    coef: np.ndarray
    rmse_train: float
    rmse_holdout: float
    residual: np.ndarray  # y - X beta on every row
    n_train: int
    n_holdout: int

    @property
    def params(self) -> dict[str, float]:
        """Return the coefficients by regressor name."""
        return dict(zip(self.names, (float(v) for v in self.coef)))


def fit_columns(X: np.ndarray, y: np.ndarray, train: np.ndarray, names: list[str]) -> LinearFit:
    """Return the :class:`LinearFit` of ``y ~ X`` trained on ``train`` and scored on the rest."""
    beta = lstsq(X[train], y[train])
    r = y - X @ beta
    return LinearFit(list(names), beta, rmse(r[train]), rmse(r[~train]), r, int(train.sum()), int((~train).sum()))


# ---------------------------------------------------------------------------------------------
# channel selection (when model_channels is absent for an axis)


@dataclass
class ChannelSelection:
    """The outcome of the correlation screening of one (axis, term)'s training data."""

    channels: list[str]
    partial_corr: list[float]
    source: str  # "model_channels" or "screening"
    max_channels: int = 0
    skipped_collinear: list[str] = field(default_factory=list)


class _ChannelSearch:
    """The stepwise channel search of one (axis, term), on one Gram matrix of the centred, scaled columns.

    Columns: the selection's base (position basis, maybe the direction), then each usable channel's
    dT, then y. Every subset fit is a solve on a block of ``G``, so the search costs no refits.
    """

    def __init__(self, B: np.ndarray, D: np.ndarray, y: np.ndarray, names: list[str], limits: tuple[int, float, float]):
        self.n, self.nb = y.size, B.shape[1]
        Z = np.column_stack([B] + [D[:, [j]] for j in range(D.shape[1])] + [y[:, None]])
        Z = Z / np.maximum(np.sqrt(np.mean(Z * Z, axis=0)), 1e-300)
        self.G = Z.T @ Z
        self.iy = self.G.shape[0] - 1
        self.ridge = 1e-12 * self.n
        self.names = names
        self.max_channels, self.alpha_in, self.alpha_out = limits
        self.chosen: list[int] = []  # indices into the usable channels
        self.skipped: list[str] = []

    def _solve(self, cols: Sequence[int], target: int) -> tuple[list[int], np.ndarray]:
        """Return (the base and ``cols``' rows of G, the coefficients of column ``target`` on them)."""
        idx = list(range(self.nb)) + [self.nb + c for c in cols]
        Gs = self.G[np.ix_(idx, idx)] + self.ridge * np.eye(len(idx))
        return idx, np.linalg.solve(Gs, self.G[idx, target])

    def rss(self, cols: list[int]) -> float:
        """Return the residual sum of squares of y on the base and the channels ``cols``."""
        G, iy = self.G, self.iy
        idx, b = self._solve(cols, iy)
        return max(float(G[iy, iy] - b @ G[idx, iy]), 1e-300)

    def explained(self, c: int, cols: list[int]) -> float:
        """Return the R^2 of channel ``c`` on the base and the channels ``cols``."""
        G, k = self.G, self.nb + c
        idx, b = self._solve(cols, k)
        return 1.0 - max(float(G[k, k] - b @ G[idx, k]), 0.0) / max(float(G[k, k] - G[0, k] ** 2 / G[0, 0]), 1e-300)

    def forward(self) -> bool:
        """Add channels while the best one's F test is significant (Bonferroni); return whether any was added."""
        chosen, added = self.chosen, False
        while len(chosen) < self.max_channels + 4:  # room to overshoot: backward() prunes the proxies
            rest = [c for c in range(len(self.names)) if c not in chosen]
            if not rest:
                break
            base = self.rss(chosen)
            best, best_rss = None, base
            for c in rest:
                if self.explained(c, chosen) > 1.0 - 1e-5:
                    if self.names[c] not in self.skipped:
                        self.skipped.append(self.names[c])
                    continue
                r = self.rss(chosen + [c])
                if r < best_rss * (1.0 - 1e-12):
                    best, best_rss = c, r
            dof = self.n - self.nb - len(chosen) - 1
            if best is None or dof <= 0:
                break
            p = float(stats.f.sf((base - best_rss) / (best_rss / dof), 1, dof))
            if p > self.alpha_in / len(rest):
                break
            chosen.append(best)
            added = True
        return added

    def backward(self) -> bool:
        """Remove the least significant channel while it is not significant or too many are in."""
        chosen, removed = self.chosen, False
        while chosen:
            full = self.rss(chosen)
            dof = self.n - self.nb - len(chosen)
            worst, worst_p = None, -1.0
            for c in chosen:
                p = float(stats.f.sf((self.rss([k for k in chosen if k != c]) - full) / (full / dof), 1, dof))
                if p > worst_p:
                    worst, worst_p = c, p
            if worst is None or (worst_p <= self.alpha_out and len(chosen) <= self.max_channels):
                break
            chosen.remove(worst)
            removed = True
        return removed

    def partial_correlations(self) -> list[float]:
        """Return the partial correlation of each chosen channel with y given all the others."""
        G, iy, chosen = self.G, self.iy, self.chosen
        pcs = []
        full = self.rss(chosen)
        for c in chosen:
            without = self.rss([k for k in chosen if k != c])
            idx, bxc = self._solve([k for k in chosen if k != c], self.nb + c)
            cov = G[self.nb + c, iy] - bxc @ G[idx, iy]
            pcs.append(float(np.sign(cov) * np.sqrt(max(0.0, 1.0 - full / without))))
        return pcs


def select_channels(
    td: TermData, prep: PreparedBundle, max_channels: int | None = None, alpha_in: float = 1e-2, alpha_out: float = 1e-6
) -> ChannelSelection:
    """Return a deterministic stepwise selection of channels for ``td`` by partial correlation (ch. 5.4, 6.4.2).

    Forward: from the position basis, add the channel whose dT has the largest
    partial correlation with the training errors given what is in (the largest
    drop of RSS), while its F test is significant at ``alpha_in`` (Bonferroni
    over the remaining channels), up to ``max_channels`` + 4. Backward: remove
    the channel whose F test for removal is least significant while it is not
    significant at ``alpha_out`` or more than ``max_channels`` are in (a proxy
    picked early that later channels explain, the masking the thesis warns
    about in 6.4.2), then go forward again; at most four cycles. Exact
    duplicates (a channel the others explain to R^2 > 1 - 1e-5) are skipped.
    Ties break on channel order. When both approach directions were measured, the
    direction is a nuisance column of the selection's base (not of the model), so a
    reversal error cannot steer the choice. All subset fits come from one Gram matrix of
    the centred, scaled training columns, so the search costs no refits.
    ``max_channels`` defaults to half the usable channels, within 4..12 (the
    thesis kept 18 of 50 for five axes; one axis's errors rarely need more).
    """
    tr = td.train
    y = td.y[tr]
    B, _ = position_basis(td.pos[tr])
    if np.unique(td.direction[tr]).size > 1:
        # the approach direction is a nuisance of the selection only (a reversal error must not make a
        # channel that happens to track the sweep order look better); it never enters the standard model
        B = np.column_stack([B, td.direction[tr]])
    D = td.temps[tr] - td.temps[0]
    usable = [j for j in range(D.shape[1]) if np.all(np.isfinite(D[:, j])) and np.ptp(D[:, j]) > 0]
    if max_channels is None:
        max_channels = int(np.clip(len(usable) // 2, 4, 12))
    names = [prep.channels[j] for j in usable]
    search = _ChannelSearch(B, D[:, usable], y, names, (max_channels, alpha_in, alpha_out))
    search.forward()
    for _ in range(4):
        if not search.backward():
            break
        if not search.forward():
            break
    search.backward()
    pcs = search.partial_correlations()
    return ChannelSelection([names[c] for c in search.chosen], pcs, "screening", max_channels, search.skipped)


def model_channels_for(td: TermData, prep: PreparedBundle) -> ChannelSelection:
    """Return the user's ``model_channels`` for the axis, or driftlab's own screening when absent."""
    if td.axis in prep.model_channels:
        return ChannelSelection(list(prep.model_channels[td.axis]), [], "model_channels")
    return select_channels(td, prep)


@dataclass
class StandardModel:
    """The spec section 2 model of one (axis, term): design, fit and channel selection."""

    td: TermData
    selection: ChannelSelection
    X: np.ndarray
    names: list[str]
    fit: LinearFit

    @property
    def channels(self) -> list[str]:
        """Return the channels the model uses."""
        return self.selection.channels


def standard_design(td: TermData, prep: PreparedBundle, channels: list[str]) -> tuple[np.ndarray, list[str]]:
    """Return the spec section 2 design matrix (position cubic + dT of ``channels``) and its names."""
    B, names = position_basis(td.pos, td.pos[td.train])
    cols = [B]
    for ch in channels:
        j = prep.channel_index(ch)
        cols.append(td.dT(td.temps[:, j])[:, None])
        names.append(f"dT_{ch}")
    return np.column_stack(cols), names


def fit_standard_model(td: TermData, prep: PreparedBundle) -> StandardModel:
    """Return the standard model of ``td`` fitted on its training rows and scored on the held-out rows."""
    sel = model_channels_for(td, prep)
    X, names = standard_design(td, prep, sel.channels)
    ok = np.all(np.isfinite(X), axis=0)
    if not ok.all():  # a channel with no reading at all cannot enter the model
        dropped = [n for n, good in zip(names, ok) if not good]
        sel = ChannelSelection(
            [c for c in sel.channels if f"dT_{c}" not in dropped],
            sel.partial_corr,
            sel.source,
            sel.max_channels,
            sel.skipped_collinear,
        )
        X, names = standard_design(td, prep, sel.channels)
    return StandardModel(td, sel, X, names, fit_columns(X, td.y, td.train, names))


# ---------------------------------------------------------------------------------------------
# thermocouple noise: a denoised view of the temperatures for the effect search (errors in variables)

#: window lengths (scans, odd) tried by the discrepancy-principle smoother, shortest first
DENOISE_WINDOWS = (5, 9, 17, 33, 65)


def scan_noise(x: np.ndarray) -> float:
    """Return the noise of one reading of a smooth series: 1.4826 MAD of second differences / sqrt(6).

    Second differences cancel any trend that is locally linear over three scans
    (temperatures are slow), so only the scan-to-scan noise is left (variance 6 sigma^2).
    """
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 10:
        return 0.0
    return robust_sigma(np.diff(x, 2)) / np.sqrt(6.0)


def denoise_series(x: np.ndarray, windows: tuple[int, ...] = DENOISE_WINDOWS) -> tuple[np.ndarray, int]:
    """Return a zero-phase denoised copy of a temperature series and the window used (1 = untouched).

    Savitzky-Golay (local quadratic, centred: no lag is introduced) with the longest
    window whose removed part is still no larger than 1.1 x the series' own scan
    noise (``scan_noise``) - the discrepancy principle: the smoother may take away
    the noise, and at most about half a noise sigma of the signal. Noise-aware and
    scale-free: a quiet channel or a fast one is left nearly untouched.
    """
    x = np.asarray(x, dtype=float)
    if x.size < 20 or not np.all(np.isfinite(x)):
        return x, 1
    s = scan_noise(x)
    if s <= 0.0:
        return x, 1
    best, used = x, 1
    for w in windows:
        if w >= x.size:
            break
        sm = savgol_filter(x, w, 2, mode="interp")
        if float(np.sqrt(np.mean((x - sm) ** 2))) > 1.1 * s:
            break
        best, used = sm, w
    return best, used


def denoised_view(prep: PreparedBundle) -> PreparedBundle:
    """Return ``prep`` with every channel denoised (``denoise_series``) and re-interpolated to the error times.

    The readings' own noise enters the standard model through its dT regressors
    (errors in variables): coefficients fitted to noisy readings are attenuated and
    extrapolate badly, and a smoothed copy of a channel (a short lag, a proxy
    channel, even a drift) then "improves" the model without any physical effect.
    The effect search holds every candidate to this view as well (diagnosis.py).
    """
    G = prep.grid_T.copy()
    for j in range(G.shape[1]):
        G[:, j], _ = denoise_series(G[:, j])
    terms = []
    for td in prep.terms:
        T_at = np.empty_like(td.temps)
        for j in range(G.shape[1]):
            T_at[:, j] = np.interp(td.t, prep.grid_t, G[:, j])
        terms.append(replace(td, temps=T_at))
    return replace(prep, grid_T=G, terms=terms)


def refit_standard(td: TermData, prep: PreparedBundle, sel: ChannelSelection) -> StandardModel:
    """Return the standard model of ``td`` on the given channel selection (no screening)."""
    X, names = standard_design(td, prep, sel.channels)
    return StandardModel(td, sel, X, names, fit_columns(X, td.y, td.train, names))
