"""Scenarios: the default staged plan, YAML loading, one-line errors naming the field."""

from pathlib import Path

import pytest

from driftlab.daq.sim.scenario import HiddenEffect, Scenario, default_plan, load_scenario
from driftlab.errors import ValidationError

EXAMPLES = Path(__file__).resolve().parents[3] / "examples" / "scenarios"


def test_default_plan_is_staged_and_contiguous():
    plan = default_plan(72.0)
    assert plan[0].start_s == 0 and plan[-1].end_s == 72 * 3600
    for a, b in zip(plan, plan[1:]):
        assert a.end_s == b.start_s
    assert len({s.name for s in plan}) == len(plan)
    kinds = {(s.heat_source, s.axis) for s in plan}
    for want in [
        ("spindle", "Z"),
        ("feed", "X"),
        ("feed", "Y"),
        ("feed", "Z"),
        ("feed", "A"),
        ("feed", "B"),
        ("combined", "Z"),
        ("idle", None),
        ("off", None),
    ]:
        assert want in kinds
    # intensities change from cycle to cycle, so heat-up histories are not copies of each other
    assert len({s.spindle_rpm for s in plan if s.heat_source == "spindle"}) == 3
    assert all(s.start_s % 60 == 0 for s in plan)


def test_short_plan_is_compressed_with_every_stage():
    plan = default_plan(6.0)
    assert plan[-1].end_s == 6 * 3600
    assert {s.heat_source for s in plan} == {"spindle", "feed", "combined", "idle", "off"}
    assert {s.axis for s in plan if s.heat_source == "feed"} == {"X", "Y", "Z", "A", "B"}


def test_examples_load():
    names = {p.stem for p in EXAMPLES.glob("*.yaml")}
    assert {"clean", "thesis", "lag-z", "screw-x", "fault-t34", "two-effects", "reference"} <= names
    for p in EXAMPLES.glob("*.yaml"):
        s = load_scenario(p)
        assert s.name == p.stem
    assert load_scenario(EXAMPLES / "clean.yaml").hidden == []
    kinds = {e.kind for e in load_scenario(EXAMPLES / "thesis.yaml").hidden}
    assert kinds == {"screw_expansion", "reversal"}


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("hours: -3\n", "hours:"),
        ("hourz: 3\n", "hourz:"),
        ("hidden:\n  - {kind: drift, axis: X, term: dx, params: {}}\n", "hidden.0: drift needs param 'rate_per_day'"),
        ("hidden:\n  - {kind: warp, axis: X, term: dx}\n", "hidden.0.kind"),
        (
            "hidden:\n"
            "  - {kind: unmapped_channel, axis: Z, term: dz, channels: [T34], params: {coef_per_degC: 1e-3}}\n",
            "T34 is a model channel",
        ),
        ("hidden:\n  - {kind: reversal, axis: A, term: alpha, params: {magnitude_mm: 0.004}}\n", "magnitude_rad"),
        ("hidden:\n  - {kind: sensor_fault, channels: [T9], params: {start_s: 10, mode: melted}}\n", "mode"),
        (
            "hidden:\n  - {kind: quadratic, axis: X, term: dx, channels: [T99], params: {coef_per_degC2: 1}}\n",
            "unknown channel 'T99'",
        ),
        ("hidden:\n  - {kind: drift, axis: X, term: dx, params: {rate_per_day: 1, speed: 2}}\n", "does not take"),
        ("stages:\n  - {name: a, start_s: 0, end_s: 60, heat_source: feed}\n", "stages.0: a feed stage needs an axis"),
        ("started_at: yesterday\n", "started_at"),
        ("hours: [1\n", "not valid YAML"),
        ("- 1\n- 2\n", "expected a mapping"),
    ],
)
def test_bad_scenarios_fail_in_one_line(tmp_path, text, needle):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ValidationError) as exc:
        load_scenario(p)
    msg = exc.value.one_line()
    assert needle in msg
    assert "\n" not in str(exc.value)
    assert str(p) in msg


def test_yaml_quirks(tmp_path):
    p = tmp_path / "q.yaml"
    p.write_text(
        "stages:\n  - {name: night, start_s: 0, end_s: 60, heat_source: off}\n"
        "hidden:\n  - {kind: drift, axis: X, term: dx, params: {rate_per_day: 1e-3}}\n"
    )
    s = load_scenario(p)
    assert s.stages[0].heat_source == "off"  # not YAML 1.1's false
    assert s.hidden[0].params["rate_per_day"] == 1e-3  # not YAML 1.1's string "1e-3"


def test_missing_file_is_a_validation_error(tmp_path):
    with pytest.raises(ValidationError, match="cannot read"):
        load_scenario(tmp_path / "nope.yaml")


def test_built_in_code():
    s = Scenario(
        hours=2, seed=9, hidden=[HiddenEffect(kind="drift", axis="B", term="beta", params={"rate_per_day": 1e-6})]
    )
    assert s.plan()[-1].end_s == 7200
    assert s.model_copy(update={"hours": 3.0}).plan()[-1].end_s == 10800
    assert s.start_hour_of_day == 8.0
