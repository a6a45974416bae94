"""The DNC drip feed against a control written from the manuals (``dnc_counterpart``), in simulated time.

The link's pacing and handshake code runs unchanged; only its clock, its sleep and its byte line are
the counterpart's, so a 1,500-block program with a 2 s feed hold takes a fraction of a second and the
result does not depend on the machine's load.
"""

from __future__ import annotations

import numpy as np
import pytest

from driftlab.compensator.compensate import ErrorModel, compensate_program
from driftlab.compensator.gcode import parse_program
from driftlab.compensator.stream import Clocks, FixedTemperatures, StaticModel, Streamer, StreamerSettings
from driftlab.daq.dnc import DC1, DC2, DC4, ETX, NUL, PROFILES, DncLink, encode_block
from driftlab.errors import InstrumentError, ValidationError
from tests.compensator.test_stream import doc
from tests.daq.dnc_counterpart import TAPES, Clock, TapeControl, TapeLine


def _program(blocks: int, seed: int = 1) -> str:
    """Return a walk of short G1 moves (none long enough to be subdivided) with a comment and a feed or two."""
    rng = np.random.default_rng(seed)
    pose = np.array([10.0, 10.0, -5.0])
    out = ["%", "(drip feed test)", "G90 G21 G1 F2400"]
    for k in range(blocks - 1):
        pose = np.clip(pose + rng.normal(0, 1.0, 3), -250, 250)
        words = " ".join(f"{a}{v:.3f}" for a, v in zip("XYZ", pose))
        out.append(f"N{k + 10} {words}" + (" F1800" if k % 97 == 0 else ""))
    return "\n".join(out + ["M30", "%"]) + "\n"


def _offline(text: str, temps: dict[str, float]) -> list[str]:
    """Return the blocks of the offline program, as a control would hold them (stripped, no comments)."""
    out = compensate_program(parse_program(text), ErrorModel.from_document(doc(0.01, 1)), temps).text.decode()
    return [s.strip() for s in out.splitlines() if s.strip() and s.strip() != "%" and not s.strip().startswith("(")]


def _control(clock: Clock, name: str = "generic", **kw) -> TapeControl:
    return TapeControl(clock, TAPES[name], **kw)


def _stream(text, clock, control, name="generic", baud=115200, max_age_s=120.0, **link_kw):
    model = ErrorModel.from_document(doc(0.01, 1))
    link = DncLink(TapeLine(control), PROFILES[name], baud, "8N1", clock=clock.now, sleep=clock.sleep, **link_kw)
    settings = StreamerSettings(clocks=Clocks(clock=clock.now, sleep=clock.sleep, epoch_s=0.0))
    streamer = Streamer(
        parse_program(text),
        StaticModel(model),
        FixedTemperatures({"T1": 26.0}),
        settings,
        max_age_s=max_age_s,
        refresh_s=min(30.0, max_age_s),
    )
    result = streamer.run(link)
    _finish(clock, control)
    return result, link


def _finish(clock: Clock, control: TapeControl) -> None:
    """Let the control run what it holds (the sender is done once the line is)."""
    for _ in range(100_000):
        if not control._wire and control._next_exec is None:
            return
        clock.sleep(0.01)


def test_1500_blocks_at_115200_baud_through_a_2s_feed_hold_arrive_as_the_offline_program():
    """The issue's target: 1 KiB buffer, a block every 5 ms, a 2 s feed hold in the middle."""
    text = _program(1500)
    clock = Clock()
    control = _control(clock, baud=115200, buffer_bytes=1024, block_s=0.005, holds=[(4.0, 2.0)])
    result, link = _stream(text, clock, control)
    expected = _offline(text, {"T1": 26.0})
    assert len(expected) >= 1500
    assert control.blocks == expected  # every block, in order, as the offline program has it
    assert any(" Z-" in b or "Z-" in b for b in control.blocks)  # corrected (26 degC: the head has grown)
    assert control.overflow == 0 and control.parity_errors == 0
    assert control.starved == 0  # the line kept ahead of the control, before and after the hold
    assert control.max_held <= 1024
    assert control.dc3_sent >= 2  # the buffer filled before the hold and during it
    assert link.report.longest_hold_s >= 1.9  # the feed hold was waited out
    assert control.overrun <= link.ahead_chars + 2  # DC3 honoured within a few characters
    assert result.blocks_sent == len(expected)
    # the whole run at the line's pace: 7.5 s of blocks plus the hold, not more than a little slack
    assert 9.4 < clock.t < 11.0


def test_a_sender_that_ignores_dc3_overflows_the_buffer():
    """What the handshake is for: the whole tape written at once (pyserial's socket:// has no flow control)."""
    text = _program(1500)
    clock = Clock()
    control = _control(clock, baud=115200, buffer_bytes=1024, block_s=0.005, holds=[(4.0, 2.0)])
    line = TapeLine(control)
    expected = _offline(text, {"T1": 26.0})
    line.write(b"%\n" + b"".join(b.encode() + b"\n" for b in expected) + b"%\n")
    _finish(clock, control)
    assert control.dc3_sent >= 1 and control.overflow > 1000
    assert control.blocks != expected


def test_a_sender_that_reads_dc3_but_does_not_pace_its_writes_overflows_too():
    """In band, DC3 stops only what has not been written: a socket's queue runs on regardless."""
    text = _program(600)
    clock = Clock()
    control = _control(clock, baud=115200, buffer_bytes=1024, block_s=0.005)
    _stream(text, clock, control, ahead_chars=1_000_000)
    assert control.overflow > 0


def test_a_feed_hold_of_ten_minutes_is_waited_out_and_stale_blocks_are_corrected_again():
    text = _program(400)
    clock = Clock()
    control = _control(clock, baud=115200, block_s=0.005, holds=[(0.5, 600.0)])
    result, link = _stream(text, clock, control, max_age_s=60.0)
    assert control.blocks == _offline(text, {"T1": 26.0})
    assert control.overflow == 0 and control.starved == 0
    assert link.report.longest_hold_s > 599.0
    assert result.recomputed > 0  # the blocks prepared before the hold were older than 60 s: corrected again


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_each_profile_frames_the_tape_as_its_manual_says(name):
    text = _program(80)
    clock = Clock()
    control = _control(clock, name, baud=9600, block_s=0.02, start_at_s=1.5)
    raw: list[bytes] = []
    line = TapeLine(control)
    write = line.write
    line.write = lambda data: (raw.append(data), write(data))[1]  # type: ignore[method-assign]
    link = DncLink(line, PROFILES[name], 9600, "8N1", clock=clock.now, sleep=clock.sleep)
    blocks = [b for b in _offline(text, {"T1": 20.0})]
    link.send_program(iter(blocks))
    _finish(clock, control)
    tape = b"".join(raw)
    assert control.blocks == blocks and control.overflow == 0 and control.early == 0
    assert control.eobs == {TAPES[name].eob}
    if name == "haas-dc":  # Setting 14 DC CODES: DC2 before all other data, DC4 after it
        assert tape[:1] == bytes([DC2]) and tape[-1:] == bytes([DC4])
    if name == "heidenhain":  # NUL NUL, lines ended CR LF, ETX after the last; no % marks
        assert tape.startswith(bytes([NUL, NUL])) and tape.endswith(b"\r\n" + bytes([ETX])) and b"%" not in tape
    else:
        assert tape.lstrip(bytes([NUL, DC2])).startswith(b"%" + TAPES[name].eob)
        assert tape.rstrip(bytes([DC4])).endswith(b"%" + TAPES[name].eob)
    if TAPES[name].starts_with_dc1:
        assert control._start_sent and clock.t > 1.5  # nothing left before the control's DC1


def test_a_control_reset_stops_the_feed_in_one_line():
    text = _program(400)
    clock = Clock()
    control = _control(clock, "fanuc", baud=115200, reset_at_s=0.5)
    link = DncLink(TapeLine(control), PROFILES["fanuc"], 115200, "8N1", clock=clock.now, sleep=clock.sleep)
    with pytest.raises(InstrumentError, match="reset"):
        link.send_program(iter(_offline(text, {"T1": 20.0})))
    assert 0 < len(control.blocks) < 400


def test_a_dc1_before_the_start_is_waited_for_without_a_limit():
    clock = Clock()
    control = _control(clock, "heidenhain", baud=9600, start_at_s=3600.0)
    link = DncLink(TapeLine(control), PROFILES["heidenhain"], 9600, "8N1", clock=clock.now, sleep=clock.sleep)
    link.send_program(iter(["G1 X1", "G1 X2"]))
    _finish(clock, control)
    assert control.blocks == ["G1 X1", "G1 X2"] and control.early == 0 and clock.t > 3600.0


def test_only_printable_7_bit_ascii_leaves():
    assert encode_block("G1 X1 (ok)", b"\n") == b"G1 X1 (ok)\n"
    for bad in ("G1 X1 (r\u00e9glage)", "G1 X1 (\x13)", "G1 X1 (50%)"):
        with pytest.raises(ValidationError):
            encode_block(bad, b"\n")


def test_bad_line_settings_are_refused():
    with pytest.raises(ValidationError, match="--line"):
        DncLink(TapeLine(_control(Clock())), PROFILES["generic"], 9600, "9X1")
    with pytest.raises(ValidationError, match="--baud"):
        DncLink(TapeLine(_control(Clock())), PROFILES["generic"], 10, "8N1")
    assert DC1 == 0x11
