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
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

from driftlab.errors import ValidationError
from driftlab.models.features import channel_columns, fill_gaps

#: words in a channel's location that mark it as sitting on a heat source (ch. 5.4)
HEAT_SOURCE_WORDS: tuple[str, ...] = ("motor", "nut", "gear", "spindle bearing")


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
        return {
            "kept": list(self.kept),
            "kept_reason": dict(self.kept_reason),
            "dropped": dict(self.dropped),
        }


def correlation_matrix(temperatures: pd.DataFrame) -> pd.DataFrame:
    """Return the correlation coefficients of every pair of channels over the record (eq. 6.1)."""
    chans = channel_columns(temperatures)
    return temperatures[chans].corr(method="pearson", min_periods=3)


def _is_heat_site(location: str) -> bool:
    """Return True when a location text names a heat source."""
    loc = location.lower()
    return any(w in loc for w in HEAT_SOURCE_WORDS)


def screen_channels(
    temperatures: pd.DataFrame,
    channels: Mapping[str, Mapping[str, str]] | None = None,
    room_channels: Sequence[str] = (),
    *,
    r_min: float = 0.98,
    gradient_degC: float = 0.15,
    explained_degC: float = 0.1,
    always_keep: Sequence[str] = (),
) -> ScreeningResult:
    """Return the screening of all channels of a campaign (ch. 5.4).

    Two channels are redundant when their correlation is at least ``r_min`` and the rms of
    their difference (about its mean) is at most ``gradient_degC``; redundant groups are found
    by complete-linkage clustering so every pair in a group meets both tests. A structure keeps
    the two channels with the largest gradient between them; a further channel of that structure
    is dropped when the two corners explain it to ``explained_degC`` rms.
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
    for c in always_keep:
        if c in chans and c not in dropped and c not in kept_reason:
            kept_reason[c] = "required by the user's model channels"
    pool = [c for c in chans if c not in kept_reason and c not in dropped]
    if len(pool) >= 2:
        idx = [chans.index(c) for c in pool]
        P = T[:, idx]
        D = P[:, :, None] - P[:, None, :]
        sd = np.sqrt(np.nanmean((D - np.nanmean(D, axis=0)) ** 2, axis=0))
        r = np.nan_to_num(R.loc[pool, pool].to_numpy(float))
        dist = np.maximum((1 - r) / (1 - r_min), sd / gradient_degC)
        np.fill_diagonal(dist, 0.0)
        dist = 0.5 * (dist + dist.T)
        labels = fcluster(linkage(squareform(dist, checks=False), method="complete"), t=1.0, criterion="distance")
    else:
        labels = np.ones(len(pool), int)
    groups: dict[int, list[str]] = {}
    for c, g in zip(pool, labels):
        groups.setdefault(int(g), []).append(c)
    reps: list[str] = []
    for members in groups.values():
        heat = [c for c in members if _is_heat_site(meta.get(c, {}).get("location", ""))]
        cand = heat or members
        # the most central site: highest mean correlation with its group (T7 for T1-T8, ch. 5.4)
        rep = max(cand, key=lambda c: (float(np.nanmean(R.loc[c, members])), -chans.index(c)))
        reps.append(rep)
        why = "heat-source site" if rep in heat else "one site for a group that rises and falls together"
        kept_reason[rep] = why + (f" (represents {', '.join(m for m in members if m != rep)})" if len(members) > 1 else "")
        for m in members:
            if m != rep:
                d = float(np.sqrt(np.nanvar(temps[m].to_numpy(float) - temps[rep].to_numpy(float))))
                dropped[m] = (
                    f"no new information: r={R.loc[m, rep]:.3f} with kept {rep}, "
                    f"difference {d:.3f} degC rms (ch. 5.4)"
                )
    # structures: keep the two corners spanning the gradient, drop what they explain
    by_struct: dict[str, list[str]] = {}
    for c in reps:
        s = meta.get(c, {}).get("structure", "")
        if s and not _is_heat_site(meta.get(c, {}).get("location", "")):
            by_struct.setdefault(s, []).append(c)
    for s, members in by_struct.items():
        if len(members) <= 2:
            continue
        M = temps[members].to_numpy(float)
        best, pair = -1.0, (0, 1)
        for i in range(len(members)):
            for j in range(i + 1, len(members)):
                g = float(np.nanstd(M[:, i] - M[:, j]))
                if g > best:
                    best, pair = g, (i, j)
        a, b = members[pair[0]], members[pair[1]]
        A = np.column_stack([np.ones(M.shape[0]), M[:, pair[0]], M[:, pair[1]]])
        for k, c in enumerate(members):
            if k in pair:
                kept_reason[c] = f"corner of {s} spanning its gradient with {b if c == a else a}"
                continue
            coef, *_ = np.linalg.lstsq(A, M[:, k], rcond=None)
            res = float(np.std(M[:, k] - A @ coef))
            if res <= explained_degC:
                del kept_reason[c]
                dropped[c] = f"inside the gradient of {s}: explained by corners {a}, {b} to {res:.3f} degC rms"
    kept = [c for c in chans if c in kept_reason]
    return ScreeningResult(matrix=R, kept=kept, kept_reason=kept_reason, dropped=dropped)
