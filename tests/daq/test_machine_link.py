"""Machine link: exact bytes of the streaming protocol, low-water refills, resent blocks, positions."""

from __future__ import annotations

import pytest

from driftlab.daq.machine_link import SerialMachineLink
from driftlab.daq.protocols import MachineLink
from driftlab.errors import InstrumentError, ValidationError
from tests.daq.protocol_helpers import TIMEOUT, expected_protocol


def _link(ch, sleeps=None):
    return SerialMachineLink(ch, poll_s=1.0, sleep=(sleeps.append if sleeps is not None else lambda s: None))


def test_position_and_buffer_exact_bytes():
    pairs = [(b"POS?\n", b"POS X10.0000 Y-2.5000 Z0.0000 A0.0000 B90.0000\n"), (b"STAT?\n", b"STAT 5 8 0\n")]
    with expected_protocol(_link, pairs) as link:
        assert isinstance(link, MachineLink)
        assert link.position() == {"X": 10.0, "Y": -2.5, "Z": 0.0, "A": 0.0, "B": 90.0}
        assert link.buffer_free() == 5


def test_streaming_refills_only_at_the_low_water_mark():
    sleeps: list[float] = []
    lines = ["G1 X1 F600", "", "(comment)", "G1 X2", "G1 X3", "G1 X4", "G1 X5"]
    pairs = [
        (b"STAT?\n", b"STAT 4 4 0\n"),  # empty: fill to the high-water mark (3)
        (b"BLK 1 G1 X1 F600\n", b"ACK 1\n"),
        (b"BLK 2 G1 X2\n", b"ACK 2\n"),
        (b"BLK 3 G1 X3\n", b"ACK 3\n"),
        (b"STAT?\n", b"STAT 1 4 0\n"),  # 3 queued > low water 1: wait
        (b"STAT?\n", b"STAT 2 4 1\n"),  # 2 queued: still wait
        (b"STAT?\n", b"STAT 3 4 2\n"),  # 1 queued: refill
        (b"BLK 4 G1 X4\n", b"ACK 4\n"),
        (b"BLK 5 G1 X5\n", b"ACK 5\n"),
        (b"STAT?\n", b"STAT 3 4 4\n"),  # wait for completion
        (b"STAT?\n", b"STAT 4 4 5\n"),
    ]
    with expected_protocol(lambda ch: _link(ch, sleeps), pairs) as link:
        report = link.send_program(iter(lines), low_water=1, high_water=3)
    assert report.blocks_sent == 5 and report.polls == 4 and report.min_free_seen == 1 and report.starved == 0
    assert sleeps == [1.0, 1.0, 1.0]


def test_full_reply_waits_and_resends_the_same_block():
    pairs = [
        (b"STAT?\n", b"STAT 1 2 0\n"),
        (b"BLK 1 G0 Z5\n", b"ERR FULL\n"),
        (b"STAT?\n", b"STAT 2 2 0\n"),
        (b"BLK 1 G0 Z5\n", b"ACK 1\n"),
    ]
    with expected_protocol(_link, pairs) as link:
        report = link.send_program(["G0 Z5"], low_water=1, wait=False)
    assert report.blocks_sent == 1


def test_lost_ack_resends_block_with_same_sequence_number():
    pairs = [
        (b"STAT?\n", b"STAT 8 8 0\n"),
        (b"BLK 1 G1 Y1 F100\n", TIMEOUT),
        (b"BLK 1 G1 Y1 F100\n", b"ACK 1\n"),  # the controller de-duplicates by seq
        (b"STAT?\n", b"STAT 8 8 1\n"),
    ]
    with expected_protocol(_link, pairs) as link:
        assert link.send_program(["G1 Y1 F100"]).blocks_sent == 1


def test_rejected_block_is_an_instrument_error():
    pairs = [(b"STAT?\n", b"STAT 8 8 0\n")] + [(b"BLK 1 G7 X1\n", b"ERR SYNTAX unsupported G7\n")] * 3
    with expected_protocol(_link, pairs) as link:
        with pytest.raises(InstrumentError, match="controller|dut"):
            link.send_program(["G7 X1"])


def test_starvation_is_counted():
    pairs = [
        (b"STAT?\n", b"STAT 1 1 0\n"),
        (b"BLK 1 G1 X1 F10\n", b"ACK 1\n"),
        (b"STAT?\n", b"STAT 1 1 1\n"),  # drained completely while code was waiting: starved
        (b"BLK 2 G1 X2\n", b"ACK 2\n"),
    ]
    with expected_protocol(_link, pairs) as link:
        report = link.send_program(["G1 X1 F10", "G1 X2"], low_water=0, wait=False)
    assert report.starved == 1


def test_low_water_must_be_below_high_water():
    with expected_protocol(_link, [(b"STAT?\n", b"STAT 4 4 0\n")]) as link:
        with pytest.raises(ValidationError):
            link.send_program(["G1 X1 F10"], low_water=4)


def test_garbled_status_is_retried():
    pairs = [(b"STAT?\n", b"STAT 9 8 0\n"), (b"STAT?\n", b"STAT 3 8 0\n")]  # free > capacity: invalid
    with expected_protocol(_link, pairs) as link:
        assert link.buffer_free() == 3
