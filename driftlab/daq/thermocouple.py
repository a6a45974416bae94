"""Thermocouple card (thesis ch. 5.3, appendix B): EMF to degC for types E, J, K, T, cold junction, calibration.

Conversion follows the NIST ITS-90 thermocouple reference functions, NIST Monograph 175 (1993).
Types J, K and T (:data:`TYPES`, :func:`emf_mv`, :func:`temperature_c`) use the published forward
pieces (type K with its exponential term above 0 degC) and inverse polynomials refined by two
Newton steps on the forward function. Type E (chromel-constantan), the thesis card's type:

* forward  E(t) = sum c_i t^i   (mV, t in degC), two ranges -270..0 and 0..1000 degC;
* inverse  t(E) = sum d_i E^i   (degC, E in mV), -8.825..0 mV and 0..76.373 mV,
  refined here by one Newton step on the forward function so that the inverse agrees
  with the reference function to well under 1 mK instead of the +-0.02 degC of the
  bare inverse polynomial.

Cold-junction compensation: the card measures E_meas = E(t_hot) - E(t_cj); the hot
junction's EMF is E_total = E_meas + E(t_cj), then inverted.  Per-channel calibration
(appendix B) scales and shifts the result: t = slope * t_raw + offset (example:
slope 1.000414, offset -0.20638 degC).

Legacy protocol of the thesis' DAS-TC card, driftlab's own (rig driver ``thesis-tc-card``; no
instrument on the market speaks it; a shop's scanner: :mod:`driftlab.daq.keysight34970a`). Card
protocol (ASCII, one ``\\n``-terminated line each way; the simulated card in
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

# ----------------------------------------------------------------------------- types J, K, T
# NIST ITS-90 reference function coefficients, NIST Monograph 175 (1993), tables of section 6
# (as published in the NIST ITS-90 Thermocouple Database, SRD 60). Forward: E (mV) = sum c_i t^i
# (t in degC), type K above 0 degC plus a0 exp(a1 (t - a2)^2). Inverse: t = sum d_i E^i (E in mV).

# Type J (iron / copper-nickel): forward -210..760 degC and 760..1200 degC.
J_FWD_LOW = (
    0.0,
    0.503811878150e-01,
    0.304758369300e-04,
    -0.856810657200e-07,
    0.132281952950e-09,
    -0.170529583370e-12,
    0.209480906970e-15,
    -0.125383953360e-18,
    0.156317256970e-22,
)
J_FWD_HIGH = (
    0.296456256810e03,
    -0.149761277860e01,
    0.317871039240e-02,
    -0.318476867010e-05,
    0.157208190040e-08,
    -0.306913690560e-12,
)
# inverse -8.095..0 mV, 0..42.919 mV, 42.919..69.553 mV
J_INV = (
    (
        0.0,
        1.9528268e01,
        -1.2286185e00,
        -1.0752178e00,
        -5.9086933e-01,
        -1.7256713e-01,
        -2.8131513e-02,
        -2.3963370e-03,
        -8.3823321e-05,
    ),
    (0.0, 1.978425e01, -2.001204e-01, 1.036969e-02, -2.549687e-04, 3.585153e-06, -5.344285e-08, 5.099890e-10),
    (-3.11358187e03, 3.00543684e02, -9.94773230e00, 1.70276630e-01, -1.43033468e-03, 4.73886084e-06),
)
# Type K (nickel-chromium / nickel-aluminium): forward -270..0 degC and 0..1372 degC (+ exponential term).
K_FWD_NEG = (
    0.0,
    0.394501280250e-01,
    0.236223735980e-04,
    -0.328589067840e-06,
    -0.499048287770e-08,
    -0.675090591730e-10,
    -0.574103274280e-12,
    -0.310888728940e-14,
    -0.104516093650e-16,
    -0.198892668780e-19,
    -0.163226974860e-22,
)
K_FWD_POS = (
    -0.176004136860e-01,
    0.389212049750e-01,
    0.185587700320e-04,
    -0.994575928740e-07,
    0.318409457190e-09,
    -0.560728448890e-12,
    0.560750590590e-15,
    -0.320207200030e-18,
    0.971511471520e-22,
    -0.121047212750e-25,
)
K_EXP = (0.118597600000e00, -0.118343200000e-03, 0.126968600000e03)  # a0, a1, a2 (0..1372 degC only)
# inverse -5.891..0 mV, 0..20.644 mV, 20.644..54.886 mV
K_INV = (
    (
        0.0,
        2.5173462e01,
        -1.1662878e00,
        -1.0833638e00,
        -8.9773540e-01,
        -3.7342377e-01,
        -8.6632643e-02,
        -1.0450598e-02,
        -5.1920577e-04,
    ),
    (
        0.0,
        2.508355e01,
        7.860106e-02,
        -2.503131e-01,
        8.315270e-02,
        -1.228034e-02,
        9.804036e-04,
        -4.413030e-05,
        1.057734e-06,
        -1.052755e-08,
    ),
    (-1.318058e02, 4.830222e01, -1.646031e00, 5.464731e-02, -9.650715e-04, 8.802193e-06, -3.110810e-08),
)
# Type T (copper / copper-nickel): forward -270..0 degC and 0..400 degC.
T_FWD_NEG = (
    0.0,
    0.387481063640e-01,
    0.441944343470e-04,
    0.118443231050e-06,
    0.200329735540e-07,
    0.901380195590e-09,
    0.226511565930e-10,
    0.360711542050e-12,
    0.384939398830e-14,
    0.282135219250e-16,
    0.142515947790e-18,
    0.487686622860e-21,
    0.107955392700e-23,
    0.139450270620e-26,
    0.797951539270e-30,
)
T_FWD_POS = (
    0.0,
    0.387481063640e-01,
    0.332922278800e-04,
    0.206182434040e-06,
    -0.218822568460e-08,
    0.109968809280e-10,
    -0.308157587720e-13,
    0.454791352900e-16,
    -0.275129016730e-19,
)
# inverse -5.603..0 mV, 0..20.872 mV
T_INV = (
    (0.0, 2.5949192e01, -2.1316967e-01, 7.9018692e-01, 4.2527777e-01, 1.3304473e-01, 2.0241446e-02, 1.2668171e-03),
    (0.0, 2.592800e01, -7.602961e-01, 4.637791e-02, -2.165394e-03, 6.048144e-05, -7.293422e-07),
)


@dataclass(frozen=True)
class ThermocoupleType:
    """One letter type's NIST ITS-90 reference functions: forward pieces, inverse pieces and their ranges."""

    letter: str
    t_breaks: tuple[float, ...]  # degC: piece k of the forward function covers t_breaks[k]..t_breaks[k+1]
    forward: tuple[tuple[float, ...], ...]
    mv_breaks: tuple[float, ...]  # mV: inverse piece k covers mv_breaks[k]..mv_breaks[k+1]
    inverse: tuple[tuple[float, ...], ...]
    exponential: tuple[float, float, float] | None = None  # type K above 0 degC

    def _pieces(self, x: np.ndarray, breaks: tuple[float, ...]) -> np.ndarray:
        return np.clip(np.searchsorted(np.asarray(breaks[1:-1]), x, side="right"), 0, len(breaks) - 2)

    def emf_mv(self, t_c: float | np.ndarray) -> np.ndarray:
        """Return the reference EMF (mV, reference junction at 0 degC) at ``t_c`` degC."""
        t = np.asarray(t_c, dtype=float)
        lo, hi = self.t_breaks[0], self.t_breaks[-1]
        if np.any((t < lo) | (t > hi)):
            raise ValidationError(f"type {self.letter} reference function is defined for {lo:g}..{hi:g} degC")
        return self._forward(t)

    def _forward(self, t: np.ndarray) -> np.ndarray:
        k = self._pieces(t, self.t_breaks)
        out = np.zeros(t.shape)
        for i, coeffs in enumerate(self.forward):
            sel = k == i
            if np.any(sel):
                out = np.where(sel, _poly(coeffs, t), out)
        if self.exponential is not None:  # NIST type K: + a0 exp(a1 (t - a2)^2) for t >= 0
            a0, a1, a2 = self.exponential
            out = out + np.where(t >= 0.0, a0 * np.exp(a1 * (t - a2) ** 2), 0.0)
        return out

    def _slope(self, t: np.ndarray) -> np.ndarray:
        k = self._pieces(t, self.t_breaks)
        out = np.zeros(t.shape)
        for i, coeffs in enumerate(self.forward):
            der = np.polynomial.polynomial.polyder(np.asarray(coeffs))
            out = np.where(k == i, _poly(der, t), out)
        if self.exponential is not None:
            a0, a1, a2 = self.exponential
            out = out + np.where(t >= 0.0, a0 * np.exp(a1 * (t - a2) ** 2) * 2.0 * a1 * (t - a2), 0.0)
        return out

    def temperature_c(self, emf_mv: float | np.ndarray) -> np.ndarray:
        """Return degC for an EMF in mV: NIST inverse polynomial refined by two Newton steps; NaN out of range."""
        e = np.asarray(emf_mv, dtype=float)
        inside = np.isfinite(e) & (e >= self.mv_breaks[0]) & (e <= self.mv_breaks[-1])
        ec = np.where(inside, e, 0.0)
        k = self._pieces(ec, self.mv_breaks)
        t = np.zeros(ec.shape)
        for i, coeffs in enumerate(self.inverse):
            t = np.where(k == i, _poly(coeffs, ec), t)
        lo, hi = self.t_breaks[0], self.t_breaks[-1]
        # Newton steps on the forward reference function remove the inverse's +-0.05 degC approximation
        for _ in range(2):
            t = np.clip(t - (self._forward(np.clip(t, lo, hi)) - ec) / self._slope(np.clip(t, lo, hi)), lo, hi)
        return np.where(inside, t, np.nan)


TYPES: dict[str, ThermocoupleType] = {
    "E": ThermocoupleType(
        "E", (-270.0, 0.0, 1000.0), (E_FWD_NEG, E_FWD_POS), (E_MV_MIN, 0.0, E_MV_MAX), (E_INV_NEG, E_INV_POS)
    ),
    "J": ThermocoupleType("J", (-210.0, 760.0, 1200.0), (J_FWD_LOW, J_FWD_HIGH), (-8.095, 0.0, 42.919, 69.553), J_INV),
    "K": ThermocoupleType(
        "K", (-270.0, 0.0, 1372.0), (K_FWD_NEG, K_FWD_POS), (-5.891, 0.0, 20.644, 54.886), K_INV, K_EXP
    ),
    "T": ThermocoupleType("T", (-270.0, 0.0, 400.0), (T_FWD_NEG, T_FWD_POS), (-5.603, 0.0, 20.872), T_INV),
}


def thermocouple_type(letter: str) -> ThermocoupleType:
    """Return the reference functions of type ``letter`` (E, J, K or T); ValidationError otherwise."""
    try:
        return TYPES[str(letter).upper()]
    except KeyError:
        raise ValidationError(f"thermocouple type {letter!r} is not one of {' '.join(TYPES)}") from None


def emf_mv(letter: str, t_c: float | np.ndarray) -> np.ndarray:
    """Return the NIST ITS-90 reference EMF (mV) of type ``letter`` at ``t_c`` degC."""
    return thermocouple_type(letter).emf_mv(t_c)


def temperature_c(letter: str, emf: float | np.ndarray) -> np.ndarray:
    """Return degC for an EMF (mV) of type ``letter``; NaN outside the inverse function's range."""
    return thermocouple_type(letter).temperature_c(emf)


def _poly(coeffs: Sequence[float] | np.ndarray, x: np.ndarray) -> np.ndarray:
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


def _conversions(tc_type: str) -> tuple[Callable[..., np.ndarray], Callable[..., np.ndarray]]:
    """Return (forward, inverse) of a type; type E keeps its own vectorised two-piece path."""
    if str(tc_type).upper() == "E":
        return type_e_emf_mv, type_e_temperature_c
    kind = thermocouple_type(tc_type)
    return kind.emf_mv, kind.temperature_c


def card_emf_to_temperature(
    volts: np.ndarray,
    cold_junction_c: float,
    calibrations: Sequence[ChannelCalibration] | None = None,
    tc_type: str = "E",
) -> tuple[np.ndarray, np.ndarray]:
    """Return (degC, open mask) for card EMFs in volts: cold-junction compensated, calibrated; NaN where open."""
    forward, _ = _conversions(tc_type)
    return _compensated(volts, float(forward(cold_junction_c)), calibrations, tc_type)


def card_block_to_temperature(
    volts: np.ndarray,
    cold_junction_c: np.ndarray,
    calibrations: Sequence[ChannelCalibration] | None = None,
    tc_type: str = "E",
) -> tuple[np.ndarray, np.ndarray]:
    """Return (degC, open mask) for a block of scans: volts (n, c), one cold junction (degC) per scan."""
    forward, _ = _conversions(tc_type)
    return _compensated(volts, forward(np.asarray(cold_junction_c, dtype=float))[:, None], calibrations, tc_type)


def _compensated(
    volts: np.ndarray,
    e_cj_mv: float | np.ndarray,
    calibrations: Sequence[ChannelCalibration] | None,
    tc_type: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Return (degC, open mask) of EMFs (V) whose cold junction's EMF is `e_cj_mv`: calibrated, NaN where open."""
    _, inverse = _conversions(tc_type)
    v = np.asarray(volts, dtype=float)
    over = ~np.isfinite(v) | (np.abs(v) >= OVER_RANGE_V)
    # cold-junction compensation: E(t_hot) = E_measured + E(t_cj) (NIST Monograph 175, section 2)
    total_mv = np.where(over, np.nan, v * 1e3) + e_cj_mv
    t_raw = inverse(total_mv)
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


def block_interval(who: str, interval_s: float | None, n: int) -> float:
    """Return the pacing interval of a block read of ``n`` scans; ValidationError before ``pace`` or for n < 1."""
    if interval_s is None:
        raise ValidationError(f"{who}: call pace(interval_s) before reading blocks")
    if n < 1:
        raise ValidationError("a block holds at least one scan")
    return interval_s


class ThermocoupleCard:
    """The thesis' DAS-TC card (legacy protocol; type E by default, J, K, T too): a TemperatureScanner."""

    def __init__(
        self,
        channel: LineChannel,
        channel_map: Mapping[int, str],
        calibrations: Mapping[str, ChannelCalibration] | None = None,
        clock: Callable[[], float] = time.monotonic,
        tc_type: str = "E",
    ) -> None:
        self.tc_type = thermocouple_type(tc_type).letter
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
        tc_type: str = "E",
    ) -> ThermocoupleCard:
        """Return a card on a VISA resource name or a serial device/URL."""
        thermocouple_type(tc_type)  # refuse an unknown type before opening the port
        channel = LineChannel(open_port(address, timeout_s), "thermocouple card", policy)
        return cls(channel, channel_map, calibrations, tc_type=tc_type)

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
        temps, open_mask = card_emf_to_temperature(volts[idx], cj, cals, self.tc_type)
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
        interval = block_interval("thermocouple card", self._interval_s, n)
        cj, volts = self.read_block(first_index, n)
        idx = np.array(list(self._map)) - self._first
        names = tuple(self._map.values())
        cals = [self._cal.get(name, ChannelCalibration()) for name in names] if self._cal else None
        temps, open_mask = card_block_to_temperature(volts[:, idx], cj, cals, self.tc_type)
        return ScanBlock(first_index, np.arange(first_index, first_index + n) * interval, names, temps, open_mask)
