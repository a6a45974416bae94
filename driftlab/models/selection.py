"""Correlation screening of thermocouples (ch. 5.4, table 5.2; eqs. 6.1-6.2).

A channel is dropped when it carries no new information: it rises and falls with a channel
that is kept (high correlation) *and* stays close to it (no gradient between the two sites).
Room channels are always kept (the room is a heat source and sink, ch. 5.4); of each group of
redundant channels the one on a heat source (motor, ballscrew nut, spindle) is preferred; a
structure keeps at most the two corners that span its gradient, plus any channel the corners
do not explain.

When the campaign's work-space errors are given, they choose among redundant sites: which member
of a group of near-duplicate thermocouples stands for the group, and whether two sites whose
temperatures nearly agree must both stay because their difference (a gradient across a structure)
moves the tool. A stepwise least squares of every (axis, term) error series on the temperatures
(forward entry, swaps of a chosen site for a better one, backward removal) picks the sites the
errors need; the temperature screening then decides the rest as without errors.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.metrics import rmse
from driftlab.models.features import channel_columns, fill_gaps

#: words in a channel's location that mark it as sitting on a heat source (ch. 5.4)
HEAT_SOURCE_WORDS: tuple[str, ...] = ("motor", "nut", "gear", "z axis ballscrew")


class ScreeningRecord(TypedDict):
    """The JSON form of a :class:`ScreeningResult` (kept and dropped channels with reasons)."""

    kept: list[str]
    kept_reason: dict[str, str]
    dropped: dict[str, str]
    #: per kept channel, its correlation with each kept channel (None where undefined)
    correlation_kept: dict[str, list[float | None]]


@dataclass
class ScreeningResult:
    """The correlation matrix, the kept channels with why, the dropped channels with why."""

    matrix: pd.DataFrame
    kept: list[str]
    kept_reason: dict[str, str] = field(default_factory=dict)
    dropped: dict[str, str] = field(default_factory=dict)

    def table(self, channels: Sequence[str] | None = None) -> pd.DataFrame:
        """Return the correlation table of ``channels`` (default: the kept ones) in the layout of table 5.2."""
        chans = list(channels) if channels is not None else self.kept
        return self.matrix.loc[chans, chans].round(2)

    def to_dict(self) -> ScreeningRecord:
        """Return the JSON form (kept with reasons, dropped with reasons)."""
        tab = self.table()
        return {
            "kept": list(self.kept),
            "kept_reason": dict(self.kept_reason),
            "dropped": dict(self.dropped),
            "correlation_kept": {c: [None if not np.isfinite(v) else float(v) for v in tab[c]] for c in tab.columns},
        }


def correlation_matrix(temperatures: pd.DataFrame) -> pd.DataFrame:
    """Return the correlation coefficients of every pair of channels over the record (eq. 6.1)."""
    chans = channel_columns(temperatures)
    return temperatures[chans].corr(method="pearson", min_periods=3)


def _is_heat_site(location: str) -> bool:
    """Return True when a location text names a heat source."""
    loc = location.lower()
    return any(w in loc for w in HEAT_SOURCE_WORDS)


def _explain(T: np.ndarray, j: int, pool: Sequence[int], k: int) -> tuple[float, list[int]]:
    """Return the rms residual of column j fitted on up to k columns of ``pool`` chosen greedily, and those columns."""
    y = T[:, j] - T[:, j].mean()
    chosen: list[int] = []
    r = y
    C = T[:, list(pool)] - T[:, list(pool)].mean(axis=0)
    Cr = C.copy()
    for _ in range(min(k, len(pool))):
        norm2 = (Cr**2).sum(axis=0)
        gain = np.where(norm2 > 1e-12, (Cr.T @ r) ** 2 / np.maximum(norm2, 1e-300), -1.0)
        for i in chosen:
            gain[i] = -1.0
        b = int(np.argmax(gain))
        if gain[b] <= 0:
            break
        chosen.append(b)
        q = Cr[:, b] / np.sqrt(norm2[b])
        r = r - q * (q @ r)
        Cr = Cr - np.outer(q, q @ Cr)
    return rmse(r), [pool[i] for i in chosen]


def _gradient_partner(
    c: str,
    structure: str,
    kept: Mapping[str, str],
    meta: Mapping[str, Mapping[str, str]],
    temps: pd.DataFrame,
    gradient_degC: float,
) -> tuple[str, float] | None:
    """Return (kept site, rms difference) when ``c`` is the second corner of a structure with a real gradient."""
    if not structure:
        return None
    mates = [k for k in kept if meta.get(k, {}).get("structure", "") == structure]
    if len(mates) != 1:
        return None
    d = float(np.nanstd(temps[c].to_numpy(float) - temps[mates[0]].to_numpy(float)))
    return (mates[0], d) if d >= gradient_degC else None


@dataclass
class _ErrorDesign:
    """Sufficient statistics of every (axis, term) error series regressed on the temperatures.

    Geometry (the error's shape along the travel, the approach direction) is removed by taking
    deviations of the errors *and* the temperatures from their means at each (axis, term,
    position, direction): what is left is the thermal drift, linear in the temperatures.
    """

    names: list[str]  # "axis/term" per series
    gram: np.ndarray  # (J, p, p) X'X of the centred temperatures
    cross: np.ndarray  # (J, p) X'y
    yy: np.ndarray  # (J,) y'y


def _segments(temps: pd.DataFrame, n: int) -> list[pd.DataFrame]:
    """Return ``temps`` split into the ``n`` campaigns it concatenates (time_s starts again at each)."""
    t = temps["time_s"].to_numpy(float)
    cuts = [0, *(np.flatnonzero(np.diff(t) <= 0) + 1).tolist(), len(t)]
    if len(cuts) - 1 != n:
        raise ValidationError(
            f"{n} error frames for temperatures of {len(cuts) - 1} campaign(s) (time_s restarts at each campaign)"
        )
    return [temps.iloc[a:b] for a, b in zip(cuts[:-1], cuts[1:])]


def _error_design(
    temps: pd.DataFrame, chans: Sequence[str], errors: pd.DataFrame | Sequence[pd.DataFrame]
) -> _ErrorDesign | None:
    """Return the regression statistics of the work-space errors on the channels (None: nothing usable)."""
    frames = [errors] if isinstance(errors, pd.DataFrame) else list(errors)
    segs = _segments(temps, len(frames)) if len(frames) > 1 else [temps]
    X_parts, keys, y_parts = [], [], []
    for k, (seg, err) in enumerate(zip(segs, frames)):
        need = {"time_s", "axis", "term", "value"}
        if err is None or err.empty:
            continue
        if not need <= set(err.columns):
            raise ValidationError(f"work-space errors need columns {sorted(need)}, got {list(err.columns)}")
        e = err[np.isfinite(err["value"].to_numpy(float)) & np.isfinite(err["time_s"].to_numpy(float))]
        if e.empty or len(seg) < 2:
            continue
        ts = seg["time_s"].to_numpy(float)
        te = e["time_s"].to_numpy(float)
        T = seg[list(chans)].to_numpy(float)
        X_parts.append(np.column_stack([np.interp(te, ts, np.nan_to_num(T[:, i])) for i in range(len(chans))]))
        pos = e["position"].to_numpy(float).round(6) if "position" in e else np.zeros(len(e))
        d = e["direction"].to_numpy() if "direction" in e else np.zeros(len(e))
        keys.append(
            pd.DataFrame(
                {
                    "campaign": k,
                    "axis": e["axis"].astype(str).to_numpy(),
                    "term": e["term"].astype(str).to_numpy(),
                    "position": pos,
                    "direction": d,
                }
            )
        )
        y_parts.append(e["value"].to_numpy(float))
    if not X_parts:
        return None
    X = np.vstack(X_parts)
    y = np.concatenate(y_parts)
    key = pd.concat(keys, ignore_index=True)
    group = (
        key.groupby(["campaign", "axis", "term", "position", "direction"], sort=False, dropna=False).ngroup().to_numpy()
    )
    series = key.groupby(["axis", "term"], sort=False, dropna=False).ngroup().to_numpy()
    # deviations from each point's mean over the campaign: geometry out, thermal drift in
    Xd = X - pd.DataFrame(X).groupby(group).transform("mean").to_numpy()
    yd = y - pd.Series(y).groupby(group).transform("mean").to_numpy()
    names, grams, crosses, yys = [], [], [], []
    first = key.groupby(series).first()
    for j in range(int(series.max()) + 1):
        m = series == j
        yy = float(yd[m] @ yd[m])
        if m.sum() < 8 or not yy > 0:
            continue
        names.append(f"{first.loc[j, 'axis']}/{first.loc[j, 'term']}")
        grams.append(Xd[m].T @ Xd[m])
        crosses.append(Xd[m].T @ yd[m])
        yys.append(yy)
    if not names:
        return None
    return _ErrorDesign(names, np.array(grams), np.array(crosses), np.array(yys))


def _partial_r2(des: _ErrorDesign, S: Sequence[int]) -> np.ndarray:
    """Return (J, p): the share of each series' residual (after the channels S) that each channel removes."""
    G, b, yy = des.gram, des.cross, des.yy
    J, p, _ = G.shape
    diag = np.einsum("jii->ji", G)
    if S:
        S = list(S)
        Gss = G[:, S][:, :, S] + np.eye(len(S))[None] * (1e-10 * diag[:, S].mean(axis=1) + 1e-300)[:, None, None]
        M = np.linalg.solve(Gss, G[:, S, :])  # (J, s, p)
        bS = b[:, S]
        beta = np.linalg.solve(Gss, bS[:, :, None])[:, :, 0]
        rss = yy - np.einsum("js,js->j", bS, beta)
        cd = diag - np.einsum("jsp,jsp->jp", G[:, S, :], M)
        br = b - np.einsum("jsp,js->jp", M, bS)
    else:
        rss, cd, br = yy.copy(), diag.copy(), b.copy()
    ok = cd > 1e-9 * np.maximum(diag, 1e-300)
    gain = np.where(ok, br**2 / np.where(ok, cd, 1.0), 0.0)
    r2 = np.clip(gain / np.maximum(rss, 1e-300)[:, None], 0.0, 1.0 - 1e-12)
    if S:
        r2[:, S] = 0.0
    return r2


def _error_stepwise(
    des: _ErrorDesign, base: Sequence[int], cands: Sequence[int], r2_in: float, r2_out: float
) -> dict[int, tuple[float, str]]:
    """Return channel -> (share, series) for the sites the errors need beyond ``base``.

    Forward: the candidate whose entry most lowers the summed log residual of all series enters
    when it removes at least ``r2_in`` of some series' residual. Swaps: each chosen site gives way
    to the candidate that does better in its place (a redundant group is represented by the member
    that best explains the errors). Backward: a chosen site that no series needs by ``r2_out``
    leaves. Repeats until nothing changes (a bounded number of passes).
    """
    sel: list[int] = []
    pool = [c for c in cands if c not in base]

    def score(S: Sequence[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r2 = _partial_r2(des, [*base, *S])
        return r2.max(axis=0), r2.argmax(axis=0), -np.log1p(-r2).sum(axis=0)

    for _ in range(6 * len(pool) + 6):
        changed = False
        free = [c for c in pool if c not in sel]
        if free:
            mx, _, gain = score(sel)
            k = max(free, key=lambda c: gain[c])
            if mx[k] >= r2_in:
                sel.append(k)
                changed = True
        for s in list(sel):
            others = [x for x in sel if x != s]
            _, _, gain = score(others)
            alt = max((c for c in pool if c not in others), key=lambda c: gain[c])
            if alt != s and gain[alt] > gain[s] * (1 + 1e-3) + 1e-9:
                sel[sel.index(s)] = alt
                changed = True
        worst: tuple[int, float] | None = None
        for s in sel:
            mx, _, _ = score([x for x in sel if x != s])
            if mx[s] < r2_out and (worst is None or mx[s] < worst[1]):
                worst = (s, float(mx[s]))
        if worst is not None:
            sel.remove(worst[0])
            changed = True
        if not changed:
            break
    out: dict[int, tuple[float, str]] = {}
    for s in sel:
        mx, arg, _ = score([x for x in sel if x != s])
        out[s] = (float(mx[s]), des.names[int(arg[s])])
    return out


@dataclass(frozen=True)
class ScreeningOptions:
    """The thresholds of the screening (ch. 5.4); see ``screen_channels``."""

    #: a channel is explained when the kept ones leave at most this much of it (degC rms) ...
    explained_degC: float = 0.3
    #: ... or this share of its own variation, whichever is larger
    explained_fraction: float = 0.15
    #: how many kept channels may explain one
    n_explain: int = 3
    #: kept sites correlated with a channel by at least this may explain it
    related_r: float = 0.9
    #: a structure's second corner is kept when it differs from the first by this much (degC rms)
    gradient_degC: float = 0.8
    #: with errors: a site enters when it removes this share of some series' remaining residual ...
    error_r2_in: float = 0.03
    #: ... and stays while it removes this share
    error_r2_out: float = 0.02
    #: channels kept whatever the screening finds (the user's model channels)
    always_keep: tuple[str, ...] = ()


@dataclass(frozen=True)
class _Channels:
    """A campaign's channels as the screening reads them (gaps filled)."""

    temps: pd.DataFrame
    chans: list[str]
    meta: dict[str, dict[str, str]]
    room: Sequence[str]
    #: the correlation matrix (eq. 6.1), rows and columns in ``chans`` order
    R: pd.DataFrame
    #: the readings, NaN as 0 (what the explaining fits read)
    Tf: np.ndarray
    #: the standard deviation of each channel's finite readings
    std: np.ndarray
    options: ScreeningOptions
    #: channel -> its column
    idx: dict[str, int] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "idx", {c: i for i, c in enumerate(self.chans)})

    def structure(self, c: str) -> str:
        return self.meta.get(c, {}).get("structure", "")

    def related(self, i: int, j: int) -> bool:
        """Return True when channel j may explain channel i: the room, its structure, or correlated by related_r."""
        st = self.structure(self.chans[i])
        k = self.chans[j]
        return bool(
            k in self.room
            or (st and self.structure(k) == st)
            or abs(float(np.nan_to_num(self.R.iloc[i, j]))) >= self.options.related_r
        )

    def tolerance(self, i: int) -> float:
        """Return the rms residual below which channel i counts as explained."""
        return max(self.options.explained_degC, self.options.explained_fraction * self.std[i])


def _first_sorting(ch: _Channels, finite: np.ndarray) -> tuple[dict[str, str], dict[str, str]]:
    """Return (kept with why, dropped with why) before any channel is compared with another."""
    kept_reason: dict[str, str] = {}
    dropped: dict[str, str] = {}
    for i, c in enumerate(ch.chans):
        if not finite[:, i].any():
            dropped[c] = "no readings"
        elif c in ch.room:
            kept_reason[c] = "room air: the room is a heat source and sink; both room channels are kept (ch. 5.4)"
        elif ch.std[i] < 1e-6:
            dropped[c] = "constant over the campaign: no information"
        elif _is_heat_site(ch.meta.get(c, {}).get("location", "")):
            kept_reason[c] = "on a heat source: " + ch.meta[c]["location"]
    for c in ch.options.always_keep:
        if c in ch.chans and c not in dropped and c not in kept_reason:
            kept_reason[c] = "required by the user's model channels"
    return kept_reason, dropped


def _keep_error_sites(ch: _Channels, des: _ErrorDesign, kept_reason: dict[str, str], rest: Sequence[str]) -> None:
    """Keep (in ``kept_reason``) the sites of ``rest`` that the work-space errors need, with why."""
    idx, o = ch.idx, ch.options
    need = _error_stepwise(des, [idx[c] for c in kept_reason], [idx[c] for c in rest], o.error_r2_in, o.error_r2_out)
    for i, (share, series) in sorted(need.items()):
        others = [j for j in [*(idx[k] for k in kept_reason), *need] if j != i and ch.related(i, j)]
        resid, used = _explain(ch.Tf, i, others, o.n_explain)
        why = (
            f"explains the work-space errors: removes {100 * share:.0f}% of what the other kept sites leave of {series}"
        )
        if others and resid <= ch.tolerance(i):  # its temperature is nearly another's: the difference moves the tool
            why += (
                f", though its temperature follows {', '.join(ch.chans[u] for u in used)} to {resid:.2f} degC rms "
                "(the best of its redundant group, or a gradient the errors need)"
            )
        kept_reason[ch.chans[i]] = why


def _visit_order(
    ch: _Channels, rest: Sequence[str], corners_rule: bool
) -> tuple[list[str], dict[str, tuple[str, float]]]:
    """Return the order the rest is visited in and the corners spanning a gradient (with ``corners_rule``).

    Structure by structure: its most active site first, then each time the site farthest (in rms
    difference) from those already ordered.
    """
    temps, idx = ch.temps, ch.idx
    by_struct: dict[str, list[str]] = {}
    for c in rest:
        by_struct.setdefault(ch.structure(c) or c, []).append(c)
    order: list[str] = []
    corners: dict[str, tuple[str, float]] = {}
    for members in by_struct.values():
        first = max(members, key=lambda c: ch.std[idx[c]])
        seq = [first]
        left = [c for c in members if c != first]
        while left:
            nxt = max(left, key=lambda c: min(float(np.nanstd(temps[c] - temps[o])) for o in seq))
            seq.append(nxt)
            left.remove(nxt)
        order += seq
        if len(seq) >= 2 and corners_rule:
            d = float(np.nanstd(temps[seq[0]].to_numpy(float) - temps[seq[1]].to_numpy(float)))
            if d >= ch.options.gradient_degC:  # the structure bends: keep the two corners that span it
                corners[seq[0]] = (seq[1], d)
                corners[seq[1]] = (seq[0], d)
    return order, corners


def _judge(
    ch: _Channels,
    c: str,
    verdicts: tuple[dict[str, str], dict[str, str]],
    corner: tuple[str, float] | None,
    errors_judged: bool,
) -> None:
    """Keep or drop channel ``c`` (into ``verdicts``: kept with why, dropped with why) against the kept ones.

    ``corner``: the site it spans a gradient with (kept then); None: judged by what the kept ones
    explain. ``errors_judged``: the work-space errors have already kept the sites they need.
    """
    kept_reason, dropped = verdicts
    idx, st = ch.idx, ch.structure(c)
    # explainers: kept sites of the same structure, kept sites that rise and fall with it, the room
    pool = [idx[k] for k in kept_reason if ch.related(idx[c], idx[k])]
    resid, used = _explain(ch.Tf, idx[c], pool, ch.options.n_explain)
    names = [ch.chans[u] for u in used]
    if corner is not None:
        kept_reason[c] = (
            f"corner of {st} spanning its gradient with {corner[0]} ({corner[1]:.2f} degC rms difference, eqs. 3.4-3.5)"
        )
    elif pool and resid <= ch.tolerance(idx[c]):
        R = ch.R
        best = max(names, key=lambda k: abs(float(R.loc[c, k])))
        dropped[c] = (
            f"no new information: explained by kept {', '.join(names)} to {resid:.3f} degC rms "
            f"(r={R.loc[c, best]:.2f} with {best}) (ch. 5.4)"
            + ("; the work-space errors need it no more than the kept sites" if errors_judged else "")
        )
    else:
        kept_reason[c] = f"new information on {st or 'its site'}: {resid:.2f} degC rms not explained by the others"


def screen_channels(
    temperatures: pd.DataFrame,
    channels: Mapping[str, Mapping[str, str]] | None = None,
    room_channels: Sequence[str] = (),
    *,
    errors: pd.DataFrame | Sequence[pd.DataFrame] | None = None,
    options: ScreeningOptions | None = None,
) -> ScreeningResult:
    """Return the screening of all channels of a campaign (ch. 5.4), by the thresholds of ``options``.

    Room channels and the sites of heat sources (motors, ballscrew nuts, gear trains, the spindle)
    are kept. Every other channel is then visited, structure by structure, starting in each
    structure with its most active site and then the one that differs most from it (the corners
    spanning its gradient): it is kept only if the channels kept so far cannot explain it, i.e. if
    a least-squares fit on up to ``n_explain`` of them (kept sites of its structure, kept sites
    correlated with it by at least ``related_r``, the room) leaves more than ``explained_degC`` or
    ``explained_fraction`` of its own variation (whichever is larger) unexplained. A structure's
    second corner is kept whenever it differs from the first by ``gradient_degC`` rms or more (a
    gradient bends the structure, eqs. 3.4-3.5, even when both corners correlate).

    ``errors`` (the bundle's errors frame: time_s, axis, term, position, direction, value; or one
    frame per campaign when ``temperatures`` concatenates several, time_s restarting at each) lets
    the work-space errors choose among redundant sites before the temperature screening: the sites
    a stepwise least squares of all (axis, term) series needs - each entering or staying only if it
    removes ``error_r2_in`` (``error_r2_out`` to stay) of some series' remaining residual - are kept,
    whether or not their temperatures are explained by others (a gradient between near-duplicates
    moves the tool); the corners rule is then left to the errors.
    """
    temps = fill_gaps(temperatures)
    chans = channel_columns(temps)
    if not chans:
        raise ValidationError("no temperature channels to screen")
    T = temps[chans].to_numpy(float)
    finite = np.isfinite(T)
    std = np.array([float(np.std(T[finite[:, i], i])) if finite[:, i].any() else 0.0 for i in range(len(chans))])
    meta = {c: dict(v) for c, v in (channels or {}).items()}
    R = correlation_matrix(temps)
    ch = _Channels(temps, chans, meta, room_channels, R, np.nan_to_num(T), std, options or ScreeningOptions())
    kept_reason, dropped = _first_sorting(ch, finite)
    rest = [c for c in chans if c not in kept_reason and c not in dropped]
    des = _error_design(temps, chans, errors) if errors is not None else None
    if des is not None:
        _keep_error_sites(ch, des, kept_reason, rest)
        rest = [c for c in rest if c not in kept_reason]
    order, corners = _visit_order(ch, rest, corners_rule=des is None)  # with errors, the errors judge the gradients
    for c in order:
        corner = corners.get(c) or (
            _gradient_partner(c, ch.structure(c), kept_reason, meta, temps, ch.options.gradient_degC)
            if des is None
            else None
        )
        _judge(ch, c, (kept_reason, dropped), corner, errors_judged=des is not None)
    kept = [c for c in chans if c in kept_reason]
    return ScreeningResult(matrix=R, kept=kept, kept_reason=kept_reason, dropped=dropped)
