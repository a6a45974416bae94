"""Campaign plans (YAML): staged single-heat-source tests (thesis ch. 4.3, 5.2) -> a timeline of steps.

A plan lists stages in the order the errors are allocated: one heat source at a
time (the spindle at an rpm, an axis oscillating at a feed, a motor holding a
position), then their combinations, with cool-downs in between. Each stage names
the axis under test, the error sweep run on it (positions, both approach
directions, interval) and its duration; the plan gives the thermocouple scan
interval and the machine with its channel map (or "from scenario").

The plan compiles to a deterministic timeline of four kinds of step, in the
style of bluesky's plan stubs (one typed function per step): `scans` yields the
thermocouple scans, `sweep_points` the error-measurement points, `moves` the
commands that bring the axis to each point ahead of its reading, `stage_starts`
the moments the machine conditions change; `steps` merges them in time order
from a `Cursor`, which is all the scheduler must remember to resume.

Example (the shipped examples/plans/z-axis-test.yaml is the thesis' Z-axis test)::

    format: driftlab-plan/1
    name: z-axis-test
    machine: {id: vmc-5ax-01, channels: from scenario}
    scan_interval_s: 30
    stages:
      - name: spindle-10k
        heat: [{kind: spindle, rpm: 10000}]
        axis: Z
        duration_s: 28800
        sweep: {positions: [0, 100, 200, 300, 400], interval_s: 1800, point_s: 6, term: dz}
      - {name: cool-down-1, axis: Z, duration_s: 21600}
"""

from __future__ import annotations

import hashlib
import heapq
import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Final, Literal, TypedDict

import pydantic
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from driftlab.campaigns.bundle import ID_PATTERN
from driftlab.campaigns.setups import Setup, all_cells, coverage, default_laser_setup
from driftlab.errors import ValidationError
from driftlab.physics.geometry import Geometry
from driftlab.vocabulary import Axis, Term, heat_source
from driftlab.yamlfile import read_yaml

PLAN_FORMAT: Final = "driftlab-plan/1"
FROM_SCENARIO: Final = "from scenario"


class _Strict(BaseModel):
    """Base of plan models: unknown keys are an error (a misspelt key must not be ignored)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class SpindleSource(_Strict):
    """The spindle running at a constant speed."""

    kind: Literal["spindle"]
    rpm: float = Field(gt=0, le=60000)

    def key(self) -> str:
        """Return the identity of this heat source for the staging-order check."""
        return "spindle"


class AxisSource(_Strict):
    """An axis oscillating between two positions at a feed (its motor, screw and slides warm up)."""

    kind: Literal["axis"]
    axis: Axis
    feed_mm_min: float = Field(gt=0, le=100000)
    from_pos: float = 0.0
    to_pos: float

    @model_validator(mode="after")
    def _span(self) -> AxisSource:
        """Refuse a zero-length oscillation (it would not move the axis)."""
        if self.from_pos == self.to_pos:
            raise ValueError("from_pos and to_pos must differ")
        return self

    def key(self) -> str:
        """Return the identity of this heat source for the staging-order check."""
        return f"axis:{self.axis}"


class MotorHoldSource(_Strict):
    """An axis motor holding a position under servo (heats the motor, not the screw)."""

    kind: Literal["motor_hold"]
    axis: Axis
    position: float = 0.0

    def key(self) -> str:
        """Return the identity of this heat source for the staging-order check."""
        return f"motor_hold:{self.axis}"


HeatSource = Annotated[SpindleSource | AxisSource | MotorHoldSource, Field(discriminator="kind")]


class Sweep(_Strict):
    """An error sweep of the axis under test: every position from both directions (ch. 5.5)."""

    positions: list[float] = Field(min_length=1)
    directions: list[Literal[1, -1]] = Field(default=[1, -1], min_length=1)
    interval_s: float = Field(gt=0, description="time from the start of one sweep to the next")
    point_s: float = Field(default=5.0, gt=0, description="move, settle and read time per point")
    samples: int = Field(default=10, ge=1, le=1000, description="laser readings averaged per point")
    term: Term | None = Field(
        default=None, description="error term the laser is set up for (default: the axis' own motion)"
    )
    lead_s: float | None = Field(
        default=None, gt=0, description="the move to a point starts this long before it is read (default 0.8 point_s)"
    )

    @field_validator("directions")
    @classmethod
    def _distinct(cls, v: list[int]) -> list[int]:
        """Refuse a direction listed twice."""
        if len(set(v)) != len(v):
            raise ValueError("a direction is listed twice")
        return v

    def move_lead_s(self) -> float:
        """Return how long before its reading the move to a point is commanded."""
        return self.lead_s if self.lead_s is not None else 0.8 * self.point_s

    def points(self) -> list[tuple[float, int]]:
        """Return (position, direction) in visiting order: ascending for +1, then descending for -1."""
        out: list[tuple[float, int]] = []
        for d in self.directions:
            for p in sorted(set(self.positions), reverse=(d == -1)):
                out.append((p, d))
        return out

    def length_s(self) -> float:
        """Return how long one sweep takes."""
        return len(self.points()) * self.point_s


class BundleStage(TypedDict):
    """A plan's stage as a bundle v1 campaign.json record (the stage table's row)."""

    name: str
    start_s: float
    end_s: float
    heat_source: str
    axis: str
    spindle_rpm: float
    feed_mm_min: float


class Stage(_Strict):
    """One stage of the campaign: its heat sources (none = cool-down), axis under test, sweep, duration."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.+\-]+$")
    heat: list[HeatSource] = Field(default_factory=list)
    axis: Axis
    duration_s: float = Field(gt=0)
    sweep: Sweep | None = None
    setup: str | None = Field(
        default=None, description="id of the plan's setup mounted in this stage (default: a laser for sweep.term)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> Stage:
        """Check one source per kind and axis, and that a sweep fits in its interval and stage."""
        keys = [h.key() for h in self.heat]
        if len(set(keys)) != len(keys):
            raise ValueError(f"heat source listed twice in stage {self.name!r}")
        axes = [h.axis for h in self.heat if not isinstance(h, SpindleSource)]
        if len(set(axes)) != len(axes):
            raise ValueError(f"an axis cannot both oscillate and hold in stage {self.name!r}")
        if self.sweep is not None:
            allowed = LASER_TERMS[self.axis]
            if self.setup is not None and self.sweep.term is not None:
                raise ValueError(f"stage {self.name!r} names a setup: its terms come from the setup, not sweep.term")
            if self.setup is None and self.sweep.term is not None and self.sweep.term not in allowed:
                raise ValueError(
                    f"the laser cannot measure {self.sweep.term} of the {self.axis} axis "
                    f"(table 5.3: {', '.join(allowed)})"
                )
            if self.sweep.move_lead_s() > self.sweep.point_s:
                raise ValueError(f"sweep lead_s {self.sweep.lead_s:g} is longer than point_s {self.sweep.point_s:g}")
            length = self.sweep.length_s()
            if length > self.sweep.interval_s:
                raise ValueError(
                    f"sweep of {length:g} s ({len(self.sweep.points())} points x {self.sweep.point_s:g} s) "
                    f"is longer than its interval_s {self.sweep.interval_s:g}"
                )
            if length > self.duration_s:
                raise ValueError(f"sweep of {length:g} s is longer than the stage ({self.duration_s:g} s)")
        return self

    @property
    def kind(self) -> str:
        """Return 'cool-down', 'single' (one heat source) or 'combined'."""
        return {0: "cool-down", 1: "single"}.get(len(self.heat), "combined")

    def heat_label(self) -> str:
        """Return the stage's heat source in the one vocabulary (``vocabulary.HEAT_SOURCES``): idle, spindle, feed,
        combined, motor_hold."""
        return heat_source("+".join(h.kind for h in self.heat))

    def spindle_rpm(self) -> float:
        """Return the commanded spindle speed in this stage (0 when the spindle is off)."""
        return sum(h.rpm for h in self.heat if isinstance(h, SpindleSource))

    def term(self) -> str:
        """Return the error term the laser measures in this stage (the axis' own motion by default)."""
        if self.sweep is not None and self.sweep.term is not None:
            return self.sweep.term
        return DEFAULT_TERM[self.axis]

    def feed_mm_min(self) -> float:
        """Return the oscillation feed of this stage (0 when no axis oscillates)."""
        return max((h.feed_mm_min for h in self.heat if isinstance(h, AxisSource)), default=0.0)


# Table 5.3: the error terms a laser interferometer measures for each axis' motion (the others
# need proximity sensors on reference surfaces).
LASER_TERMS: dict[str, tuple[str, ...]] = {
    "X": ("dx", "dy", "dz", "beta", "gamma"),
    "Y": ("dx", "dy", "dz", "alpha", "gamma"),
    "Z": ("dx", "dy", "dz", "alpha", "beta"),
    "A": ("alpha",),
    "B": ("beta",),
}
DEFAULT_TERM = {"X": "dx", "Y": "dy", "Z": "dz", "A": "alpha", "B": "beta"}


class ChannelInfo(_Strict):
    """Where a thermocouple sits (Table 5.1) and the structure it belongs to."""

    location: str
    structure: str = ""


class MachineRef(_Strict):
    """The machine under test and its thermocouple channel map (or the scenario's)."""

    # the bundle's machine.id rule: a campaign the daemon records can be exported, imported and addressed
    # by the API as /machines/{id}
    id: str = Field(min_length=1, max_length=64, pattern=ID_PATTERN)
    name: str = ""
    channels: Literal["from scenario"] | dict[str, ChannelInfo] = FROM_SCENARIO
    room_channels: list[str] = Field(default_factory=list)
    travel: dict[Axis, tuple[float, float]] = Field(
        default_factory=dict, description="travel limits per axis (mm; degrees for A, B): moves must stay inside"
    )
    geometry: Geometry | None = Field(
        default=None, description="the machine's stated lengths for table 6.3 (campaign.json machine.geometry)"
    )

    @model_validator(mode="after")
    def _rooms_known(self) -> MachineRef:
        """Require room channels to be in the channel map when one is given."""
        if isinstance(self.channels, dict):
            unknown = [c for c in self.room_channels if c not in self.channels]
            if unknown:
                raise ValueError(f"room channel(s) {', '.join(unknown)} not in channels")
            if not self.channels:
                raise ValueError("channels is empty")
        return self


class Instruments(_Strict):
    """Resource names of the real instruments (unused in simulated mode)."""

    thermocouple: str | None = None
    laser: str | None = None
    probe: str | None = None
    machine_link: str | None = None


class Plan(_Strict):
    """A campaign plan: machine, scan interval and the ordered stages."""

    format: Literal["driftlab-plan/1"] = PLAN_FORMAT
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    description: str = ""
    machine: MachineRef
    scan_interval_s: float = Field(gt=0, description="thermocouple scan interval")
    state_every: int = Field(default=1, ge=1, description="log the machine state every N scans")
    staged_order: bool = Field(
        default=True, description="require each heat source to run alone before it runs in a combination"
    )
    instruments: Instruments = Field(default_factory=Instruments)
    setups: dict[str, Setup] = Field(default_factory=dict, description="instrument setups by id (ch. 5.5)")
    stages: list[Stage] = Field(min_length=1)

    @model_validator(mode="after")
    def _setups(self) -> Plan:
        """Check every stage's setup exists, measures the stage's axis, and sees every sweep position."""
        for i, stage in enumerate(self.stages):
            if stage.setup is None:
                continue
            where = f"stages[{i}] ({stage.name})"
            setup = self.setups.get(stage.setup)
            if setup is None:
                known = ", ".join(sorted(self.setups)) or "none"
                raise ValueError(f"{where}: setup {stage.setup!r} is not among the plan's setups ({known})")
            if setup.axis != stage.axis:
                raise ValueError(
                    f"{where}: setup {stage.setup!r} measures the {setup.axis} axis, the stage moves {stage.axis}"
                )
            if stage.sweep is None:
                raise ValueError(f"{where}: setup {stage.setup!r} is mounted but the stage has no sweep")
            limit = setup.range_deg()
            if limit is not None:
                out = [p for p in stage.sweep.positions if abs(p) > limit + 1e-9]
                if out:
                    raise ValueError(
                        f"{where}: sweep positions {', '.join(f'{p:g}' for p in out)} deg are beyond the angular "
                        f"optics' +-{limit:g} deg (fig. 5.9; mount the counter-rotating table, fig. 5.10)"
                    )
        for i, what, axis, values, lo, hi in self.travel_violations(self.machine.travel):
            stage = self.stages[i]
            where = f"stages[{i}] ({stage.name})"
            if what == "sweep":
                raise ValueError(f"{where}: sweep positions {values} outside the {axis} travel {lo:g}..{hi:g}")
            if what == "pose":
                raise ValueError(
                    f"{where}: setup {stage.setup!r} stands {axis} at {values}, outside its travel {lo:g}..{hi:g}"
                )
            raise ValueError(f"{where}: {axis} oscillation {values} outside its travel {lo:g}..{hi:g}")
        return self

    @model_validator(mode="after")
    def _order(self) -> Plan:
        """Check stage names are unique and (ch. 4.3) combinations only follow their single stages."""
        names = [s.name for s in self.stages]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"stage name(s) used twice: {', '.join(dup)}")
        if self.staged_order:
            seen_alone: set[str] = set()
            for stage in self.stages:
                keys = [h.key() for h in stage.heat]
                if len(keys) == 1:
                    seen_alone.add(keys[0])
                elif len(keys) > 1:
                    missing = [k for k in keys if k not in seen_alone]
                    if missing:
                        raise ValueError(
                            f"stage {stage.name!r} combines {', '.join(missing)} before it ran alone "
                            "(ch. 4.3: one heat source at a time, then combinations; "
                            "set staged_order: false to allow)"
                        )
        return self

    def travel_violations(
        self, travel: Mapping[Axis, tuple[float, float]] | Mapping[str, tuple[float, float]]
    ) -> Iterator[tuple[int, str, str, str, float, float]]:
        """Yield (stage index, 'sweep' | 'pose' | 'heat', axis, values, lo, hi) for what leaves ``travel``.

        ``travel`` maps an axis to its (lo, hi) limits (mm; degrees for A, B); axes it lacks are not
        checked. Per stage: sweep positions, then the setup's stand of the other axes, then oscillations.
        """

        def inside(v: float, lim: tuple[float, float]) -> bool:
            return lim[0] - 1e-9 <= v <= lim[1] + 1e-9

        for i, stage in enumerate(self.stages):
            lim = travel.get(stage.axis)
            if lim is not None and stage.sweep is not None:
                out = [p for p in stage.sweep.positions if not inside(p, lim)]
                if out:
                    yield i, "sweep", stage.axis, ", ".join(f"{p:g}" for p in out), *lim
            setup = self.setups.get(stage.setup) if stage.setup else None
            for ax, v in setup.pose.items() if setup else ():
                lim = travel.get(ax)
                if lim is not None and not inside(v, lim):
                    yield i, "pose", ax, f"{v:g}", *lim
            for h in stage.heat:
                if not isinstance(h, AxisSource):
                    continue
                lim = travel.get(h.axis)
                if lim is not None and not (inside(h.from_pos, lim) and inside(h.to_pos, lim)):
                    yield i, "heat", h.axis, f"{h.from_pos:g}..{h.to_pos:g}", *lim

    # -- setups and coverage ----------------------------------------------------------------------

    def stage_setup(self, i: int) -> tuple[str, Setup] | None:
        """Return (id, setup) mounted in stage i: its named setup, or the laser of a legacy sweep.term."""
        stage = self.stages[i]
        if stage.sweep is None:
            return None
        if stage.setup is not None:
            return stage.setup, self.setups[stage.setup]
        term = stage.term()
        return f"laser-{stage.axis}-{term}", default_laser_setup(stage.axis, term)

    def used_setups(self) -> dict[str, Setup]:
        """Return every setup some stage mounts (named ones and legacy lasers), in plan order."""
        out: dict[str, Setup] = {}
        for i in range(len(self.stages)):
            got = self.stage_setup(i)
            if got is not None:
                out.setdefault(*got)
        return out

    def coverage(self) -> dict[str, list[str]]:
        """Return, for each of the thirty motion-error terms, the stages that measure it (empty: none)."""
        pairs = []
        for i, stage in enumerate(self.stages):
            got = self.stage_setup(i)
            if got is not None:
                pairs += [(c, stage.name) for c in got[1].cells()]
        return coverage(pairs)

    def missing_terms(self) -> list[str]:
        """Return the motion-error terms no stage measures (what the model will lack)."""
        cov = self.coverage()
        return [c for c in all_cells() if not cov[c]]

    # -- timeline -------------------------------------------------------------------------------

    def stage_bounds(self) -> list[tuple[float, float]]:
        """Return (start_s, end_s) of every stage, back to back from t = 0."""
        out: list[tuple[float, float]] = []
        t = 0.0
        for s in self.stages:
            out.append((t, t + s.duration_s))
            t += s.duration_s
        return out

    @property
    def total_s(self) -> float:
        """Return the campaign's length."""
        return sum(s.duration_s for s in self.stages)

    @property
    def n_scans(self) -> int:
        """Return how many thermocouple scans the campaign takes (at k * scan_interval_s < total_s)."""
        return max(1, math.ceil(self.total_s / self.scan_interval_s - 1e-9))

    def scan_time(self, k: int) -> float:
        """Return the time of scan k."""
        return k * self.scan_interval_s

    def stage_at(self, t_s: float) -> int:
        """Return the index of the stage running at time t_s (the last one at or after the end)."""
        for i, (_, end) in enumerate(self.stage_bounds()):
            if t_s < end:
                return i
        return len(self.stages) - 1

    def sweep_points(self) -> list[SweepPoint]:
        """Return every error-measurement point of the campaign in time order, numbered from 0."""
        out: list[SweepPoint] = []
        for i, (stage, (start, end)) in enumerate(zip(self.stages, self.stage_bounds())):
            if stage.sweep is None:
                continue
            setup_id, setup = self.stage_setup(i)  # type: ignore[misc]
            m = 0
            while start + m * stage.sweep.interval_s + stage.sweep.length_s() <= end + 1e-9:
                t0 = start + m * stage.sweep.interval_s
                for n, (pos, d) in enumerate(stage.sweep.points()):
                    out.append(
                        SweepPoint(
                            index=len(out),
                            t_s=t0 + n * stage.sweep.point_s,
                            stage=i,
                            sweep=m,
                            axis=stage.axis,
                            position=pos,
                            direction=d,
                            samples=stage.sweep.samples,
                            term=setup.terms[0],
                            move_s=t0 + n * stage.sweep.point_s - stage.sweep.move_lead_s(),
                            setup=setup_id,
                            terms=tuple(setup.terms),
                        )
                    )
                m += 1
        return out

    def bundle_stages(self) -> list[BundleStage]:
        """Return the stages as bundle v1 campaign.json records."""
        return [
            {
                "name": s.name,
                "start_s": a,
                "end_s": b,
                "heat_source": s.heat_label(),
                "axis": s.axis,
                "spindle_rpm": s.spindle_rpm(),
                "feed_mm_min": s.feed_mm_min(),
            }
            for s, (a, b) in zip(self.stages, self.stage_bounds())
        ]

    def fingerprint(self) -> str:
        """Return a hash of everything that fixes the timeline (a resumed run must use the same plan)."""
        doc = self.model_dump(mode="json", exclude={"description", "instruments"})
        # fields added with setups are left out while unused: a campaign started before they existed resumes
        if not doc["setups"]:
            del doc["setups"]
        if not doc["machine"]["travel"]:
            del doc["machine"]["travel"]
        doc["machine"].pop("geometry", None)  # stated lengths do not move the timeline
        for st in doc["stages"]:
            if st["setup"] is None:
                del st["setup"]
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


# -- steps ----------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Scan:
    """Step: read every thermocouple once (scan number k) at t_s; log the machine state if `log_state`."""

    index: int
    t_s: float
    log_state: bool


@dataclass(frozen=True, slots=True)
class SweepPoint:
    """Step: move the axis under test to `position` approaching from `direction`, read the error."""

    index: int
    t_s: float
    stage: int
    sweep: int
    axis: str
    position: float
    direction: int
    samples: int
    term: str = "dz"
    move_s: float = 0.0
    setup: str = ""
    terms: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Move:
    """Step: command the move to sweep point `point` (read at its own time), from its approach side."""

    point: int
    t_s: float


@dataclass(frozen=True, slots=True)
class StageStart:
    """Step: set the machine to stage `stage`'s conditions (heat sources on/off) at t_s."""

    stage: int
    t_s: float


Step = StageStart | Scan | SweepPoint | Move


@dataclass(frozen=True, slots=True)
class Cursor:
    """Where a campaign stands: the next scan and next sweep point still to be stored."""

    next_scan: int = 0
    next_point: int = 0


def scans(plan: Plan, start: int = 0) -> Iterator[Scan]:
    """Yield the thermocouple scans from scan `start` to the end of the campaign."""
    for k in range(start, plan.n_scans):
        yield Scan(k, plan.scan_time(k), k % plan.state_every == 0)


def sweep_points(points: list[SweepPoint], start: int = 0) -> Iterator[SweepPoint]:
    """Yield the sweep points from point `start` on."""
    yield from points[start:]


def stage_starts(plan: Plan, after_s: float) -> Iterator[StageStart]:
    """Yield the stage changes at or after time `after_s`, preceded by the stage already running then."""
    bounds = plan.stage_bounds()
    current = plan.stage_at(after_s)
    yield StageStart(current, after_s if after_s > bounds[current][0] else bounds[current][0])
    for i in range(current + 1, len(plan.stages)):
        yield StageStart(i, bounds[i][0])


def moves(points: list[SweepPoint], start: int, after_s: float) -> Iterator[Move]:
    """Yield the moves to the sweep points from point `start` on (none earlier than `after_s`)."""
    for p in points[start:]:
        yield Move(p.index, max(p.move_s, after_s))


_ORDER = {StageStart: 0, Scan: 1, Move: 2, SweepPoint: 3}


def cursor_time(plan: Plan, points: list[SweepPoint], cursor: Cursor) -> float:
    """Return the time of the first step still to be done at `cursor` (the campaign's end if none).

    That is the earliest of the next scan and the move towards the next sweep point: a resumed run
    commands that move at the time the uninterrupted run did, so the axis is in place when read.
    """
    times = []
    if cursor.next_scan < plan.n_scans:
        times.append(plan.scan_time(cursor.next_scan))
    if cursor.next_point < len(points):
        times.append(points[cursor.next_point].move_s)
    return min(times) if times else plan.total_s


def steps(plan: Plan, cursor: Cursor = Cursor(), points: list[SweepPoint] | None = None) -> Iterator[Step]:
    """Yield every step still to be done from `cursor`, in time order (stage change, scan, point at ties)."""
    pts = plan.sweep_points() if points is None else points
    if cursor.next_scan >= plan.n_scans and cursor.next_point >= len(pts):
        return iter(())
    t0 = cursor_time(plan, pts, cursor)
    streams: list[Iterator[Step]] = [
        stage_starts(plan, t0),
        scans(plan, cursor.next_scan),
        sweep_points(pts, cursor.next_point),
        moves(pts, cursor.next_point, t0),
    ]
    return heapq.merge(*streams, key=_step_key)


def _step_key(s: Step) -> tuple[float, int, int]:
    """Return the sort key of a step: time, then stage change before scan before sweep point."""
    return (s.t_s, _ORDER[type(s)], _seq(s))


def _seq(s: Step) -> int:
    """Return the step's number within its own stream (for a total order at equal times)."""
    if isinstance(s, StageStart):
        return s.stage
    return s.point if isinstance(s, Move) else s.index


# -- loading ---------------------------------------------------------------------------------------


def _loc(loc: tuple[Any, ...]) -> str:
    """Return a pydantic error location as a field path like stages[2].sweep.interval_s."""
    out = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            out += f"[{part}]"
        elif i >= 2 and loc[i - 2] == "heat" and part in ("spindle", "axis", "motor_hold"):
            continue  # the discriminated-union tag pydantic inserts, not a field the user wrote
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def parse_plan(doc: Any, source: str = "<plan>") -> Plan:
    """Return the validated Plan of a parsed YAML document; errors name the file and the field."""
    if not isinstance(doc, dict):
        raise ValidationError(f"{source}: a plan must be a mapping, got {type(doc).__name__}")
    try:
        return Plan.model_validate(doc)
    except pydantic.ValidationError as exc:
        err = exc.errors()[0]
        msg = str(err["msg"]).removeprefix("Value error, ")
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        raise ValidationError(f"{source}: {_loc(tuple(err['loc']))}: {msg}{more}") from None


def load_plan(path: str | Path) -> Plan:
    """Return the validated Plan read from a YAML file."""
    p = Path(path)
    got = read_yaml(p)
    if got.unreadable is not None:
        raise ValidationError(f"{p}: cannot read plan: {got.unreadable.strerror}")
    if got.problem is not None:
        raise ValidationError(f"{p}{got.at(':{}')}: not valid YAML: {got.problem}")
    return parse_plan(got.doc, str(p))
