"""Diagnosis findings folded into the next fit (issue 6): ``driftlab fit --findings REPORT.json``.

A diagnosis report v1 (``driftlab diagnose``) names effects the standard model misses, each on one
(axis, term). Each accepted effect becomes the physical regressor of its catalogue entry, offered to
the per-link models of that (axis, term) as a candidate term (or forced in):

========================  ==================================================================
``reversal``              approach direction of the axis (``dir[X]``)
``screw_expansion``       position x dT_k (``pos[X]*dT[T9]``), with dT_k as a candidate
``unmapped_channel``      dT_k, even when k is outside the bundle's ``model_channels``
``thermal_lag``           first-order lag of dT_k with the reported ``tau_s`` (``lag2400[T34]``), dT_k a candidate
``quadratic``             dT_k^2 (``dT[T37]^2``), dT_k a candidate
``drift``                 days since the model's time origin (``days[A]``)
``sensor_fault``          channel k replaced by its virtual-sensor estimate (neighbours' readings) from start_s
========================  ==================================================================

The model document records every such term among its terms' features, the substitutions of faulty
channels (``substitutions``), the time origin of drift terms (``time_origin``) and what became of
each finding (``findings``), so that ``document.predict_*`` reproduces them from the document alone.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, NotRequired, TypedDict

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.models.features import Feature, channel_columns, fill_gaps
from driftlab.models.virtual_sensor import fit_virtual_sensors
from driftlab.vocabulary import AXES, EFFECT_KINDS, TERMS

REPORT_FORMAT = "driftlab-diagnosis/1"
#: the effect catalogue of the bundle spec (section 3)
FINDING_KINDS: tuple[str, ...] = EFFECT_KINDS
#: kinds that name at least one thermocouple
CHANNEL_KINDS = frozenset(
    {
        "screw_expansion",
        "unmapped_channel",
        "thermal_lag",
        "sensor_fault",
        "quadratic",
        "sensor_drift",
        "direction_thermal",
    }
)
#: kinds the fit does not fold in (yet): reported in the document's ``findings`` with the reason
NOT_FOLDED: Mapping[str, str] = {
    "operating_condition": "a direct machine-state term: the fitting catalogue has no such feature yet (reported only)",
    "sensor_drift": "a drifting thermocouple: the fit has no ramp substitution yet (reported only)",
    "datum_shift": "a measurement artefact (a re-zeroed line): not a term of the machine's model (reported only)",
    "unsensed_source": "a lag of a heat-source schedule: the fitting catalogue has no such feature yet (reported only)",
    "direction_thermal": "direction x temperature: the fitting catalogue has no such feature yet (reported only)",
}
#: parameters a finding must carry to be folded in (the others are reported but not needed)
NEEDED_PARAMS: Mapping[str, tuple[str, ...]] = {"thermal_lag": ("tau_s",), "sensor_fault": ("start_s",)}
#: neighbours of a virtual sensor that replaces a faulty channel
N_NEIGHBOURS = 4


class FindingRecord(TypedDict):
    """The JSON form of a :class:`Finding`: the report's effect entry, reduced to what the fit uses."""

    kind: str
    axis: str | None
    term: str | None
    channels: list[str]
    #: the effect's figures as the report states them (``tau_s``, ``start_s``, ``mode``, per-channel maps...)
    params: dict[str, object]


class FindingsRecord(TypedDict):
    """The JSON form of :class:`Findings` kept in a fit job's parameters (re-read by ``parse_findings``)."""

    format: str
    bundle: str
    effects: list[FindingRecord]


class FindingOutcomeRecord(FindingRecord):
    """One entry of the model document's ``findings``: the finding and what became of it."""

    folded: bool
    note: NotRequired[str]  # why it was not folded in
    substituted: NotRequired[list[str]]  # a sensor fault: the channels replaced by their estimates
    terms: NotRequired[list[str]]  # the terms it added
    forced: NotRequired[bool]
    entered: NotRequired[dict[str, list[str]]]  # feature name -> the element.param models that kept it


@dataclass(frozen=True)
class Finding:
    """One accepted effect of a diagnosis report: kind, (axis, term), channels and catalogue parameters."""

    kind: str
    axis: str | None  # None (with term) for a broken channel that feeds no model
    term: str | None
    channels: tuple[str, ...] = ()
    params: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> FindingRecord:
        """Return the JSON form (the report's effect entry, reduced to what the fit uses)."""
        return {
            "kind": self.kind,
            "axis": self.axis,
            "term": self.term,
            "channels": list(self.channels),
            "params": dict(self.params),
        }

    def start_s(self, channel: str) -> float:
        """Return when a sensor fault of ``channel`` started (s since the report bundle's start)."""
        by = self.params.get("start_s_by_channel") or {}
        return float(by.get(channel, self.params["start_s"]))


@dataclass(frozen=True)
class Findings:
    """The effects of one diagnosis report and the bundle it was made on."""

    bundle: str
    effects: tuple[Finding, ...]

    def to_dict(self) -> FindingsRecord:
        """Return the JSON form kept in a fit job's parameters (re-read by ``parse_findings``)."""
        return {"format": REPORT_FORMAT, "bundle": self.bundle, "effects": [e.to_dict() for e in self.effects]}


def parse_findings(data: Any, source: str = "findings") -> Findings:
    """Return the findings of a diagnosis report v1 (a dict), or raise ValidationError with one line."""

    def bad(msg: str) -> ValidationError:
        return ValidationError(f"{source}: {msg}")

    if not isinstance(data, Mapping):
        raise bad("not a diagnosis report (a JSON object expected)")
    if data.get("format") != REPORT_FORMAT:
        raise bad(f"format must be {REPORT_FORMAT!r}, got {data.get('format')!r}")
    effects = data.get("effects")
    if not isinstance(effects, list):
        raise bad("'effects' must be a list")
    out = []
    for i, e in enumerate(effects):
        where = f"effects[{i}]"
        if not isinstance(e, Mapping):
            raise bad(f"{where} is not an object")
        kind = e.get("kind")
        if kind not in FINDING_KINDS:
            raise bad(f"{where}: unknown kind {kind!r} (one of {', '.join(FINDING_KINDS)})")
        axis, term = e.get("axis"), e.get("term")
        if kind in ("sensor_fault", "sensor_drift") and axis is None and term is None:
            pass  # a broken channel that feeds no model: a finding about the temperatures only
        elif axis not in AXES:
            raise bad(f"{where}: axis must be one of {' '.join(AXES)}, got {axis!r}")
        elif term not in TERMS:
            raise bad(f"{where}: term must be one of {' '.join(TERMS)}, got {term!r}")
        channels = e.get("channels", [])
        if not isinstance(channels, list) or not all(isinstance(c, str) and c for c in channels):
            raise bad(f"{where}: channels must be a list of channel names")
        if kind in CHANNEL_KINDS and not channels:
            raise bad(f"{where}: a {kind} finding names its channel(s)")
        params = e.get("params", {})
        if not isinstance(params, Mapping):
            raise bad(f"{where}: params must be an object")
        for p in NEEDED_PARAMS.get(kind, ()):
            v = params.get(p)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v):
                raise bad(f"{where}: {kind} needs a number {p!r}")
        if kind == "thermal_lag" and float(params["tau_s"]) <= 0:
            raise bad(f"{where}: tau_s must be > 0")
        if kind == "sensor_fault" and float(params["start_s"]) < 0:
            raise bad(f"{where}: start_s must be >= 0")
        out.append(Finding(kind, axis, term, tuple(channels), dict(params)))
    return Findings(str(data.get("bundle", "")), tuple(out))


def load_findings(path: str | Path) -> Findings:
    """Return the findings of a diagnosis report file, or raise ValidationError with one line."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except OSError as exc:
        raise ValidationError(f"findings {p}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ValidationError(f"findings {p}: not JSON ({exc})") from None
    return parse_findings(data, f"findings {p}")


def finding_features(f: Finding) -> tuple[list[Feature], list[Feature]]:
    """Return (the finding's own terms, supporting candidates) it adds to its (axis, term)'s models."""
    chans = f.channels
    axis = f.axis or ""  # every kind below but sensor_fault names its axis (parse_findings)
    if f.kind == "reversal":
        return [Feature("direction", label=axis)], []
    if f.kind == "screw_expansion":  # eq. 3.2, plus dT_k itself when k is not in the model
        return [Feature("pos_dT", (c,), label=axis) for c in chans], [Feature("dT", (c,)) for c in chans]
    if f.kind == "unmapped_channel":
        return [Feature("dT", (c,)) for c in chans], []
    if f.kind == "thermal_lag":  # a lag of a channel outside the model enters with that channel's dT
        tau = float(f.params["tau_s"])
        return [Feature("lag", (c,), tau_s=tau) for c in chans], [Feature("dT", (c,)) for c in chans]
    if f.kind == "quadratic":  # dT_k^2 about the model's reference needs dT_k beside it
        return [Feature("quad", (c,)) for c in chans], [Feature("dT", (c,)) for c in chans]
    if f.kind == "drift":
        return [Feature("time", label=axis)], []
    return [], []  # sensor_fault: a substitution of the input, not a term


# ----------------------------------------------------------------------------- substitutions


class SubstitutionRecord(TypedDict):
    """The JSON form of a :class:`Substitution` kept in a model document (``substitutions``)."""

    channel: str
    neighbours: list[str]
    coef: list[float]
    since: str  # ISO 8601
    start_s: float
    mode: str


@dataclass(frozen=True)
class Substitution:
    """A faulty channel replaced from ``since`` by a linear estimate from its neighbours (ch. 6.6)."""

    channel: str
    neighbours: tuple[str, ...]
    coef: tuple[float, ...]  # intercept first, then one per neighbour (degC per degC)
    since: datetime
    start_s: float  # the same instant in seconds since the diagnosed bundle's start
    mode: str = ""

    def estimate(self, readings: Mapping[str, Any]) -> np.ndarray:
        """Return the estimate of the channel (degC) from its neighbours' readings."""
        out = np.asarray(self.coef[0], float)
        for c, k in zip(self.neighbours, self.coef[1:]):
            out = out + float(k) * np.asarray(readings[c], float)
        return out

    def to_dict(self) -> SubstitutionRecord:
        """Return the JSON form kept in a model document (``substitutions``)."""
        return {
            "channel": self.channel,
            "neighbours": list(self.neighbours),
            "coef": [float(c) for c in self.coef],
            "since": self.since.isoformat(),
            "start_s": self.start_s,
            "mode": self.mode,
        }


def fit_substitution(
    temperatures: pd.DataFrame,
    channel: str,
    start_s: float,
    exclude: Sequence[str] = (),
    n_neighbours: int = N_NEIGHBOURS,
    structures: Mapping[str, str] | None = None,
    room: Sequence[str] = (),
) -> tuple[tuple[str, ...], tuple[float, ...]]:
    """Return (neighbours, coefficients) of ``channel``'s virtual sensor, fitted on the scans before ``start_s``.

    The neighbours are the other sites of the channel's structure and the room air when the bundle
    names structures (as the diagnosis does), else the ``n_neighbours`` that best explain it.
    """
    before = temperatures[temperatures["time_s"] < start_s]
    others = [
        c
        for c in channel_columns(before)
        if c != channel and c not in exclude and np.isfinite(before[c].to_numpy(float)).any()
    ]
    if before.shape[0] < 10 or not others:
        raise ValidationError(
            f"findings: too few readings before t={start_s:.0f} s to estimate {channel} from its neighbours"
        )
    st = (structures or {}).get(channel, "")
    near = [c for c in others if st and st not in ("", "unspecified", "room") and (structures or {}).get(c) == st]
    if near:
        pool = near + [c for c in room if c in others and c not in near]
        n_neighbours = len(pool)
    else:
        pool = others
    sensor = fit_virtual_sensors(before[["time_s", channel, *pool]], [channel, *pool], n_neighbours=n_neighbours)[
        channel
    ]
    return tuple(sensor.neighbours), tuple(float(c) for c in sensor.coef)


def apply_substitutions(
    temperatures: pd.DataFrame, started_at: datetime, substitutions: Sequence[Substitution]
) -> pd.DataFrame:
    """Return the temperatures with each substituted channel replaced by its estimate from ``since`` on."""
    if not substitutions:
        return temperatures
    out = temperatures.copy()
    filled = fill_gaps(temperatures)
    t = out["time_s"].to_numpy(float)
    for s in substitutions:
        if s.channel not in out.columns:
            continue
        from_s = (s.since - started_at).total_seconds()
        m = t >= from_s
        if m.any():
            v = out[s.channel].to_numpy(float).copy()
            v[m] = s.estimate({c: filled[c].to_numpy(float)[m] for c in s.neighbours})
            out[s.channel] = v
    return out


# ----------------------------------------------------------------------------- a plan for the fit


@dataclass(frozen=True)
class Extra:
    """A term a finding adds to the models of one (axis, term): forced in, or offered as a candidate."""

    axis: str
    term: str
    feature: Feature
    forced: bool
    finding: int  # index into the findings


@dataclass
class FindingsPlan:
    """What the fit does with the findings: bundles with faulty channels substituted, extra terms, inputs."""

    findings: Findings
    bundles: list[Any]
    extras: list[Extra]
    channels: list[str]  # channels the extra terms and substitutions read (model inputs)
    lags: list[tuple[str, float]]
    substitutions: list[Substitution]
    skipped: dict[int, str] = field(default_factory=dict)  # finding index -> why it was not folded in

    def records(self, entered: Mapping[str, list[str]]) -> list[FindingOutcomeRecord]:
        """Return the document's ``findings``: each finding, the terms it added and the models they entered.

        ``entered`` maps a feature name to the ``element.param`` models that kept it.
        """
        out = []
        for i, f in enumerate(self.findings.effects):
            rec: FindingOutcomeRecord = {**f.to_dict(), "folded": i not in self.skipped}
            if i in self.skipped:
                rec["note"] = self.skipped[i]
            elif f.kind == "sensor_fault":
                rec["substituted"] = [s.channel for s in self.substitutions if s.channel in f.channels]
            else:
                mine = [e for e in self.extras if e.finding == i]
                rec["terms"] = [e.feature.name for e in mine if not _support(e, mine)]
                rec["forced"] = bool(mine and mine[0].forced)
                rec["entered"] = {e.feature.name: entered.get(e.feature.name, []) for e in mine}
            out.append(rec)
        return out


def _support(e: Extra, mine: Sequence[Extra]) -> bool:
    """Return True for a supporting candidate (dT_k beside the finding's own term)."""
    return e.feature.kind == "dT" and any(o.feature.kind != "dT" for o in mine)


def _report_bundle(findings: Findings, bundles: Sequence[Any]) -> Any:
    """Return the bundle the report was made on: by name, else the only one."""
    for b in bundles:
        if b.name == findings.bundle:
            return b
    if len(bundles) == 1:
        return bundles[0]
    names = ", ".join(b.name for b in bundles)
    raise ValidationError(
        f"findings: the report is of bundle {findings.bundle!r}, none of the campaigns ({names}); "
        f"its sensor-fault times cannot be placed"
    )


def plan_findings(
    findings: Findings, bundles: Sequence[Any], force: bool = False, measured: set[tuple[str, str]] | None = None
) -> FindingsPlan:
    """Return how the fit folds ``findings`` into the models of ``bundles`` (validated against them).

    A finding whose channel some campaign lacks is an error; one on an (axis, term) no campaign
    measured is skipped (recorded in the document with a note).
    """
    if measured is None:
        measured = set()
        for b in bundles:
            measured |= set(map(tuple, b.errors[["axis", "term"]].drop_duplicates().to_numpy().tolist()))
    extras: list[Extra] = []
    channels: list[str] = []
    lags: list[tuple[str, float]] = []
    skipped: dict[int, str] = {}
    faults: list[tuple[str, float, str]] = []
    for i, f in enumerate(findings.effects):
        for c in f.channels:
            lacking = [b.name for b in bundles if c not in b.temperatures.columns]
            if lacking:
                raise ValidationError(
                    f"findings: channel {c} of the {f.kind} finding on {f.axis}/{f.term} is not "
                    f"in campaign {lacking[0]!r}"
                )
        if f.kind == "sensor_fault":
            for c in f.channels:
                if c not in [x for x, _, _ in faults]:
                    faults.append(
                        (c, f.start_s(c), str((f.params.get("mode_by_channel") or {}).get(c, f.params.get("mode", ""))))
                    )
            continue
        if f.kind in NOT_FOLDED:
            skipped[i] = NOT_FOLDED[f.kind]
            continue
        if f.axis is None or f.term is None or (f.axis, f.term) not in measured:
            skipped[i] = f"no {f.axis}/{f.term} measurements in these campaigns"
            continue
        own, support = finding_features(f)
        extras += [Extra(f.axis, f.term, ft, force, i) for ft in own]
        extras += [Extra(f.axis, f.term, ft, False, i) for ft in support]
        channels += [c for c in f.channels if c not in channels]
        lags += [(c, float(ft.tau_s or 0)) for ft in own if ft.kind == "lag" for c in ft.channels]
    subs: list[Substitution] = []
    out_bundles = list(bundles)
    if faults:
        src = _report_bundle(findings, bundles)
        t0 = src.meta.started_at
        faulty = [c for c, _, _ in faults]
        for c, start_s, mode in faults:
            neighbours, coef = fit_substitution(
                src.temperatures,
                c,
                start_s,
                exclude=faulty,
                structures={k: ch.structure for k, ch in src.meta.channels.items()},
                room=src.meta.room_channels,
            )
            subs.append(Substitution(c, neighbours, coef, t0 + timedelta(seconds=start_s), start_s, mode))
            channels += [x for x in (c, *neighbours) if x not in channels]
        for c in channels:
            lacking = [b.name for b in bundles if c not in b.temperatures.columns]
            if lacking:
                raise ValidationError(
                    f"findings: channel {c} (a virtual sensor's neighbour) is not in campaign {lacking[0]!r}"
                )
        out_bundles = [
            replace(b, temperatures=apply_substitutions(b.temperatures, b.meta.started_at, subs)) for b in bundles
        ]
    return FindingsPlan(findings, out_bundles, extras, channels, list(dict.fromkeys(lags)), subs, skipped)
