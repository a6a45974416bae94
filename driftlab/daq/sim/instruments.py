"""Simulated instruments: line-protocol servers on loopback TCP that answer like the real ones.

Each server reads the state of a :class:`World` (the VirtualMachine, or the small
deterministic ``driftlab.testing.tinyworld.TinyWorld`` of the unit tests) at the time of a shared
:class:`Clock`, and speaks exactly the protocol documented in its driver module, so the
real drivers open them through the real libraries:

* thermocouple card and A/D card: any RawPort (pyvisa ``TCPIP0::127.0.0.1::PORT::SOCKET``
  or pyserial ``socket://127.0.0.1:PORT``);
* laser interferometer: pyvisa-py, ``TCPIP0::127.0.0.1::PORT::SOCKET`` (:func:`visa_address`);
* machine controller (motion code, positions, probe): pyserial, ``socket://127.0.0.1:PORT``
  (:func:`serial_url`).

Faults are injected per server with :meth:`LineServer.inject` (``"timeout"``: the reply is
swallowed; ``"garble"``: the reply is corrupted), applied after the command took effect,
as a real line fault would be.  Every server stops its threads in :meth:`LineServer.close`.
"""

from __future__ import annotations

import logging
import math
import re
import socket
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol, Self, runtime_checkable

import numpy as np

from driftlab.daq.laser import air_refractive_index, value_to_fringes
from driftlab.daq.probe import LobingMap
from driftlab.daq.proximity import ReferenceSurfaceArray
from driftlab.daq.thermocouple import type_e_emf_mv
from driftlab.vocabulary import AXES, TRANSLATIONS

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- world and clock


@runtime_checkable
class World(Protocol):
    """What the simulated instruments read: VirtualMachine and testing.tinyworld.TinyWorld satisfy it."""

    def temperatures(self, t_s: float) -> Mapping[str, float]:
        """Return degC per thermocouple channel at ``t_s`` (NaN where the junction is open)."""

    def state(self, t_s: float) -> Mapping[str, float | str | None]:
        """Return the machine state at ``t_s`` (spindle rpm, feed, positions)."""

    def measure_error(self, t_s: float, axis: str, position: float, direction: int) -> Mapping[str, float]:
        """Return the error terms (dx, dy, dz mm; alpha, beta, gamma rad) of ``axis`` at ``position``."""


@runtime_checkable
class Clock(Protocol):
    """Simulation time shared by the servers and the drivers' waits."""

    def now(self) -> float:
        """Return the simulation time (s)."""

    def sleep(self, dt_s: float) -> None:
        """Let ``dt_s`` seconds of simulation time pass."""


class ManualClock:
    """A clock that moves only when slept on: deterministic tests, no wall-clock waits."""

    def __init__(self, t0_s: float = 0.0) -> None:
        self._t = float(t0_s)
        self._lock = threading.Lock()

    def now(self) -> float:
        """Return the simulation time (s)."""
        with self._lock:
            return self._t

    def sleep(self, dt_s: float) -> None:
        """Advance the simulation time by ``dt_s`` immediately."""
        with self._lock:
            self._t += max(float(dt_s), 0.0)

    def advance_to(self, t_s: float) -> None:
        """Move the clock forward to ``t_s`` (never backwards)."""
        with self._lock:
            self._t = max(self._t, float(t_s))


class WallClock:
    """Simulation time running ``acceleration`` times faster than the wall clock (demos)."""

    def __init__(self, acceleration: float = 60.0, t0_s: float = 0.0) -> None:
        self.acceleration = acceleration
        self._t0 = t0_s
        self._start = time.monotonic()

    def now(self) -> float:
        """Return the accelerated simulation time (s)."""
        return self._t0 + (time.monotonic() - self._start) * self.acceleration

    def sleep(self, dt_s: float) -> None:
        """Wait ``dt_s`` simulation seconds (dt_s / acceleration real seconds)."""
        time.sleep(max(dt_s, 0.0) / self.acceleration)


def room_air_c(world: World, t_s: float, channels: tuple[str, ...] = ("T49", "T50")) -> float:
    """Return the air temperature along the beam: mean of the room channels (20 degC if none).

    The laser's weather station is its own sensor, so the world's true temperatures are
    used where it has them (not the thermocouple scan with its noise and faults).
    """
    true = getattr(world, "true_temperatures", None)
    temps = true(t_s) if callable(true) else world.temperatures(t_s)
    vals = [temps[c] for c in channels if c in temps and math.isfinite(temps[c])]
    return float(np.mean(vals)) if vals else 20.0


# --------------------------------------------------------------------------- stages (where the axes are)


class Stage(Protocol):
    """Where an axis is at a time, and from which direction it arrived."""

    def where(self, axis: str, t_s: float) -> tuple[float, int]:
        """Return (position, approach direction +1/-1) of ``axis`` at ``t_s``."""


class FixedStage:
    """A stage whose positions are set by hand (unit tests)."""

    def __init__(self) -> None:
        self.positions = {a: (0.0, 1) for a in AXES}

    def move(self, axis: str, position: float, direction: int = 1) -> None:
        """Place ``axis`` at ``position`` arriving from ``direction``."""
        self.positions[axis] = (float(position), int(direction))

    def where(self, axis: str, t_s: float) -> tuple[float, int]:
        """Return the position set for ``axis``."""
        return self.positions[axis]


class WorldStage:
    """A stage that follows the world's own machine state (``state(t)`` keys x, y, z, a, b)."""

    def __init__(self, world: World, lookback_s: float = 1.0) -> None:
        self.world = world
        self.lookback_s = lookback_s

    def _pos(self, axis: str, t_s: float) -> float:
        state = self.world.state(t_s)
        value = state.get(axis.lower()) if isinstance(state, Mapping) else getattr(state, axis.lower(), None)
        return float(value) if value is not None else 0.0

    def where(self, axis: str, t_s: float) -> tuple[float, int]:
        """Return the world's position of ``axis`` and the direction it was last moving in."""
        now, before = self._pos(axis, t_s), self._pos(axis, t_s - self.lookback_s)
        return now, (1 if now >= before else -1)


# --------------------------------------------------------------------------- the TCP line server


class LineServer(ABC):
    """A threaded ``\\n``-line server on 127.0.0.1 (ephemeral port); subclasses implement handle()."""

    name = "instrument"
    #: appended to every reply (a server whose replies carry their own line ends sets b"")
    terminator = b"\n"

    def __init__(self) -> None:
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(4)
        self._listener.settimeout(0.05)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._conns: list[socket.socket] = []
        self._lock = threading.RLock()
        self._faults: deque[tuple[str, str]] = deque()
        self.received: list[str] = []
        self._started = False

    @property
    def port(self) -> int:
        """Return the TCP port the server listens on."""
        return int(self._listener.getsockname()[1])

    def start(self) -> Self:
        """Start accepting connections; return self."""
        if not self._started:
            t = threading.Thread(target=self._accept_loop, name=f"sim-{self.name}-accept", daemon=True)
            t.start()
            self._threads.append(t)
            self._started = True
        return self

    def __enter__(self) -> LineServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def inject(self, *faults: str, on: str = "") -> None:
        """Queue faults for the next replies (to commands starting with ``on``): ``"timeout"``, ``"garble"``, or
        ``"drop"`` (the connection is closed instead of the reply, after the command took effect)."""
        for f in faults:
            if f not in ("timeout", "garble", "drop"):
                raise ValueError(f"unknown fault {f!r}")
            self._faults.append((f, on))

    def _take_fault(self, text: str) -> str | None:
        for i, (kind, prefix) in enumerate(self._faults):
            if text.startswith(prefix):
                del self._faults[i]
                return kind
        return None

    def on_connect(self) -> None:
        """Reset per-session state when a client connects (servers whose sessions have state override it)."""
        return None

    def drop(self) -> None:
        """Close every open connection at once (a cable pulled): the next read of the driver fails."""
        for c in list(self._conns):
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def split_frames(self, buf: bytes) -> tuple[list[bytes], bytes]:
        """Return the complete commands in ``buf`` and the bytes left over (``\\n``-terminated lines here)."""
        *frames, rest = buf.split(b"\n")
        return frames, rest

    @abstractmethod
    def handle(self, line: str) -> str | None:
        """Return the reply to one command line (None: no reply)."""

    def _reply(self, line: bytes) -> bytes | None:
        try:
            text = line.decode("ascii").strip()
        except UnicodeDecodeError:
            return b"ERR SYNTAX\n"
        with self._lock:
            self.received.append(text)
            try:
                reply = self.handle(text)
            except Exception as exc:  # a simulator bug must not kill the server thread
                log.exception("%s: handling %r failed", self.name, text)
                reply = f"ERR INTERNAL {type(exc).__name__}"
            fault = self._take_fault(text)
        if fault == "drop":
            return b""
        if reply is None or fault == "timeout":
            return None
        if fault == "garble":
            return b"\xfe" + reply[::-1].encode("ascii")[:7] + b"#?\n"
        return reply.encode("ascii") + self.terminator

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            conn.settimeout(0.05)
            with self._lock:
                self.on_connect()
            self._conns.append(conn)
            t = threading.Thread(target=self._serve, args=(conn,), name=f"sim-{self.name}-conn", daemon=True)
            t.start()
            self._threads.append(t)

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        with conn:
            while not self._stop.is_set():
                try:
                    data = conn.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not data:
                    break
                buf += data
                frames, buf = self.split_frames(buf)
                out = b""  # the replies to every command of this chunk go out in one send (no Nagle stalls)
                for line in frames:
                    reply = self._reply(line)
                    if reply == b"":  # a dropped connection: what was answered before it still goes out
                        try:
                            if out:
                                conn.sendall(out)
                            conn.shutdown(socket.SHUT_RDWR)
                        except OSError:
                            pass
                        return
                    if reply is not None:
                        out += reply
                if out:
                    try:
                        conn.sendall(out)
                    except OSError:
                        return

    def close(self) -> None:
        """Stop the server and join its threads."""
        self._stop.set()
        try:
            self._listener.close()
        except OSError:
            pass
        for t in self._threads:
            t.join(timeout=5.0)
        for c in self._conns:
            try:
                c.close()
            except OSError:
                pass


def visa_address(server: LineServer) -> str:
    """Return the pyvisa resource name of a simulated instrument."""
    return f"TCPIP0::127.0.0.1::{server.port}::SOCKET"


def serial_url(server: LineServer) -> str:
    """Return the pyserial URL of a simulated instrument."""
    return f"socket://127.0.0.1:{server.port}"


# --------------------------------------------------------------------------- thermocouple card

OPEN_CIRCUIT_CODE = "+9.9E37"


class SimThermocoupleCard(LineServer):
    """A DAS-TC style type E card: EMF = E(T_world) - E(T_cj); open junctions read over-range.

    Besides single scans (``SCAN?``) it answers the buffered block mode of
    :mod:`driftlab.daq.thermocouple`: its pacer takes scan k at ``k * interval`` seconds of the
    shared clock, and ``FETC?`` returns any run of scans already taken, evaluated in one
    vectorised pass over the world (``temperatures_block``) when the world offers it.
    """

    name = "tc-card"
    buffer_scans = 1 << 20  # scans the card keeps before the oldest are overwritten
    max_block = 10_000  # scans one FETC? may ask for

    def __init__(
        self,
        world: World,
        clock: Clock,
        channel_map: Mapping[int, str],
        cold_junction_c: float = 24.0,
        noise_uv: float = 0.0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.world, self.clock = world, clock
        self.channel_map = dict(channel_map)
        self.cold_junction_c = cold_junction_c
        self.noise_uv = noise_uv
        self._rng = np.random.default_rng(seed)
        self.interval_s: float | None = None  # the pacer's scan interval, once set by PACE

    def _temperatures(self, times: np.ndarray, names: list[str | None]) -> np.ndarray:
        """Return (N, C) world temperatures at the instants for the named channels (NaN: unwired)."""
        block = getattr(self.world, "temperatures_block", None)
        if callable(block):
            return np.asarray(block(times, [n or "" for n in names]), dtype=float)
        out = np.full((times.size, len(names)), math.nan)
        for i, t in enumerate(times.tolist()):
            temps = self.world.temperatures(t)
            out[i] = [temps.get(n, math.nan) if n else math.nan for n in names]
        return out

    def _volts(self, temps: np.ndarray) -> np.ndarray:
        """Return the card's EMFs (V) for junction temperatures; open or railed junctions read over-range."""
        bad = ~(np.isfinite(temps) & (temps >= -270.0) & (temps <= 1000.0))  # open lead, or pinned at a rail
        e_cj = float(type_e_emf_mv(self.cold_junction_c))
        volts = (type_e_emf_mv(np.where(bad, 0.0, temps)) - e_cj) * 1e-3
        if self.noise_uv:
            volts = volts + self.noise_uv * 1e-6 * self._rng.standard_normal(volts.shape)
        return np.where(bad, float(OPEN_CIRCUIT_CODE), volts)

    def _fetch(self, first: int, last: int, k: int, n: int) -> str:
        """Return the FETC? reply for scans k..k+n-1 of channels first..last."""
        if self.interval_s is None:
            return "ERR NOPACE"
        if not (0 <= first <= last < 64 and k >= 0 and 1 <= n <= self.max_block):
            return "ERR RANGE"
        interval, now = self.interval_s, self.clock.now()
        if (k + n - 1) * interval > now + 1e-9 * max(1.0, abs(now)):
            return "ERR NOTREADY"
        if k < math.floor(now / interval + 1e-9) - self.buffer_scans + 1:
            return "ERR OVERWRITTEN"
        times = np.arange(k, k + n) * interval  # scan k at exactly k * interval, as the campaign plan times it
        names = [self.channel_map.get(ch) for ch in range(first, last + 1)]
        data = np.empty((n, 2 + last - first))
        data[:, 0] = self.cold_junction_c
        data[:, 1:] = self._volts(self._temperatures(times, names))
        return f"{k},{n},{data.astype('>f8').tobytes().hex()}"

    def handle(self, line: str) -> str | None:
        """Answer *IDN?, CJC?, SCAN? first,last, PACE interval and FETC? first,last,k,n."""
        if line == "*IDN?":
            return "DRIFTLAB,SIM-DASTC,0,1.0"
        if line == "CJC?":
            return f"{self.cold_junction_c:.4f}"
        m = re.fullmatch(r"SCAN\? (\d+),(\d+)", line)
        if m:
            first, last = int(m.group(1)), int(m.group(2))
            if not 0 <= first <= last < 64:
                return "ERR RANGE"
            names = [self.channel_map.get(ch) for ch in range(first, last + 1)]
            volts = self._volts(self._temperatures(np.array([self.clock.now()]), names))[0]
            return ",".join(OPEN_CIRCUIT_CODE if v == float(OPEN_CIRCUIT_CODE) else f"{v:.9e}" for v in volts.tolist())
        m = re.fullmatch(r"PACE (\S+)", line)
        if m:
            try:
                interval = float(m.group(1))
            except ValueError:
                return "ERR PARAM"
            if not (math.isfinite(interval) and interval > 0):
                return "ERR PARAM"
            self.interval_s = interval
            return "OK"
        m = re.fullmatch(r"FETC\? (\d+),(\d+),(\d+),(\d+)", line)
        if m:
            return self._fetch(*(int(g) for g in m.groups()))
        return "ERR SYNTAX"


# --------------------------------------------------------------------------- laser interferometer


@dataclass
class _LaserRef:
    t_s: float
    position: float
    error: float


class SimHead(LineServer):
    """What every simulated laser head shares: the world's error field at the stage position, the optics
    mounted, the beam's state and the datum the count starts from; subclasses speak a command set."""

    name = "laser"

    def __init__(
        self,
        world: World,
        clock: Clock,
        stage: Stage,
        pressure_pa: float = 101325.0,
        rh_percent: float = 50.0,
        signal_percent: float = 88.0,
    ) -> None:
        super().__init__()
        self.world, self.clock, self.stage = world, clock, stage
        self.pressure_pa, self.rh_percent = pressure_pa, rh_percent
        self.signal_percent = signal_percent
        self.mode, self.axis, self.term = "LIN", "X", "dx"
        #: the optics mounted on the machine (mode, axis, term, rotary range in deg or None), None: a bench
        #: head that answers for any configuration (driver tests)
        self.mounted: tuple[str, str, str, float | None] | None = None
        self._ref: _LaserRef | None = None
        self._air_cache: tuple[float, float] | None = None
        self.beam: str = "ok"  # "ok", "weak" (low signal), "broken" (ERR BEAM)

    def break_beam(self, how: str = "broken") -> None:
        """Interrupt the beam: ``"weak"`` reports a low signal, ``"broken"`` an error reply."""
        with self._lock:
            self.beam = how

    def mount(self, mode: str | None, axis: str = "X", term: str = "dx", range_deg: float | None = None) -> None:
        """Mount optics for one measurement (what an operator does between stages); None: take them off.

        The head then answers only for that optics, axis and term (``ERR OPTICS`` otherwise) and, on a
        rotary axis, loses the beam beyond ``range_deg`` of rotation (fig. 5.9: +-10 deg).
        """
        with self._lock:
            self.mounted = None if mode is None else (mode, axis, term, range_deg)
            self._ref = None

    def _optics_fault(self, t: float) -> str | None:
        """Return the error reply when the configured measurement is not what is mounted, or out of its range."""
        m = self.mounted
        if m is None:
            return None
        if m[:3] != (self.mode, self.axis, self.term):
            return "ERR OPTICS"
        if m[3] is not None and abs(self.stage.where(self.axis, t)[0]) > m[3] + 1e-9:
            return "ERR BEAM"
        return None

    def restore_beam(self) -> None:
        """Realign the optics (the count still needs a new REF)."""
        with self._lock:
            self.beam = "ok"

    def datum(self) -> dict[str, float] | None:
        """Return the head's present datum (time, position and error at REF), or None before any."""
        with self._lock:
            ref = self._ref
            return None if ref is None else {"t_s": ref.t_s, "position": ref.position, "error": ref.error}

    def restore_reference(self, t_s: float, position: float, error: float) -> None:
        """Put a saved datum back (a head that kept its count while the PC restarted)."""
        with self._lock:
            self._ref = _LaserRef(float(t_s), float(position), float(error))

    restore_datum = restore_reference  # the name the datum()/restore pair had first

    def _air_c(self, t: float) -> float:
        # a point's settle polls and averaged readings all ask at one instant: evaluate the room once
        cached = self._air_cache
        if cached is not None and cached[0] == t:
            return cached[1]
        air = room_air_c(self.world, t)
        self._air_cache = (t, air)
        return air

    def _true_value(self, t: float) -> tuple[float, float]:
        position, direction = self.stage.where(self.axis, t)
        err = float(self.world.measure_error(t, self.axis, position, direction).get(self.term, 0.0))
        return position, err

    def _relative(self, t: float) -> tuple[float, float]:
        """Return (error - datum error, travel since the datum) of the configured measurement at ``t``.

        Power-on (no datum yet): the count starts from wherever the axis is.
        """
        position, err = self._true_value(t)
        if self._ref is None:
            self._ref = _LaserRef(t, position, err)
        return err - self._ref.error, position - self._ref.position

    def _take_datum(self, t: float) -> None:
        position, err = self._true_value(t)
        self._ref = _LaserRef(t, position, err)


class SimLaser(SimHead):
    """The thesis' laser head (legacy protocol of driftlab.daq.laser) on the world's error field."""

    def handle(self, line: str) -> str | None:
        """Answer the laser protocol."""
        t = self.clock.now()
        word, _, arg = line.partition(" ")
        if line == "*IDN?":
            return "DRIFTLAB,SIM-LASER,0,1.0"
        if word in ("MODE", "AXIS", "TERM"):
            valid = {"MODE": ("LIN", "STR", "ANG"), "AXIS": AXES,
                     "TERM": ("dx", "dy", "dz", "alpha", "beta", "gamma")}[word]  # fmt: skip
            if arg not in valid:
                return "ERR PARAM"
            setattr(self, word.lower(), arg)
            self._ref = None
            return "OK"
        if line == "REF":
            if self.beam != "ok":
                return "ERR BEAM"
            fault = self._optics_fault(t)
            if fault is not None:
                return fault
            position, err = self._true_value(t)
            self._ref = _LaserRef(t, position, err)
            return "OK"
        if line == "ENV?":
            return f"{self._air_c(t):.3f},{self.pressure_pa:.1f},{self.rh_percent:.1f}"
        if word == "MEAS?" and arg:
            try:
                n = int(arg)
            except ValueError:
                return "ERR PARAM"
            if not 1 <= n <= 1000:
                return "ERR PARAM"
            one = self.handle("MEAS?")  # the head samples back to back: the same instant here
            return one if one is None or one.startswith("ERR") else ";".join([one] * n)
        if line == "MEAS?":
            if self.beam == "broken":
                return "ERR BEAM"
            fault = self._optics_fault(t)
            if fault is not None:
                return fault
            position, err = self._true_value(t)
            if self._ref is None:  # power-on: the count starts from wherever the axis is
                self._ref = _LaserRef(t, position, err)
            value = err - self._ref.error
            if self.mode == "LIN":
                value += position - self._ref.position
            n_air = float(air_refractive_index(self._air_c(t), self.pressure_pa, self.rh_percent))
            fringes = float(value_to_fringes(self.mode, value, n_air))
            signal = 4.0 if self.beam == "weak" else self.signal_percent
            return f"{fringes:.5f},{signal:.1f}"
        return "ERR SYNTAX"


# --------------------------------------------------------------------------- A/D card (proximity sensors)


class SimADCard(LineServer):
    """A DT2801 style A/D card; ``sources`` give each wired channel's voltage at a time."""

    name = "ad-card"

    def __init__(self, clock: Clock, n_channels: int = 16) -> None:
        super().__init__()
        self.clock = clock
        self.n_channels = n_channels
        self._sources: list[tuple[list[int], Callable[[float], np.ndarray]]] = []

    def wire(self, channels: list[int], source: Callable[[float], np.ndarray]) -> None:
        """Connect sensors on ``channels``; ``source(t)`` returns their voltages in that order."""
        self._sources.append((list(channels), source))

    def unwire(self) -> None:
        """Disconnect every sensor (a fixture taken off: its channels read 0 V, out of range)."""
        self._sources.clear()

    def voltages(self, t: float) -> np.ndarray:
        """Return every channel's voltage (unwired channels sit at 0 V)."""
        v = np.zeros(self.n_channels)
        for chans, source in self._sources:
            v[chans] = np.clip(source(t), 0.0, 10.0)
        return v

    def handle(self, line: str) -> str | None:
        """Answer *IDN? and VOLT? first,last."""
        if line == "*IDN?":
            return "DRIFTLAB,SIM-DT2801,0,1.0"
        m = re.fullmatch(r"VOLT\? (\d+),(\d+)", line)
        if m:
            first, last = int(m.group(1)), int(m.group(2))
            if not 0 <= first <= last < self.n_channels:
                return "ERR RANGE"
            v = self.voltages(self.clock.now())
            return ",".join(f"{x:.6f}" for x in v[first : last + 1])
        return "ERR SYNTAX"


def reference_surface_source(
    world: World, stage: Stage, axis: str, array: ReferenceSurfaceArray
) -> Callable[[float], np.ndarray]:
    """Return a voltage source for a reference-surface array reading the world's errors of ``axis``."""

    def source(t: float) -> np.ndarray:
        position, direction = stage.where(axis, t)
        err = world.measure_error(t, axis, position, direction)
        values = np.array([float(err.get(term, 0.0)) for term in array.terms()])
        return array.forward(values)

    return source


def roll_pair_source(
    world: World,
    stage: Stage,
    axis: str,
    gap_term: str,
    roll_term: str,
    separation_mm: float,
    calibrations: tuple[tuple[float, float], tuple[float, float]],
) -> Callable[[float], np.ndarray]:
    """Return a voltage source for two sensors on parallel reference lines (fig. 5.11)."""
    (c_a, s_a), (c_b, s_b) = calibrations

    def source(t: float) -> np.ndarray:
        position, direction = stage.where(axis, t)
        err = world.measure_error(t, axis, position, direction)
        gap, roll = float(err.get(gap_term, 0.0)), float(err.get(roll_term, 0.0))
        lift = 0.5 * separation_mm * math.tan(roll)
        return np.array([c_a + s_a * (gap + lift), c_b + s_b * (gap - lift)])

    return source


def spindle_bar_source(
    world: World,
    stage: Stage,
    spacing_mm: float,
    calibrations: tuple[tuple[float, float], ...],
    axis: str = "Z",
) -> Callable[[float], np.ndarray]:
    """Return a voltage source for the four-sensor spindle bar array (fig. 5.18).

    The bar follows the world's work-space error of ``axis`` at its present position:
    X sensors at the lower and upper level read dx and dx + L tan(beta), Y sensors dy and
    dy - L tan(alpha) (the geometry of driftlab.daq.probe.spindle_angles).
    """
    consts = np.array([c for c, _ in calibrations])
    slopes = np.array([s for _, s in calibrations])

    def source(t: float) -> np.ndarray:
        position, direction = stage.where(axis, t)
        e = world.measure_error(t, axis, position, direction)
        dx, dy = float(e.get("dx", 0.0)), float(e.get("dy", 0.0))
        alpha, beta = float(e.get("alpha", 0.0)), float(e.get("beta", 0.0))
        gaps = np.array([dx, dx + spacing_mm * math.tan(beta), dy, dy - spacing_mm * math.tan(alpha)])
        return consts + slopes * gaps

    return source


# --------------------------------------------------------------------------- machine controller


_WORD = re.compile(r"([A-Z])\s*([-+]?\d*\.?\d+(?:[eE][-+]?\d+)?)")


@dataclass
class _Block:
    seq: int
    target: dict[str, float]
    feed: float  # mm/min (deg/min for rotary-only moves)
    dwell_s: float


@dataclass(frozen=True)
class SimSphere:
    """A reference sphere in the work space."""

    centre: tuple[float, float, float]
    radius_mm: float


def world_sphere_offset(world: World) -> Callable[[float, np.ndarray], np.ndarray]:
    """Return offset(t, centre): first-order sum of the linear axes' translation errors at the sphere."""

    def offset(t: float, centre: np.ndarray) -> np.ndarray:
        out = np.zeros(3)
        for i, axis in enumerate(("X", "Y", "Z")):
            err = world.measure_error(t, axis, float(centre[i]), 1)
            out += [float(err.get(term, 0.0)) for term in TRANSLATIONS]
        return out

    return offset


class SimController(LineServer):
    """A CNC controller: a block buffer executed at the programmed feed, positions, probing."""

    name = "controller"

    def __init__(
        self,
        world: World,
        clock: Clock,
        capacity: int = 16,
        rapid_mm_min: float = 10000.0,
        spheres: Mapping[str, SimSphere] | None = None,
        stylus_radius_mm: float = 1.0,
        lobing: LobingMap | None = None,
        sphere_offset: Callable[[float, np.ndarray], np.ndarray] | None = None,
    ) -> None:
        super().__init__()
        self.world, self.clock = world, clock
        self.capacity = capacity
        self.rapid_mm_min = rapid_mm_min
        self.spheres = dict(spheres or {})
        self.stylus_radius_mm = stylus_radius_mm
        self.lobing = lobing or LobingMap()
        self.sphere_offset = sphere_offset or world_sphere_offset(world)
        self.pos = {a: 0.0 for a in AXES}
        self.direction = {a: 1 for a in AXES}
        self._queue: deque[_Block] = deque()
        self._current: tuple[_Block, dict[str, float], float, float] | None = None  # block, start, t0, duration
        self._t_exec = clock.now()
        self._feed = 1000.0
        self._modal_g = 1
        self.accepted_seq = 0
        self.done_seq = 0
        self.executed: list[str] = []
        self.max_queued = 0

    # -- motion
    def _duration(self, start: dict[str, float], blk: _Block) -> float:
        lin = math.dist([start[a] for a in "XYZ"], [blk.target[a] for a in "XYZ"])
        rot = math.dist([start[a] for a in "AB"], [blk.target[a] for a in "AB"])
        length = lin if lin > 0 else rot
        return blk.dwell_s + (60.0 * length / blk.feed if length > 0 else 0.0)

    def _advance(self, now: float) -> None:
        while True:
            if self._current is None:
                if not self._queue:
                    self._t_exec = max(self._t_exec, now)
                    return
                blk = self._queue.popleft()
                start = dict(self.pos)
                self._current = (blk, start, self._t_exec, self._duration(start, blk))
            blk, start, t0, dur = self._current
            for a in AXES:
                if blk.target[a] != start[a]:
                    self.direction[a] = 1 if blk.target[a] > start[a] else -1
            if t0 + dur <= now:
                self.pos = dict(blk.target)
                self.done_seq = blk.seq
                self._t_exec = t0 + dur
                self._current = None
                continue
            frac = min(max((now - t0) / dur, 0.0), 1.0) if dur > 0 else 1.0
            self.pos = {a: start[a] + frac * (blk.target[a] - start[a]) for a in AXES}
            return

    def where(self, axis: str, t_s: float) -> tuple[float, int]:
        """Return (position, approach direction) of ``axis`` at ``t_s`` (a Stage for the laser)."""
        with self._lock:
            self._advance(t_s)
            return self.pos[axis], self.direction[axis]

    def _queued(self) -> int:
        return len(self._queue) + (1 if self._current is not None else 0)

    def _parse_block(self, seq: int, code: str) -> _Block:
        code = re.sub(r"\(.*?\)|;.*$", "", code.upper()).strip()
        target = {a: (self._queue[-1].target[a] if self._queue else
                      self._current[0].target[a] if self._current else self.pos[a]) for a in AXES}  # fmt: skip
        dwell = 0.0
        g = self._modal_g
        feed = self._feed
        if _WORD.sub("", code).strip():
            raise ValueError("unparsed characters")
        for m in _WORD.finditer(code):
            letter, value = m.group(1), float(m.group(2))
            if letter == "G":
                if value not in (0, 1, 4, 90):
                    raise ValueError(f"unsupported G{value:g}")
                if value in (0, 1):
                    g = int(value)
                elif value == 4:
                    g = 4
            elif letter in AXES:
                target[letter] = value
            elif letter == "F":
                if value <= 0:
                    raise ValueError("feed must be positive")
                feed = value
            elif letter == "P":
                dwell = value
            elif letter not in ("N", "M", "S", "T"):
                raise ValueError(f"unknown word {letter}")
        # modal state changes only once the whole block is accepted
        self._feed = feed
        if g in (0, 1):
            self._modal_g = g
        return _Block(seq, target, self.rapid_mm_min if g == 0 else feed, dwell if g == 4 else 0.0)

    # -- probing
    def _probe(self, start: np.ndarray, u: np.ndarray, dist: float, t: float) -> np.ndarray | None:
        best: float | None = None
        for sphere in self.spheres.values():
            c = np.array(sphere.centre) + self.sphere_offset(t, np.array(sphere.centre))
            reach = sphere.radius_mm + self.stylus_radius_mm
            w = start - c
            b = float(w @ u)
            disc = b * b - (float(w @ w) - reach * reach)
            if disc < 0:
                continue
            lam = -b - math.sqrt(disc)
            if lam >= 0 and (best is None or lam < best):
                best = lam
        if best is None:
            return None
        lam = best + float(self.lobing.pretravel(u[None, :])[0])
        if lam > dist:
            return None
        return start + lam * u

    def handle(self, line: str) -> str | None:
        """Answer the controller protocol (see driftlab.daq.machine_link)."""
        now = self.clock.now()
        self._advance(now)
        word, _, arg = line.partition(" ")
        if line == "STAT?":
            return f"STAT {self.capacity - self._queued()} {self.capacity} {self.done_seq}"
        if line == "POS?":
            return "POS " + " ".join(f"{a}{self.pos[a]:.4f}" for a in AXES)
        if word == "BLK":
            seq_s, _, code = arg.partition(" ")
            try:
                seq = int(seq_s)
            except ValueError:
                return "ERR SYNTAX"
            if seq <= self.accepted_seq:
                return f"ACK {seq}"  # a resent block: acknowledged once more, not queued twice
            if seq != self.accepted_seq + 1:
                return f"ERR SEQ {self.accepted_seq}"
            if self._queued() >= self.capacity:
                return "ERR FULL"
            try:
                blk = self._parse_block(seq, code)
            except ValueError as exc:
                return f"ERR SYNTAX {exc}"
            self._queue.append(blk)
            self.executed.append(code)
            self.accepted_seq = seq
            self.max_queued = max(self.max_queued, self._queued())
            self._advance(now)
            return f"ACK {seq}"
        if word == "PRB":
            try:
                vals = [float(v) for v in arg.split(",")]
                start, u, dist = np.array(vals[:3]), np.array(vals[3:6]), vals[6]
            except (ValueError, IndexError):
                return "ERR SYNTAX"
            if self._queued():
                return "ERR BUSY"
            u = u / np.linalg.norm(u)
            hit = self._probe(start, u, dist, now)
            if hit is None:
                return "MISS"
            return "HIT " + ",".join(f"{v:.6f}" for v in hit)
        return "ERR SYNTAX"
