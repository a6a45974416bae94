"""The machine envelope (issue 24): what the compensator refuses before the first byte is written or sent.

Each case of the issue, reproduced through the command line: a target beyond the travel, a G91
runaway, feeds <= 0, a late block needing too many subdivisions while streaming, temperatures far
above the fitted range, an implausible correction, a document without an envelope. Every refusal
is one line naming the block, the limit and the value, and leaves no output file (nor its .part)
and no block on the controller.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from driftlab.cli import main
from driftlab.compensator.compensate import ErrorModel, FirstPass, scan_program
from driftlab.compensator.guard import Guard
from driftlab.compensator.stream import FixedTemperatures, StaticModel, Streamer
from driftlab.daq.sim.instruments import SimController, WallClock, serial_url
from driftlab.errors import ValidationError
from driftlab.models.envelope import Envelope, envelope_from_mapping, merge
from driftlab.testing.tinyworld import TinyWorld
from tests.compensator.test_stream import doc

#: the virtual machine's travel (daq.sim.truth.AXIS_RANGE) with 10 mm / 10 deg of room
TRAVEL = {"X": [-10.0, 264.0], "Y": [-10.0, 264.0], "Z": [-264.0, 10.0], "A": [-55.0, 55.0], "B": [-55.0, 55.0]}


@pytest.fixture
def setup(tmp_path: Path):
    """Return (model without an envelope, machine file, temperatures, output directory)."""
    old = doc(0.01, 4)
    del old["envelope"]
    model = tmp_path / "model.json"
    model.write_text(json.dumps(old))
    machine = tmp_path / "machine.json"
    machine.write_text(json.dumps({"travel": TRAVEL}))
    temps = tmp_path / "temperatures.csv"
    pd.DataFrame({"time_s": [0.0], "T1": [26.0]}).to_csv(temps, index=False)
    out = tmp_path / "out"
    out.mkdir()
    return model, machine, temps, out


def _offline(tmp_path: Path, setup, program: bytes | str, *extra: str) -> tuple[int, list[str], list[str]]:
    """Run `compensate -o` on ``program``; return (exit code, stdout lines, stderr lines)."""
    model, machine, temps, out = setup
    prog = tmp_path / "p.nc"
    prog.write_bytes(program.encode() if isinstance(program, str) else program)
    args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(out / "o.nc")]
    code = main(args + ["--machine-file", str(machine), *extra])
    return code, [], []


@pytest.mark.parametrize(
    "program,extra,expected",
    [
        # the first case: accepted before, with a correction of Y -11,343 mm
        (
            "G90 G21\nG1 X10 Y10 Z-10 F1000\nG1 X999999 F1000\n",
            ["--max-segment-mm", "1000"],
            "p.nc:3: target X 999999 mm is outside the travel -10..264 mm; program not accepted",
        ),
        # G91 runaway: 2,000 x G1 X99999 wrote 229 MB of .part before; the second block leaves the travel
        (
            "G91 G21\n" + "G1 X99999 F1000\n" * 2000,
            [],
            "p.nc:2: target X 99999 mm is outside the travel -10..264 mm; program not accepted",
        ),
        ("G90 G21\nG1 X10 F0\nG1 X20\n", [], "p.nc:2: feed 'F0' must be positive"),
        ("G90 G21\nG1 X10 F1000\nG1 X20 F-100\n", [], "p.nc:3: feed 'F-100' must be positive"),
        ("G90\nG1 X1 F1000\nG1 A1000000\n", [], "p.nc:3: target A 1e+06 deg is outside the travel -55..55 deg"),
        # a late block that needs more than 100,000 subdivisions inside the travel
        (
            "G90\nG1 X1 F1000\n" * 500 + "G1 X250\n",
            ["--max-segment-mm", "0.001"],
            "p.nc:1001: segment would need more than 100000 subdivisions",
        ),
        # the start pose counts: G91 from --start
        ("G91\nG1 X-5 F1000\n", ["--start=-6,0,0,0,0"], "p.nc:2: target X -11 mm is outside the travel -10..264"),
    ],
    ids=["far-target", "g91-runaway", "feed-zero", "feed-negative", "late-rotary", "late-subdivision", "g91-start"],
)
def test_refused_before_anything_is_written(tmp_path, setup, capsys, program, extra, expected):
    code, _, _ = _offline(tmp_path, setup, program, *extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("driftlab: error: ") and expected in err[0], err
    assert list(setup[3].iterdir()) == []  # neither the output nor its .part


def test_a_program_inside_the_envelope_is_written(tmp_path, setup, capsys):
    code, _, _ = _offline(tmp_path, setup, "G90 G21\nG1 X10 Y10 Z-10 F1000\nG1 X250\n", "--json")
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["max_correction"]["Z"] == pytest.approx(0.06)  # 26 degC: the head grew 0.06 mm
    assert "extrapolated" not in summary
    assert [p.name for p in setup[3].iterdir()] == ["o.nc"]


def test_a_document_without_travel_needs_a_machine_file(tmp_path, setup, capsys):
    model, _, temps, out = setup
    prog = tmp_path / "p.nc"
    prog.write_text("G90\nG1 X1 F100\n")
    code = main(["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(out / "o.nc")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "carries no machine travel" in err[0] and "--machine-file" in err[0]
    assert list(out.iterdir()) == []


def test_the_documents_envelope_is_used_and_the_machine_file_wins(tmp_path, setup, capsys):
    model, machine, temps, out = setup
    body = json.loads(model.read_text())
    body["envelope"] = {"travel": {"X": [0.0, 5.0]}}
    model.write_text(json.dumps(body))
    prog = tmp_path / "p.nc"
    prog.write_text("G90\nG1 X10 F100\n")
    base = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(out / "o.nc")]
    assert main(base) == 2
    assert "p.nc:2: target X 10 mm is outside the travel 0..5 mm" in capsys.readouterr().err
    assert main(base + ["--machine-file", str(machine)]) == 0  # the file's X travel replaces the document's


@pytest.mark.parametrize(
    "body,expected",
    [
        ({"travel": {"X": [0, "254"]}}, "travel.X.1: Input should be a valid number"),
        ({"travel": {"X": [0, True]}}, "travel.X.1: Input should be a valid number"),
        ({"travel": {"X": [254, 0]}}, "travel of X must be two finite numbers, low < high"),
        ({"travel": {"C": [0, 1]}}, "travel.C.[key]"),
        ({"max_correction": {"Z": 0}}, "max_correction of Z must be a positive finite number"),
        # issue 34: a guard switched off by data is refused, not obeyed
        ({"max_correction": {"Z": 1e9}}, "max_correction of Z 1e+09 mm is above 5 mm: no thermal error is that large"),
        ({"max_correction": {"B": 10}}, "max_correction of B 10 deg is above 1 deg"),
        ({"extrapolation_margin_degC": 1e9}, "extrapolation_margin_degC: Input should be less than or equal to 30"),
        ({"travel": {}, "speed": 1}, "speed: Extra inputs are not permitted"),
        ([1, 2], "expected a mapping"),
    ],
)
def test_bad_machine_files_are_one_line(tmp_path, setup, capsys, body, expected):
    machine = setup[1]
    machine.write_text(json.dumps(body))
    code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 F100\n")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and expected in err[0], err
    assert list(setup[3].iterdir()) == []


def test_a_yaml_machine_file(tmp_path, setup, capsys):
    machine = tmp_path / "machine.yaml"
    machine.write_text("travel:\n  X: [0, 254]\n  Z: [-254, 0]\nmax_correction:\n  Z: 0.05\n")
    model, _, temps, out = setup
    prog = tmp_path / "p.nc"
    prog.write_text("G90\nG1 X1 Z-1 F100\n")
    args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(out / "o.nc")]
    assert main(args + ["--machine-file", str(machine)]) == 2  # 0.06 mm of Z correction > 0.05 mm
    err = capsys.readouterr().err.strip()
    assert "p.nc:2: correction of Z -0.06 mm exceeds the largest plausible 0.05 mm" in err
    assert list(out.iterdir()) == []


def test_an_implausible_correction_is_refused(tmp_path, setup, capsys):
    """A broken model (a metre per degC) commands metres: refused at the first block, not sent."""
    model = setup[0]
    body = json.loads(model.read_text())
    body["terms"][0]["coefficients"] = [1000.0]
    model.write_text(json.dumps(body))
    code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 Y1 Z-1 F100\n")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "p.nc:2: correction of Z -6000 mm exceeds the largest plausible 1 mm" in err[0]
    assert list(setup[3].iterdir()) == []


def test_a_corrected_target_beyond_the_travel_is_refused(tmp_path, setup, capsys):
    """Z at its lowest travel: the head's growth (-0.06 mm) would take it beyond."""
    code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 Z-264 F100\n")
    err = capsys.readouterr().err.strip()
    assert code == 2 and "p.nc:2: corrected target Z -264.06 mm is outside the travel -264..10 mm" in err


def test_a_corrected_target_within_half_a_step_of_the_travel_is_refused_first(tmp_path, setup, capsys):
    """The quantiser sends each point within half a step (1.25 um) of its correction: a corrected target
    1 um inside the travel could be sent 0.25 um outside it, so the first pass refuses it before the
    output is opened (streamed, it would have stopped mid-part); 2 um inside is written."""
    code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 Z-263.939 F100\n")
    err = capsys.readouterr().err.strip()
    assert code == 2 and "p.nc:2: corrected target Z -263.999 mm is within the positioning step" in err, err
    assert "of the travel -264..10 mm: the step sent could leave it" in err
    assert list(setup[3].iterdir()) == []
    code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 Z-263.938 F100\n")
    assert code == 0, capsys.readouterr().err


def test_extrapolation_is_refused_unless_allowed(tmp_path, setup, capsys, caplog):
    """60 degC above anything in the campaign: refused; with --allow-extrapolation logged and reported."""
    temps = setup[2]
    pd.DataFrame({"time_s": [0.0], "T1": [100.0]}).to_csv(temps, index=False)  # fitted on 10..40 degC
    code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 F100\n")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "T1 100 degC is 60 degC above the range the model was fitted on (10..40 degC, margin 5 degC)" in err[0]
    assert "--allow-extrapolation" in err[0]
    assert list(setup[3].iterdir()) == []
    with caplog.at_level(logging.WARNING, logger="driftlab.compensator.guard"):
        code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 F100\n", "--allow-extrapolation", "--json")
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["extrapolated"]["T1"]["beyond_degC"] == pytest.approx(60.0)
    assert any("extrapolating: temperatures: T1 100 degC" in r.getMessage() for r in caplog.records)


def test_within_the_margin_is_not_extrapolation(tmp_path, setup, capsys):
    pd.DataFrame({"time_s": [0.0], "T1": [44.0]}).to_csv(setup[2], index=False)  # 4 degC above, margin 5
    code, _, _ = _offline(tmp_path, setup, "G90\nG1 X1 F100\n", "--json")
    assert code == 0 and "extrapolated" not in json.loads(capsys.readouterr().out)


def test_timed_programs_check_the_scans_they_use(tmp_path, setup, capsys):
    """With a table and a timed program, each block's scan is checked: a hot scan at T=3600 is refused."""
    pd.DataFrame({"time_s": [0.0, 3600.0, 7200.0], "T1": [20.0, 90.0, 20.0]}).to_csv(setup[2], index=False)
    code, _, _ = _offline(tmp_path, setup, "G90\n(T=0)\nG1 X1 F100\n(T=3600)\nG1 X2\n")
    err = capsys.readouterr().err
    assert code == 2 and "T1 90 degC is 50 degC above" in err
    assert list(setup[3].iterdir()) == []


# ----------------------------------------------------------------------------- streaming


def test_streaming_refuses_a_late_block_before_sending_anything(tmp_path, setup, capsys):
    """The issue: `G1 A1000000` late in a program was refused after 789 blocks had run."""
    model, machine, temps, _ = setup
    prog = tmp_path / "late.nc"
    prog.write_text("G90 G1 F6000\n" + "".join(f"X{k % 50} Y{k % 40}\n" for k in range(900)) + "G1 A1000000\n")
    with SimController(TinyWorld(channels=2), WallClock(acceleration=1e9), capacity=64) as sim:
        args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "--port", serial_url(sim)]
        code = main(args + ["--machine-file", str(machine)])
        executed = list(sim.executed)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "late.nc:902: target A 1e+06 deg is outside the travel -55..55 deg" in err[0]
    assert executed == []


def test_streaming_refuses_feed_zero_before_sending_anything(tmp_path, setup, capsys):
    """The issue: the controller rejected F0 after 806 blocks."""
    model, machine, temps, _ = setup
    prog = tmp_path / "f0.nc"
    prog.write_text("G90 G1 F6000\n" + "".join(f"X{k % 50}\n" for k in range(900)) + "G1 X3 F0\n")
    with SimController(TinyWorld(channels=2), WallClock(acceleration=1e9), capacity=64) as sim:
        args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "--port", serial_url(sim)]
        code = main(args + ["--machine-file", str(machine)])
        executed = list(sim.executed)
    assert code == 2 and "f0.nc:902: feed 'F0' must be positive" in capsys.readouterr().err
    assert executed == []


def test_the_streamer_stops_when_the_temperatures_leave_the_range_mid_run(tmp_path):
    """Readings that climb beyond the margin during a run: the streamer stops before using them."""
    model = ErrorModel.from_document(doc(0.01, 1))
    prog = tmp_path / "p.nc"
    prog.write_text("G90 G1 F1000\n" + "".join(f"X{k}\n" for k in range(1, 40)))
    from driftlab.compensator.gcode import parse_program

    program = parse_program(prog.read_bytes(), name=str(prog))
    readings = FixedTemperatures({"T1": 25.0})
    now = [0.0]
    guard = Guard.for_model(model)
    streamer = Streamer(
        program,
        StaticModel(model),
        readings,
        refresh_s=1.0,
        lookahead=4,
        batch_lines=2,
        clock=lambda: now[0],
        sleep=lambda s: None,
        guard=guard,
    )
    streamer.prime()
    sent = []
    lines = streamer.lines()
    for _ in range(5):
        sent.append(next(lines))
    readings.values = {"T1": 80.0}  # 40 degC above the fitted 40 degC
    now[0] = 2.0
    with pytest.raises(ValidationError, match="T1 80 degC is 40 degC above"):
        for text in lines:
            sent.append(text)
    assert len(sent) == 5  # nothing prepared with the refused readings left


def test_the_streamer_checks_every_point_it_prepares(tmp_path):
    """A point whose correction leaves the envelope is never queued, even when the first pass was skipped."""
    body = doc(0.01, 1)
    body["envelope"] = {"travel": TRAVEL, "max_correction": {"Z": 0.02}}
    model = ErrorModel.from_document(body)
    from driftlab.compensator.gcode import parse_program

    program = parse_program("G90 G1 F1000\nX1\nX2\n", name="p.nc")
    streamer = Streamer(
        iter([program]), StaticModel(model), FixedTemperatures({"T1": 25.0}), guard=Guard.for_model(model)
    )  # 0.05 mm of Z correction; pieces (an iterator) are not checked up front: the caller's first pass does
    with pytest.raises(ValidationError, match="p.nc:2: correction of Z -0.05 mm exceeds the largest plausible 0.02"):
        streamer.prime()
    assert not streamer._ready


def test_the_streamer_checks_a_whole_program_before_preparing_anything():
    """Given a whole program and a guard, the streamer runs the first pass itself: a late block is refused first."""
    model = ErrorModel.from_document(doc(0.01, 1))
    from driftlab.compensator.gcode import parse_program

    text = "G90 G1 F1000\n" + "".join(f"X{k}\n" for k in range(1, 301))  # X 265 on line 266: beyond 264
    program = parse_program(text, name="p.nc")
    guard = Guard(envelope_from_mapping({"travel": TRAVEL}), model.ranges)
    streamer = Streamer(program, StaticModel(model), FixedTemperatures({"T1": 25.0}), lookahead=8, guard=guard)
    with pytest.raises(ValidationError, match=r"p.nc:266: target X 265 mm is outside the travel -10..264 mm"):
        streamer.prime()
    assert not streamer._ready and streamer.result.blocks_sent == 0
    # the same program within the travel streams (the check does not refuse what is inside)
    ok = parse_program("G90 G1 F1000\n" + "".join(f"X{k}\n" for k in range(1, 200)), name="p.nc")
    inside = Streamer(ok, StaticModel(model), FixedTemperatures({"T1": 25.0}), lookahead=8, guard=guard)
    inside.prime()
    assert len(inside._ready) >= 8  # a batch of lines prepared ahead


# ----------------------------------------------------------------------------- pieces


def test_the_first_pass_carries_the_pose_across_pieces(tmp_path):
    """G91 blocks spread over many pieces are checked where they really go (not each piece from home)."""
    model = ErrorModel.from_document(doc(0.0, 1))
    prog = tmp_path / "p.nc"
    prog.write_text("G91 G1 F1000\n" + "X1.0 (step)\n" * 300)  # ends at X 300, beyond 264
    guard = Guard(envelope_from_mapping({"travel": TRAVEL}))
    check = FirstPass(guard, model, {"T1": 20.0})
    with pytest.raises(ValidationError, match=r"p.nc:266: target X 265 mm is outside the travel -10..264 mm"):
        scan_program(prog, "p.nc", (4, 3), chunk_bytes=256, check=check)


def test_envelopes_merge_key_by_key():
    doc_env = Envelope(travel={"X": (0.0, 10.0), "Y": (0.0, 5.0)}, max_correction={"Z": 0.5}, source="doc")
    file_env = envelope_from_mapping({"travel": {"X": [0, 20]}}, "m.yaml")
    both = merge(doc_env, file_env)
    assert both is not None
    assert both.travel == {"X": (0.0, 20.0), "Y": (0.0, 5.0)}
    assert both.max_correction == {"Z": 0.5}  # the file stated none: the document's stands
    assert both.source == "doc, m.yaml"
    lo, hi, mc = both.limits()
    assert lo[:2] == [0.0, 0.0] and np.isinf(lo[2]) and mc[2] == 0.5


# ----------------------------------------------------------------------------- the envelope travels with the model


@pytest.mark.slow
def test_fit_writes_the_machine_files_envelope_into_the_document(tmp_path, capsys):
    """`fit --machine-file` puts the envelope in the registered document; compensate then needs no file."""
    from driftlab.campaigns.store import connect
    from tests.jobs.conftest import MACHINE, bundle

    url = f"sqlite:///{tmp_path / 's.sqlite'}"
    with connect(url) as store:
        cid = store.campaigns.import_bundle(bundle())
    machine = tmp_path / "machine.yaml"
    machine.write_text("travel:\n  X: [-10, 264]\n  Y: [-10, 264]\n  Z: [-264, 10]\nmax_correction:\n  Z: 0.5\n")
    assert main(["fit", "--campaign", str(cid), "--db", url, "--no-network", "--machine-file", str(machine)]) == 0
    capsys.readouterr()
    assert main(["models", "show", "current", "--machine", MACHINE, "--db", url, "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    document = document.get("document", document)
    assert document["envelope"]["travel"]["X"] == [-10.0, 264.0]
    assert document["envelope"]["max_correction"]["Z"] == 0.5
    model = tmp_path / "model.json"
    model.write_text(json.dumps(document))
    temps = tmp_path / "t.csv"
    reference = {c: r["reference"] for c, r in document["inputs"].items()}
    pd.DataFrame({"time_s": [0.0], **{c: [v] for c, v in reference.items()}}).to_csv(temps, index=False)
    prog = tmp_path / "p.nc"
    prog.write_text("G90\nG1 X10 Y10 Z-10 F1000\nG1 X999999\n")
    args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(tmp_path / "o.nc")]
    assert main(args) == 2  # no --machine-file: the document's own travel refuses the far target
    assert "p.nc:3: target X 999999 mm is outside the travel -10..264 mm" in capsys.readouterr().err
    prog.write_text("G90\nG1 X10 Y10 Z-10 F1000\nG1 X200\n")
    assert main(args) == 0


def test_kept_commands_still_name_the_first_bad_block(tmp_path):
    """Offline, blocks are solved in runs spanning pieces: an early bad correction is still named before a later
    target beyond the travel, and nothing is written."""
    from driftlab.compensator.compensate import compensate_file

    model = ErrorModel.from_document(doc(0.01, 1))  # X correction -1.2e-4 mm per mm of X at T1 = 26 degC
    lines = ["G90 G1 F1000", *(f"X{k}" for k in range(1, 99)), "X210", *(f"X{k}" for k in range(100, 200)), "X300"]
    prog = tmp_path / "p.nc"
    prog.write_text("\n".join(lines) + "\n")
    guard = Guard(envelope_from_mapping({"travel": TRAVEL, "max_correction": {"X": 0.025}}), model.ranges)
    out = tmp_path / "out.nc"
    with pytest.raises(ValidationError, match=r"p.nc:100: correction of X -0.0252 mm exceeds the largest plausible"):
        compensate_file(prog, model, {"T1": 26.0}, out, chunk_bytes=256, guard=guard)
    assert not out.exists() and not (tmp_path / "out.nc.part").exists()
    # without the bad block the later target is named
    prog.write_text("\n".join(ln for ln in lines if ln != "X210") + "\n")
    with pytest.raises(ValidationError, match=r"p.nc:200: target X 300 mm is outside the travel"):
        compensate_file(prog, model, {"T1": 26.0}, out, chunk_bytes=256, guard=guard)


@pytest.mark.parametrize(
    "change,expected",
    [
        (lambda d: d.update(terms=[]), "has no terms (terms: []): it would correct nothing; refused"),
        (lambda d: d["inputs"]["T1"].update(min=41.0), "input range min 41 is above max 40"),
        (lambda d: d.update(envelope={**d["envelope"], "max_correction": {"X": 1e9}}), "is above 5 mm"),
        (lambda d: d.update(envelope={**d["envelope"], "extrapolation_margin_degC": 1e9}), "less than or equal to 30"),
    ],
)
def test_model_documents_that_switch_a_guard_off_are_one_line(tmp_path, capsys, change, expected):
    from tests.compensator.test_stream import doc

    body = doc(0.01, 3)
    change(body)
    model = tmp_path / "m.json"
    model.write_text(json.dumps(body))
    prog = tmp_path / "p.nc"
    prog.write_text("G90 G1 X1 F100\n")
    temps = tmp_path / "t.csv"
    temps.write_text("time_s,T1\n0,25\n")
    out = tmp_path / "out.nc"
    code = main(["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and expected in err[0], err
    assert not out.exists()


def test_o_writes_only_a_regular_file(tmp_path, capsys):
    import os

    from tests.compensator.test_stream import doc

    model = tmp_path / "m.json"
    model.write_text(json.dumps(doc(0.01, 3)))
    prog = tmp_path / "p.nc"
    prog.write_text("G90 G1 X1 F100\n")
    temps = tmp_path / "t.csv"
    temps.write_text("time_s,T1\n0,25\n")
    target = tmp_path / "precious.nc"
    target.write_text("keep me\n")
    link = tmp_path / "link.nc"
    link.symlink_to(target)
    fifo = tmp_path / "fifo.nc"
    os.mkfifo(fifo)
    part_link = tmp_path / "out2.nc.part"
    part_link.symlink_to(target)
    base = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o"]
    for out, needle in (
        ("/dev/full", "is a device"),
        ("/dev/null", "is a device"),
        (str(fifo), "is a FIFO"),
        (str(link), "is a symbolic link"),
        (str(tmp_path), "is a directory"),
        (str(tmp_path / "out2.nc"), "is a symbolic link"),  # its .part is a link
    ):
        assert main(base + [out]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and "nothing written" in err[0], err
    assert target.read_text() == "keep me\n" and link.is_symlink() and fifo.exists()
    good = tmp_path / "good.nc"
    assert main(base + [str(good)]) == 0 and good.is_file() and not (tmp_path / "good.nc.part").exists()
    assert main(base + [str(good)]) == 0  # a regular file is replaced, as before
