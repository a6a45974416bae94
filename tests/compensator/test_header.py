"""The header comment of a corrected program (issue 35.8): model, temperatures used, driftlab, date.

Checked with a reading of ISO 6983's comment written here (a line that is one parenthesised comment of
printable 7-bit ASCII with no parenthesis inside), and the rest of the program byte for byte the
output without the header.
"""

from __future__ import annotations

import io
import json
import re
from datetime import UTC, datetime
from pathlib import Path

import pandas as pd

from driftlab.cli import main
from driftlab.compensator.compensate import ErrorModel, TemperatureTable, compensate_stream
from driftlab.compensator.header import HeaderedOut, program_header, temperature_lines
from tests.compensator.test_stream import doc

COMMENT = re.compile(rb"^\([\x20-\x27\x2a-\x7e]*\)$")
PROGRAM = "%\n(T=0)\nG90 G1 X0 Y0 Z0 F3000\nX4 Y2\n(T=3600)\nX8 Y4 A1.5\nG0 Z-20\nM30\n%\n"


def test_the_header_is_ascii_comments_after_the_tape_start() -> None:
    lines = program_header(
        "vmc-5ax-01",
        7,
        'ETag "abc"',
        temperature_lines({"T1": [20.0, 25.5], "T2": [21.0, 21.0]}, [0.0, 3600.0], "CSV "),
        "0.1.0",
        datetime(2026, 3, 2, 8, 0, tzinfo=UTC),
    )
    assert lines[0] == "(driftlab: thermal drift corrected by driftlab 0.1.0 2026-03-02T08:00:00Z)"
    assert lines[1] == '(driftlab: model vmc-5ax-01 v7 ETag "abc")'
    assert lines[2] == "(driftlab: temperatures CSV scans t = 0..3600 s, 2 scans)"
    assert lines[3] == "(driftlab: degC: T1 20.00..25.50 T2 21.00)"
    assert all(COMMENT.match(ln.encode()) and len(ln) <= 78 for ln in lines)
    # nothing a comment cannot hold gets through: parentheses, the degree sign, the micro sign
    (odd,) = program_header("m(1)", None, "°C µm", [], "x")[1:]
    assert COMMENT.match(odd.encode()), odd
    out = io.BytesIO()
    w = HeaderedOut(out, ["(h)"])
    w.write(b"%\nG1 X")
    w.write(b"1\n")
    w.close()
    assert out.getvalue() == b"%\n(h)\nG1 X1\n"
    out = io.BytesIO()
    w = HeaderedOut(out, ["(h)"])
    w.write(b"G1 X1\r\nG1 X2\r\n")
    assert out.getvalue() == b"(h)\r\nG1 X1\r\nG1 X2\r\n"


def test_a_corrected_program_carries_its_header(tmp_path: Path, capsys) -> None:
    prog = tmp_path / "part.nc"
    prog.write_text(PROGRAM)
    document = doc(0.01, 4)
    model_path = tmp_path / "model.json"
    model_path.write_text(json.dumps(document))
    temps = tmp_path / "temperatures.csv"
    frame = pd.DataFrame({"time_s": [0.0, 3600.0], "T1": [20.0, 26.0], "T2": [20.0, 21.0]})
    frame.to_csv(temps, index=False)
    machine = tmp_path / "machine.json"
    machine.write_text(json.dumps({"travel": {"X": [-10, 300], "Y": [-10, 300], "Z": [-300, 10]}}))
    out = tmp_path / "out.nc"
    args = ["compensate", str(prog), "--model", str(model_path), "--temps", str(temps), "-o", str(out)]
    assert main([*args, "--machine-file", str(machine)]) == 0
    data = out.read_bytes().splitlines()
    assert data[0] == b"%"
    header = [ln for ln in data[1:] if ln.startswith(b"(driftlab: ")]
    assert data[1 : 1 + len(header)] == header and len(header) == 4
    assert all(COMMENT.match(ln) for ln in header), header
    text = b"\n".join(header).decode()
    assert "thermal drift corrected by driftlab" in text and f"model {document['machine']} v" in text
    assert "document sha256 " in text and "t = 0..3600 s, 2 scans" in text and "T1 20.00..26.00" in text
    assert all(b < 128 for b in out.read_bytes())
    # the rest is byte for byte the program corrected without a header
    plain = io.BytesIO()
    compensate_stream(prog, ErrorModel.from_document(document), TemperatureTable.from_frame(frame), plain)
    body = [ln for ln in data if not any(ln == h for h in header)]
    assert b"\n".join(body) + b"\n" == plain.getvalue()
