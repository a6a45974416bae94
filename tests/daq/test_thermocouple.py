"""Type E conversion against NIST ITS-90 table values, the card driver's exact bytes, open junctions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from driftlab.daq.protocols import FLAG_OPEN, TemperatureScanner
from driftlab.daq.thermocouple import (
    APPENDIX_B_EXAMPLE,
    E_INV_POS,
    ChannelCalibration,
    ThermocoupleCard,
    card_emf_to_temperature,
    type_e_emf_mv,
    type_e_temperature_c,
)
from driftlab.errors import InstrumentError, ValidationError
from tests.daq.protocol_helpers import TIMEOUT, expected_protocol

# NIST ITS-90 type E table (NIST Monograph 175), reference junction at 0 degC: degC -> mV.
NIST_TABLE_E = [(-200, -8.825), (-100, -5.237), (0, 0.0), (25, 1.495), (100, 6.319), (200, 13.421),
                (500, 37.005), (1000, 76.373)]  # fmt: skip


@pytest.mark.parametrize(("t_c", "mv"), NIST_TABLE_E)
def test_forward_matches_nist_table(t_c, mv):
    assert float(type_e_emf_mv(t_c)) == pytest.approx(mv, abs=0.0006)


@pytest.mark.parametrize(("t_c", "mv"), [p for p in NIST_TABLE_E if -200 <= p[0]])
def test_inverse_matches_nist_table(t_c, mv):
    # the table is rounded to 1 uV, i.e. about 0.02 degC at 60 uV/degC
    assert float(type_e_temperature_c(mv)) == pytest.approx(t_c, abs=0.02)


def test_inverse_is_exact_inverse_of_reference_function():
    t = np.linspace(-195.0, 995.0, 400)
    back = type_e_temperature_c(type_e_emf_mv(t))
    assert np.max(np.abs(back - t)) < 1e-4
    # the bare NIST inverse polynomial alone is only good to about +-0.02 degC
    bare = np.polynomial.polynomial.polyval(type_e_emf_mv(t[t > 0]), E_INV_POS)
    assert np.max(np.abs(bare - t[t > 0])) > 1e-3


def test_out_of_range_emf_is_nan():
    assert np.isnan(type_e_temperature_c(80.0))
    assert np.isnan(type_e_temperature_c(-9.0))
    with pytest.raises(ValidationError):
        type_e_emf_mv(1200.0)


def test_cold_junction_compensation_and_calibration():
    cj = 23.5
    volts = (type_e_emf_mv([100.0, 25.0, 40.0]) - type_e_emf_mv(cj)) * 1e-3
    temps, open_mask = card_emf_to_temperature(volts, cj)
    assert temps == pytest.approx([100.0, 25.0, 40.0], abs=1e-4)
    assert not open_mask.any()
    cal = [APPENDIX_B_EXAMPLE, ChannelCalibration(), ChannelCalibration(1.0, 0.5)]
    temps_cal, _ = card_emf_to_temperature(volts, cj, cal)
    assert temps_cal[0] == pytest.approx(1.000414 * 100.0 - 0.20638, abs=1e-4)
    assert temps_cal[2] == pytest.approx(40.5, abs=1e-4)


def test_open_circuit_codes_are_flagged_not_temperatures():
    temps, open_mask = card_emf_to_temperature(np.array([9.9e37, 0.0, np.nan, 0.5]), 20.0)
    assert list(open_mask) == [True, False, True, True]
    assert np.isnan(temps[[0, 2, 3]]).all()
    assert temps[1] == pytest.approx(20.0, abs=1e-4)


def _emf(t, cj=24.0):
    return f"{(float(type_e_emf_mv(t)) - float(type_e_emf_mv(cj))) * 1e-3:.9e}"


def _card(channel, clock=lambda: 12.5):
    return ThermocoupleCard(channel, {0: "T1", 1: "T2", 3: "T4"}, {"T4": APPENDIX_B_EXAMPLE}, clock=clock)


def test_card_scan_exact_bytes_and_open_flag():
    reply = ",".join([_emf(30.0), "+9.9E37", _emf(99.0), _emf(50.0)])
    pairs = [(b"CJC?\n", b"24.0000\n"), (b"SCAN? 0,3\n", reply.encode() + b"\n")]
    with expected_protocol(_card, pairs) as card:
        assert isinstance(card, TemperatureScanner)
        scan = card.scan()
    assert scan.t_s == 12.5
    assert list(scan.values) == ["T1", "T2", "T4"]
    assert scan.values["T1"] == pytest.approx(30.0, abs=1e-4)
    assert math.isnan(scan.values["T2"]) and scan.flags == {"T2": FLAG_OPEN}
    assert not scan.ok("T2") and scan.ok("T1")
    assert scan.values["T4"] == pytest.approx(1.000414 * 50.0 - 0.20638, abs=1e-4)


def test_card_retries_garbled_reply_then_succeeds():
    good = ",".join([_emf(30.0), _emf(31.0), _emf(32.0), _emf(33.0)]).encode() + b"\n"
    sleeps: list[float] = []
    pairs = [
        (b"CJC?\n", b"24.0000\n"),
        (b"SCAN? 0,3\n", b"1.0e-3,2.0e-3\n"),  # wrong number of fields
        (b"SCAN? 0,3\n", b"\xff\xfe\n"),  # not ASCII
        (b"SCAN? 0,3\n", good),
    ]
    with expected_protocol(_card, pairs, sleeps=sleeps) as card:
        scan = card.scan()
    assert scan.values["T1"] == pytest.approx(30.0, abs=1e-4)
    assert sleeps == [0.01, 0.02]  # exponential backoff


def test_card_timeouts_raise_one_line_instrument_error():
    pairs = [(b"CJC?\n", TIMEOUT)] * 3
    with expected_protocol(_card, pairs) as card:
        with pytest.raises(InstrumentError) as info:
            card.scan()
    message = str(info.value)
    assert "\n" not in message and "timeout" in message and "3 attempts" in message


def test_card_rejects_implausible_cold_junction():
    pairs = [(b"CJC?\n", b"250.0\n")] * 3
    with expected_protocol(_card, pairs) as card:
        with pytest.raises(InstrumentError, match="cold junction out of range"):
            card.scan()


def test_card_channel_validation():
    with pytest.raises(ValidationError):
        ThermocoupleCard(None, {64: "T65"})  # type: ignore[arg-type]
    with pytest.raises(ValidationError):
        ThermocoupleCard(None, {k: f"T{k}" for k in range(65)})  # type: ignore[arg-type]
    with pytest.raises(ValidationError):
        ThermocoupleCard(None, {0: "T1", 1: "T1"})  # type: ignore[arg-type]
    with pytest.raises(ValidationError):
        ThermocoupleCard(None, {0: "T1"}, {"T9": ChannelCalibration()})  # type: ignore[arg-type]


def test_full_64_channel_scan():
    reply = ",".join(_emf(20.0 + 0.1 * k) for k in range(64)).encode() + b"\n"
    pairs = [(b"CJC?\n", b"24.0000\n"), (b"SCAN? 0,63\n", reply)]
    with expected_protocol(lambda ch: ThermocoupleCard(ch, {k: f"C{k}" for k in range(64)}), pairs) as card:
        scan = card.scan()
    assert len(scan.values) == 64 and not scan.flags
    assert scan.values["C63"] == pytest.approx(26.3, abs=1e-4)


# -- buffered block-scan mode (PACE / FETC?) -----------------------------------------------------


def _block_hex(rows):
    return np.asarray(rows, dtype=">f8").tobytes().hex()


def _emf_v(t, cj=24.0):
    return (float(type_e_emf_mv(t)) - float(type_e_emf_mv(cj))) * 1e-3


def test_block_scan_exact_bytes_open_flag_and_times():
    from driftlab.daq.protocols import BlockScanner

    rows = [
        [24.0, _emf_v(30.0), 9.9e37, _emf_v(99.0), _emf_v(50.0)],
        [24.5, _emf_v(31.0, 24.5), _emf_v(40.0, 24.5), _emf_v(98.0, 24.5), _emf_v(51.0, 24.5)],
    ]
    pairs = [(b"PACE 0.1\n", b"OK\n"), (b"FETC? 0,3,7,2\n", f"7,2,{_block_hex(rows)}\n".encode())]
    with expected_protocol(_card, pairs) as card:
        assert isinstance(card, BlockScanner)
        card.pace(0.1)
        block = card.scan_block(7, 2)
    assert block.first_index == 7 and len(block) == 2 and block.channels == ("T1", "T2", "T4")
    assert block.t_s.tolist() == [7 * 0.1, 8 * 0.1]  # scan k at exactly k * interval, as the plan times it
    assert block.values[0, 0] == pytest.approx(30.0, abs=1e-6) and block.values[1, 0] == pytest.approx(31.0, abs=1e-6)
    assert math.isnan(block.values[0, 1]) and block.open[:, 1].tolist() == [True, False]
    assert block.values[1, 1] == pytest.approx(40.0, abs=1e-6)
    assert block.values[0, 2] == pytest.approx(1.000414 * 50.0 - 0.20638, abs=1e-6)  # calibrated, channel 3
    scan = block.scan(0)
    assert scan.t_s == 7 * 0.1 and scan.flags == {"T2": FLAG_OPEN} and scan.values["T1"] == block.values[0, 0]


def test_block_scan_matches_the_single_scan_conversion():
    volts = np.array([[_emf_v(t) for t in (20.0, -50.0, 300.0, 25.0)]] * 3)
    temps, open_mask = __import__("driftlab.daq.thermocouple", fromlist=["x"]).card_block_to_temperature(
        volts, np.full(3, 24.0)
    )
    single, _ = card_emf_to_temperature(volts[0], 24.0)
    assert not open_mask.any()
    assert np.array_equal(temps[1], single)  # the same arithmetic, element by element


def test_block_scan_rejects_wrong_replies_and_retries():
    good = f"0,1,{_block_hex([[24.0, _emf_v(30.0), _emf_v(31.0), 0.0, _emf_v(32.0)]])}\n".encode()
    short = f"0,1,{_block_hex([[24.0, _emf_v(30.0)]])}\n".encode()
    sleeps: list[float] = []
    pairs = [
        (b"PACE 0.5\n", b"OK\n"),
        (b"FETC? 0,3,0,1\n", b"ERR NOTREADY\n"),  # asked before the pacer took the scan
        (b"FETC? 0,3,0,1\n", short),  # wrong length
        (b"FETC? 0,3,0,1\n", good),
    ]
    with expected_protocol(_card, pairs, sleeps=sleeps) as card:
        card.pace(0.5)
        block = card.scan_block(0, 1)
    assert block.values[0, 0] == pytest.approx(30.0, abs=1e-6) and len(sleeps) == 2
    bad_cj = f"0,1,{_block_hex([[250.0, 0.0, 0.0, 0.0, 0.0]])}\n".encode()
    with expected_protocol(_card, [(b"PACE 1.0\n", b"OK\n")] + [(b"FETC? 0,3,0,1\n", bad_cj)] * 3) as card:
        card.pace(1.0)
        with pytest.raises(InstrumentError, match="cold junction out of range"):
            card.scan_block(0, 1)
    with expected_protocol(_card, []) as card:
        with pytest.raises(ValidationError, match="pace"):
            card.scan_block(0, 1)
        with pytest.raises(ValidationError):
            card.pace(0.0)
