"""Virtual-machine scenarios: the staged test plan, noise levels, room and hidden effects.

A scenario is built in code (``Scenario(hours=12, hidden=[HiddenEffect(...)])``) or read from YAML
with ``load_scenario(path)``. When ``stages`` is omitted the staged single-heat-source plan of the
thesis (ch. 5.2 Fig. 5.1, ch. 6.3) is generated: spindle alone, then each axis feed alone, the
rotary drives, spindle and Z feed combined, with cool-downs and a power-off night between them.
"""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic import ValidationError as PydanticValidationError

from driftlab.daq.sim.sites import MODEL_CHANNELS, SITE_INDEX
from driftlab.errors import ValidationError
from driftlab.physics.geometry import Geometry
from driftlab.vocabulary import EFFECT_KINDS, ROTATIONS, Axis, Term
from driftlab.yamlfile import read_yaml

HeatSource = Literal["spindle", "feed", "combined", "idle", "off"]

ANGLE_TERMS: frozenset[str] = frozenset(ROTATIONS)
HEAT_SOURCES: tuple[str, ...] = ("spindle", "feed", "combined", "idle", "off")
#: the catalogue's kinds the virtual machine can plant (the first seven of the spec's section 3)
KINDS: tuple[str, ...] = EFFECT_KINDS[:7]
#: 0.1 arc-second (ch. 5.5 laser angle accuracy) in rad
ARCSEC_0_1_RAD = 0.1 / 3600.0 * math.pi / 180.0

# effect catalogue (spec section 3): required and optional params per kind
_REQUIRED: dict[str, tuple[str, ...]] = {
    "reversal": (),  # magnitude_mm or magnitude_rad, checked against the term
    "screw_expansion": ("coef_per_mm_degC",),
    "unmapped_channel": ("coef_per_degC",),
    "thermal_lag": ("tau_s",),
    "sensor_fault": ("start_s", "mode"),
    "drift": ("rate_per_day",),
    "quadratic": ("coef_per_degC2",),
}
_OPTIONAL: dict[str, tuple[str, ...]] = {
    "reversal": ("magnitude_mm", "magnitude_rad"),
    "thermal_lag": ("coef_per_degC",),  # only where the channel has no base coefficient on the term
    "sensor_fault": ("tau_s", "rail_degC"),  # detachment time constant; value an open card reports
}
_N_CHANNELS: dict[str, tuple[int, int]] = {
    "reversal": (0, 0),
    "drift": (0, 0),
    "screw_expansion": (1, 1),
    "unmapped_channel": (1, 1),
    "thermal_lag": (1, 1),
    "quadratic": (1, 1),
    "sensor_fault": (1, 50),
}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MachineInfo(_Strict):
    """Machine identity and resolution as written to campaign.json."""

    id: str = Field(default="vmc-5ax-01", min_length=1, max_length=64)
    name: str = "five-axis VMC with A/B tilt table (virtual)"
    resolution_mm: float = Field(default=0.0025, gt=0)
    resolution_deg: float = Field(default=0.001, gt=0)
    #: the stated dimensions of table 6.3's physical check (absent: the fit reports "no geometry")
    geometry: Geometry | None = None


class Noise(_Strict):
    """Measurement noise (1 sigma): laser lengths, laser angles (ch. 5.5), thermocouple scans (ch. 5.3).

    The thermocouple default is 0.01 degC, not the ~0.05 degC of a raw reading (ch. 5.3: +/-0.1 degC
    ice-bath repeatability; the DAS-TC card smooths its scans, ch. 6.3): scan noise enters the
    standard model through its dT regressors, and at 0.05 degC the arm-bending angle of Table 6.3
    (2.4e-5 rad/degC of gradient) would add 1.2e-6 rad - 2.5x the laser's 0.1 arc-second - so no
    model could reach the stated laser noise. At 0.01 degC the clean residual is within 1.12x of it.
    """

    length_mm: float = Field(default=0.0005, ge=0, allow_inf_nan=False)
    angle_rad: float = Field(default=ARCSEC_0_1_RAD, ge=0, allow_inf_nan=False)
    thermocouple_degC: float = Field(default=0.01, ge=0, allow_inf_nan=False)


class Room(_Strict):
    """Hall air: mean, ceiling-minus-floor difference, daily cycle and its peak hour, local disturbances."""

    mean_degC: float = Field(default=20.0, allow_inf_nan=False)
    ceiling_floor_degC: float = Field(default=1.5, allow_inf_nan=False)
    daily_amplitude_degC: float = Field(default=1.0, ge=0, allow_inf_nan=False)
    peak_hour: float = Field(default=15.0, ge=0, lt=24)
    # local air at each site (drafts, sun patches, coolant mist): a random first-order (Ornstein-
    # Uhlenbeck) disturbance per site, so no thermocouple is an exact mix of the others (Table 5.2)
    local_sigma_degC: float = Field(default=0.3, ge=0, allow_inf_nan=False)
    local_tau_s: float = Field(default=2700.0, gt=0, allow_inf_nan=False)


class Stage(_Strict):
    """One stage of the staged test plan (bundle v1 ``stages``)."""

    name: str = Field(min_length=1)
    start_s: float = Field(ge=0, allow_inf_nan=False)
    end_s: float = Field(ge=0, allow_inf_nan=False)
    heat_source: HeatSource
    axis: Axis | None = None
    spindle_rpm: float = Field(default=0.0, ge=0, allow_inf_nan=False)
    feed_mm_min: float = Field(default=0.0, ge=0, allow_inf_nan=False)  # deg/min for A/B

    @field_validator("heat_source", mode="before")
    @classmethod
    def _yaml_off(cls, v: Any) -> Any:
        return "off" if v is False else v  # YAML 1.1 reads a bare `off` as false

    @model_validator(mode="after")
    def _consistent(self) -> Stage:
        if self.end_s <= self.start_s:
            raise ValueError(f"end_s {self.end_s} must be after start_s {self.start_s}")
        if self.heat_source in ("feed", "combined"):
            if self.axis is None:
                raise ValueError(f"a {self.heat_source} stage needs an axis")
            if self.feed_mm_min <= 0:
                raise ValueError(f"a {self.heat_source} stage needs feed_mm_min > 0")
        if self.heat_source in ("spindle", "combined") and self.spindle_rpm <= 0:
            raise ValueError(f"a {self.heat_source} stage needs spindle_rpm > 0")
        return self


class HiddenEffect(_Strict):
    """An effect of the catalogue (spec section 3) planted in the truth but absent from the standard model."""

    kind: Literal[
        "reversal", "screw_expansion", "unmapped_channel", "thermal_lag", "sensor_fault", "drift", "quadratic"
    ]
    axis: Axis | None = None
    term: Term | None = None
    channels: list[str] = Field(default_factory=list)
    params: dict[str, float | str] = Field(default_factory=dict)

    @field_validator("params", mode="before")
    @classmethod
    def _numbers(cls, v: Any) -> Any:
        # YAML 1.1 reads "1e-3" (no dot) as a string: accept any numeric string as a number
        if isinstance(v, dict):
            out = {}
            for key, val in v.items():
                if isinstance(val, str) and key != "mode":
                    try:
                        val = float(val)
                    except ValueError:
                        pass
                out[key] = val
            return out
        return v

    @field_validator("channels")
    @classmethod
    def _known_channels(cls, v: list[str]) -> list[str]:

        for ch in v:
            if ch not in SITE_INDEX:
                raise ValueError(f"unknown channel {ch!r} (T1..T50)")
        return v

    @model_validator(mode="after")
    def _catalogue(self) -> HiddenEffect:
        k = self.kind
        if k != "sensor_fault" and (self.axis is None or self.term is None):
            raise ValueError(f"{k} needs an axis and a term")
        lo, hi = _N_CHANNELS[k]
        if not lo <= len(self.channels) <= hi:
            want = "no channels" if hi == 0 else ("exactly one channel" if lo == hi else "at least one channel")
            raise ValueError(f"{k} takes {want}, got {self.channels}")
        allowed = set(_REQUIRED[k]) | set(_OPTIONAL.get(k, ()))
        for p in self.params:
            if p not in allowed:
                raise ValueError(f"{k} does not take param {p!r} (allowed: {sorted(allowed)})")
        for p in _REQUIRED[k]:
            if p not in self.params:
                raise ValueError(f"{k} needs param {p!r}")
        for p, v in self.params.items():
            if p != "mode" and (isinstance(v, str) or not math.isfinite(float(v))):
                raise ValueError(f"param {p} must be a finite number, got {v!r}")
        if k == "reversal":
            want = "magnitude_rad" if self.term in ANGLE_TERMS else "magnitude_mm"
            if set(self.params) != {want}:
                raise ValueError(f"reversal on {self.term} needs exactly param {want!r}")
        if k == "thermal_lag" and float(self.params["tau_s"]) <= 0:
            raise ValueError("thermal_lag tau_s must be > 0")
        if k == "sensor_fault":
            if self.params["mode"] not in ("detached", "open"):
                raise ValueError(f"sensor_fault mode must be 'detached' or 'open', got {self.params['mode']!r}")
            if float(self.params["start_s"]) < 0:
                raise ValueError("sensor_fault start_s must be >= 0")
            if float(self.params.get("tau_s", 300.0)) <= 0:
                raise ValueError("sensor_fault tau_s must be > 0")
        if k == "unmapped_channel":
            assert self.axis is not None  # checked above: every kind but sensor_fault has an axis
            if self.channels[0] in MODEL_CHANNELS[self.axis]:
                raise ValueError(
                    f"{self.channels[0]} is a model channel of {self.axis}; unmapped_channel needs one "
                    f"outside model_channels (e.g. T11, T21, T31, T36, T47)"
                )
        return self


class Scenario(_Strict):
    """Everything that defines one simulated campaign; the result is a pure function of it."""

    name: str = "scenario"
    seed: int = 0
    hours: float = Field(default=24.0, gt=0, le=24 * 60, allow_inf_nan=False)
    scan_interval_s: float = Field(default=60.0, gt=0, allow_inf_nan=False)
    sweep_interval_s: float = Field(default=600.0, gt=0, allow_inf_nan=False)
    thermal_step_s: float = Field(default=60.0, gt=0, le=600, allow_inf_nan=False)
    points_per_axis: int = Field(default=11, ge=4, le=101)
    started_at: str = "2026-03-02T08:00:00Z"
    machine: MachineInfo = MachineInfo()
    room: Room = Room()
    noise: Noise = Noise()
    stages: list[Stage] | None = None
    hidden: list[HiddenEffect] = Field(default_factory=list)

    @field_validator("started_at")
    @classmethod
    def _iso(cls, v: str) -> str:
        try:
            dt = datetime.fromisoformat(v.replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(f"not an ISO 8601 time: {v!r}") from None
        if dt.tzinfo is None:
            raise ValueError(f"needs a time zone (e.g. 'Z'): {v!r}")
        return v

    @field_validator("stages")
    @classmethod
    def _ordered(cls, v: list[Stage] | None) -> list[Stage] | None:
        if v:
            for i in range(1, len(v)):
                if v[i].start_s < v[i - 1].end_s:
                    raise ValueError(f"stage {v[i].name!r} starts before stage {v[i - 1].name!r} ends")
            names = [st.name for st in v]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ValueError(f"stage names must be unique, {dup[0]!r} is used twice")
        return v

    @property
    def duration_s(self) -> float:
        """Return the campaign length in seconds."""
        return self.hours * 3600.0

    @property
    def start_hour_of_day(self) -> float:
        """Return the UTC hour of day of started_at (phase of the room's daily cycle)."""
        dt = datetime.fromisoformat(self.started_at.replace("Z", "+00:00"))
        return dt.hour + dt.minute / 60.0 + dt.second / 3600.0

    def plan(self) -> list[Stage]:
        """Return the staged plan: the given stages ([] = machine off throughout), or the default plan for ``hours``."""
        return list(self.stages) if self.stages is not None else default_plan(self.hours, self.thermal_step_s)


# one 24 h cycle of the staged plan (ch. 5.2 Fig. 5.1): (hours, heat_source, axis); an axis 1..3 is the
# 1st..3rd linear axis in the cycle's order (_ORDERS)
_CYCLE: tuple[tuple[float, HeatSource, Axis | int | None], ...] = (
    (3.0, "spindle", "Z"),
    (1.5, "idle", None),
    (2.0, "feed", 1),
    (1.0, "idle", None),
    (2.0, "feed", 2),
    (1.0, "idle", None),
    (2.0, "feed", 3),
    (1.0, "idle", None),
    (1.5, "feed", "A"),
    (1.5, "feed", "B"),
    (1.0, "idle", None),
    (2.5, "combined", "Z"),
    (4.0, "off", None),
)
_ORDERS: tuple[tuple[Axis, Axis, Axis], ...] = (("X", "Y", "Z"), ("Z", "X", "Y"), ("Y", "Z", "X"))
_RPM = (8000.0, 12000.0, 6000.0)
_FEED = (4000.0, 2500.0, 5000.0)
_ROT_FEED = (3600.0, 2400.0, 4800.0)  # deg/min


def default_plan(hours: float, step_s: float = 60.0) -> list[Stage]:
    """Return the default staged plan: 24 h cycles (compressed when shorter), intensities varying per cycle."""
    total = hours * 3600.0
    scale = min(1.0, hours / 24.0)
    stages: list[Stage] = []
    t = 0.0
    cycle = 0
    while t < total - 1e-9:
        c = cycle % 3
        for j, (dur_h, source, axis) in enumerate(_CYCLE):
            if t >= total - 1e-9:
                break
            ax = _ORDERS[c][axis - 1] if isinstance(axis, int) else axis
            end = min(total, round((t + dur_h * 3600.0 * scale) / step_s) * step_s)
            if end <= t:
                continue
            rpm = _RPM[c] if source in ("spindle", "combined") else 0.0
            feed = 0.0
            if source in ("feed", "combined"):
                feed = _ROT_FEED[c] if ax in ("A", "B") else _FEED[c]
            if source == "spindle":
                name = f"spindle-{rpm / 1000:.0f}k"
            elif source == "feed":
                assert ax is not None  # every feed stage of _CYCLE names an axis
                name = f"feed-{ax.lower()}-{feed:.0f}"
            elif source == "combined":
                assert ax is not None  # as is every combined stage
                name = f"spindle-{rpm / 1000:.0f}k+feed-{ax.lower()}-{feed:.0f}"
            else:
                name = "cool-down" if source == "idle" else "power-off"
            stages.append(
                Stage(
                    name=f"c{cycle + 1}.{j + 1}-{name}",
                    start_s=t,
                    end_s=end,
                    heat_source=source,
                    axis=ax if source != "idle" and source != "off" else None,
                    spindle_rpm=rpm,
                    feed_mm_min=feed,
                )
            )
            t = end
        cycle += 1
    return stages


def _one_line(exc: PydanticValidationError) -> str:
    """Return the first pydantic error as 'field.path: message'."""
    err = exc.errors()[0]
    loc = ".".join(str(x) for x in err.get("loc", ())) or "scenario"
    msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")
    return f"{loc}: {msg}"


def scenario_from_dict(data: Any, source: str = "scenario") -> Scenario:
    """Return a validated Scenario from a plain mapping, or raise ValidationError naming the field."""
    if not isinstance(data, dict):
        raise ValidationError(f"{source}: expected a mapping of scenario fields, got {type(data).__name__}")
    try:
        return Scenario.model_validate(data)
    except PydanticValidationError as exc:
        raise ValidationError(f"{source}: {_one_line(exc)}") from None


def load_scenario(path: str | Path) -> Scenario:
    """Return the Scenario in a YAML file, or raise ValidationError with a one-line message."""
    p = Path(path)
    got = read_yaml(p, encoding="utf-8")
    if got.unreadable is not None:
        raise ValidationError(f"scenario {p}: cannot read ({got.unreadable.strerror or got.unreadable})")
    if got.problem is not None:
        raise ValidationError(f"scenario {p}:{got.at(' line {}')}: not valid YAML ({got.problem})")
    data = got.doc
    if data is None:
        data = {}
    if isinstance(data, dict) and "name" not in data:
        data = {**data, "name": p.stem}
    return scenario_from_dict(data, f"scenario {p}")
