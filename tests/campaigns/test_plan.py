"""Campaign plans: validation with one-line errors, the staged order of ch. 4.3, the step timeline."""

from __future__ import annotations

import math
import random
import time
from pathlib import Path

import pytest
import yaml

from driftlab.campaigns.clock import SimClock, WallClock
from driftlab.campaigns.plan import (
    Cursor,
    Move,
    Scan,
    StageStart,
    SweepPoint,
    load_plan,
    parse_plan,
    steps,
)
from driftlab.errors import ValidationError

ROOT = Path(__file__).resolve().parents[2]
Z_TEST = ROOT / "examples" / "plans" / "z-axis-test.yaml"
Z_DEMO = ROOT / "examples" / "plans" / "z-axis-demo.yaml"


def _doc(**over: object) -> dict:
    """Return a small valid plan document with top-level overrides."""
    doc = {
        "name": "t",
        "machine": {
            "id": "m1",
            "channels": {"T1": {"location": "x"}, "T49": {"location": "room"}},
            "room_channels": ["T49"],
        },
        "scan_interval_s": 10,
        "stages": [
            {
                "name": "sp",
                "axis": "Z",
                "duration_s": 100,
                "heat": [{"kind": "spindle", "rpm": 8000}],
                "sweep": {"positions": [0, 50], "interval_s": 40, "point_s": 5},
            },
            {"name": "cool", "axis": "Z", "duration_s": 60},
            {
                "name": "z",
                "axis": "Z",
                "duration_s": 100,
                "heat": [{"kind": "axis", "axis": "Z", "feed_mm_min": 3000, "to_pos": 400}],
                "sweep": {"positions": [0, 50], "interval_s": 50, "point_s": 5},
            },
            {
                "name": "both",
                "axis": "Z",
                "duration_s": 100,
                "heat": [
                    {"kind": "spindle", "rpm": 8000},
                    {"kind": "axis", "axis": "Z", "feed_mm_min": 3000, "to_pos": 400},
                ],
                "sweep": {"positions": [0, 50], "interval_s": 50, "point_s": 5},
            },
        ],
    }
    doc.update(over)
    return doc


def test_example_plans_follow_the_thesis_order() -> None:
    """The shipped Z-axis plan runs spindle alone, Z feed alone, then both, with cool-downs between."""
    plan = load_plan(Z_TEST)
    kinds = [(s.kind, s.heat_label()) for s in plan.stages]
    assert ("single", "spindle") in kinds and ("single", "feed") in kinds
    assert kinds.index(("combined", "combined")) > kinds.index(("single", "feed"))
    assert any(k == "cool-down" for k, _ in kinds[1:])
    assert {s.axis for s in plan.stages} == {"Z"}
    assert plan.total_s >= 24 * 3600
    demo = load_plan(Z_DEMO)
    assert demo.total_s / 3600 < 50  # under a minute at 3600x
    assert [s.heat_label() for s in demo.stages if s.heat] == [s.heat_label() for s in plan.stages if s.heat]


def test_bundle_stages_are_back_to_back() -> None:
    """Stages become bundle v1 records with contiguous start/end times."""
    plan = parse_plan(_doc())
    recs = plan.bundle_stages()
    assert [r["start_s"] for r in recs] == [0, 100, 160, 260]
    assert recs[-1]["end_s"] == plan.total_s == 360
    # one vocabulary of heat sources with the simulator (vocabulary.HEAT_SOURCES)
    assert recs[3]["heat_source"] == "combined" and recs[3]["spindle_rpm"] == 8000
    assert recs[1]["heat_source"] == "idle" and recs[2]["feed_mm_min"] == 3000


@pytest.mark.parametrize(
    ("mutate", "field", "words"),
    [
        (lambda d: d.update(scan_interval_s=0), "scan_interval_s", "greater than 0"),
        (lambda d: d["stages"][0].update(colour="red"), "stages[0].colour", "Extra inputs"),
        (lambda d: d["stages"][0]["heat"][0].update(rpm=-5), "stages[0].heat[0].rpm", "greater than 0"),
        (lambda d: d["stages"][2]["heat"][0].update(kind="laser"), "stages[2].heat[0]", "kind"),
        (lambda d: d["stages"][0]["sweep"].update(directions=[1, 1]), "stages[0].sweep.directions", "twice"),
        (lambda d: d["stages"][0]["sweep"].update(interval_s=10), "stages[0]", "longer than its interval_s"),
        (lambda d: d["stages"][0].update(axis="Q"), "stages[0].axis", "X"),
        (lambda d: d["stages"][0]["sweep"].update(term="gamma"), "stages[0]", "cannot measure gamma of the Z"),
        (lambda d: d["machine"].update(room_channels=["T50"]), "machine", "T50"),
        (lambda d: d["stages"].insert(0, d["stages"].pop(3)), "(top level)", "before it ran alone"),
        (lambda d: d["stages"].append(dict(d["stages"][1])), "(top level)", "used twice"),
    ],
)
def test_bad_plan_names_file_and_field(tmp_path: Path, mutate, field: str, words: str) -> None:
    """A bad plan is one line naming the file and the field at fault."""
    doc = _doc()
    mutate(doc)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValidationError) as err:
        load_plan(path)
    msg = err.value.one_line()
    assert msg.startswith(f"{path}: {field}:"), msg
    assert words in msg
    assert "\n" not in str(err.value)


def test_combination_first_allowed_when_order_check_is_off() -> None:
    """staged_order: false lets a plan start with a combination (e.g. a production-like test)."""
    doc = _doc(staged_order=False)
    doc["stages"].insert(0, doc["stages"].pop(3))
    assert parse_plan(doc).stages[0].kind == "combined"


def test_unreadable_and_malformed_yaml(tmp_path: Path) -> None:
    """A missing file and a YAML syntax error are one-line ValidationErrors naming the file."""
    with pytest.raises(ValidationError, match="cannot read plan"):
        load_plan(tmp_path / "nope.yaml")
    bad = tmp_path / "syntax.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ValidationError, match=rf"{bad}:\d+: not valid YAML"):
        load_plan(bad)
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n")
    with pytest.raises(ValidationError, match="must be a mapping"):
        load_plan(lst)


def test_sweep_points_both_directions_inside_their_stage() -> None:
    """Each sweep visits every position ascending (+1) then descending (-1), within its stage."""
    plan = parse_plan(_doc())
    pts = plan.sweep_points()
    first = [(p.position, p.direction) for p in pts if p.stage == 0 and p.sweep == 0]
    assert first == [(0, 1), (50, 1), (50, -1), (0, -1)]
    bounds = plan.stage_bounds()
    for p in pts:
        assert bounds[p.stage][0] <= p.t_s < bounds[p.stage][1]
        assert p.samples == 10
    assert [p.index for p in pts] == list(range(len(pts)))
    assert [p.t_s for p in pts] == sorted(p.t_s for p in pts)
    # stage 0: sweeps at 0, 40, 80 (80 + 20 s ends at the stage end); cool-down: none; stages 2, 3: +0, +50
    assert [(p.stage, p.sweep) for p in pts if p.direction == 1 and p.position == 0] == [
        (0, 0),
        (0, 1),
        (0, 2),
        (2, 0),
        (2, 1),
        (3, 0),
        (3, 1),
    ]


def test_steps_are_in_time_order_and_cover_everything() -> None:
    """The merged timeline has every scan and point once, in time order, stage changes first at ties."""
    plan = parse_plan(_doc())
    all_steps = list(steps(plan))
    assert [s.t_s for s in all_steps] == sorted(s.t_s for s in all_steps)
    moves = [s for s in all_steps if isinstance(s, Move)]
    pts = plan.sweep_points()
    assert [m.point for m in moves] == [p.index for p in pts]
    assert all(pts[m.point].t_s - m.t_s == pytest.approx(4.0) for m in moves)  # 0.8 x point_s
    assert [s.index for s in all_steps if isinstance(s, Scan)] == list(range(plan.n_scans)) == list(range(36))
    assert len([s for s in all_steps if isinstance(s, SweepPoint)]) == len(plan.sweep_points())
    assert [(s.stage, s.t_s) for s in all_steps if isinstance(s, StageStart)] == [(0, 0), (1, 100), (2, 160), (3, 260)]
    at_100 = [type(s).__name__ for s in all_steps if s.t_s == 100]
    assert at_100 == ["StageStart", "Scan"]
    assert {p.term for p in pts} == {"dz"}


def test_resuming_from_any_cursor_gives_the_rest_of_the_timeline() -> None:
    """From the cursor after any prefix, steps() yields exactly the remaining scans and points."""
    plan = load_plan(Z_DEMO)
    full = [s for s in steps(plan) if not isinstance(s, (StageStart, Move))]
    rng = random.Random(4)
    for cut in [0, 1, len(full) - 1, len(full)] + rng.sample(range(len(full)), 25):
        done = full[:cut]
        cur = Cursor(
            next_scan=sum(isinstance(s, Scan) for s in done), next_point=sum(isinstance(s, SweepPoint) for s in done)
        )
        rest = list(steps(plan, cur))
        assert [s for s in rest if not isinstance(s, (StageStart, Move))] == full[cut:]
        if rest:
            # a stage change re-establishes the stage running at the resume time before any reading
            first = next(i for i, s in enumerate(rest) if isinstance(s, StageStart))
            assert all(isinstance(s, Move) for s in rest[:first])
            nxt = next(s for s in rest[first:] if isinstance(s, (Scan, SweepPoint)))
            assert rest[first].stage == plan.stage_at(nxt.t_s)
            # every remaining point is preceded by its move, never earlier than the resume time
            order = [(type(s).__name__, getattr(s, "point", getattr(s, "index", None))) for s in rest]
            for s in rest:
                if isinstance(s, SweepPoint):
                    assert order.index(("Move", s.index)) < order.index(("SweepPoint", s.index))
            # moves happen exactly when they did in the run that was never interrupted
            full_moves = {s.point: s.t_s for s in steps(plan) if isinstance(s, Move)}
            assert all(s.t_s == full_moves[s.point] for s in rest if isinstance(s, Move))


def test_fingerprint_tracks_the_timeline_only() -> None:
    """Changing the description keeps the fingerprint; changing a duration changes it."""
    a = parse_plan(_doc())
    assert parse_plan(_doc(description="notes")).fingerprint() == a.fingerprint()
    doc = _doc()
    doc["stages"][1]["duration_s"] = 61
    assert parse_plan(doc).fingerprint() != a.fingerprint()


def test_sim_clock_jumps_exactly_and_paces() -> None:
    """The simulated clock lands on each step's exact time and keeps the wall-clock pace at its speed."""
    fast = SimClock(speed=math.inf, start_s=50.0)
    assert [fast.wait_until(t) for t in (50.0, 50.1, 1e6)] == [50.0, 50.1, 1e6]
    # the lag is bounded by the wall time that actually passed beyond the pace (exact bounds, whatever the
    # machine's load: a stalled test process makes the lag larger and the bound with it)
    before = time.monotonic()
    paced = SimClock(speed=1000.0, start_s=10.0)
    t0 = time.monotonic()
    assert paced.wait_until(110.0) == 110.0
    assert time.monotonic() - t0 >= 0.099
    lag = paced.lag_s()
    assert lag <= (time.monotonic() - before) * 1000.0 - 100.0 + 1e-6  # 100 s of the 110 were the wait
    late = SimClock(speed=1000.0, start_s=0.0)
    time.sleep(0.05)  # 50 simulated seconds of set-up
    assert late.lag_s() >= 49.0
    anchored = time.monotonic()
    late.anchor()  # pacing starts now: set-up time is not lag
    assert late.lag_s() <= (time.monotonic() - anchored) * 1000.0 + 1e-6 and late.now() == 0.0
    with pytest.raises(ValueError):
        SimClock(speed=0)


def test_wall_clock_counts_from_campaign_start() -> None:
    """The wall clock is seconds since the campaign's start epoch and records late steps as they ran."""
    clock = WallClock(started_epoch_s=time.time() - 100.0)
    assert 100.0 <= clock.now() < 200.0
    assert clock.wait_until(5.0) >= 100.0
    assert clock.max_lag_s() >= 95.0
