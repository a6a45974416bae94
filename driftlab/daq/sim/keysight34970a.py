"""A simulated Keysight/Agilent 34970A answering its SCPI command set from the virtual machine.

Written from the same pages as the driver (Agilent 34970A/34972A User's Guide ch. 4 and 5), and
answering what the guide says the mainframe answers, so that :mod:`driftlab.daq.keysight34970a`
- the driver a shop uses - is what the simulated campaign drives:

* headers in short or long form, any case, ``;``-separated, the optional ``SENSe:`` node;
* ``CONF:TEMP TC,<type>,(@list)``, ``CONF:VOLT:DC [range,](@list)`` (each redefines the scan
  list and clears reading memory), ``UNIT:TEMP``, ``TEMP:TRAN:TC:RJUN:TYPE``, ``:RJUN``,
  ``:CHEC``, ``ROUT:SCAN`` / ``ROUT:SCAN?`` (definite-length block ``#214(@101,102,103)``),
  ``TRIG:SOUR`` / ``:TIM`` / ``:COUN``, ``INIT``, ``ABOR``, ``READ?``, ``FETC?``, ``DATA:POIN?``,
  ``DATA:REM? <n>``, ``SYST:ERR?``, ``*IDN?``, ``*RST``, ``*CLS``;
* errors go to the queue (``-113,"Undefined header"``, ``-222,"Data out of range"``, ...) and a
  query that fails sends nothing, as on the instrument;
* the physics of the reference junction: with ``FIX`` the mainframe assumes the junction is at the
  temperature it was given while the terminal block is really at ``terminal_c``, so the reading is
  off by the difference (through the NIST functions), as a real wrongly-set fixed junction is;
  an open thermocouple reads the overload ``+9.90000000E+37`` with the check on; ``EXT`` without a
  stored reference reads the overload too (the guide: the register powers on at 9.9E+37).

The timer scan (``TRIG:SOUR TIM``) takes sweep k at ``t_INIT + k x interval`` of the shared clock
and keeps the readings in a 50,000-reading memory (oldest overwritten), evaluated lazily and
vectorised over the world when they are removed.
"""

from __future__ import annotations

import math
import re
from collections import deque
from collections.abc import Callable, Mapping
from typing import ClassVar

import numpy as np

from driftlab.daq.sim.instruments import Clock, LineServer, World
from driftlab.daq.thermocouple import TYPES

KEYWORDS = (
    "ABORt ALARm CHANnel CHECk CLEar CONFigure COUNt DATA DC ERRor FETCh FORMat INITiate MEASure POINts READ "
    "READing REMove RJUNction ROUTe SCAN SENSe SIZE SOURce SYSTem TCouple TEMPerature TIME TIMer TRANsducer TRIGger "
    "TYPE UNIT VOLTage"
).split()
_SHORT = {}
for _k in KEYWORDS:
    short = "".join(ch for ch in _k if ch.isupper())
    _SHORT[short] = short
    _SHORT[_k.upper()] = short

MEMORY_READINGS = 50_000
OVERLOAD = 9.9e37
TC_TYPES = ("B", "E", "J", "K", "N", "R", "S", "T")
_RJ = {"INT": "INT", "INTERNAL": "INT", "EXT": "EXT", "EXTERNAL": "EXT", "FIX": "FIX", "FIXED": "FIX"}


def format_readings(values: np.ndarray) -> str:
    """Return readings in the mainframe's form ``+2.13450000E+01,...`` (``{:+.8E}`` of each), built at once."""
    x = np.asarray(values, dtype=float).ravel()
    if x.size == 0:
        return ""
    ax = np.abs(x)
    exp = np.where(ax > 0, np.floor(np.log10(np.where(ax > 0, ax, 1.0))), 0).astype(np.int64)
    digits = np.rint(ax / 10.0 ** (exp - 8)).astype(np.int64)
    carry = digits >= 1_000_000_000  # 9.999999996 rounds up to 10.00000000
    exp, digits = np.where(carry, exp + 1, exp), np.where(carry, digits // 10, digits)
    small = (digits < 100_000_000) & (ax > 0)  # log10 rounding just below a power of ten
    exp, digits = np.where(small, exp - 1, exp), np.where(small, np.rint(ax / 10.0 ** (exp - 9)), digits)
    digits = digits.astype(np.int64)
    out = np.empty((x.size, 16), dtype=np.uint8)
    out[:, 0] = np.where(np.signbit(x), 45, 43)
    # the nine mantissa digits, last first, one integer division each (a division by a constant, where the
    # remainder by one was as slow again): 0.45 -> 0.23 ms a block of 10,000 readings (the server's share)
    cols, q = np.empty((9, x.size), dtype=np.int64), digits
    for k in range(8, -1, -1):
        nq = q // 10
        cols[k] = q - nq * 10
        q = nq
    cols += 48
    out[:, 1], out[:, 3:11] = cols[0], cols[1:].T
    out[:, 2], out[:, 11], out[:, 15] = 46, 69, 44
    out[:, 12] = np.where(exp < 0, 45, 43)
    out[:, 13] = 48 + (np.abs(exp) // 10) % 10
    out[:, 14] = 48 + np.abs(exp) % 10
    return out.tobytes()[:-1].decode("ascii")


class ScpiError(Exception):
    """A command error: its code and message go to the error queue."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code, self.message = code, message


def normalise_header(header: str) -> str:
    """Return a SCPI header in short form (``SENSe:TEMPerature:...`` -> ``TEMP:...``); ScpiError -113 if unknown."""
    if header.startswith("*"):  # IEEE 488.2 common commands
        if header.upper() in ("*IDN?", "*RST", "*CLS", "*OPC?", "*OPC"):
            return header.upper()
        raise ScpiError(-113, "Undefined header")
    query = header.endswith("?")
    body = header[:-1] if query else header
    words = []
    for word in body.lstrip(":").split(":"):
        short = _SHORT.get(re.sub(r"\d+$", "", word).upper())
        if short is None:
            raise ScpiError(-113, "Undefined header")
        words.append(short)
    if words and words[0] == "SENS":
        words = words[1:]
    return ":".join(words) + ("?" if query else "")


def parse_channel_list(text: str) -> list[int]:
    """Return the channels of ``(@101:103,110)``; ScpiError -222 for a malformed list."""
    m = re.fullmatch(r"\(@([\d:,\s]*)\)", text.strip())
    if not m:
        raise ScpiError(-222, "Data out of range")
    out: list[int] = []
    for part in filter(None, (p.strip() for p in m.group(1).split(","))):
        lo, _, hi = part.partition(":")
        a, b = int(lo), int(hi or lo)
        if a > b or not all(1 <= c // 100 <= 3 and 1 <= c % 100 <= 22 for c in (a, b)) or a // 100 != b // 100:
            raise ScpiError(-222, "Data out of range")
        out.extend(range(a, b + 1))
    return sorted(set(out))


def split_params(text: str) -> tuple[list[str], list[int] | None]:
    """Return (plain parameters, channel list or None) of a parameter string."""
    chans = None
    m = re.search(r"\(@[^)]*\)", text)
    if m:
        chans = parse_channel_list(m.group(0))
        text = text[: m.start()] + text[m.end() :]
    params = [p.strip() for p in text.split(",") if p.strip()]
    return params, chans


class Sim34970A(LineServer):
    """A 34970A mainframe with 34901A multiplexers whose thermocouples and volt inputs read a World."""

    name = "34970a"

    def __init__(
        self,
        world: World,
        clock: Clock,
        channel_map: Mapping[int, str] | None = None,
        model: str = "34970A",
        terminal_c: float = 24.0,
        noise_c: float = 0.0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.world, self.clock = world, clock
        self.channel_map = dict(channel_map or {})
        self.model = model
        self.terminal_c = terminal_c
        self.noise_c = noise_c
        self._rng = np.random.default_rng(seed)
        self.errors: deque[tuple[int, str]] = deque(maxlen=10)
        self._sources: list[tuple[list[int], Callable[[float], np.ndarray]]] = []
        self.reset()

    # -- state
    def reset(self) -> None:
        """Return to the factory state (``*RST``)."""
        self.function: dict[int, tuple[str, str]] = {}  # channel -> ("TEMP", type) | ("VOLT", range)
        self.rjun_type: dict[int, str] = {}
        self.rjun_c: dict[int, float] = {}
        self.check: dict[int, bool] = {}
        self.unit = "C"
        self.scan_list: list[int] = []
        self.trig_source = "IMM"
        self.trig_timer_s = 1.0
        self.trig_count: float = 1.0
        self._t0: float | None = None  # time of INIT
        self._removed = 0  # readings removed (or overwritten) since INIT
        self._frozen: int | None = None  # scans taken when ABORt stopped the run

    def wire(self, channels: list[int], source: Callable[[float], np.ndarray]) -> None:
        """Connect voltage sensors to ``channels`` (34970A channel numbers); ``source(t)`` gives their volts."""
        self._sources.append((list(channels), source))

    def voltages(self, t: float) -> np.ndarray:
        """Return the DC volts of the scan list's volt channels at ``t`` (unwired channels 0 V)."""
        return self._volts_at([c for c in self.scan_list if self.function.get(c, ("", ""))[0] == "VOLT"], t)

    def unwire(self) -> None:
        """Disconnect every voltage sensor (their channels read 0 V)."""
        self._sources.clear()

    def _clear_memory(self) -> None:
        self._t0, self._removed, self._frozen = None, 0, None

    # -- measurement
    def _sweeps(self, times: np.ndarray) -> np.ndarray:
        """Return the readings (n, channels) of the scan list at ``times``, in the configured unit."""
        chans = self.scan_list
        out = np.zeros((times.size, len(chans)))
        tc = [i for i, c in enumerate(chans) if self.function.get(c, ("", ""))[0] == "TEMP"]
        if tc:
            names = [self.channel_map.get(chans[i], "") for i in tc]
            block = getattr(self.world, "temperatures_block", None)
            if callable(block):
                temps = np.asarray(block(times, names), dtype=float)
            else:
                temps = np.array([[self.world.temperatures(t).get(n, math.nan) for n in names] for t in times.tolist()])
            if self.noise_c:
                temps = temps + self.noise_c * self._rng.standard_normal(temps.shape)
            out[:, tc] = self._thermocouples([chans[i] for i in tc], temps)
        volt = [i for i, c in enumerate(chans) if self.function.get(c, ("", ""))[0] == "VOLT"]
        if volt:
            for row, t in enumerate(times.tolist()):
                out[row, volt] = self._volts_at([chans[i] for i in volt], t)
        return out

    def _thermocouples(self, channels: list[int], true_c: np.ndarray) -> np.ndarray:
        """Return what the mainframe reports for junctions at ``true_c`` (scans x ``channels``): RJ physics,
        open check, unit; every channel at once but a fixed junction's (its own conversion, column by column)."""
        open_ = ~np.isfinite(true_c) | (true_c < -200.0) | (true_c > 1000.0)
        t = np.where(open_, self.terminal_c, true_c)
        rjs = [self.rjun_type.get(c, "FIX") for c in channels]
        for col, (channel, rj) in enumerate(zip(channels, rjs, strict=True)):
            tc_type = self.function[channel][1]
            if rj == "FIX" and tc_type in TYPES:
                kind = TYPES[tc_type]
                col_t = np.ascontiguousarray(t[:, col])  # the column alone, as it was converted one channel a call
                emf = kind.emf_mv(col_t) - kind.emf_mv(self.terminal_c) + kind.emf_mv(self.rjun_c.get(channel, 0.0))
                t[:, col] = kind.temperature_c(emf)
        if self.unit == "F":
            t = t * 9.0 / 5.0 + 32.0
        elif self.unit == "K":
            t = t + 273.15
        check = np.array([self.check.get(c, False) for c in channels], dtype=bool)
        external = np.array([rj == "EXT" for rj in rjs], dtype=bool)
        bad = (open_ & check) | external | ~np.isfinite(t)
        return np.where(bad, OVERLOAD, t)

    def _volts_at(self, channels: list[int], t: float) -> np.ndarray:
        """Return the volts of ``channels`` at ``t``: each wired source evaluated once, unwired channels 0 V."""
        out = np.zeros(len(channels))
        for wired, source in self._sources:
            hit = [(i, wired.index(c)) for i, c in enumerate(channels) if c in wired]
            if hit:
                v = np.asarray(source(t), dtype=float)
                for i, j in hit:
                    out[i] = v[j]
        return out

    def _taken(self, now: float) -> int:
        """Return the sweeps taken since INIT by ``now``."""
        if self._t0 is None:
            return 0
        if self._frozen is not None:
            return self._frozen
        n: float = math.inf
        if self.trig_source == "TIM":
            n = math.floor((now - self._t0) / self.trig_timer_s + 1e-9) + 1
        return int(max(0, min(n, self.trig_count)))

    def _readings(self, r0: int, r1: int) -> np.ndarray:
        """Return readings r0..r1-1 of the run (reading r is sweep r // channels, channel r % channels)."""
        width = len(self.scan_list)
        s0, s1 = r0 // width, (r1 - 1) // width + 1
        assert self._t0 is not None
        step = self.trig_timer_s if self.trig_source == "TIM" else 0.0
        times = self._t0 + np.arange(s0, s1) * step
        return self._sweeps(times).ravel()[r0 - s0 * width : r1 - s0 * width]

    def _memory(self) -> tuple[int, int]:
        """Return (first, end) reading numbers held in memory now (oldest overwritten past 50,000)."""
        end = self._taken(self.clock.now()) * len(self.scan_list)
        self._removed = max(self._removed, end - MEMORY_READINGS)
        return self._removed, end

    @staticmethod
    def _format(values: np.ndarray) -> str:
        return format_readings(values)

    # -- the command set
    def handle(self, line: str) -> str | None:
        """Answer one line of ``;``-separated SCPI commands (replies of several queries joined by ``;``)."""
        replies: list[str] = []
        for command in filter(None, (c.strip() for c in line.split(";"))):
            header, _, arg = command.partition(" ")
            try:
                reply = self._command(normalise_header(header), arg.strip())
            except ScpiError as exc:
                self.errors.append((exc.code, exc.message))
                return ";".join(replies) if replies else None
            if reply is not None:
                replies.append(reply)
        return ";".join(replies) if replies else None

    def _command(self, head: str, arg: str) -> str | None:
        """Answer one command (header without its parameters, and its parameter string)."""
        params, chans = split_params(arg)
        handler = self._HANDLERS.get(head)
        if handler is None:
            raise ScpiError(-113, "Undefined header")
        return handler(self, head, params, chans)

    def _session(self, head: str, params: list[str], chans: list[int] | None) -> str | None:
        """Answer a command of the session: identification, reset, the error queue."""
        if head == "*IDN?":
            return f"Agilent Technologies,{self.model},0,13-2-2"
        if head in ("*RST", "*CLS"):
            if head == "*RST":
                self.reset()
            self.errors.clear()
            return None
        if head == "SYST:ERR?":
            code, msg = self.errors.popleft() if self.errors else (0, "No error")
            return f'{code:+d},"{msg}"'
        raise ScpiError(-113, "Undefined header")

    def _configure(self, head: str, params: list[str], chans: list[int] | None) -> str | None:
        """Answer a channel configuration command: function (thermocouple, DC volts), unit, junction, check."""
        if head == "CONF:TEMP":
            if len(params) < 2 or params[0].upper() not in ("TC", "TCOUPLE") or not chans:
                if len(params) < 2:
                    raise ScpiError(-109, "Missing parameter")
                raise ScpiError(-224, "Illegal parameter value")
            tc_type = params[1].upper()
            if tc_type not in TC_TYPES:
                raise ScpiError(-224, "Illegal parameter value")
            for c in chans:
                self.function[c] = ("TEMP", tc_type)
                self.rjun_type.setdefault(c, "FIX")
                self.check.setdefault(c, False)
            self.scan_list = chans
            self._clear_memory()
            return None
        if head == "CONF:VOLT:DC":
            if not chans:
                raise ScpiError(-109, "Missing parameter")
            rng = params[0].upper() if params else "DEF"
            if rng not in ("AUTO", "DEF", "MIN", "MAX"):
                try:
                    float(rng)
                except ValueError:
                    raise ScpiError(-224, "Illegal parameter value") from None
            for c in chans:
                self.function[c] = ("VOLT", rng)
            self.scan_list = chans
            self._clear_memory()
            return None
        if head == "UNIT:TEMP":
            unit = params[0].upper() if params else ""
            if unit not in ("C", "CEL", "F", "FAR", "K"):
                raise ScpiError(-224, "Illegal parameter value")
            self.unit = unit[0]
            return None
        if head in ("TEMP:TRAN:TC:RJUN:TYPE", "TEMP:TRAN:TC:RJUN", "TEMP:TRAN:TC:CHEC"):
            if not params or not chans:
                raise ScpiError(-109, "Missing parameter")
            if any(self.function.get(c, ("", ""))[0] != "TEMP" for c in chans):
                raise ScpiError(-221, "Settings conflict")
            value = params[0].upper()
            for c in chans:
                if head.endswith("TYPE"):
                    if value not in _RJ:
                        raise ScpiError(-224, "Illegal parameter value")
                    self.rjun_type[c] = _RJ[value]
                elif head.endswith("CHEC"):
                    if value not in ("ON", "OFF", "1", "0"):
                        raise ScpiError(-224, "Illegal parameter value")
                    self.check[c] = value in ("ON", "1")
                else:
                    try:
                        t = float(value)
                    except ValueError:
                        raise ScpiError(-224, "Illegal parameter value") from None
                    if not -20.0 <= t <= 80.0:
                        raise ScpiError(-222, "Data out of range")
                    self.rjun_c[c] = t
            self._clear_memory()
            return None
        raise ScpiError(-113, "Undefined header")

    def _scan(self, head: str, params: list[str], chans: list[int] | None) -> str | None:
        """Answer a command of the scan list and the trigger system (immediate or timer scan)."""
        if head == "ROUT:SCAN":
            if chans is None:
                raise ScpiError(-109, "Missing parameter")
            if any(c not in self.function for c in chans):
                raise ScpiError(-221, "Settings conflict")
            self.scan_list = chans
            self._clear_memory()
            return None
        if head == "ROUT:SCAN?":
            body = "(@" + ",".join(str(c) for c in self.scan_list) + ")"
            return f"#{len(str(len(body)))}{len(body)}{body}"
        if head == "TRIG:SOUR":
            src = params[0].upper() if params else ""
            table = {"IMM": "IMM", "IMMEDIATE": "IMM", "TIM": "TIM", "TIMER": "TIM", "BUS": "BUS"}
            if src not in table:
                raise ScpiError(-224, "Illegal parameter value")
            self.trig_source = table[src]
            self._clear_memory()
            return None
        if head == "TRIG:TIM":
            try:
                timer_s = float(params[0])
            except (IndexError, ValueError):
                raise ScpiError(-224, "Illegal parameter value") from None
            if not 0.0 <= timer_s <= 359_999.0:
                raise ScpiError(-222, "Data out of range")
            self.trig_timer_s = round(timer_s, 3)
            self._clear_memory()
            return None
        if head == "TRIG:COUN":
            value_s = params[0].upper() if params else ""
            if value_s in ("INF", "INFINITY"):
                self.trig_count = math.inf
            else:
                try:
                    count = int(float(value_s))
                except ValueError:
                    raise ScpiError(-224, "Illegal parameter value") from None
                if not 1 <= count <= 50_000:
                    raise ScpiError(-222, "Data out of range")
                self.trig_count = float(count)
            self._clear_memory()
            return None
        if head == "INIT":
            if not self.scan_list:
                raise ScpiError(-221, "Settings conflict")
            self._clear_memory()
            self._t0 = self.clock.now()
            return None
        if head == "ABOR":
            if self._t0 is not None:
                self._frozen = self._taken(self.clock.now())
            return None
        raise ScpiError(-113, "Undefined header")

    def _data(self, head: str, params: list[str], chans: list[int] | None) -> str | None:
        """Answer a command of readings: a triggered READ?, and the timer scan's reading memory."""
        if head == "READ?":
            if not self.scan_list:
                raise ScpiError(-221, "Settings conflict")
            if self.trig_source != "IMM" or math.isinf(self.trig_count):
                raise ScpiError(-214, "Trigger deadlock")
            now = self.clock.now()
            return self._format(self._sweeps(np.full(int(self.trig_count), now)).ravel())
        if head == "FETC?":
            first, end = self._memory()
            if end == 0:
                raise ScpiError(-230, "Data stale")
            return self._format(self._readings(first, end))
        if head == "DATA:POIN?":
            first, end = self._memory()
            return f"{end - first:+d}"
        if head == "DATA:REM?":
            try:
                n = int(params[0])
            except (IndexError, ValueError):
                raise ScpiError(-109, "Missing parameter") from None
            first, end = self._memory()
            if not 1 <= n <= end - first:
                raise ScpiError(-222, "Data out of range")
            self._removed = first + n
            return self._format(self._readings(first, first + n))
        raise ScpiError(-113, "Undefined header")

    #: command header -> the method that answers it
    _HANDLERS: ClassVar[dict[str, Callable[[Sim34970A, str, list[str], list[int] | None], str | None]]] = {
        "*IDN?": _session,
        "*RST": _session,
        "*CLS": _session,
        "SYST:ERR?": _session,
        "CONF:TEMP": _configure,
        "CONF:VOLT:DC": _configure,
        "UNIT:TEMP": _configure,
        "TEMP:TRAN:TC:RJUN:TYPE": _configure,
        "TEMP:TRAN:TC:RJUN": _configure,
        "TEMP:TRAN:TC:CHEC": _configure,
        "ROUT:SCAN": _scan,
        "ROUT:SCAN?": _scan,
        "TRIG:SOUR": _scan,
        "TRIG:TIM": _scan,
        "TRIG:COUN": _scan,
        "INIT": _scan,
        "ABOR": _scan,
        "READ?": _data,
        "FETC?": _data,
        "DATA:POIN?": _data,
        "DATA:REM?": _data,
    }


def mainframe_channels(n: int) -> list[int]:
    """Return the first ``n`` 34901A channels of a three-slot mainframe: 101..120, 201..220, 301..320."""
    if not 1 <= n <= 60:
        raise ValueError("a 34970A with three 34901A modules has 60 channels")
    return [100 * (1 + i // 20) + 1 + i % 20 for i in range(n)]


def sim_channel_map(names: list[str]) -> dict[int, str]:
    """Return the wiring of named thermocouples onto consecutive 34901A channels (101, 102, ... 201, ...)."""
    return dict(zip(mainframe_channels(len(names)), names, strict=True))
