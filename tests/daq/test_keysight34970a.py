"""Keysight 34970A driver: exact bytes of the User's Guide command forms, the error queue, timeouts, memory.

The byte-level exchanges use the guide's own forms (ch. 5: ``CONF:TEMP TC,<type>,(@list)``,
``SYST:ERR?`` -> ``+0,"No error"``, the overload ``+9.90000000E+37`` of an open thermocouple,
``DATA:POINts?`` / ``DATA:REMove?``); the end-to-end tests run the driver through pyvisa against
driftlab's simulated mainframe and against pyvisa-sim's static dialogues (not driftlab's code).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from driftlab.daq.keysight34970a import Keysight34970A, Keysight34970AVolts, channel_list, parse_idn
from driftlab.daq.protocols import FLAG_OPEN, BlockScanner, TemperatureScanner
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.thermocouple import ChannelCalibration
from driftlab.errors import InstrumentError, ValidationError
from tests.daq.protocol_helpers import TIMEOUT, expected_protocol

ROOT = Path(__file__).resolve().parents[2]
OK = b'+0,"No error"\n'
CHANS = {101: "T1", 102: "T2", 103: "T3", 110: "T10"}
LIST = b"(@101:103,110)"


def config_pairs(tc: bytes = b"E", rj: bytes = b"INT") -> list[tuple[bytes, object]]:
    """Return the configuration dialogue: every setting followed by a read of the error queue."""
    settings = [
        b"CONF:TEMP TC," + tc + b"," + LIST,
        b"UNIT:TEMP C," + LIST,
        b"SENS:TEMP:TRAN:TC:RJUN:TYPE " + rj + b"," + LIST,
        b"SENS:TEMP:TRAN:TC:CHEC ON," + LIST,
        b"ROUT:SCAN " + LIST,
        b"TRIG:SOUR IMM",
        b"TRIG:COUN 1",
    ]
    pairs: list[tuple[bytes, object]] = [(b"*CLS\n", None)]
    for s in settings:
        pairs += [(s + b"\n", None), (b"SYST:ERR?\n", OK)]
    return pairs


def test_channel_lists_are_scpi_ranges():
    assert channel_list([103, 101, 102, 110, 201, 202]) == "(@101:103,110,201:202)"
    assert channel_list([305]) == "(@305)"
    with pytest.raises(ValidationError, match="slot x 100"):
        channel_list([401])
    with pytest.raises(ValidationError, match="unique"):
        channel_list([101, 101])


def test_idn_names_a_34970a_family_unit():
    assert parse_idn("HEWLETT-PACKARD,34970A,0,13-2-2")[1] == "34970A"
    assert parse_idn("Keysight Technologies,DAQ970A,MY58000000,A.01.00-01.00-01.00")[1] == "DAQ970A"
    with pytest.raises(ValueError, match="34970A"):
        parse_idn("Keysight Technologies,34465A,MY1,A.02")


def test_configuration_reads_the_error_queue_after_every_setting():
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS), config_pairs()) as card:
        card.configure()
        assert isinstance(card, TemperatureScanner) and isinstance(card, BlockScanner)


def test_fixed_reference_junction_sends_its_temperature():
    pairs = config_pairs(tc=b"T", rj=b"FIX")
    fixed = [(b"SENS:TEMP:TRAN:TC:RJUN 0.010," + LIST + b"\n", None), (b"SYST:ERR?\n", OK)]
    pairs = pairs[:7] + fixed + pairs[7:]
    factory = lambda ch: Keysight34970A(ch, CHANS, tc_type="T", reference_junction="FIXED", fixed_junction_c=0.01)  # noqa: E731
    with expected_protocol(factory, pairs) as card:
        card.configure()


def test_a_refused_setting_is_one_line_naming_command_and_every_queued_error():
    pairs = [
        (b"*CLS\n", None),
        (b"CONF:TEMP TC,E," + LIST + b"\n", None),
        (b"SYST:ERR?\n", b'-222,"Data out of range"\n'),
        (b"SYST:ERR?\n", b'+521,"Input buffer overflow"\n'),
        (b"SYST:ERR?\n", OK),
    ]
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS), pairs) as card:
        with pytest.raises(InstrumentError) as err:
            card.configure()
    msg = err.value.one_line()
    assert "CONF:TEMP TC,E,(@101:103,110)" in msg and "-222,Data out of range" in msg and "+521,Input" in msg


def test_scan_converts_overload_to_open_and_applies_calibration():
    reply = b"+2.13450000E+01,+9.90000000E+37,-1.00000000E+00,+2.50000000E+01\n"
    pairs = [*config_pairs(), (b"READ?\n", reply)]
    cal = {"T3": ChannelCalibration(slope=1.000414, offset_c=-0.20638)}
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS, calibrations=cal, clock=lambda: 7.0), pairs) as card:
        scan = card.scan()
    assert scan.t_s == 7.0
    assert scan.values["T1"] == pytest.approx(21.345, abs=1e-9)
    assert math.isnan(scan.values["T2"]) and scan.flags == {"T2": FLAG_OPEN}
    assert scan.values["T3"] == pytest.approx(1.000414 * -1.0 - 0.20638, abs=1e-12)
    assert list(scan.values) == ["T1", "T2", "T3", "T10"]


def test_a_lost_reading_is_retried_then_validated():
    good = b"+2.1E+01,+2.2E+01,+2.3E+01,+2.4E+01\n"
    pairs = [*config_pairs(), (b"READ?\n", TIMEOUT), (b"READ?\n", b"+2.1E+01,+2.2E+01\n"), (b"READ?\n", good)]
    sleeps: list[float] = []
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS), pairs, sleeps=sleeps) as card:
        assert card.scan().values["T10"] == 24.0
    assert len(sleeps) == 2


def test_a_scan_that_never_validates_is_an_instrument_error():
    pairs = [*config_pairs(), *[(b"READ?\n", TIMEOUT)] * 3]
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS), pairs, policy=RetryPolicy(3, 0.0)) as card:
        with pytest.raises(InstrumentError, match=r"READ\?.*gave up after 3"):
            card.scan()


def pace_pairs() -> list[tuple[bytes, object]]:
    out: list[tuple[bytes, object]] = []
    for s in (b"TRIG:SOUR TIM", b"TRIG:TIM 0.100", b"TRIG:COUN INF", b"INIT"):
        out += [(s + b"\n", None), (b"SYST:ERR?\n", OK)]
    return out


def readings(rows: np.ndarray) -> bytes:
    return ",".join(f"{v:+.8E}" for v in rows.ravel().tolist()).encode() + b"\n"


def test_buffered_scans_are_removed_from_memory_in_whole_sweeps():
    rows = 20.0 + np.arange(12).reshape(3, 4) * 0.001
    pairs = [
        *config_pairs(),
        *pace_pairs(),
        (b"DATA:POIN?\n", b"+12\n"),
        (b"DATA:REM? 8\n", readings(rows[:2])),
        (b"DATA:POIN?\n", b"+4\n"),
        (b"DATA:REM? 4\n", readings(rows[2:])),
    ]
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS), pairs) as card:
        card.pace(0.1)
        first = card.scan_block(40, 2)  # the first block read is the timer run's scan 0
        again = card.scan_block(40, 2)  # read again (a retried batch): from the driver, no bytes
        last = card.scan_block(42, 1)
    np.testing.assert_allclose(first.values, rows[:2], atol=1e-9)
    np.testing.assert_array_equal(again.values, first.values)
    np.testing.assert_allclose(last.t_s, [4.2])
    assert last.values[0, 3] == pytest.approx(20.011, abs=1e-9)
    with pytest.raises(ValidationError, match="pace"):
        Keysight34970A(None, CHANS).scan_block(0, 1)  # type: ignore[arg-type]


def test_scans_not_yet_taken_and_a_lost_remove_reply_are_faults_never_repeated():
    pairs = [
        *config_pairs(),
        *pace_pairs(),
        (b"DATA:POIN?\n", b"+4\n"),
        (b"DATA:POIN?\n", b"+8\n"),
        (b"DATA:REM? 8\n", TIMEOUT),  # erased by the instrument, reply lost: not asked again
    ]
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS), pairs) as card:
        card.pace(0.1)
        with pytest.raises(InstrumentError, match="2 scans asked for, 1 in memory"):
            card.scan_block(0, 2)
        with pytest.raises(InstrumentError, match="2 buffered scans lost"):
            card.scan_block(0, 2)
        with pytest.raises(InstrumentError, match="already read and erased"):
            card.scan_block(0, 2)


def test_dc_volt_channels_for_the_proximity_sensors():
    pairs = [(b"*CLS\n", None)]
    for s in (b"CONF:VOLT:DC 10,(@201:205)", b"ROUT:SCAN (@201:205)", b"TRIG:SOUR IMM", b"TRIG:COUN 1"):
        pairs += [(s + b"\n", None), (b"SYST:ERR?\n", OK)]
    pairs.append((b"READ?\n", b"+5.0E+00,+5.1E+00,+5.2E+00,+5.3E+00,+5.4E+00\n"))
    with expected_protocol(lambda ch: Keysight34970AVolts(ch, [201, 202, 203, 204, 205]), pairs) as adc:
        np.testing.assert_allclose(adc.read_volts([4, 0]), [5.4, 5.0])


def test_bad_options_are_one_line_errors():
    with pytest.raises(ValidationError, match="type 'X'"):
        Keysight34970A(None, CHANS, tc_type="X")  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="INT, FIX or EXT"):
        Keysight34970A(None, CHANS, reference_junction="ICE")  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="fixed_junction_c"):
        Keysight34970A(None, CHANS, reference_junction="FIX")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- end to end


def test_driver_against_pyvisa_sim_dialogues_reads_type_e_to_1_mk():
    """pyvisa-sim's static dialogues (examples/rigs/keysight-34970a.pyvisa-sim.yaml) are not driftlab's code."""
    from driftlab.daq.transport import LineChannel, VisaPort, visa_resource_manager

    rm = visa_resource_manager(f"{ROOT / 'examples/rigs/keysight-34970a.pyvisa-sim.yaml'}@sim")
    chans = {100 + i: f"T{i}" for i in range(1, 11)}
    card = Keysight34970A(LineChannel(VisaPort.open("GPIB0::9::INSTR", resource_manager=rm), "34970A"), chans)
    try:
        assert card.identify().startswith("HEWLETT-PACKARD,34970A")
        card.configure()
        scan = card.scan()
    finally:
        card.close()
        rm.close()
    expected = [21.345, 22.012, 20.8765, 24.5001, 19.999, 23.1234, 21.7779, 22.0005, 25.05, 18.333]
    for i, want in enumerate(expected, start=1):
        assert abs(scan.values[f"T{i}"] - want) < 1e-3
    assert scan.flags == {}


def test_driver_against_the_simulated_mainframe_timer_scan_and_reference_junction():
    import pyvisa

    from driftlab.daq.sim.instruments import ManualClock, visa_address
    from driftlab.daq.sim.keysight34970a import Sim34970A
    from driftlab.daq.transport import LineChannel, VisaPort
    from driftlab.testing.tinyworld import TinyWorld

    world, clock = TinyWorld(channels=3), ManualClock()
    wiring = {101: "T1", 102: "T2", 103: "T3", 104: "nowhere"}
    names = {101: "a", 102: "b", 103: "c", 104: "open"}
    with Sim34970A(world, clock, wiring, terminal_c=24.0) as sim:
        rm = pyvisa.ResourceManager("@py")
        try:
            io = LineChannel(VisaPort.open(visa_address(sim), resource_manager=rm), "34970A")
            card = Keysight34970A(io, names, clock=clock.now)
            assert "34970A" in card.identify()
            card.configure()
            scan = card.scan()
            truth = world.temperatures(0.0)
            assert scan.values["a"] == pytest.approx(truth["T1"], abs=1e-6)
            assert scan.flags == {"open": FLAG_OPEN}
            # a fixed junction set 1 degC off the terminal block's real temperature reads about 1 degC off
            fixed = Keysight34970A(io, names, reference_junction="FIX", fixed_junction_c=23.0, clock=clock.now)
            fixed.configure()
            off = fixed.scan().values["a"] - truth["T1"]
            assert -1.1 < off < -0.9
            card.configure()
            clock.advance_to(10.0)
            card.pace(0.5)  # scan k of the run at 10 + 0.5 k
            clock.advance_to(12.0)
            block = card.scan_block(20, 5)
            want = [world.temperatures(10.0 + 0.5 * k)["T2"] for k in range(5)]
            np.testing.assert_allclose(block.values[:, 1], want, atol=1e-6)
            with pytest.raises(InstrumentError, match="in memory"):
                card.scan_block(25, 1)  # not taken until 12.5
            io.close()
        finally:
            rm.close()


@pytest.mark.parametrize("unit", ["C", "F", "K"])
def test_the_simulated_mainframe_converts_each_channel_as_if_it_were_scanned_alone(unit: str) -> None:
    """The scan list is converted at once (types, junctions, open check, unit per channel): each column is what
    a mainframe configured with that channel alone reports (guide ch. 4, Temperature Measurement Configuration)."""
    from driftlab.daq.sim.instruments import ManualClock
    from driftlab.daq.sim.keysight34970a import Sim34970A
    from driftlab.testing.tinyworld import TinyWorld

    world = TinyWorld(channels=6, open_channels={"T2": 0.0, "T5": 0.0})
    wiring = {101 + k: f"T{k + 1}" for k in range(6)}
    # channel -> thermocouple type, junction, fixed junction degC, open check
    setup = {101: ("E", "INT", None, True), 102: ("K", "FIX", 12.5, True), 103: ("J", "FIX", None, False),
             104: ("T", "EXT", None, True), 105: ("E", "FIX", 3.0, False), 106: ("K", "INT", None, False)}  # fmt: skip

    def commands(chans: list[int]) -> list[str]:
        out = []
        for c in chans:
            tc, rj, fixed, check = setup[c]
            out += [f"CONF:TEMP TC,{tc},(@{c})", f"TEMP:TRAN:TC:RJUN:TYPE {rj},(@{c})"]
            out += [f"TEMP:TRAN:TC:RJUN {fixed},(@{c})"] if fixed is not None else []
            out += [f"TEMP:TRAN:TC:CHEC {'ON' if check else 'OFF'},(@{c})"]
        return [*out, f"UNIT:TEMP {unit}", f"ROUT:SCAN {channel_list(chans)}", "TRIG:SOUR IMM", "TRIG:COUN 1"]

    def read(chans: list[int]) -> list[str]:
        card = Sim34970A(world, ManualClock(600.0), wiring, terminal_c=26.0)
        for command in commands(chans):
            card.handle(command)
        assert not card.errors, card.errors
        reply = card.handle("READ?")
        assert reply is not None
        return reply.split(",")

    alone = [read([c])[0] for c in setup]
    assert read(list(setup)) == alone
    assert alone[1] == "+9.90000000E+37" and alone[3] == "+9.90000000E+37"  # open with check on; EXT: no reference
    assert alone[4] != "+9.90000000E+37"  # open, check off: the terminal's temperature, as the mainframe reads it


def test_block_readings_decode_exactly_as_float_does_and_the_simulator_formats_as_the_mainframe():
    from driftlab.daq.keysight34970a import parse_readings
    from driftlab.daq.sim.keysight34970a import format_readings

    rng = np.random.default_rng(7)
    values = np.concatenate(
        [20 + rng.random(300), rng.normal(0, 500, 300), [0.0, 9.9e37, 9.9999999996, 1e-5, -273.15, 1e-12]]
    )
    text = format_readings(values)
    assert text == ",".join(f"{v:+.8E}" for v in values.tolist())  # the form of the guide's examples
    np.testing.assert_allclose(parse_readings(text, values.size), [float(f) for f in text.split(",")], rtol=1e-15)
    # any other valid number form still parses (the slow path), a wrong count does not
    np.testing.assert_allclose(parse_readings("21.5,+2.2E+01,-3", 3), [21.5, 22.0, -3.0])
    with pytest.raises(ValueError, match="expected 4 readings, got 3"):
        parse_readings(text.rsplit(",", len(values) - 3)[0], 4)


def test_a_full_reading_memory_is_refused_never_misplaced():
    pairs = [*config_pairs(), *pace_pairs(), (b"DATA:POIN?\n", b"+49998\n")]
    with expected_protocol(lambda ch: Keysight34970A(ch, CHANS), pairs) as card:
        card.pace(0.1)
        with pytest.raises(InstrumentError, match="memory full"):
            card.scan_block(0, 2)
        with pytest.raises(InstrumentError, match="out of step"):  # and every later block, without a guess
            card.scan_block(2, 2)
