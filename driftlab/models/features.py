"""Physically recast regression terms (ch. 6.4.2): dT, structure means, gradients, position x dT, lags."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, NotRequired, TypedDict, Unpack, get_args

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.physics.lag import first_order_lag
from driftlab.vocabulary import AXES

Kind = Literal[
    "intercept",
    "position",
    "direction",
    "dT",
    "lag",
    "mean",
    "gradient",
    "pos_dT",
    "quad",
    "time",
    "session",
    "lever",
]
#: the kinds, in the order of ``Kind``
KINDS: tuple[str, ...] = get_args(Kind)
#: kinds that read a joint coordinate or approach direction; their ``label`` names the axis
AXIS_KINDS: frozenset[str] = frozenset({"position", "direction", "pos_dT", "lever"})
#: columns of a (N, 5) joint array


class FeatureRecord(TypedDict):
    """The JSON form of a :class:`Feature` stored in a model document."""

    kind: str
    name: str
    channels: NotRequired[list[str]]
    power: NotRequired[int]
    tau_s: NotRequired[float]
    label: NotRequired[str]


@dataclass(frozen=True)
class Feature:
    """One regression term: how to compute a column from temperatures, position and direction."""

    kind: str
    channels: tuple[str, ...] = ()
    power: int = 1
    tau_s: float | None = None
    label: str = ""

    def __post_init__(self) -> None:
        """Check the kind and the number of channels it needs."""
        if self.kind not in KINDS:
            raise ValidationError(f"unknown feature kind {self.kind!r}")
        need = {"dT": 1, "lag": 1, "pos_dT": 1, "quad": 1, "time": 0, "session": 0, "lever": 1}
        if self.kind == "gradient" and not (len(self.channels) >= 2 and 1 <= self.power < len(self.channels)):
            raise ValidationError(f"a gradient needs channels on both sides, got {self.channels} split at {self.power}")
        if self.kind in need and len(self.channels) != need[self.kind]:
            raise ValidationError(f"feature {self.kind} needs {need[self.kind]} channel(s), got {self.channels}")
        if self.kind == "mean" and len(self.channels) < 2:
            raise ValidationError("a structure mean needs at least two channels")
        if self.kind == "lag" and not (self.tau_s and self.tau_s > 0):
            raise ValidationError("a lag feature needs tau_s > 0")
        if self.kind == "session" and not self.label:
            raise ValidationError("a session offset needs the session's label")
        if self.kind == "lever" and not (self.label and (self.power >= 2 or (self.tau_s and self.tau_s > 0))):
            raise ValidationError("a lever term needs its axis and a power of 2 or more, or a lag (else it is pos_dT)")

    @property
    def name(self) -> str:
        """Return the term's display name, e.g. ``pos[X]*dT[T9]`` or ``grad[T34-T32]``."""
        c = self.channels
        ax = f"[{self.label}]" if self.label and (self.kind in AXIS_KINDS or self.kind == "time") else ""
        if self.kind == "intercept":
            return "const"
        if self.kind == "position":
            return f"pos{ax}" if self.power == 1 else f"pos{ax}^{self.power}"
        if self.kind == "direction":
            return f"dir{ax}"
        if self.kind == "dT":
            return f"dT[{c[0]}]"
        if self.kind == "lag":
            return f"lag{int(round(self.tau_s or 0))}[{c[0]}]"
        if self.kind == "pos_dT":
            return f"pos{ax}*dT[{c[0]}]"
        if self.kind == "lever":
            inner = f"lag{int(round(self.tau_s))}[{c[0]}]" if self.tau_s else f"dT[{c[0]}]"
            return f"pos{ax}{'' if self.power == 1 else f'^{self.power}'}*{inner}"
        if self.kind == "quad":
            return f"dT[{c[0]}]^2"
        if self.kind == "time":
            return f"days{ax}"
        if self.kind == "session":
            return f"datum[{self.label}]"
        if self.kind == "gradient":
            return f"grad[{c[0]}-{c[1]}]" if len(c) == 2 else f"grad[{self.label or '+'.join(c)}]"
        return f"mean[{self.label or '+'.join(c)}]"

    def to_dict(self) -> FeatureRecord:
        """Return the JSON form stored in a model document."""
        out: FeatureRecord = {"kind": self.kind, "name": self.name}
        if self.channels:
            out["channels"] = list(self.channels)
        if self.kind in ("position", "lever") or (self.kind == "gradient" and len(self.channels) > 2):
            out["power"] = self.power
        if self.tau_s is not None:
            out["tau_s"] = float(self.tau_s)
        if self.label:
            out["label"] = self.label
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Feature:
        """Rebuild a feature from its JSON form."""
        return cls(
            kind=str(d["kind"]),
            channels=tuple(d.get("channels", ())),
            power=int(d.get("power", 1)),
            tau_s=None if d.get("tau_s") is None else float(d["tau_s"]),
            label=str(d.get("label", "")),
        )


INTERCEPT = Feature("intercept")


@dataclass
class Inputs:
    """Inputs at the error samples: dT per channel, lagged dT and (drift terms) days since the time origin."""

    dT: pd.DataFrame
    lagged: dict[tuple[str, float], np.ndarray] = field(default_factory=dict)
    days: np.ndarray | None = None
    #: the instrument session of each sample (``session`` terms); None outside a campaign
    session: np.ndarray | None = None

    def __len__(self) -> int:
        """Return the number of samples."""
        return len(self.dT)

    def take(self, index: np.ndarray) -> Inputs:
        """Return the inputs restricted to the rows ``index`` (boolean mask or integer positions)."""
        idx = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index)
        return Inputs(
            dT=self.dT.iloc[idx].reset_index(drop=True),
            lagged={k: v[idx] for k, v in self.lagged.items()},
            days=None if self.days is None else self.days[idx],
            session=None if self.session is None else self.session[idx],
        )


def channel_columns(temperatures: pd.DataFrame) -> list[str]:
    """Return the thermocouple columns of a temperatures frame (everything but ``time_s``)."""
    return [c for c in temperatures.columns if c != "time_s"]


def fill_gaps(temperatures: pd.DataFrame) -> pd.DataFrame:
    """Return temperatures with missing readings interpolated in time (edges held)."""
    out = temperatures.copy()
    chans = channel_columns(out)
    if not chans:
        return out
    t = out["time_s"].to_numpy(float)
    for c in chans:
        v = out[c].to_numpy(float)
        ok = np.isfinite(v)
        if ok.all() or not ok.any():
            continue
        out[c] = np.interp(t, t[ok], v[ok])
    return out


def build_inputs(
    temperatures: pd.DataFrame,
    at_times: np.ndarray,
    reference: Mapping[str, float],
    channels: Sequence[str] | None = None,
    lags: Iterable[tuple[str, float]] = (),
) -> Inputs:
    """Return dT = T - T_ref (eq. 3.1) and lagged dT for ``channels``, interpolated to ``at_times``."""
    chans = list(channels) if channels is not None else list(reference)
    missing = [c for c in chans if c not in temperatures.columns]
    if missing:
        raise ValidationError(f"temperatures lack channel(s) {', '.join(missing)}")
    temps = fill_gaps(temperatures[["time_s", *chans]])
    t = temps["time_s"].to_numpy(float)
    at = np.asarray(at_times, float)
    dT = {}
    series = {}
    for c in chans:
        d = temps[c].to_numpy(float) - float(reference[c])
        series[c] = d
        dT[c] = np.interp(at, t, d)
    lagged = {}
    for c, tau in lags:
        if c not in series:
            continue
        lagged[(c, float(tau))] = np.interp(at, t, first_order_lag(series[c], t, float(tau)))
    return Inputs(dT=pd.DataFrame(dT, columns=chans), lagged=lagged)


def inputs_from_snapshot(temperatures: Mapping[str, float], reference: Mapping[str, float]) -> Inputs:
    """Return single-sample inputs from one reading per channel (lags taken as settled: lag = dT)."""
    dT = {c: [float(v) - float(reference[c])] for c, v in temperatures.items() if c in reference}
    return Inputs(dT=pd.DataFrame(dT))


def _dT(inputs: Inputs, channel: str) -> np.ndarray:
    """Return dT of one channel, or raise a one-line error naming it."""
    if channel not in inputs.dT.columns:
        raise ValidationError(f"no temperature for channel {channel}")
    return inputs.dT[channel].to_numpy(float)


def _axis_column(feature: Feature, values: np.ndarray | None, n: int) -> np.ndarray:
    """Return the per-sample coordinate (or direction) a feature reads: a (N,) array, or the column of its
    axis label in (N, 5)."""
    if values is None:
        return np.zeros(n)
    v = np.asarray(values, float)
    if v.ndim == 2:
        if feature.label not in AXES:
            raise ValidationError(f"feature {feature.name} names no axis, so it cannot read a (N, 5) array")
        return v[:, AXES.index(feature.label)]
    return np.broadcast_to(v, (n,)).astype(float)


def evaluate(
    feature: Feature,
    inputs: Inputs,
    position: np.ndarray | None = None,
    direction: np.ndarray | None = None,
) -> np.ndarray:
    """Return the column of one feature for every sample.

    ``position``/``direction`` are (N,) for the feature's own joint, or (N, 5) joint coordinates and
    approach directions from which a feature labelled with an axis takes its column.
    """
    if len(inputs.dT.columns):
        n = len(inputs)
    elif position is not None:
        n = np.asarray(position).shape[0] if np.ndim(position) else 1
    else:
        n = 1
    k = feature.kind
    if k == "intercept":
        return np.ones(n)
    if k == "position":
        return _axis_column(feature, position, n) ** feature.power
    if k == "direction":
        return _axis_column(feature, direction, n).copy()
    if k == "dT":
        return _dT(inputs, feature.channels[0])
    if k == "lag":
        key = (feature.channels[0], float(feature.tau_s or 0))
        # a snapshot carries no history: a settled lag equals its input
        return inputs.lagged[key] if key in inputs.lagged else _dT(inputs, feature.channels[0])
    if k == "pos_dT":
        return _axis_column(feature, position, n) * _dT(inputs, feature.channels[0])  # eq. 3.2
    if k == "lever":  # a link's thermal term seen through the chain's lever arm (eq. 4.12 to first order)
        key = (feature.channels[0], float(feature.tau_s or 0))
        inner = inputs.lagged[key] if feature.tau_s and key in inputs.lagged else _dT(inputs, feature.channels[0])
        return _axis_column(feature, position, n) ** feature.power * inner
    if k == "quad":  # a nonlinear thermal response (ch. 6.4.2)
        return _dT(inputs, feature.channels[0]) ** 2
    if k == "time":  # a slow change not explained by temperature: wear, material instability (ch. 6.4.3)
        if inputs.days is None:
            raise ValidationError(f"term {feature.name} needs the time of each sample")
        return np.broadcast_to(np.asarray(inputs.days, float), (n,)).copy()
    if k == "session":
        # a laser zeroed when it was set up reads every error less its value at that moment (ch. 5.5):
        # an unknown constant per setup session, nothing outside a campaign (compensation)
        if inputs.session is None:
            return np.zeros(n)
        return (np.asarray(inputs.session) == feature.label).astype(float)
    if k == "gradient":  # eqs. 3.4-3.5: one side of a structure minus the other
        a, b = feature.channels[: feature.power], feature.channels[feature.power :]
        return np.mean([_dT(inputs, c) for c in a], axis=0) - np.mean([_dT(inputs, c) for c in b], axis=0)
    return np.mean([_dT(inputs, c) for c in feature.channels], axis=0)  # eq. 3.3


def design_matrix(
    features: Sequence[Feature],
    inputs: Inputs,
    position: np.ndarray | None = None,
    direction: np.ndarray | None = None,
) -> pd.DataFrame:
    """Return the (N, k) design matrix of ``features`` as a DataFrame named by term."""
    cols = {f.name: evaluate(f, inputs, position, direction) for f in features}
    return pd.DataFrame(cols, columns=[f.name for f in features])


def required_channels(features: Iterable[Feature]) -> list[str]:
    """Return the channels a list of features reads, in first-use order."""
    out: list[str] = []
    for f in features:
        for c in f.channels:
            if c not in out:
                out.append(c)
    return out


def required_lags(features: Iterable[Feature]) -> list[tuple[str, float]]:
    """Return the (channel, tau_s) lags a list of features needs."""
    return [
        (f.channels[0], float(f.tau_s or 0)) for f in features if f.kind == "lag" or (f.kind == "lever" and f.tau_s)
    ]


#: opposite sides of a structure, recognised in the sites' locations (Table 5.1 wording)
SIDES: tuple[tuple[str, str], ...] = (("upper", "lower"), ("top", "bottom"), ("front", "back"), ("left", "right"))


def _splits(channels: Sequence[str], locations: Mapping[str, str]) -> list[tuple[str, str, list[str], list[str]]]:
    """Return (side, other side, sites on one, sites on the other) for every pair of opposite sides found."""
    out = []
    for a, b in SIDES:
        one = [c for c in channels if a in locations.get(c, "").lower().split()]
        two = [c for c in channels if b in locations.get(c, "").lower().split()]
        if one and two and len(one) + len(two) > 2:
            out.append((a, b, one, two))
    return out


@dataclass(frozen=True)
class CandidateSpec:
    """What the candidate terms of a link or joint are built from, beside its channels and their structures."""

    #: the moving axes: their position shape, approach direction and ballscrew position x dT
    axes: Sequence[str] = ()
    #: axis -> its ballscrew channels (eq. 3.2)
    screw_channels: Mapping[str, Sequence[str]] | None = None
    #: the time constants of the first-order lags of dT
    lag_taus_s: Sequence[float] = ()
    #: the channels lagged (None: every channel)
    lag_channels: Sequence[str] | None = None
    #: the room's channels (ceiling first, floor second)
    room_channels: Sequence[str] = ()
    #: structure -> all its sites that read (a structure's mean is over them, eq. 3.3)
    structure_members: Mapping[str, Sequence[str]] | None = None
    #: channel -> its location text (opposite sides are recognised in it)
    locations: Mapping[str, str] | None = None
    #: the highest power of the position shape
    max_power: int = 3


class CandidateFields(TypedDict, total=False):
    """``CandidateSpec``'s fields as keywords of ``candidate_features``."""

    axes: Sequence[str]
    screw_channels: Mapping[str, Sequence[str]] | None
    lag_taus_s: Sequence[float]
    lag_channels: Sequence[str] | None
    room_channels: Sequence[str]
    structure_members: Mapping[str, Sequence[str]] | None
    locations: Mapping[str, str] | None
    max_power: int


def candidate_features(
    channels: Sequence[str],
    structures: Mapping[str, str],
    spec: CandidateSpec | None = None,
    **fields: Unpack[CandidateFields],
) -> list[Feature]:
    """Return the candidate terms of a link or joint error (ch. 6.4.2).

    For each moving axis in ``axes``: its position shape (pos, pos^2, pos^3), approach direction
    (reversal) and position x dT of its ballscrew channels (eq. 3.2). For the temperatures: dT per
    channel, the mean of each structure over all its sites (eq. 3.3, from ``structure_members``),
    gradients between the kept sites of a structure and between its opposite sides (upper-lower,
    front-back, left-right from the sites' ``locations``; eqs. 3.4-3.5), the room's ceiling-floor
    difference, and first-order lags of dT. The named inputs are ``spec``'s (``CandidateSpec``),
    each also accepted by keyword.
    """
    sp = replace(spec or CandidateSpec(), **fields)
    room_channels = sp.room_channels
    out: list[Feature] = []
    for ax in sp.axes:
        out += [Feature("position", power=p, label=ax) for p in range(1, sp.max_power + 1)]
        out.append(Feature("direction", label=ax))
        out += [Feature("pos_dT", (c,), label=ax) for c in (sp.screw_channels or {}).get(ax, ()) if c in channels]
    out += [Feature("dT", (c,)) for c in channels]
    by_struct: dict[str, list[str]] = {}
    for c in channels:
        s = structures.get(c, "")
        if s and c not in room_channels:
            by_struct.setdefault(s, []).append(c)
    members = dict(sp.structure_members or {})
    for s, cs in by_struct.items():
        group = [c for c in members.get(s, cs)]
        if len(group) >= 2:
            out.append(Feature("mean", tuple(group), label=s))
        for side_a, side_b, a, b in _splits(group, sp.locations or {}):
            out.append(Feature("gradient", tuple(a + b), power=len(a), label=f"{s} {side_a}-{side_b}"))
        for i in range(len(cs)):
            for j in range(i + 1, len(cs)):
                out.append(Feature("gradient", (cs[j], cs[i])))
    if len(room_channels) >= 2 and all(c in channels for c in room_channels[:2]):
        out.append(Feature("gradient", (room_channels[0], room_channels[1])))
    for tau in sp.lag_taus_s:
        for c in sp.lag_channels if sp.lag_channels is not None else channels:
            if c in channels:
                out.append(Feature("lag", (c,), tau_s=float(tau)))
    return out


def session_terms(sessions: np.ndarray | None, rows: np.ndarray) -> list[Feature]:
    """Return one offset term per zeroed session among ``rows`` (none for the first when all rows are zeroed).

    With every row relative to its own datum the intercept carries the first session's offset;
    rows against a stable artefact pin the intercept themselves.
    """
    if sessions is None:
        return []
    s = np.asarray(sessions, dtype=object)[rows]
    labels = list(dict.fromkeys(x for x in s if x))
    if labels and all(s != ""):
        labels = labels[1:]
    return [Feature("session", label=x) for x in labels]
