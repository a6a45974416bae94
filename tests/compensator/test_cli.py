"""`driftlab compensate`: offline to a file, streaming to the simulated controller, one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import pandas as pd
import pytest

from driftlab.cli import main
from driftlab.compensator.gcode import parse_program
from driftlab.daq.sim.instruments import SimController, WallClock, serial_url
from driftlab.testing.tinyworld import TinyWorld
from tests.compensator.test_stream import Api, doc

PROGRAM = "%\n(T=0)\nG90 G1 X0 Y0 Z0 F3000\nX4 Y2\n(T=3600)\nX8 Y4 A1.5\nG0 Z20\nM30\n%\n"


@pytest.fixture
def files(tmp_path):
    prog = tmp_path / "part.nc"
    prog.write_text(PROGRAM)
    model = tmp_path / "model.json"
    model.write_text(json.dumps(doc(0.01, 4)))
    temps = tmp_path / "temperatures.csv"
    pd.DataFrame({"time_s": [0.0, 3600.0], "T1": [20.0, 26.0], "T2": [20.0, 21.0]}).to_csv(temps, index=False)
    return prog, model, temps


def test_offline_compensation_writes_the_corrected_program(files, tmp_path, capsys):
    prog, model, temps = files
    out = tmp_path / "out.nc"
    code = main(
        [
            "compensate",
            str(prog),
            "--model",
            str(model),
            "--machine",
            "m1",
            "--temps",
            str(temps),
            "-o",
            str(out),
            "--json",
        ]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["model"] == "m1 v4" and summary["temperatures"] == "nearest scan to each block's time"
    lines = [ln for ln in out.read_text().splitlines() if not ln.startswith("(driftlab: ")]  # the header
    assert lines[:3] == ["%", "(T=0)", "G90 G1 X0 Y0 Z0 F3000"]  # 20 degC at t = 0: nothing to correct
    assert lines[3] == "X4 Y2"
    # after an hour T1 is 26 degC: the head has grown 0.06 mm, the X scale 2e-5 * 6 per mm
    back = parse_program(out.read_bytes())
    z = back.target_int[:, 2] * back.scale[2]
    assert z[-2] == pytest.approx(-0.06)
    assert summary["max_correction"]["Z"] == pytest.approx(0.06)


def test_bad_block_is_one_line_error_and_nothing_is_written(files, tmp_path):
    prog, model, temps = files
    prog.write_text(PROGRAM.replace("X4 Y2", "X4 Y2 I5"))
    out = tmp_path / "out.nc"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "driftlab.cli",
            "compensate",
            str(prog),
            "--model",
            str(model),
            "--temps",
            str(temps),
            "-o",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"driftlab: error: {prog}:4: word 'I'")
    assert not out.exists()


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--machine", "other"], "model of machine m1, not other"),
        (["--start", "1,2"], "--start must be five numbers"),
        (["--hysteresis-steps", "0.5"], "--hysteresis-steps must be in [0, 0.5)"),
        ([], "needs -o"),
    ],
)
def test_usage_errors(files, capsys, extra, needle):
    prog, model, temps = files
    args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps)] + extra
    if needle != "needs -o":
        args += ["-o", str(prog.with_suffix(".out"))]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_streaming_to_the_simulated_controller_through_the_api(capsys):
    clock = WallClock(acceleration=600.0)
    api = Api()
    try:
        with SimController(TinyWorld(channels=2), clock, capacity=8) as sim:
            prog_text = "G90 G1 F6000\n" + "".join(f"X{k} Y{k}\n" for k in range(1, 13)) + "M30\n"
            import pathlib
            import tempfile  # noqa: E401

            with tempfile.TemporaryDirectory() as d:
                prog = pathlib.Path(d) / "p.nc"
                prog.write_text(prog_text)
                code = main(
                    [
                        "compensate",
                        str(prog),
                        "--api",
                        api.url,
                        "--machine",
                        "m1",
                        "--port",
                        serial_url(sim),
                        "--low-water",
                        "2",
                        "--high-water",
                        "6",
                        "--json",
                    ]
                )
                bad = pathlib.Path(d) / "bad.nc"
                bad.write_text("G1 X1\nG2 X2 Y2 R1\n")
                code_bad = main(
                    ["compensate", str(bad), "--api", api.url, "--machine", "m1", "--port", serial_url(sim)]
                )
            executed = list(sim.executed)
    finally:
        api.stop()
    assert code == 0 and code_bad == 2
    out, err = capsys.readouterr()
    summary = json.loads(out.strip().splitlines()[0])
    assert summary["blocks_sent"] == 14 == len(executed)  # the bad program sent nothing
    assert executed[1] == "X1 Y1 Z-0.05"
    assert "bad.nc:2:" in err


def _controller_program(lines: int, seed: int = 3) -> str:
    """Return a program in the simulated controller's dialect: a walk of short moves (some long enough to be
    subdivided) with mixed decimals, rapid moves, blank lines, and a long comment line every third line
    (comments are not sent: they make the file span several pieces without making it slow to stream)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    out = ["%", "(the controller's dialect: G90, G0/G1, F)", "G90 G1 F3000"]
    note = "(" + "tool path note, " * 8 + ")"
    pose = np.zeros(5)
    for k in range(lines):
        r = rng.random()
        if k % 3 == 0:
            out.append(note)
        elif r < 0.01:
            out.append("")
        elif r < 0.03:
            out.append(f"G0 Z{round(float(rng.uniform(5, 30)), 1)}")
        else:
            pose += rng.normal(0, [3.0, 3.0, 1.0, 0.5, 0.5])
            words = [
                f"{a}{round(float(v), int(rng.integers(0, 4)))}"
                for a, v in zip("XYZAB", pose)
                if rng.random() < (0.8 if a in "XYZ" else 0.2)
            ]
            feed = f" F{2000 + k % 7}" if r > 0.98 else ""
            out.append(("G1 " if r < 0.1 else "") + (" ".join(words) or "X1.5") + feed)
    return "\n".join(out + ["M30", "%"]) + "\n"


def test_port_sends_exactly_the_blocks_the_offline_path_writes(files, tmp_path, capsys):
    """`--port` and `-o` read the program through the same pieces: the controller gets the offline file's blocks."""
    from driftlab.compensator.compensate import STREAM_CHUNK_BYTES

    _, model, _ = files
    temps = tmp_path / "latest.csv"
    temps.write_text("time_s,T1,T2\n0.0,26.5,21.0\n")  # one scan: both paths use it for every block
    prog = tmp_path / "long.nc"
    prog.write_text(_controller_program(6000))
    assert prog.stat().st_size > STREAM_CHUNK_BYTES  # several pieces
    out = tmp_path / "out.nc"
    assert main(["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(out)]) == 0
    offline = [
        ln.strip()
        for ln in out.read_text().splitlines()
        if ln.strip() and ln.strip() != "%" and not ln.strip().startswith("(")
    ]
    # a controller that runs the blocks as fast as they come: the link never waits for the buffer to drain
    with SimController(TinyWorld(channels=2), WallClock(acceleration=1e9), capacity=256) as sim:
        code = main(
            ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "--port", serial_url(sim), "--json"]
        )
        executed = list(sim.executed)
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert executed == offline
    assert summary["blocks_sent"] == len(offline) > 4000 + 100  # some segments were cut into more blocks
    assert any(" Z" in b and "Z-" in b for b in executed[:20])  # corrected (26.5 degC: the head has grown)
