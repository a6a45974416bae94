"""Keysight (Agilent, HP) 34970A / 34972A / DAQ970A data acquisition unit over VISA: thermocouples and DC volts.

Written from the instrument's own programming reference:

* Agilent 34970A/34972A Data Acquisition / Switch Unit User's Guide (34970-90003, 34972-90001),
  chapter 4 "Features and Functions": Scanning (scan list in ascending channel order, INITiate
  stores readings in memory, READ? returns them), Temperature Measurement Configuration
  (thermocouple types B E J K N R S T, reference junction INTernal / EXTernal / FIXed,
  thermocouple check: an open channel reads the overload +9.9E+37), Reading Format;
* the same guide, chapter 5 "Remote Interface Reference": CONFigure:TEMPerature TCouple,<type>,
  UNIT:TEMPerature, [SENSe:]TEMPerature:TRANsducer:TCouple:RJUNction:TYPE and :RJUNction,
  [SENSe:]TEMPerature:TRANsducer:TCouple:CHECk, ROUTe:SCAN, TRIGger:SOURce / :TIMer / :COUNt,
  INITiate, READ?, "Scan Memory Commands" (DATA:POINts?, DATA:REMove? <n>: read and erase the n
  oldest readings, an error if fewer are stored), SYSTem:ERRor? (``+0,"No error"`` when empty),
  CONFigure:VOLTage:DC;
* Keysight DAQ970A/DAQ973A Programming Guide (DAQ970-90002), which keeps these commands.

Library first: pymeasure's ``agilent34970A`` is an unfinished stub (an error-queue reader only),
QCoDeS drives the 34980A switch matrix and the 34465A DMM, InstrumentKit has no 34970A; so this is
a driver of its own on pyvisa, through the same byte seam as every driftlab driver
(:class:`driftlab.daq.transport.LineChannel`), and tested byte for byte against the guide's
command forms (tests/daq/test_keysight34970a.py).

Every configuration command is followed by ``SYST:ERR?``: the instrument accepts a bad
setting silently and only says so in its error queue, so the driver refuses to run on a
configuration the instrument did not take (one-line :class:`InstrumentError` naming the command).

The scanner satisfies :class:`~driftlab.daq.protocols.TemperatureScanner` (``READ?``: one
sweep of the scan list) and :class:`~driftlab.daq.protocols.BlockScanner`: ``pace`` starts
the instrument's own timer (``TRIG:SOUR TIM``, ``TRIG:TIM``, ``TRIG:COUN INF``, ``INIT``), scan
k of the run is taken at k x interval from ``INIT`` and kept in reading memory, and
``scan_block`` removes whole sweeps with ``DATA:REMove?``. Removal erases, so the driver keeps the
last block it read (a block read again is answered from it); a ``DATA:REMove?`` whose reply is
lost is not repeated (its readings are gone from the instrument): those scans are reported lost.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Protocol, TypeVar

import numpy as np

from driftlab.daq.protocols import FLAG_OPEN, ScanBlock, TemperatureScan
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.thermocouple import ChannelCalibration, block_interval
from driftlab.daq.transport import LineChannel, open_port
from driftlab.errors import InstrumentError, ValidationError

#: models that answer this command set (the second field of ``*IDN?``)
MODELS = ("34970A", "34972A", "DAQ970A", "DAQ973A")
#: thermocouple types the mainframe converts (User's Guide ch. 4, Temperature Measurement Configuration)
TC_TYPES = ("B", "E", "J", "K", "N", "R", "S", "T")
REFERENCE_JUNCTIONS = {"INT": "INT", "INTERNAL": "INT", "EXT": "EXT", "EXTERNAL": "EXT", "FIX": "FIX", "FIXED": "FIX"}
#: the overload value the mainframe returns for an open thermocouple (TC check on) or an overload
OVERLOAD = 9.9e37
#: reading memory by model (34970A/34972A User's Guide ch. 5 Scan Memory Commands; DAQ970A Programming Guide)
MEMORY_READINGS = {"34970A": 50_000, "34972A": 50_000, "DAQ970A": 100_000, "DAQ973A": 100_000}


def check_channels(channels: Iterable[int]) -> list[int]:
    """Return the channel numbers (slot x 100 + channel, slots 1-3, channels 1-99) sorted; ValidationError if not."""
    out = sorted(int(c) for c in channels)
    if not out:
        raise ValidationError("a 34970A scan list needs at least one channel")
    bad = [c for c in out if not (1 <= c // 100 <= 3 and 1 <= c % 100 <= 99)]
    if bad:
        raise ValidationError(f"34970A channel {bad[0]}: channels are slot x 100 + channel, e.g. 101..120, 201..220")
    if len(set(out)) != len(out):
        raise ValidationError("34970A channels must be unique")
    return out


def channel_list(channels: Iterable[int]) -> str:
    """Return the SCPI channel list of ``channels``: consecutive runs as ranges, ``(@101:110,201)``."""
    chans = check_channels(channels)
    parts: list[str] = []
    start = prev = chans[0]
    for c in [*chans[1:], None]:
        if c is not None and c == prev + 1:
            prev = c
            continue
        parts.append(f"{start}" if start == prev else f"{start}:{prev}")
        if c is not None:
            start = prev = c
    return "(@" + ",".join(parts) + ")"


_POW10 = 10.0 ** np.arange(-99, 100)


def _parse_fixed(raw: bytes, n: int) -> np.ndarray | None:
    """Return n readings in the mainframe's own fixed form ``+2.13450000E+01`` decoded at once, None if not that form.

    The User's Guide (ch. 5, Reading Format) gives readings as SD.DDDDDDDDESDD, 15 characters, comma
    separated; a block of a thousand scans is decoded here in one pass instead of value by value.
    """
    if len(raw) != 16 * n - 1:
        return None
    a = np.frombuffer(raw + b",", dtype=np.uint8).reshape(n, 16)
    digits = a[:, [1, 3, 4, 5, 6, 7, 8, 9, 10, 13, 14]].astype(np.int64) - 48
    if (
        not np.all((digits >= 0) & (digits <= 9))
        or not np.all((a[:, 2] == 46) & (a[:, 11] == 69) & (a[:, 15] == 44))
        or not np.all(((a[:, 0] == 43) | (a[:, 0] == 45)) & ((a[:, 12] == 43) | (a[:, 12] == 45)))
    ):
        return None
    mantissa = digits[:, :9] @ (10 ** np.arange(8, -1, -1, dtype=np.int64))
    exponent = (digits[:, 9] * 10 + digits[:, 10]) * np.where(a[:, 12] == 45, -1, 1) - 8
    sign = np.where(a[:, 0] == 45, -1.0, 1.0)
    return sign * mantissa * _POW10[exponent + 99]


def parse_readings(text: str, expected: int) -> np.ndarray:
    """Return the ASCII readings of a reply (``+2.13450000E+01,...``) as floats; ValueError if not ``expected``."""
    fast = _parse_fixed(text.encode("ascii"), expected) if expected > 0 else None
    if fast is not None:
        return fast
    values = np.array(text.split(","), dtype=float) if text else np.zeros(0)
    if values.size != expected:
        raise ValueError(f"expected {expected} readings, got {values.size}")
    return values


def parse_error(text: str) -> tuple[int, str]:
    """Return (code, message) of a ``SYST:ERR?`` reply such as ``-113,"Undefined header"``."""
    code_s, _, msg = text.partition(",")
    return int(code_s), msg.strip().strip('"')


def parse_idn(text: str) -> tuple[str, str, str, str]:
    """Return (maker, model, serial, firmware) of an ``*IDN?`` reply; ValueError if it is not a 34970A family unit."""
    fields = [f.strip() for f in text.split(",")]
    if len(fields) != 4:
        raise ValueError("not an *IDN? reply")
    if fields[1].upper() not in MODELS:
        raise ValueError(f"model {fields[1]!r} is not one of {', '.join(MODELS)}")
    return fields[0], fields[1], fields[2], fields[3]


class ScpiInstrument:
    """A SCPI instrument on a line channel: settings checked against the error queue, identification."""

    def __init__(self, channel: LineChannel) -> None:
        self._io = channel
        self.idn: str | None = None

    def identify(self) -> str:
        """Return the ``*IDN?`` reply, checked to be a 34970A family unit."""
        reply = self._io.query("*IDN?", lambda t: (parse_idn(t), t)[1])
        self.idn = reply
        return reply

    def errors(self) -> list[tuple[int, str]]:
        """Return (and empty) the instrument's error queue, oldest first."""
        out: list[tuple[int, str]] = []
        for _ in range(32):  # the queue holds at most 10 (34970A); more means a reply we do not understand
            code, msg = self._io.query("SYST:ERR?", parse_error)
            if code == 0:
                return out
            out.append((code, msg))
        raise InstrumentError(f"{self._io.name}: the error queue does not empty")

    def setting(self, command: str) -> None:
        """Send a setting, then read the error queue: InstrumentError naming the command if it was refused."""
        self._io.write(command)
        errs = self.errors()
        if errs:
            what = "; ".join(f"{code:+d},{msg}" for code, msg in errs)
            raise InstrumentError(f"{self._io.name}: {command!r} refused: {what}")

    def close(self) -> None:
        """Release the instrument's port."""
        self._io.close()


class _Mainframe(Protocol):
    """A driver of a 34970A family mainframe: identified, configured and closed."""

    def identify(self) -> str: ...

    def configure(self) -> None: ...

    def close(self) -> None: ...


_M = TypeVar("_M", bound=_Mainframe)


def identified(card: _M) -> _M:
    """Return the card identified (``*IDN?``) and configured; closed again if either fails."""
    try:
        card.identify()
        card.configure()
    except BaseException:
        card.close()
        raise
    return card


class Keysight34970A(ScpiInstrument):
    """Thermocouple channels of a 34970A/34972A/DAQ970A: a TemperatureScanner and BlockScanner.

    ``channel_map`` maps channel numbers (``101`` = slot 1, channel 1) to driftlab channel names;
    the mainframe scans them in ascending channel order and converts the EMF to degC itself with
    the reference junction chosen (``INT``: the 34901A/34902A terminal block's isothermal sensor;
    ``FIX``: a known junction temperature ``fixed_junction_c``, an ice point for the best accuracy;
    ``EXT``: a reference channel the user has set up). Appendix B calibrations apply on top.
    """

    def __init__(
        self,
        channel: LineChannel,
        channel_map: Mapping[int, str],
        tc_type: str = "E",
        reference_junction: str = "INT",
        fixed_junction_c: float | None = None,
        open_check: bool = True,
        calibrations: Mapping[str, ChannelCalibration] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(channel)
        self.tc_type = str(tc_type).upper()
        if self.tc_type not in TC_TYPES:
            raise ValidationError(f"34970A thermocouple type {tc_type!r} is not one of {' '.join(TC_TYPES)}")
        rj = REFERENCE_JUNCTIONS.get(str(reference_junction).upper())
        if rj is None:
            raise ValidationError(f"34970A reference junction {reference_junction!r}: use INT, FIX or EXT")
        self.reference_junction = rj
        if rj == "FIX":
            if fixed_junction_c is None or not -20.0 <= float(fixed_junction_c) <= 80.0:
                raise ValidationError("34970A fixed reference junction needs fixed_junction_c in -20..80 degC")
        self.fixed_junction_c = None if fixed_junction_c is None else float(fixed_junction_c)
        self.open_check = bool(open_check)
        chans = check_channels(channel_map)
        names = [channel_map[c] for c in chans]
        if len(set(names)) != len(names):
            raise ValidationError("thermocouple channel names must be unique")
        self._chans = chans
        self._names = tuple(names)
        self._cal = dict(calibrations or {})
        unknown = set(self._cal) - set(names)
        if unknown:
            raise ValidationError(f"calibration for unknown channel(s): {', '.join(sorted(unknown))}")
        self._clock = clock
        self._configured = False
        self._interval_s: float | None = None
        self._origin: int | None = None  # the daemon's scan number of the timer run's scan 0
        self._taken = 0  # scans removed from reading memory so far
        self._cache_first = 0  # run scan number of the first row kept
        self._cache = np.zeros((0, len(chans)))
        self._overflowed = False

    @classmethod
    def open(
        cls,
        address: str,
        channel_map: Mapping[int, str],
        timeout_s: float = 5.0,
        policy: RetryPolicy | None = None,
        **options: object,
    ) -> Keysight34970A:
        """Return the scanner on a VISA resource (``GPIB0::9::INSTR``, ``TCPIP0::host::inst0::INSTR``, ...)."""
        return identified(cls(LineChannel(open_port(address, timeout_s), "34970A", policy), channel_map, **options))  # type: ignore[arg-type]

    @property
    def channels(self) -> Sequence[str]:
        """Return the channel names in scan (ascending channel number) order."""
        return list(self._names)

    @property
    def scan_list(self) -> str:
        """Return the SCPI channel list of the configured channels."""
        return channel_list(self._chans)

    def configure(self) -> None:
        """Configure thermocouple channels, units, reference junction, open check and the scan list; check each."""
        chans = self.scan_list
        self._io.write("*CLS")
        self.setting(f"CONF:TEMP TC,{self.tc_type},{chans}")
        self.setting(f"UNIT:TEMP C,{chans}")
        self.setting(f"SENS:TEMP:TRAN:TC:RJUN:TYPE {self.reference_junction},{chans}")
        if self.reference_junction == "FIX":
            self.setting(f"SENS:TEMP:TRAN:TC:RJUN {self.fixed_junction_c:.3f},{chans}")
        self.setting(f"SENS:TEMP:TRAN:TC:CHEC {'ON' if self.open_check else 'OFF'},{chans}")
        self.setting(f"ROUT:SCAN {chans}")
        self.setting("TRIG:SOUR IMM")
        self.setting("TRIG:COUN 1")
        self._configured = True
        self._interval_s = None

    def _convert(self, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (calibrated degC, open mask) of readings shaped (..., channels)."""
        open_mask = ~np.isfinite(readings) | (np.abs(readings) >= OVERLOAD * 0.99)
        temps = np.where(open_mask, np.nan, readings)
        if self._cal:
            cals = [self._cal.get(n, ChannelCalibration()) for n in self._names]
            temps = np.array([c.slope for c in cals]) * temps + np.array([c.offset_c for c in cals])
        return temps, open_mask

    def read_temperatures(self) -> np.ndarray:
        """Return one sweep of the scan list as the mainframe reports it (degC, overload for open channels)."""
        if not self._configured:
            self.configure()
        if self._interval_s is not None:
            raise ValidationError("34970A: the timer scan is running (pace); read it with scan_block")
        return self._io.query("READ?", lambda t: parse_readings(t, len(self._chans)))

    def scan(self) -> TemperatureScan:
        """Return one scan: calibrated degC per channel, open thermocouples NaN flagged open."""
        t_s = self._clock()
        temps, open_mask = self._convert(self.read_temperatures())
        values = {n: float(temps[i]) for i, n in enumerate(self._names)}
        flags = {n: FLAG_OPEN for i, n in enumerate(self._names) if open_mask[i]}
        return TemperatureScan(t_s=t_s, values=values, flags=flags)

    def pace(self, interval_s: float) -> None:
        """Start the mainframe's timer: a sweep every ``interval_s`` (1 ms steps) into reading memory, from now."""
        if not (math.isfinite(interval_s) and 0.0 < interval_s <= 359_999.0):
            raise ValidationError("the scan interval must be 0 < interval <= 359999 s (TRIG:TIM)")
        if not self._configured:
            self.configure()
        self.setting("TRIG:SOUR TIM")
        self.setting(f"TRIG:TIM {interval_s:.3f}")
        self.setting("TRIG:COUN INF")
        self.setting("INIT")
        self._interval_s = float(interval_s)
        self._overflowed = False
        self._origin = None
        self._taken = 0
        self._cache_first = 0
        self._cache = np.zeros((0, len(self._chans)))

    def stored_readings(self) -> int:
        """Return how many readings the mainframe holds in memory (``DATA:POIN?``)."""

        def parse(text: str) -> int:
            n = int(float(text))
            if n < 0:
                raise ValueError("negative count")
            return n

        return self._io.query("DATA:POIN?", parse)

    def _remove(self, scans: int) -> np.ndarray:
        """Return the ``scans`` oldest sweeps erased from memory, shaped (scans, channels)."""
        width = len(self._chans)
        if self._overflowed:
            raise InstrumentError("34970A: reading memory overflowed earlier; buffered scans are out of step")
        have = self.stored_readings()
        model = self.idn.split(",")[1].strip().upper() if self.idn and self.idn.count(",") >= 1 else ""
        if have > MEMORY_READINGS.get(model, 50_000) - width:
            # full: the oldest readings were overwritten (the guide: the most recent are kept), so the count
            # of scans removed no longer says which scan the next reading is - refuse rather than misplace
            self._overflowed = True
            raise InstrumentError(
                f"34970A: reading memory full ({have} readings): older scans were overwritten; "
                "stop and resume the daemon to restart the buffered scan"
            )
        if have < scans * width:
            raise InstrumentError(f"34970A: {scans} scans asked for, {have // width} in memory (not taken yet)")
        try:
            flat = self._io.query_once(f"DATA:REM? {scans * width}", lambda t: parse_readings(t, scans * width))
        except InstrumentError as exc:
            self._taken += scans  # the instrument erased them before its reply was lost: those scans are gone
            self._cache, self._cache_first = np.zeros((0, width)), self._taken
            raise InstrumentError(f"34970A: {scans} buffered scans lost: {exc.one_line()}") from exc
        self._taken += scans
        return flat.reshape(scans, width)

    def scan_block(self, first_index: int, n: int) -> ScanBlock:
        """Return the timer's scans first_index..first_index + n - 1 (the first block read is the run's scan 0)."""
        interval = block_interval("34970A", self._interval_s, n)
        if self._origin is None:
            self._origin = first_index
        j = first_index - self._origin  # the scan of the timer run
        if j < self._cache_first:
            raise InstrumentError(f"34970A: scans {first_index}.. were already read and erased from memory")
        end = j + n
        if end > self._taken:
            rows = self._remove(end - self._taken)
            self._cache = np.vstack([self._cache, rows]) if self._cache.size else rows
        keep_from = max(self._cache_first, j)
        self._cache = self._cache[keep_from - self._cache_first :]
        self._cache_first = keep_from
        block = self._cache[j - self._cache_first : end - self._cache_first]
        temps, open_mask = self._convert(block)
        t_s = np.arange(first_index, first_index + n) * interval
        return ScanBlock(first_index, t_s, self._names, temps, open_mask)

    def abort(self) -> None:
        """Stop a running timer scan (``ABOR``) and return to single sweeps."""
        self._io.write("ABOR")
        self._interval_s = None
        self._configured = False


class Keysight34970AVolts(ScpiInstrument):
    """DC-volt channels of a 34970A family mainframe: the proximity sensors' A/D (thesis ch. 5.5, appendix C).

    ``read_volts(indices)`` reads the configured channels (index i = the i-th channel of
    ``channels`` in ascending order), the interface :mod:`driftlab.daq.proximity` calibrates to
    distance. A mainframe has one scan list, so one mainframe plays one role (thermocouples or
    proximity volts), not both.
    """

    def __init__(self, channel: LineChannel, channels: Sequence[int], range_v: float = 10.0) -> None:
        super().__init__(channel)
        self._chans = check_channels(channels)
        if range_v not in (0.1, 1.0, 10.0, 100.0, 300.0):
            raise ValidationError("34970A DC volt range must be 0.1, 1, 10, 100 or 300 V")
        self.range_v = range_v
        self.n_channels = len(self._chans)
        self._configured = False

    @classmethod
    def open(
        cls, address: str, channels: Sequence[int], range_v: float = 10.0, timeout_s: float = 5.0
    ) -> Keysight34970AVolts:
        """Return the DC-volt reader on a VISA resource, identified and configured."""
        return identified(cls(LineChannel(open_port(address, timeout_s), "34970A volts"), channels, range_v))

    def configure(self) -> None:
        """Configure DC volts on the channels (fixed range), the scan list and single sweeps; check each."""
        chans = channel_list(self._chans)
        self._io.write("*CLS")
        self.setting(f"CONF:VOLT:DC {self.range_v:g},{chans}")
        self.setting(f"ROUT:SCAN {chans}")
        self.setting("TRIG:SOUR IMM")
        self.setting("TRIG:COUN 1")
        self._configured = True

    def read_volts(self, channels: Sequence[int]) -> np.ndarray:
        """Return the voltages (V) of channel indices ``channels`` (0 = first configured channel), in that order."""
        idx = list(channels)
        if not idx or min(idx) < 0 or max(idx) >= self.n_channels:
            raise ValidationError(f"A/D channel indices must be 0..{self.n_channels - 1}")
        if not self._configured:
            self.configure()
        volts = self._io.query("READ?", lambda t: parse_readings(t, self.n_channels))
        return volts[np.array(idx)]
