"""The streaming offline compensator: byte for byte what the whole-program path writes, in constant memory.

``compensate_program`` (the program parsed and corrected in one go, as before issue 13) is the
reference: ``compensate_file`` now streams the file in pieces of whole lines and must write exactly
the same bytes, whatever the piece size (down to a few lines per piece).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from driftlab.compensator.compensate import (
    ErrorModel,
    OfflineResult,
    TemperatureTable,
    compensate_file,
    compensate_program,
    decimals_for,
)
from driftlab.compensator.gcode import parse_program
from driftlab.errors import ValidationError
from tests.compensator.test_compensate import _all_kinds_doc

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples" / "programs").glob("*.nc"))
PIECES = [64, 700, 1 << 20]  # bytes per piece: a line or two, a few dozen lines, the default


def _model() -> ErrorModel:
    return ErrorModel.from_document(_all_kinds_doc())


def _table() -> TemperatureTable:
    t = np.arange(0.0, 7200.0 + 1, 300.0)
    return TemperatureTable.from_frame(
        pd.DataFrame({"time_s": t, "T9": 20 + t / 600, "T10": 21 + np.sin(t / 900), "T11": 22 + t / 1200})
    )


def generated_program(
    seed: int, lines: int, timed: bool = True, crlf: bool = False, final_newline: bool = True, rotary: bool = True
) -> bytes:
    """Return a random program using what the parser accepts: modes, comments, stamps, mixed decimals."""
    rng = np.random.default_rng(seed)
    out = ["%", "(generated)", "N1 G90 G21 G17 G94"]
    t = 0.0
    for k in range(lines):
        r = rng.random()
        if timed and r < 0.03:
            t += float(rng.integers(1, 600))
            out.append(f"(T={t:g})")
            continue
        if r < 0.05:
            out.append("G91" if rng.random() < 0.5 else "G90")
            continue
        if r < 0.07:
            out.append("")
            continue
        words = []
        if r < 0.3:
            words.append("G1" if rng.random() < 0.8 else "G0")
        for axis, span in (("X", 300), ("Y", 200), ("Z", 150)):
            if rng.random() < 0.6:
                decimals = int(rng.integers(0, 4))
                words.append(f"{axis}{round(float(rng.uniform(-span, span)), decimals)}")
        if rotary:
            for axis in ("A", "B"):
                if rng.random() < 0.3:
                    words.append(f"{axis}{round(float(rng.uniform(-60, 60)), int(rng.integers(0, 3)))}")
        if not words or (len(words) == 1 and words[0].startswith("G")):
            words.append("X1.0")
        if rng.random() < 0.1:
            words.append(f"F{int(rng.integers(100, 3000))}")
        if rng.random() < 0.05:
            words.append("; note")
        sep = "" if rng.random() < 0.1 else " "
        out.append(f"N{k + 10} " + sep.join(words) if rng.random() < 0.5 else sep.join(words))
    out.insert(3, "G1 X0 Y0 Z0")  # a motion mode before the first axis word
    out.append("M30")
    text = ("\r\n" if crlf else "\n").join(out)
    return (text + ("\r\n" if crlf else "\n") if final_newline else text).encode()


CASES = [
    *[(f"example-{p.stem}", p.read_bytes(), {}) for p in EXAMPLES],
    ("generated-timed", generated_program(1, 600), {}),
    ("generated-untimed", generated_program(2, 600, timed=False), {}),
    ("generated-crlf", generated_program(3, 400, crlf=True), {}),
    ("generated-no-final-newline", generated_program(4, 400, final_newline=False), {}),
    ("generated-linear-only", generated_program(5, 400, rotary=False), {"start": (10.0, -5.0, 3.0, 0.0, 0.0)}),
    ("generated-long-segments", generated_program(6, 300), {"max_segment_mm": 0.7}),
    ("no-motion", b"%\n(only comments)\nM30\n%\n", {}),
    # batches of corrected points that straddle pieces (a lagged term filters a batch in time)
    ("generated-small-batches", generated_program(7, 500), {"chunk_points": 37}),
]


#: the whole-program reference of each (case, temperatures), computed once and shared by the pieces
_REFERENCES: dict[tuple[str, str], OfflineResult] = {}


def _shared_reference(name: str, temps_name: str, data: bytes, model: ErrorModel, temps, kw) -> OfflineResult:
    """Return ``compensate_program`` of a case (the reference, the same whatever the streaming piece size)."""
    key = (name, temps_name)
    if key not in _REFERENCES:
        _REFERENCES[key] = compensate_program(
            parse_program(data, "p.nc", start=kw.get("start"), min_decimals=decimals_for(0.0025, 0.001)),
            model,
            temps,
            max_segment_mm=kw.get("max_segment_mm", 5.0),
            chunk_points=kw.get("chunk_points", 1 << 17),
        )
    return _REFERENCES[key]


@pytest.mark.parametrize("piece", PIECES)
@pytest.mark.parametrize("name,data,kw", CASES, ids=[c[0] for c in CASES])
def test_streamed_output_is_byte_identical(name, data, kw, piece, tmp_path: Path) -> None:
    src = tmp_path / "p.nc"
    src.write_bytes(data)
    model, table = _model(), _table()
    for temps_name, temps in (("table", table), ("fixed", {"T9": 26.0, "T10": 21.5, "T11": 24.0})):
        ref = _shared_reference(name, temps_name, data, model, temps, kw)
        out = tmp_path / "out.nc"
        result = compensate_file(
            src,
            model,
            temps,
            out,
            chunk_bytes=piece,
            start=kw.get("start"),
            max_segment_mm=kw.get("max_segment_mm", 5.0),
            chunk_points=kw.get("chunk_points", 1 << 17),
        )
        got = out.read_bytes()
        assert got == ref.text, name
        assert result.summary() == ref.summary()


@pytest.mark.parametrize("name,data,kw", CASES, ids=[c[0] for c in CASES])
def test_output_with_the_envelope_guard_is_byte_identical(name, data, kw, tmp_path: Path) -> None:
    """With a guard the first pass solves every point and keeps the commands; the output stays the same.

    The kept commands (``KeptCommands``) replace the second pass's own solve when every point takes
    the same temperatures: the text must equal ``compensate_program``'s, which solves everything itself.
    """
    from driftlab.compensator.compensate import FirstPass, scan_program
    from driftlab.compensator.guard import Guard
    from driftlab.models.envelope import Envelope

    src = tmp_path / "p.nc"
    src.write_bytes(data)
    model, table = _model(), _table()
    axes = ("X", "Y", "Z", "A", "B")
    # the travel only: no axis limits the correction (the synthetic model corrects up to several mm)
    envelope = Envelope(travel={a: (-1e6, 1e6) for a in axes}, max_correction={})
    for temps_name, temps in (("table", table), ("fixed", {"T9": 26.0, "T10": 21.5, "T11": 24.0})):
        want = _shared_reference(name, temps_name, data, model, temps, kw).text
        out = tmp_path / "out.nc"
        opts = {"start": kw.get("start"), "max_segment_mm": kw.get("max_segment_mm", 5.0)}
        guard = Guard(envelope, model.ranges, allow_extrapolation=True)
        chunks = kw.get("chunk_points", 1 << 17)
        compensate_file(src, model, temps, out, chunk_bytes=700, chunk_points=chunks, guard=guard, **opts)
        assert out.read_bytes() == want, name
        if isinstance(temps, dict) and name.startswith("generated-long"):
            # the case kept its commands (long segments subdivided: every point solved in the first pass)
            check = FirstPass(guard, model, temps, keep=True)
            scan = scan_program(src, "p.nc", decimals_for(0.0025, 0.001), 700, check=check, **opts)
            assert scan.solved is not None and scan.solved.rows > scan.blocks
            scan.solved.close()


# ----------------------------------------------------------------------------- bad programs

GOOD = "%\nG90 G21 G1 F2000\nX1.0 Y2.0 Z-3.0\nX2.0 A5.0\nG0 Z10.0\nM30\n%\n"


def _lines(*replace: tuple[int, str]) -> bytes:
    lines = GOOD.splitlines()
    for k, text in replace:
        lines[k - 1] = text
    return ("\n".join(lines) + "\n").encode()


#: (id, program bytes (or a callable making the file), expected stderr after "driftlab: error: ")
BAD_PROGRAMS = [
    ("arc-g2", _lines((3, "G2 X1.0 Y2.0 R5")), "{p}:3: G2: circular interpolation is not supported"),
    ("arc-g3", _lines((4, "G3 X2.0 I1.0")), "{p}:4: G3: circular interpolation is not supported"),
    ("arc-word", _lines((3, "X1.0 Y2.0 I5")), "{p}:3: word 'I' belongs to arcs"),
    ("inch", _lines((2, "G20 G1")), "{p}:2: G20: inch units are not supported"),
    ("unknown-g", _lines((2, "G1 G99")), "{p}:2: unsupported G-code G99"),
    ("conflicting-motion", _lines((3, "G0 G1 X1.0")), "{p}:3: conflicting motion codes G0/G1 on one block"),
    ("conflicting-distance", _lines((2, "G90 G91 G1")), "{p}:2: conflicting distance modes G90/G91 on one block"),
    ("foreign-axis", _lines((4, "X2.0 C5.0")), "{p}:4: axis 'C' is not on this machine"),
    ("unknown-word", _lines((4, "X2.0 Q5")), "{p}:4: unsupported word 'Q'"),
    ("word-without-value", _lines((3, "X Y2.0")), "{p}:3: word 'X' has no value"),
    ("malformed-number", _lines((3, "X1.2.3")), "{p}:3: malformed number 'X1.2.3'"),
    ("number-too-long", _lines((3, "X" + "1" * 20)), "{p}:3: number after 'X' is too long"),
    ("number-without-letter", _lines((3, "X1.0 5")), "{p}:3: number without a letter"),
    ("repeated-word", _lines((3, "X1.0 X2.0")), "{p}:3: repeated word 'X'"),
    ("too-many-decimals", _lines((3, "X1.1234567891")), "{p}:3: more than 9 decimals"),
    ("axis-before-motion", b"X1.0\nG1 X2.0\n", "{p}:1: axis words before any G0/G1"),
    ("dwell-with-axis", _lines((4, "G4 P1 X2.0")), "{p}:4: G4 dwell with axis words"),
    ("unterminated-comment", _lines((3, "X1.0 (open")), "{p}:3: unterminated comment '('"),
    ("nested-comment", _lines((3, "X1.0 (a (b) c)")), "{p}:3: nested comment '('"),
    ("stray-close-paren", _lines((3, "X1.0 )")), "{p}:3: ')' without '('"),
    ("percent-not-alone", _lines((1, "% G1")), "{p}:1: '%' must stand alone on its line"),
    ("bad-time-comment", _lines((3, "(T=soon)")), "{p}:3: bad time comment (T=soon)"),
    ("infinite-time-comment", _lines((3, "(T=inf)")), "{p}:3: bad time comment (T=inf)"),
    ("nul-byte", _lines((3, "X1.0\0")), "{p}:3: unexpected character byte 0x00"),
    ("non-ascii", _lines((3, "X1.0 \u00b5")), "{p}:3: unexpected character byte 0xc2"),
    ("bad-utf8", _lines((3, "X1.0")).replace(b"X1.0", b"X1.0\xff"), "{p}:3: unexpected character byte 0xff"),
    ("value-out-of-range", _lines((3, "X999999999999.0")), "{p}:3: value of 'X' out of range"),
    ("error-far-down", _lines() * 3000 + b"G2 X1 Y1 R1\n", "{p}:21001: G2: circular interpolation"),
    ("line-too-long", b"G1 X1.0\n(" + b"c" * (1 << 21) + b")\n", "{p}:2: line longer than 1048576 bytes"),
    ("huge-subdivision", _lines((3, "X1000000.0")), "{p}:3: segment would need more than 100000 subdivisions"),
    ("feed-zero", _lines((2, "G90 G21 G1 F0")), "{p}:2: feed 'F0' must be positive"),
    ("feed-negative", _lines((4, "X2.0 A5.0 F-100")), "{p}:4: feed 'F-100' must be positive"),
    (
        "beyond-travel",
        _lines((4, "X2.0 A5000000.0")),
        "{p}:4: target A 5e+06 deg is outside the travel -2e+06..2e+06 deg",
    ),
    (
        "g91-runaway",
        b"G91 G1 F100\n" + b"X99999.0\n" * 2000,
        "{p}:22: target X 2.09998e+06 mm is outside the travel -2e+06..2e+06 mm",
    ),
    ("missing-file", None, "{p}: no such file"),
    ("directory", "dir", "{p}: not a regular file"),
    ("fifo", "fifo", "{p}: not a regular file"),
]


def _make(path: Path, data) -> None:
    if data is None:
        return
    if data == "dir":
        path.mkdir()
    elif data == "fifo":
        os.mkfifo(path)
    else:
        path.write_bytes(data)


@pytest.fixture
def model_file(tmp_path: Path) -> Path:
    path = tmp_path / "model.json"
    # travel wide enough for every program of the corpus: each case meets its own refusal first
    wide = {a: [-2e6, 2e6] for a in "XYZAB"}
    path.write_text(json.dumps({**_all_kinds_doc(), "envelope": {"travel": wide}}))
    return path


@pytest.mark.parametrize("case", BAD_PROGRAMS, ids=[c[0] for c in BAD_PROGRAMS])
def test_bad_program_is_one_line_and_writes_nothing(case, tmp_path: Path, model_file: Path, capsys) -> None:
    from driftlab.cli import main

    _, data, expected = case
    src = tmp_path / "bad.nc"
    _make(src, data)
    out = tmp_path / "out" / "o.nc"
    out.parent.mkdir()
    capsys.readouterr()
    code = main(
        [
            "compensate",
            str(src),
            "--model",
            str(model_file),
            "--machine",
            "m",
            "--temps",
            _temps(tmp_path),
            "-o",
            str(out),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("driftlab: error: " + expected.format(p=src)), err
    assert list(out.parent.iterdir()) == []  # neither the output nor its .part


def _temps(tmp_path: Path) -> str:
    path = tmp_path / "temperatures.csv"
    pd.DataFrame({"time_s": [0.0], "T9": [25.0], "T10": [21.0], "T11": [23.0]}).to_csv(path, index=False)
    return str(path)


def test_unreadable_program(tmp_path: Path, model_file: Path, monkeypatch, capsys) -> None:
    """A program that cannot be opened is one line (PermissionError simulated: root reads any file)."""
    from driftlab.cli import main

    src = tmp_path / "p.nc"
    src.write_bytes(GOOD.encode())
    real_open = Path.open

    def deny(self: Path, *args, **kwargs):
        if self.name == "p.nc":
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)

    monkeypatch.setattr(Path, "open", deny)
    out = tmp_path / "o.nc"
    code = main(["compensate", str(src), "--model", str(model_file), "--temps", _temps(tmp_path), "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [f"driftlab: error: {src}: cannot read: Permission denied"]
    assert not out.exists()


def test_a_correction_failure_half_way_leaves_no_output(tmp_path: Path) -> None:
    """The program parses but the model fails on a later piece: no output file, no .part."""
    src = tmp_path / "p.nc"
    src.write_bytes(generated_program(9, 400))
    calls = []

    def predict(q, temps, direction):
        calls.append(q.shape[0])
        if len(calls) > 3:
            raise ValidationError("model exploded")
        return {"T1": np.zeros((q.shape[0], 6))}

    with pytest.raises(ValidationError, match="model exploded"):
        compensate_file(src, ErrorModel(predict), {}, tmp_path / "o.nc", chunk_bytes=256, chunk_points=50)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.nc"]


# ----------------------------------------------------------------------------- memory

MEMORY_PROBE = r"""
import sys
from driftlab.compensator.compensate import ErrorModel, compensate_file, retain_freed_memory
from tests.compensator.test_compensate import _all_kinds_doc
retain_freed_memory()
model = ErrorModel.from_document(_all_kinds_doc())
compensate_file(sys.argv[1], model, {"T9": 26.0, "T10": 21.5, "T11": 24.0}, sys.argv[2])
print(int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1]))
"""


def _peak_rss_kb(program: Path, out: Path) -> int:
    proc = subprocess.run(
        [sys.executable, "-c", MEMORY_PROBE, str(program), str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    )
    return int(proc.stdout.split()[-1])


@pytest.mark.slow
def test_memory_is_flat_in_program_length(tmp_path: Path) -> None:
    """Peak RSS (VmHWM) of a 100k-line program is within 30 MB of a 10k-line one (measured in subprocesses)."""
    small, big = tmp_path / "s.nc", tmp_path / "b.nc"
    small.write_bytes(generated_program(11, 10_000, rotary=False))
    big.write_bytes(generated_program(11, 100_000, rotary=False))
    rss_small = _peak_rss_kb(small, tmp_path / "s.out")
    rss_big = _peak_rss_kb(big, tmp_path / "b.out")
    assert rss_big - rss_small < 30 * 1024, (rss_small, rss_big)
