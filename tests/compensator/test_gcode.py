"""Motion code: parse, modal state, byte-exact round trip, subdivision, refusal of bad blocks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from driftlab.compensator.gcode import (
    Points,
    emit,
    emit_program,
    format_fixed,
    parse_program,
    subdivide,
)
from driftlab.errors import ValidationError

SAMPLE = (
    b"%\r\n"
    b"O1000 (five-axis sample)\r\n"
    b"N10 G90 G21 G17 G1 X10.0 Y-5 F2000 ; start\r\n"
    b"N20 X20.5 Z-3.25\r\n"
    b"(T=12.5)\r\n"
    b"N30 G91 Y1.5\r\n"
    b"A10.0 B-5\r\n"
    b"G90 G0 Z50.\r\n"
    b"g1x1y2z3\r\n"
    b"M30\r\n"
    b"%"
)


def test_sample_parses_modal_state_and_targets():
    p = parse_program(SAMPLE, "s.nc")
    assert p.decimals == (4, 3)
    assert p.eol == b"\r\n"
    assert p.block_line.tolist() == [2, 3, 5, 6, 7, 8]
    assert p.incremental.tolist() == [False, False, True, True, False, False]
    assert p.rapid.tolist() == [False, False, False, False, True, False]
    mm = p.target_int * p.scale
    np.testing.assert_allclose(mm[1], [20.5, -5, -3.25, 0, 0])
    np.testing.assert_allclose(mm[2], [20.5, -3.5, -3.25, 0, 0])  # G91 Y1.5
    np.testing.assert_allclose(mm[3], [20.5, -3.5, -3.25, 10, -5])
    np.testing.assert_allclose(mm[5], [1, 2, 3, 10, -5])
    q = p.to_q(p.target_int)
    assert q[3, 3] == pytest.approx(np.deg2rad(10.0))
    # the time comment stamps its line and the lines after it; earlier lines take the first stamp
    assert np.all(p.line_time_s == 12.5)


def test_start_pose_feeds_incremental_blocks():
    p = parse_program(b"G91 G1 X1 A2\n", start=(100, 0, 0, 30, 0))
    np.testing.assert_allclose(p.target_int[0] * p.scale, [101, 0, 0, 32, 0])


def test_round_trip_without_correction_is_byte_exact():
    p = parse_program(SAMPLE)
    assert emit_program(p) == SAMPLE
    pts = subdivide(p, 1e9, 1e9)
    assert emit_program(p, pts, pts.nominal_int) == SAMPLE
    assert emit(p, pts) == SAMPLE


def _number(n: int, d: int, style: int) -> str:
    """Return n * 10**-d written with d decimals, in one of the spellings controllers accept."""
    sign = "-" if n < 0 else ""
    whole, frac = divmod(abs(n), 10**d)
    if d == 0:
        return f"{sign}{whole}" + ("." if style == 1 else "")
    f = str(frac).rjust(d, "0")
    return f"{sign}{'' if style == 2 and whole == 0 else whole}.{f}"


_number_st = st.builds(_number, st.integers(-999_999, 999_999), st.integers(0, 4), st.integers(0, 2))
_word = st.one_of(
    st.builds(lambda a, v: f"{a}{v}", st.sampled_from("XYZABxyzab"), _number_st),
    st.sampled_from(["F1500", "S10000", "M3", "M5", "T1", "N5", "G17", "G21", "G94", "G1"]),
)
_line = st.one_of(
    st.lists(_word, min_size=1, max_size=6, unique_by=lambda w: w[0].upper()).map(" ".join),
    st.lists(_word, min_size=1, max_size=4, unique_by=lambda w: w[0].upper()).map("".join),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126, exclude_characters="()"), max_size=20).map(
        lambda t: f"({t})"
    ),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=20).map(lambda t: f"; {t}"),
    st.sampled_from(["%", "", "   ", "G90", "G91", "M30"]),
)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(_line, min_size=0, max_size=25),
    st.sampled_from(["\n", "\r\n"]),
    st.booleans(),
)
def test_generated_programs_round_trip(lines, eol, final_newline):
    text = "G1 X0\n" + eol.join(lines) + (eol if final_newline and lines else "")
    data = text.encode()
    p = parse_program(data)
    pts = subdivide(p, 1e9, 1e9)
    assert emit_program(p, pts, pts.nominal_int, chunk_lines=7) == data


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from(["G90", "G91"]), st.integers(-5000, 5000), st.integers(-5000, 5000)),
        min_size=1,
        max_size=30,
    ),
    st.integers(-3, 3),
    st.integers(-2, 2),
)
def test_corrected_program_reparses_to_commanded_pose(moves, cx, ca):
    text = "G1\n" + "".join(f"{g} X{x / 100} A{a / 100}\n" for g, x, a in moves)
    p = parse_program(text)
    pts = subdivide(p, 7.0, 9.0)
    rng = np.random.default_rng(abs(cx) + 7 * abs(ca))
    sent = pts.nominal_int + rng.integers(-3, 4, size=pts.nominal_int.shape) * np.array([25, 25, 25, 1, 1])
    out = emit_program(p, pts, sent, chunk_lines=3)
    back = parse_program(out)
    # every commanded point becomes a block of the emitted program, in order
    np.testing.assert_array_equal(back.target_int, sent)


def test_subdivision_of_long_segments():
    p = parse_program(b"G1 X0 Y0\nX20 Y0\nG0 X100\nG1 A30\n")
    pts = subdivide(p, max_mm=5.0, max_deg=10.0)
    assert np.bincount(pts.block).tolist() == [1, 4, 1, 3]
    mm = pts.nominal_int * p.scale
    np.testing.assert_allclose(mm[1:5, 0], [5, 10, 15, 20])
    np.testing.assert_allclose(mm[-3:, 3], [10, 20, 30])
    # uncorrected subdivided program: the new lines carry the intermediate points
    out = emit_program(p, pts, pts.nominal_int).decode()
    assert out.splitlines() == [
        "G1 X0 Y0",
        "X5.0 Y0",
        "X10.0",
        "X15.0",
        "X20.0",
        "G0 X100",
        "G1 A10.0",
        "A20.0",
        "A30.0",
    ]


def test_incremental_subdivision_keeps_total_move():
    p = parse_program(b"G91 G1 X10 Y-7\n")
    pts = subdivide(p, max_mm=3.0)
    out = emit_program(p, pts, pts.nominal_int)
    back = parse_program(out)
    assert back.n_blocks == 5
    np.testing.assert_array_equal(back.target_int[-1], p.target_int[0])


@pytest.mark.parametrize(
    "text,line,needle",
    [
        (b"G1 X1\nG2 X2 Y2 I1 J0\n", 2, "circular interpolation"),
        (b"G20\nG1 X1\n", 1, "inch"),
        (b"G1 X1\nX1..2\n", 2, "malformed number"),
        (b"G1 X1\nX1 X2\n", 2, "repeated word 'X'"),
        (b"G1 X1\nY\n", 2, "no value"),
        (b"G1 X1\n(open comment\n", 2, "unterminated comment"),
        (b"G1 X1\nX2 C5\n", 2, "axis 'C'"),
        (b"X1\n", 1, "before any G0/G1"),
        (b"G1 X1\nX2 # 3\n", 2, "unexpected character '#'"),
        (b"G1 X1\nX2 5\n", 2, "number without a letter"),
        (b"G1 X1\nG28 X0\n", 2, "unsupported G-code G28"),
        (b"G1 X1\nG0 G1 X2\n", 2, "conflicting"),
        (b"G1 X1\n(T=abc)\n", 2, "bad time comment"),
        (b"G1 X1\nX2 %\n", 2, "'%' must stand alone"),
        (b"G1 X1\nG4 P1 X2\n", 2, "dwell"),
    ],
)
def test_bad_block_is_one_line_error_with_its_line_number(text, line, needle):
    with pytest.raises(ValidationError) as exc:
        parse_program(text, name="bad.nc")
    msg = exc.value.one_line()
    assert msg == str(exc.value)
    assert msg.startswith(f"bad.nc:{line}: ")
    assert needle in msg


def test_first_bad_line_is_reported():
    with pytest.raises(ValidationError, match=r"^p:3: .*malformed"):
        parse_program(b"G1 X1\nX2\nX1.2.3\nG2 X1\n", name="p")


def test_format_fixed():
    chars, lens = format_fixed(np.array([0, -5, 123450000, -1, 100000, 25]), 4)
    words = []
    off = 0
    for n in lens:
        words.append(bytes(chars[off : off + n]).decode())
        off += n
    assert words == ["0.0", "-0.0005", "12345.0", "-0.0001", "10.0", "0.0025"]


def test_emit_rejects_points_outside_lines():
    p = parse_program(b"G1 X1\nX2\n")
    with pytest.raises(ValueError):
        emit(p, Points(np.array([1]), p.target_int[1:]), lines=slice(0, 1))


def test_example_programs_parse_and_round_trip():
    from pathlib import Path

    files = sorted((Path(__file__).resolve().parents[2] / "examples" / "programs").glob("*.nc"))
    assert files
    for f in files:
        data = f.read_bytes()
        p = parse_program(data, str(f))
        assert p.n_blocks > 0
        assert emit_program(p, subdivide(p, 1e9, 1e9)) == data


@pytest.mark.parametrize("text", [b"", b"%\n(only comments)\n%\n", b"M3\nG4 P1\n", b"G01 X1\nG00 Z5\n"])
def test_programs_without_motion_or_with_leading_zero_codes(text):
    p = parse_program(text)
    assert p.n_blocks == text.count(b"X") + text.count(b"Z")
    pts = subdivide(p)
    assert emit_program(p, pts, pts.nominal_int) == text


@pytest.mark.parametrize(
    "code,needle",
    [
        ("G43 H1 Z50", "G43 applies a tool length offset"),
        ("G44 H1 Z50", "G44 applies a tool length offset"),
        ("G10 L2 P1 X0", "G10 sets offsets"),
        ("G65 P9000", "G65 calls a macro"),
        ("M98 P1000", "M98 calls a subprogram"),
        ("M97 P100", "M97 calls a local subprogram"),
        ("M99", "M99 returns from or loops a subprogram"),
    ],
)
def test_codes_whose_effect_on_the_axes_is_unseen_are_refused(code, needle):
    with pytest.raises(ValidationError, match=r"^P:2: ") as err:
        parse_program(f"G90 G1 X1 F100\n{code}\nX2\n".encode(), "P")
    assert needle in str(err.value) and "\n" not in str(err.value)
    parse_program(b"G90 G49 G1 X1 F100\nT1 M6\nM30\n", "P")  # a tool change and G49 (cancel) still pass
