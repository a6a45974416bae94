"""Retry with backoff, the line channel's validation, and the expected-protocol helper itself."""

from __future__ import annotations

import pytest

from driftlab.daq.retry import GarbledReply, RetryPolicy, TransportTimeout, call_with_retry
from driftlab.daq.transport import LineChannel
from driftlab.errors import InstrumentError
from tests.daq.protocol_helpers import TIMEOUT, ProtocolPort, expected_protocol


def test_backoff_delays_grow_and_cap():
    policy = RetryPolicy(attempts=6, base_delay_s=0.1, factor=3.0, max_delay_s=1.0)
    assert list(policy.delays()) == pytest.approx([0.1, 0.3, 0.9, 1.0, 1.0])
    with pytest.raises(ValueError):
        RetryPolicy(attempts=0)


def test_call_with_retry_recovers_from_transient_faults():
    outcomes = [TransportTimeout("timeout"), GarbledReply("bad"), 42]
    sleeps: list[float] = []
    flushes: list[int] = []

    def fn():
        result = outcomes.pop(0)
        if isinstance(result, Exception):
            raise result
        return result

    value = call_with_retry(fn, "dev", RetryPolicy(3, 0.5, 2.0), sleeps.append, lambda: flushes.append(1))
    assert value == 42 and sleeps == [0.5, 1.0] and len(flushes) == 2


def test_call_with_retry_gives_up_with_one_line_error():
    def fn():
        raise GarbledReply("invalid reply to 'X?':\n'abc'")

    with pytest.raises(InstrumentError) as info:
        call_with_retry(fn, "laser MEAS?", RetryPolicy(2, 0.0), lambda s: None)
    assert str(info.value) == "laser MEAS?: invalid reply to 'X?': 'abc' (gave up after 2 attempts)"


def test_non_transient_errors_are_not_retried():
    calls = []

    def fn():
        calls.append(1)
        raise KeyError("bug")

    with pytest.raises(KeyError):
        call_with_retry(fn, "dev", RetryPolicy(5, 0.0), lambda s: None)
    assert len(calls) == 1


def test_channel_never_returns_a_value_from_an_invalid_reply():
    parsed = []

    def parse(text):
        value = float(text)
        parsed.append(value)
        if value < 0:
            raise ValueError("negative")
        return value

    with expected_protocol(lambda ch: ch, [(b"V?\n", b"-1\n")] * 3) as ch:
        with pytest.raises(InstrumentError, match="negative"):
            ch.query("V?", parse)
    assert parsed == [-1.0, -1.0, -1.0]


def test_channel_flushes_input_before_each_retry():
    port = ProtocolPort([(b"V?\n", TIMEOUT), (b"V?\n", b"7\n")])
    ch = LineChannel(port, policy=RetryPolicy(2, 0.0), sleep=lambda s: None)
    assert ch.query("V?", int) == 7
    assert port.discards == 1


def test_helper_fails_on_wrong_bytes():
    with pytest.raises(AssertionError, match="expected b'A\\?\\\\n'"):
        with expected_protocol(lambda ch: ch, [(b"A?\n", b"1\n")]) as ch:
            ch.query("B?", int)


def test_helper_fails_when_a_pair_is_unused():
    with pytest.raises(AssertionError, match="only 1 of 2 expected pairs"):
        with expected_protocol(lambda ch: ch, [(b"A?\n", b"1\n"), (b"B?\n", b"2\n")]) as ch:
            ch.query("A?", int)


def test_helper_serves_unsolicited_lines_and_rejects_unscripted_reads():
    port = ProtocolPort([(b"GO\n", None), (None, b"DONE\n")])
    port.write(b"GO\n")
    assert port.read_line() == b"DONE\n"
    assert port.index == 2
    with pytest.raises(AssertionError, match="read with no reply pending"):
        ProtocolPort([(b"GO\n", None)]).read_line()


def test_helper_fails_when_a_reply_is_never_read():
    with pytest.raises(AssertionError, match="never read"):
        with expected_protocol(lambda ch: ch, [(b"A?\n", b"1\n")]) as ch:
            ch.port.write(b"A?\n")
