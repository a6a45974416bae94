"""Type E thermocouple card (thesis ch. 5.3, appendix B): EMF to degC, cold junction, calibration.

Conversion follows the NIST ITS-90 thermocouple reference functions for type E
(chromel-constantan), NIST Monograph 175 (1993):

* forward  E(t) = sum c_i t^i   (mV, t in degC), two ranges -270..0 and 0..1000 degC;
* inverse  t(E) = sum d_i E^i   (degC, E in mV), -8.825..0 mV and 0..76.373 mV,
  refined here by one Newton step on the forward function so that the inverse agrees
  with the reference function to well under 1 mK instead of the +-0.02 degC of the
  bare inverse polynomial.

Cold-junction compensation: the card measures E_meas = E(t_hot) - E(t_cj); the hot
junction's EMF is E_total = E_meas + E(t_cj), then inverted.  Per-channel calibration
(appendix B) scales and shifts the result: t = slope * t_raw + offset (example:
slope 1.000414, offset -0.20638 degC).

Card protocol (ASCII, one ``\\n``-terminated line each way; the simulated card in
``driftlab.daq.sim.instruments`` answers the same):

=================================  =============================================
``*IDN?``                          ``<maker>,<model>,<serial>,<firmware>``
``CJC?``                           cold-junction temperature, degC, e.g. ``24.125``
``SCAN? <first>,<last>``           EMF of channels first..last (0-63) in volts, comma
                                   separated; an open circuit reads over-range ``+9.9E37``
``PACE <interval_s>``              start the card's pacer: scan k of channels 0-63 is
                                   taken at k * interval_s on the card's time base and
                                   kept in its scan buffer -> ``OK``
``FETC? <first>,<last>,<k>,<n>``   buffered scans k..k+n-1 of channels first..last:
                                   ``<k>,<n>,<hex>`` where hex is the IEEE-754 float64
                                   big-endian image (SCPI ``FORM REAL,64`` sent as
                                   ``FORM HEX``, so the reply stays one line) of n rows of
                                   [cold junction degC, EMF first..last V]; ``ERR
                                   NOTREADY`` if scan k+n-1 is not taken yet, ``ERR
                                   OVERWRITTEN`` if scan k has left the buffer, ``ERR
                                   NOPACE`` before ``PACE``
=================================  =============================================

Block-scan mode is what a DAS-TC class card does at speed: its pacer scans on its own clock
into an on-board buffer and the host reads many scans per exchange, so one round trip and one
vectorised conversion serve hundreds of scans instead of one each. Scans are addressed by their
number, so reading a block again (a retry, or a host that restarted) returns the same scans.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from driftlab.daq.protocols import FLAG_OPEN, ScanBlock, TemperatureScan
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.transport import LineChannel, open_port
from driftlab.errors import ValidationError

MAX_CHANNELS = 64

# NIST ITS-90 type E reference function coefficients (NIST Monograph 175).
# Forward, -270..0 degC: E (mV) = sum c_i t^i.
E_FWD_NEG = (
    0.0,
    0.586655087080e-01,
    0.454109771240e-04,
    -0.779980486860e-06,
    -0.258001608430e-07,
    -0.594525830570e-09,
    -0.932140586670e-11,
    -0.102876055340e-12,
    -0.803701236210e-15,
    -0.439794973910e-17,
    -0.164147763550e-19,
    -0.396736195160e-22,
    -0.558273287210e-25,
    -0.346578420130e-28,
)
# Forward, 0..1000 degC.
E_FWD_POS = (
    0.0,
    0.586655087100e-01,
    0.450322755820e-04,
    0.289084072120e-07,
    -0.330568966520e-09,
    0.650244032700e-12,
    -0.191974955040e-15,
    -0.125366004970e-17,
    0.214892175690e-20,
    -0.143880417820e-23,
    0.359608994810e-27,
)
# Inverse, -8.825..0 mV (-200..0 degC): t = sum d_i E^i.
E_INV_NEG = (
    0.0,
    1.6977288e01,
    -4.3514970e-01,
    -1.5859697e-01,
    -9.2502871e-02,
    -2.6084314e-02,
    -4.1360199e-03,
    -3.4034030e-04,
    -1.1564890e-05,
    0.0,
)
# Inverse, 0..76.373 mV (0..1000 degC).
E_INV_POS = (
    0.0,
    1.7057035e01,
    -2.3301759e-01,
    6.5435585e-03,
    -7.3562749e-05,
    -1.7896001e-06,
    8.4036165e-08,
    -1.3735879e-09,
    1.0629823e-11,
    -3.2447087e-14,
)
E_MV_MIN = -8.825  # inverse range limits (mV)
E_MV_MAX = 76.373
OVER_RANGE_V = 1.0  # any |reading| this large is the card's open-circuit/over-range code


def _poly(coeffs: Sequence[float], x: np.ndarray) -> np.ndarray:
    return np.polynomial.polynomial.polyval(x, np.asarray(coeffs))


def _piecewise(neg: Sequence[float], pos: Sequence[float], x: np.ndarray, below: np.ndarray) -> np.ndarray:
    """Return poly ``neg`` where ``below`` else poly ``pos``; a branch nobody needs is not evaluated."""
    if not below.any():
        return _poly(pos, x)
    if below.all():
        return _poly(neg, x)
    return np.where(below, _poly(neg, x), _poly(pos, x))


def type_e_emf_mv(t_c: float | np.ndarray) -> np.ndarray:
    """Return the type E reference EMF (mV) at ``t_c`` degC (NIST ITS-90 forward function)."""
    t = np.asarray(t_c, dtype=float)
    if np.any((t < -270.0) | (t > 1000.0)):
        raise ValidationError("type E reference function is defined for -270..1000 degC")
    return _piecewise(E_FWD_NEG, E_FWD_POS, t, t < 0.0)


_E_SLOPE_NEG = tuple(np.polynomial.polynomial.polyder(np.asarray(E_FWD_NEG)).tolist())
_E_SLOPE_POS = tuple(np.polynomial.polynomial.polyder(np.asarray(E_FWD_POS)).tolist())


def _type_e_slope_mv_per_c(t: np.ndarray) -> np.ndarray:
    return _piecewise(_E_SLOPE_NEG, _E_SLOPE_POS, t, t < 0.0)


def type_e_temperature_c(emf_mv: float | np.ndarray) -> np.ndarray:
    """Return degC for a type E EMF in mV (NIST inverse polynomial plus one Newton step); NaN out of range."""
    e = np.asarray(emf_mv, dtype=float)
    inside = np.isfinite(e) & (e >= E_MV_MIN) & (e <= E_MV_MAX)
    ec = np.where(inside, e, 0.0)
    t0 = _piecewise(E_INV_NEG, E_INV_POS, ec, ec < 0.0)
    # One Newton step on the forward reference function removes the inverse's +-0.02 degC.
    t1 = t0 - (_piecewise(E_FWD_NEG, E_FWD_POS, t0, t0 < 0.0) - ec) / _type_e_slope_mv_per_c(t0)
    return np.where(inside, t1, np.nan)


@dataclass(frozen=True)
class ChannelCalibration:
    """Appendix B calibration of one thermocouple: t = slope * t_raw + offset_c."""

    slope: float = 1.0
    offset_c: float = 0.0

    def apply(self, t_raw: np.ndarray) -> np.ndarray:
        """Return calibrated temperatures (degC)."""
        return self.slope * np.asarray(t_raw, dtype=float) + self.offset_c


APPENDIX_B_EXAMPLE = ChannelCalibration(slope=1.000414, offset_c=-0.20638)


def card_emf_to_temperature(
    volts: np.ndarray, cold_junction_c: float, calibrations: Sequence[ChannelCalibration] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return (degC, open mask) for card EMFs in volts: cold-junction compensated, calibrated; NaN where open."""
    v = np.asarray(volts, dtype=float)
    over = ~np.isfinite(v) | (np.abs(v) >= OVER_RANGE_V)
    total_mv = np.where(over, np.nan, v * 1e3) + float(type_e_emf_mv(cold_junction_c))
    t_raw = type_e_temperature_c(total_mv)
    open_mask = over | ~np.isfinite(t_raw)
    if calibrations is not None:
        slopes = np.array([c.slope for c in calibrations])
        offsets = np.array([c.offset_c for c in calibrations])
        t_raw = slopes * t_raw + offsets
    return np.where(open_mask, np.nan, t_raw), open_mask


def card_block_to_temperature(
    volts: np.ndarray, cold_junction_c: np.ndarray, calibrations: Sequence[ChannelCalibration] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return (degC, open mask) for a block of scans: volts (n, c), one cold junction (degC) per scan."""
    v = np.asarray(volts, dtype=float)
    over = ~np.isfinite(v) | (np.abs(v) >= OVER_RANGE_V)
    e_cj = type_e_emf_mv(np.asarray(cold_junction_c, dtype=float))[:, None]
    total_mv = np.where(over, np.nan, v * 1e3) + e_cj
    t_raw = type_e_temperature_c(total_mv)
    open_mask = over | ~np.isfinite(t_raw)
    if calibrations is not None:
        slopes = np.array([c.slope for c in calibrations])
        offsets = np.array([c.offset_c for c in calibrations])
        t_raw = slopes * t_raw + offsets
    return np.where(open_mask, np.nan, t_raw), open_mask


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError("not a finite number")
    return value


class ThermocoupleCard:
    """A DAS-TC style type E scanner on a line channel; satisfies TemperatureScanner."""

    def __init__(
        self,
        channel: LineChannel,
        channel_map: Mapping[int, str],
        calibrations: Mapping[str, ChannelCalibration] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not channel_map:
            raise ValidationError("thermocouple card needs at least one channel")
        if len(channel_map) > MAX_CHANNELS or any(not 0 <= k < MAX_CHANNELS for k in channel_map):
            raise ValidationError(f"thermocouple card channels must be 0..{MAX_CHANNELS - 1}")
        if len(set(channel_map.values())) != len(channel_map):
            raise ValidationError("thermocouple channel names must be unique")
        self._io = channel
        self._map = dict(sorted(channel_map.items()))
        self._cal = dict(calibrations or {})
        unknown = set(self._cal) - set(self._map.values())
        if unknown:
            raise ValidationError(f"calibration for unknown channel(s): {', '.join(sorted(unknown))}")
        self._clock = clock
        self._first = min(self._map)
        self._last = max(self._map)
        self._interval_s: float | None = None  # the pacer's interval once pace() was sent

    @classmethod
    def open(
        cls,
        address: str,
        channel_map: Mapping[int, str],
        calibrations: Mapping[str, ChannelCalibration] | None = None,
        timeout_s: float = 2.0,
        policy: RetryPolicy | None = None,
    ) -> ThermocoupleCard:
        """Return a card on a VISA resource name or a serial device/URL."""
        channel = LineChannel(open_port(address, timeout_s), "thermocouple card", policy)
        return cls(channel, channel_map, calibrations)

    def close(self) -> None:
        """Release the card's port."""
        self._io.close()

    @property
    def channels(self) -> Sequence[str]:
        """Return the channel names in card order."""
        return list(self._map.values())

    def cold_junction_c(self) -> float:
        """Return the card's cold-junction temperature (degC), validated to a plausible range."""

        def parse(text: str) -> float:
            value = _parse_float(text)
            if not -50.0 <= value <= 100.0:
                raise ValueError("cold junction out of range")
            return value

        return self._io.query("CJC?", parse)

    def read_volts(self) -> np.ndarray:
        """Return the raw EMFs (V) of channels first..last as the card reports them."""
        n = self._last - self._first + 1

        def parse(text: str) -> np.ndarray:
            fields = text.split(",")
            if len(fields) != n:
                raise ValueError(f"expected {n} values, got {len(fields)}")
            return np.array([float(f) for f in fields])

        return self._io.query(f"SCAN? {self._first},{self._last}", parse)

    def scan(self) -> TemperatureScan:
        """Return one scan: calibrated degC per channel, open thermocouples as NaN flagged open."""
        t_s = self._clock()
        cj = self.cold_junction_c()
        volts = self.read_volts()
        idx = np.array(list(self._map)) - self._first
        names = list(self._map.values())
        cals = [self._cal.get(name, ChannelCalibration()) for name in names]
        temps, open_mask = card_emf_to_temperature(volts[idx], cj, cals)
        values = {name: float(temps[i]) for i, name in enumerate(names)}
        flags = {name: FLAG_OPEN for i, name in enumerate(names) if open_mask[i]}
        return TemperatureScan(t_s=t_s, values=values, flags=flags)

    def pace(self, interval_s: float) -> None:
        """Start the card's pacer: scan k is taken at k * interval_s and kept in the card's buffer."""
        if not (math.isfinite(interval_s) and interval_s > 0):
            raise ValidationError("the pacer interval must be a positive number of seconds")
        self._io.command(f"PACE {float(interval_s)!r}")
        self._interval_s = float(interval_s)

    def read_block(self, first_index: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Return (cold junction degC (n,), EMFs V (n, last - first + 1)) of buffered scans first_index.."""
        width = self._last - self._first + 2

        def parse(text: str) -> tuple[np.ndarray, np.ndarray]:
            k_s, n_s, data = text.split(",", 2)
            if (int(k_s), int(n_s)) != (first_index, n):
                raise ValueError(f"reply is for scans {k_s}+{n_s}")
            if len(data) != 16 * n * width:
                raise ValueError(f"expected {n} x {width} values, got {len(data) / 16:g}")
            block = np.frombuffer(bytes.fromhex(data), dtype=">f8").reshape(n, width).astype(float)
            cj = block[:, 0]
            if not (np.isfinite(block).all() and ((cj >= -50.0) & (cj <= 100.0)).all()):
                raise ValueError("cold junction out of range")
            return cj, block[:, 1:]

        return self._io.query(f"FETC? {self._first},{self._last},{first_index},{n}", parse)

    def scan_block(self, first_index: int, n: int) -> ScanBlock:
        """Return buffered scans first_index..first_index + n - 1: calibrated degC, open junctions NaN."""
        interval = self._interval_s
        if interval is None:
            raise ValidationError("thermocouple card: call pace(interval_s) before reading blocks")
        if n < 1:
            raise ValidationError("a block holds at least one scan")
        cj, volts = self.read_block(first_index, n)
        idx = np.array(list(self._map)) - self._first
        names = tuple(self._map.values())
        cals = [self._cal.get(name, ChannelCalibration()) for name in names] if self._cal else None
        temps, open_mask = card_block_to_temperature(volts[:, idx], cj, cals)
        return ScanBlock(first_index, np.arange(first_index, first_index + n) * interval, names, temps, open_mask)
