"""Correlation screening of thermocouples (ch. 5.4, table 5.2; eqs. 6.1-6.2).

A channel is dropped when it carries no new information: it rises and falls with a channel
that is kept (high correlation) *and* stays close to it (no gradient between the two sites).
Room channels are always kept (the room is a heat source and sink, ch. 5.4); of each group of
redundant channels the one on a heat source (motor, ballscrew nut, spindle) is preferred; a
structure keeps at most the two corners that span its gradient, plus any channel the corners
do not explain.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.models.features import channel_columns, fill_gaps

#: words in a channel's location that mark it as sitting on a heat source (ch. 5.4)
HEAT_SOURCE_WORDS: tuple[str, ...] = ("motor", "nut", "gear", "z axis ballscrew")


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

    def to_dict(self) -> dict[str, Any]:
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
    return float(np.sqrt(np.mean(r**2))), [pool[i] for i in chosen]


def _gradient_partner(
    c: str, structure: str, kept: Mapping[str, str], meta: Mapping[str, Mapping[str, str]], temps: pd.DataFrame,
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


def screen_channels(
    temperatures: pd.DataFrame,
    channels: Mapping[str, Mapping[str, str]] | None = None,
    room_channels: Sequence[str] = (),
    *,
    explained_degC: float = 0.3,
    explained_fraction: float = 0.15,
    n_explain: int = 3,
    related_r: float = 0.9,
    gradient_degC: float = 0.8,
    always_keep: Sequence[str] = (),
) -> ScreeningResult:
    """Return the screening of all channels of a campaign (ch. 5.4).

    Room channels and the sites of heat sources (motors, ballscrew nuts, gear trains, the spindle)
    are kept. Every other channel is then visited, structure by structure, starting in each
    structure with its most active site and then the one that differs most from it (the corners
    spanning its gradient): it is kept only if the channels kept so far cannot explain it, i.e. if
    a least-squares fit on up to ``n_explain`` of them (kept sites of its structure, kept sites
    correlated with it by at least ``related_r``, the room) leaves more than ``explained_degC`` or
    ``explained_fraction`` of its own variation (whichever is larger) unexplained. A structure's
    second corner is kept whenever it differs from the first by ``gradient_degC`` rms or more (a
    gradient bends the structure, eqs. 3.4-3.5, even when both corners correlate).
    """
    meta = {c: dict(v) for c, v in (channels or {}).items()}
    temps = fill_gaps(temperatures)
    chans = channel_columns(temps)
    if not chans:
        raise ValidationError("no temperature channels to screen")
    R = correlation_matrix(temps)
    T = temps[chans].to_numpy(float)
    finite = np.isfinite(T)
    std = np.array([float(np.std(T[finite[:, i], i])) if finite[:, i].any() else 0.0 for i in range(len(chans))])
    kept_reason: dict[str, str] = {}
    dropped: dict[str, str] = {}
    for i, c in enumerate(chans):
        if not finite[:, i].any():
            dropped[c] = "no readings"
        elif c in room_channels:
            kept_reason[c] = "room air: the room is a heat source and sink; both room channels are kept (ch. 5.4)"
        elif std[i] < 1e-6:
            dropped[c] = "constant over the campaign: no information"
        elif _is_heat_site(meta.get(c, {}).get("location", "")):
            kept_reason[c] = "on a heat source: " + meta[c]["location"]
    for c in always_keep:
        if c in chans and c not in dropped and c not in kept_reason:
            kept_reason[c] = "required by the user's model channels"
    rest = [c for c in chans if c not in kept_reason and c not in dropped]
    by_struct: dict[str, list[str]] = {}
    for c in rest:
        by_struct.setdefault(meta.get(c, {}).get("structure", "") or c, []).append(c)
    order: list[str] = []
    corners: dict[str, tuple[str, float]] = {}
    for members in by_struct.values():
        first = max(members, key=lambda c: std[chans.index(c)])
        seq = [first]
        others = [c for c in members if c != first]
        while others:
            # next: the site farthest (in rms difference) from those already ordered
            nxt = max(others, key=lambda c: min(float(np.nanstd(temps[c] - temps[o])) for o in seq))
            seq.append(nxt)
            others.remove(nxt)
        order += seq
        if len(seq) >= 2:
            d = float(np.nanstd(temps[seq[0]].to_numpy(float) - temps[seq[1]].to_numpy(float)))
            if d >= gradient_degC:  # the structure bends: keep the two corners that span it
                corners[seq[0]] = (seq[1], d)
                corners[seq[1]] = (seq[0], d)
    idx = {c: i for i, c in enumerate(chans)}
    Tf = np.nan_to_num(T)
    for c in order:
        # explainers: kept sites of the same structure, kept sites that rise and fall with it, the room
        st = meta.get(c, {}).get("structure", "")
        pool = [idx[k] for k in kept_reason
                if k in room_channels or (st and meta.get(k, {}).get("structure", "") == st)
                or abs(float(np.nan_to_num(R.loc[c, k]))) >= related_r]
        resid, used = _explain(Tf, idx[c], pool, n_explain)
        tol = max(explained_degC, explained_fraction * std[idx[c]])
        names = [chans[u] for u in used]
        corner = corners.get(c) or _gradient_partner(c, st, kept_reason, meta, temps, gradient_degC)
        if corner is not None:
            kept_reason[c] = (f"corner of {st} spanning its gradient with {corner[0]} "
                              f"({corner[1]:.2f} degC rms difference, eqs. 3.4-3.5)")
        elif pool and resid <= tol:
            best = max(names, key=lambda k: abs(float(R.loc[c, k])))
            dropped[c] = (
                f"no new information: explained by kept {', '.join(names)} to {resid:.3f} degC rms "
                f"(r={R.loc[c, best]:.2f} with {best}) (ch. 5.4)"
            )
        else:
            kept_reason[c] = f"new information on {st or 'its site'}: {resid:.2f} degC rms not explained by the others"
    kept = [c for c in chans if c in kept_reason]
    return ScreeningResult(matrix=R, kept=kept, kept_reason=kept_reason, dropped=dropped)
