"""`driftlab hal-offsets`: the external-offset component against a stand-in of LinuxCNC's hal module and motion.

The stand-in (tests/compensator/hal_standin.py) is written from LinuxCNC's documentation of external
axis offsets and of the Python hal module, not from the component. The offsets the axes end up
with are compared with the offline compensator's corrected program at the same pose: two paths
through the model agree within one positioning step.
"""

from __future__ import annotations

import json
import logging

import pytest

from driftlab.cli import main
from driftlab.compensator import hal_offsets
from driftlab.compensator.compensate import ErrorModel
from driftlab.compensator.hal_offsets import HalOffsets
from driftlab.compensator.stream import FixedTemperatures, StaticModel
from driftlab.errors import ValidationError
from tests.compensator.hal_standin import Axis, HalModule, Machine
from tests.compensator.test_stream import doc

TARGET = {"x": 100.0, "y": 50.0, "z": -20.0}
T_WARM = {"T1": 26.5}


def component(coef: float = 0.01, temps: dict[str, float] | None = None, **kw: object) -> tuple[HalOffsets, Machine]:
    hal = HalModule()
    comp = HalOffsets(
        hal,
        StaticModel(ErrorModel.from_document(doc(coef, 1))),
        FixedTemperatures(temps or T_WARM),
        **kw,  # type: ignore[arg-type]
    )
    axes = {a: Axis(min_limit=-300.0, max_limit=300.0) for a in comp.axes}
    return comp, Machine(hal.components["driftlab-hal"], axes)


def walk_to(comp: HalOffsets, m: Machine, pose: dict[str, float], steps: int = 5) -> None:
    """Move the planned position to ``pose`` in steps, one component period and 0.1 s of servo each."""
    start = {a: ax.pos_cmd for a, ax in m.axes.items()}
    for i in range(1, steps + 1):
        for a, ax in m.axes.items():
            ax.pos_cmd = start[a] + (pose.get(a, start[a]) - start[a]) * i / steps
        m.run(0.0)  # nets: the pose reaches the component
        comp.step()
        m.run(0.1)
    for _ in range(3):  # let the offsets settle at the rate OFFSET_AV_RATIO allows
        m.run(0.0)
        comp.step()
        m.run(0.5)


def offline_correction(tmp_path, pose: dict[str, float]) -> dict[str, float]:
    """Return the offline compensator's correction (mm) at ``pose``: corrected target minus nominal."""
    model = tmp_path / "model.json"
    model.write_text(json.dumps(doc(0.01, 1)))
    temps = tmp_path / "t.csv"
    temps.write_text("time_s,T1\n0.0,26.5\n")
    prog = tmp_path / "p.nc"
    prog.write_text(f"G90 G1 X{pose['x']} Y{pose['y']} Z{pose['z']} F1000\n")
    out = tmp_path / "o.nc"
    args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "--start", "0,0,0,0,0"]
    assert main([*args, "--max-segment-mm", "1000", "-o", str(out)]) == 0
    last = [ln for ln in out.read_text().splitlines() if ln.startswith("G")][-1]
    words = {w[0].lower(): float(w[1:]) for w in last.split() if w[0] in "XYZ"}
    return {a: words[a] - pose[a] for a in "xyz"}


def test_the_axes_carry_the_offline_correction(tmp_path):
    comp, m = component()
    m.machine(True)
    walk_to(comp, m, TARGET)
    want = offline_correction(tmp_path, TARGET)
    assert comp.state.fault is None
    for a in "xyz":
        assert m.axes[a].eoffset == pytest.approx(want[a], abs=0.0025 / 2 + 1e-4)  # one positioning step, 0.1 µm counts
        assert m.axes[a].position == pytest.approx(TARGET[a] + comp.state.applied[a], abs=1e-9)
    assert abs(m.axes["z"].eoffset) > 0.05  # 6.5 degC on the head: a correction worth applying
    assert comp.comp["active"] and not comp.comp["fault"]


def test_machine_off_holds_the_counts_at_zero_and_machine_on_starts_from_zero():
    comp, m = component()
    m.machine(True)
    walk_to(comp, m, TARGET)
    kept = m.axes["z"].eoffset
    m.machine(False)
    m.run(0.0)
    comp.step()
    m.run(0.1)
    assert comp.comp["z.counts"] == 0 and not comp.comp["z.enable"]
    assert m.axes["z"].eoffset == kept  # motion keeps the position at machine-off (no unexpected motion)
    m.machine(True)  # the register and the offset are zeroed; the counts go from 0 again
    m.run(0.0)
    assert m.axes["z"].eoffset == 0.0
    walk_to(comp, m, TARGET, steps=1)
    assert m.axes["z"].eoffset == pytest.approx(kept, abs=1e-9)


def test_a_correction_beyond_the_envelope_is_held_not_applied(caplog):
    comp, m = component()
    m.machine(True)
    walk_to(comp, m, TARGET)
    kept = {a: m.axes[a].eoffset for a in "xyz"}
    comp.models = StaticModel(ErrorModel.from_document(doc(5.0, 2)))  # 5 mm/degC: 32 mm at 26.5 degC
    with caplog.at_level(logging.WARNING):
        walk_to(comp, m, TARGET, steps=3)
    assert comp.state.fault is not None and "exceeds the largest plausible" in comp.state.fault
    assert comp.comp["fault"]
    assert {a: m.axes[a].eoffset for a in "xyz"} == kept
    assert sum("holding the offsets" in r.message for r in caplog.records) == 1  # logged once, not each period
    comp.models = StaticModel(ErrorModel.from_document(doc(0.01, 3)))
    walk_to(comp, m, TARGET, steps=1)
    assert comp.state.fault is None and not comp.comp["fault"]


def test_temperatures_beyond_the_fitted_range_are_held():
    comp, m = component(temps={"T1": 80.0})  # fitted on 10..40 degC
    m.machine(True)
    walk_to(comp, m, TARGET)
    assert "above the range the model was fitted on" in (comp.state.fault or "")
    assert all(m.axes[a].eoffset == 0.0 for a in "xyz")


def test_an_offset_past_the_travel_ends_at_the_travel():
    comp, m = component(coef=0.05)
    m.machine(True)
    walk_to(comp, m, {"x": 0.0, "y": 0.0, "z": -299.9})  # -0.33 mm on Z would leave the 300 mm travel
    assert "outside the travel" in (comp.state.fault or "") and comp.comp["fault"]
    assert -300.0 - 1e-9 <= m.axes["z"].position <= -299.9 and m.axes["z"].eoffset < -0.099
    walk_to(comp, m, {"x": 0.0, "y": 0.0, "z": -100.0})  # back inside: the whole correction again
    assert comp.state.fault is None and m.axes["z"].eoffset == pytest.approx(comp.state.applied["z"], abs=1e-9)
    assert comp.state.applied["z"] < -0.3


def test_bad_axes_and_scales_are_one_line():
    with pytest.raises(ValidationError, match="distinct letters"):
        component(axes="xq")
    with pytest.raises(ValidationError, match="positive"):
        component(scale={"x": 0.0})


def test_the_command_without_linuxcnc_is_one_line(tmp_path, capsys):
    model = tmp_path / "model.json"
    model.write_text(json.dumps(doc(0.01, 1)))
    temps = tmp_path / "t.csv"
    temps.write_text("time_s,T1\n0.0,26.5\n")
    assert main(["hal-offsets", "--model", str(model), "--temps", str(temps)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'hal' is not importable" in err[0]


def test_the_command_drives_the_pins_through_the_stand_in(tmp_path, capsys, monkeypatch):
    model = tmp_path / "model.json"
    model.write_text(json.dumps(doc(0.01, 1)))
    temps = tmp_path / "t.csv"
    temps.write_text("time_s,T1\n0.0,26.5\n")
    hal = HalModule(presets={"machine-on": True, "x.pos": 100.0, "z.pos": -20.0})
    monkeypatch.setattr(hal_offsets, "import_hal", lambda: hal)
    argv = ["hal-offsets", "--model", str(model), "--temps", str(temps), "--periods", "3", "--period-s", "0.001"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "driftlab-hal: 3 periods" in out and "0 fault(s)" in out
    comp = hal.components["driftlab-hal"]
    assert comp.closed  # exit() on the way out
    assert comp.values["z.counts"] != 0 and comp.values["z.enable"] and comp.values["z.scale"] == 1e-4


def test_the_documented_hal_nets_name_real_pins():
    """docs/instruments.md's HAL example: every driftlab-hal pin exists, every motion pin is a documented one."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "instruments.md").read_text()
    nets = re.findall(r"^net \S+\s+(\S+)\s+=>\s+(\S+)", text, re.MULTILINE)
    assert len(nets) >= 5
    comp, _ = component(axes="xyzab")
    ours = {f"driftlab-hal.{name}" for name in comp.comp.pins}
    documented = {
        f"axis.{a}.{p}" for a in "xyzabcuvw" for p in ("pos-cmd", "eoffset-counts", "eoffset-scale", "eoffset-enable")
    }
    documented.add("halui.machine.is-on")
    for src, dst in nets:
        for pin in (src, dst):
            if pin.startswith("driftlab-hal."):
                assert pin in ours, pin
            elif pin != "...":
                assert pin in documented, pin
