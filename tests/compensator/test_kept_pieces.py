"""The first pass keeps what it parsed for the second (issues 24, 26.5): the same pieces, the bytes it checked.

``compensate_file`` no longer reads and parses the program twice: the first pass (``Scanner`` with
``keep``) writes every parsed piece to ``parsed.ParsedPieces`` and the second pass reads them back
(``kept_pieces``). What comes back must be exactly what ``parse_pieces`` makes of the file (the
reference second pass), piece for piece and array for array.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from driftlab.compensator.compensate import (
    Grid,
    Scanner,
    _PieceReader,
    compensate_file,
    compensate_stream,
    decimals_for,
    kept_pieces,
    parse_pieces,
    program_pieces,
)
from driftlab.compensator.gcode import Program, parse_program
from driftlab.compensator.parsed import ParsedPieces
from driftlab.compensator.stream import FixedTemperatures, Pacing, StaticModel, Streamer, StreamerSettings
from tests.compensator.test_streaming import _model, _table, generated_program

DEC = decimals_for(0.0025, 0.001)


def _same(a: Program, b: Program) -> list[str]:
    """Return the fields in which two parsed pieces differ (``residuals`` aside: only the first pass has them)."""
    out = []
    for f in fields(Program):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "residuals":
            continue
        if isinstance(x, np.ndarray):
            if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
                out.append(f.name)
        elif x != y:
            out.append(f.name)
    return out


@pytest.mark.parametrize(
    ("data", "start", "segment", "max_points"),
    [
        (generated_program(11, 500), None, 5.0, None),  # time stamps from the middle, mixed decimals
        (generated_program(12, 500, timed=False), None, 5.0, None),
        (generated_program(13, 400, crlf=True, final_newline=False), None, 5.0, None),
        (generated_program(14, 400, rotary=False), (10.0, -5.0, 3.0, 0.0, 0.0), 5.0, None),
        (generated_program(15, 300), None, 0.7, 40),  # pieces halved for too many points
        (b"(T=5)\nG90 G1 X1.0 Y2.0\n" + b"X1.5 Y2.5\n(T=6)\nX3.0\n" * 200, None, 5.0, None),  # all kept as they are
    ],
)
def test_kept_pieces_are_what_the_second_pass_parses(data, start, segment, max_points, tmp_path: Path) -> None:
    src = tmp_path / "p.nc"
    src.write_bytes(data)
    keep = ParsedPieces()
    scan = Scanner(str(src), DEC, start, (segment, 5.0), None, keep).scan(src, 700)
    want = list(
        parse_pieces(
            program_pieces(src, 700),
            scan,
            str(src),
            start=start,
            min_decimals=DEC,
            max_segment_mm=segment,
            max_points=max_points,
        )
    )
    reader = _PieceReader(str(src), start, DEC, (segment, 5.0), max_points)
    got = list(kept_pieces(scan, keep, reader))
    assert len(got) == len(want) > 1
    for g, w in zip(got, want):
        assert not _same(g.program, w), (w.first_line, _same(g.program, w))
    if data.startswith(b"(T=5)"):  # one decimals, stamped from the first line: every piece kept as it is
        assert all(g.points is not None for g in got)
    keep.close()


def test_the_second_pass_corrects_the_bytes_the_first_pass_checked(tmp_path: Path) -> None:
    """A program changed on disk between the passes: what is written is the program that was checked."""
    model, temps = _model(), {"T9": 26.0, "T10": 21.5, "T11": 24.0}
    checked, changed = generated_program(21, 400), generated_program(22, 400)
    src = tmp_path / "p.nc"
    src.write_bytes(checked)
    compensate_file(src, model, temps, tmp_path / "want.nc", chunk_bytes=700)
    scan = Scanner(str(src), DEC, None, Grid().segment, None, ParsedPieces()).scan(src, 700)
    src.write_bytes(changed)
    with (tmp_path / "got.nc").open("wb") as fh:
        compensate_stream(src, model, temps, fh, chunk_bytes=700, scan=scan)
    assert (tmp_path / "got.nc").read_bytes() == (tmp_path / "want.nc").read_bytes()
    # and the file as it is now comes out otherwise (the test can fail)
    compensate_file(src, model, temps, tmp_path / "now.nc", chunk_bytes=700)
    assert (tmp_path / "now.nc").read_bytes() != (tmp_path / "want.nc").read_bytes()


def test_a_table_per_block_takes_the_kept_pieces_too(tmp_path: Path) -> None:
    """Temperatures per block (a timed program and a table) through kept pieces: as the reference pass writes."""
    model, table = _model(), _table()
    src = tmp_path / "p.nc"
    src.write_bytes(generated_program(31, 500))
    compensate_file(src, model, table, tmp_path / "kept.nc", chunk_bytes=700)
    scan = Scanner(str(src), DEC, None, Grid().segment).scan(src, 700)  # nothing kept: the file is parsed again
    assert scan.parsed is None
    with (tmp_path / "parsed.nc").open("wb") as fh:
        compensate_stream(src, model, table, fh, chunk_bytes=700, scan=scan)
    assert (tmp_path / "kept.nc").read_bytes() == (tmp_path / "parsed.nc").read_bytes()


def test_streamer_settings_and_keywords_are_one_thing() -> None:
    """``Streamer(..., settings)`` and the flat keywords it replaced stream the same lines."""
    program = parse_program(generated_program(41, 120), "p.nc")
    model = _model()
    temps = FixedTemperatures({"T9": 26.0, "T10": 21.5, "T11": 24.0})
    by_keywords = Streamer(program, StaticModel(model), temps, batch_lines=3, lookahead=5, max_segment_mm=0.9)
    settings = StreamerSettings(Grid(max_segment_mm=0.9), Pacing(batch_lines=3, lookahead=5))
    by_settings = Streamer(program, StaticModel(model), temps, settings)
    for s in (by_keywords, by_settings):
        s.prime()
    assert by_settings.batch_lines == 3 and by_settings.segment == (0.9, 5.0)
    assert list(by_keywords.lines()) == list(by_settings.lines())
    # keywords override the settings they are given with
    mixed = Streamer(program, StaticModel(model), temps, settings, batch_lines=7)
    assert mixed.batch_lines == 7 and mixed.lookahead == 5
