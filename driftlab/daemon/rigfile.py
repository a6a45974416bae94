"""Rig files: which instrument plays each role of a machine, where it is and how it is wired; open and check them.

A rig file (YAML, ``examples/rigs/``) names one instrument per role::

    name: shop-34970a-linuxcnc
    visa_library: "@py"                 # optional: @py, @ivi, FILE.yaml@sim (relative to the rig file)
    instruments:
      thermocouples:                    # role
        driver: keysight-34970a         # DRIVERS below
        resource: GPIB0::9::INSTR       # VISA resource, serial URL or host:port; "sim": the virtual machine's
        options: {tc_type: E, reference_junction: INT, channels: {101: T1, 102: T2}}
      machine:
        driver: linuxcnc
        resource: cnc-host:5007

Plans keep the stages; rigs say what hardware (``driftlab daemon --plan P --rig R``), and
``driftlab rig check R`` connects to every instrument, identifies it and reads it once. A role
whose resource is ``sim`` (or every role, with ``--sim SCENARIO``) is answered by the virtual
machine's simulated instrument for that driver, speaking the same command set.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field
from pydantic import ValidationError as PydanticError

from driftlab.daq.attocube_ids import AttocubeIDS, IDSOptics, IDSSession
from driftlab.daq.export_follower import ExportFollower
from driftlab.daq.heidenhain import HeidenhainLink
from driftlab.daq.keysight34970a import Keysight34970A, Keysight34970AVolts, identified
from driftlab.daq.laser import LaserInterferometer, SettleOptions
from driftlab.daq.linuxcnc import LinuxCNCLink
from driftlab.daq.machine_link import SerialMachineLink
from driftlab.daq.nidaq import NIDaqVolts
from driftlab.daq.proximity import ADCard
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.thermocouple import ChannelCalibration, ThermocoupleCard
from driftlab.daq.transport import LineChannel, VisaPort, open_port, visa_resource_manager
from driftlab.errors import DriftlabError, ValidationError
from driftlab.jsonsafe import finite_or_none

ROLES = ("thermocouples", "proximity", "laser", "machine")

#: driver name -> (role, what it drives and over what)
DRIVERS: dict[str, tuple[str, str]] = {
    "keysight-34970a": (
        "thermocouples",
        "Keysight/Agilent 34970A, 34972A, DAQ970A thermocouple channels, SCPI over VISA",
    ),
    "keysight-34970a-dcv": ("proximity", "DC-volt channels of a 34970A family mainframe, SCPI over VISA"),
    "nidaqmx": ("proximity", "NI-DAQmx analog inputs through NI's nidaqmx package (resource Dev1/ai0:4)"),
    "laser-export": ("laser", "a laser's capture software followed through its live export file (resource: the file)"),
    "attocube-ids3010": (
        "laser",
        "attocube IDS3010 displacement interferometer, its JSON-RPC interface over TCP (host[:port], default 9090)",
    ),
    "linuxcnc": ("machine", "LinuxCNC through linuxcncrsh, TCP (host:port, default port 5007)"),
    "heidenhain-lsv2": (
        "machine",
        "Heidenhain TNC through LSV2 (pyLSV2), TCP (host:port, default 19000): reads positions, moves nothing",
    ),
    "thesis-tc-card": ("thermocouples", "legacy: the thesis' DAS-TC card protocol (driftlab's own, CJC?/SCAN?/FETC?)"),
    "thesis-laser": ("laser", "legacy: the thesis' HP-IB laser processor protocol (driftlab's own, MODE/MEAS?)"),
    "thesis-ad-card": ("proximity", "legacy: the thesis' DT2801 A/D card protocol (driftlab's own, VOLT?)"),
    "thesis-rs232": ("machine", "legacy: the thesis' RS-232 block-streaming link (driftlab's own, STAT?/BLK/POS?)"),
}
SIM = "sim"


class InstrumentSpec(BaseModel):
    """One role's instrument: driver, where it is, its options."""

    model_config = ConfigDict(extra="forbid")

    driver: str
    resource: str = Field(min_length=1)
    timeout_s: float = Field(default=5.0, gt=0)
    options: dict[str, Any] = Field(default_factory=dict)


class RigSpec(BaseModel):
    """A rig file: a name, the VISA library, and the instrument of each role."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1)
    description: str = ""
    visa_library: str | None = None
    instruments: dict[str, InstrumentSpec]

    def role(self, role: str) -> InstrumentSpec | None:
        """Return the instrument playing ``role`` (None if the rig has none)."""
        return self.instruments.get(role)


def parse_rig(doc: Any, where: str = "rig", base: Path | None = None) -> RigSpec:
    """Return a checked rig from a parsed YAML document; ValidationError (one line) otherwise."""
    if not isinstance(doc, dict):
        raise ValidationError(f"{where}: a rig file is a mapping with name and instruments")
    try:
        rig = RigSpec.model_validate(doc)
    except PydanticError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        raise ValidationError(f"{where}: {loc}: {first['msg']}") from None
    for role, spec in rig.instruments.items():
        if role not in ROLES:
            raise ValidationError(f"{where}: instruments.{role}: unknown role (roles: {', '.join(ROLES)})")
        if spec.driver not in DRIVERS:
            raise ValidationError(
                f"{where}: instruments.{role}.driver {spec.driver!r} is not one of {', '.join(DRIVERS)}"
            )
        if DRIVERS[spec.driver][0] != role:
            raise ValidationError(
                f"{where}: instruments.{role}: driver {spec.driver} plays the {DRIVERS[spec.driver][0]} role"
            )
    lib = rig.visa_library
    if lib and base is not None and lib.endswith("@sim") and not Path(lib[:-4]).is_absolute():
        rig = rig.model_copy(update={"visa_library": f"{base / lib[:-4]}@sim"})
    return rig


def load_rig(path: Path | str) -> RigSpec:
    """Return the rig of a YAML file; ValidationError (one line) for a missing or malformed file."""
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
    except FileNotFoundError:
        raise ValidationError(f"rig file {p}: no such file") from None
    except yaml.YAMLError as exc:
        raise ValidationError(f"rig file {p}: not YAML ({' '.join(str(exc).split())[:80]})") from None
    return parse_rig(doc, f"rig {p.name}", p.parent)


# ----------------------------------------------------------------------------------- options


def _channel_map(role: str, options: Mapping[str, Any]) -> dict[int, str]:
    raw = options.get("channels")
    if not isinstance(raw, dict) or not raw:
        raise ValidationError(f"instruments.{role}.options.channels: a mapping of channel number to name")
    try:
        return {int(k): str(v) for k, v in raw.items()}
    except (TypeError, ValueError):
        raise ValidationError(f"instruments.{role}.options.channels: keys are channel numbers") from None


def _calibrations(role: str, options: Mapping[str, Any]) -> dict[str, Any]:
    out = {}
    for name, cal in (options.get("calibrations") or {}).items():
        try:
            out[str(name)] = ChannelCalibration(float(cal.get("slope", 1.0)), float(cal.get("offset_c", 0.0)))
        except (AttributeError, TypeError, ValueError):
            raise ValidationError(f"instruments.{role}.options.calibrations.{name}: slope and offset_c") from None
    return out


def _unknown(role: str, options: Mapping[str, Any], allowed: set[str]) -> None:
    extra = sorted(set(options) - allowed)
    if extra:
        raise ValidationError(
            f"instruments.{role}.options: unknown option {extra[0]!r} (takes {', '.join(sorted(allowed))})"
        )


IDS_OPTIONS = {
    "displacement_axis",
    "angle_axes",
    "angle_spacing_mm",
    "api_namespace",
    "min_contrast_permille",
    "start_measurement",
}


def ids_optics(role: str, options: Mapping[str, Any]) -> Any:
    """Return the IDS3010's beam layout from a rig's options (beams 0..2, the angle set-up's spacing)."""
    try:
        axes = options.get("angle_axes", [0, 1])
        return IDSOptics(
            displacement_axis=int(options.get("displacement_axis", 0)),
            angle_axes=(int(axes[0]), int(axes[1])),
            angle_spacing_mm=float(options.get("angle_spacing_mm", 32.0)),
        )
    except (TypeError, ValueError, IndexError, KeyError):
        raise ValidationError(
            f"instruments.{role}.options: displacement_axis a beam 0..2, angle_axes two beams, angle_spacing_mm in mm"
        ) from None
    except ValidationError as exc:
        raise ValidationError(f"instruments.{role}.options: {exc}") from None


def thermocouple_channels(rig: RigSpec) -> list[str]:
    """Return the thermocouple channel names the rig wires, in scan order."""
    spec = rig.role("thermocouples")
    if spec is None:
        return []
    cmap = _channel_map("thermocouples", spec.options)
    return [cmap[c] for c in sorted(cmap)]


# ----------------------------------------------------------------------------------- opening


@dataclass
class OpenRig:
    """The opened instruments of a rig by role, and how to close them (and any simulated servers)."""

    instruments: dict[str, Any] = field(default_factory=dict)
    servers: dict[str, Any] = field(default_factory=dict)
    closers: list[Callable[[], None]] = field(default_factory=list)

    def close(self) -> None:
        """Close every instrument, then stop the simulated servers."""
        for close in reversed(self.closers):
            try:
                close()
            except Exception:  # noqa: BLE001 - closing must not mask the outcome
                pass
        self.closers.clear()


@dataclass(frozen=True)
class _Opening:
    """One role's instrument as its opener sees it: the spec, its options, and how to reach and pace it."""

    role: str
    spec: InstrumentSpec
    rm_factory: Callable[[], Any]
    clock: Callable[[], float]
    fast: bool
    readers: Mapping[str, Callable[..., Any]]

    @property
    def options(self) -> dict[str, Any]:
        """Return the spec's driver options."""
        return dict(self.spec.options)

    def channel(self, name: str) -> LineChannel:
        """Return a line channel on the spec's resource (VISA when it names one, else serial/TCP)."""
        spec = self.spec
        if "::" in spec.resource:
            port: Any = VisaPort.open(spec.resource, timeout_s=spec.timeout_s, resource_manager=self.rm_factory())
        else:
            port = open_port(spec.resource, spec.timeout_s)
        if self.fast:  # a simulated instrument: no back-off between retries, no waiting
            return LineChannel(port, name, RetryPolicy(attempts=3, base_delay_s=0.0), sleep=_no_sleep)
        return LineChannel(port, name, None)

    def settle(self) -> SettleOptions:
        """Return a laser's point-reading settings (a simulated head settles at once: no waiting, 20 polls)."""
        return SettleOptions(sleep=_no_sleep, max_settle_polls=20) if self.fast else SettleOptions()


Opened = tuple[Any, Callable[[], None]]


def _no_sleep(_s: float) -> None:
    """Do not wait (a simulated instrument answers for simulated time)."""


def _open_keysight(o: _Opening) -> Opened:
    opts = o.options
    _unknown(
        o.role, opts, {"channels", "tc_type", "reference_junction", "fixed_junction_c", "open_check", "calibrations"}
    )
    card = identified(
        Keysight34970A(
            o.channel("34970A"),
            _channel_map(o.role, opts),
            tc_type=str(opts.get("tc_type", "E")),
            reference_junction=str(opts.get("reference_junction", "INT")),
            fixed_junction_c=opts.get("fixed_junction_c"),
            open_check=bool(opts.get("open_check", True)),
            calibrations=_calibrations(o.role, opts),
            clock=o.clock,
        )
    )
    return card, card.close


def _open_keysight_dcv(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, {"channels", "range_v"})
    chans = opts.get("channels")
    if not isinstance(chans, list) or not chans:
        raise ValidationError(f"instruments.{o.role}.options.channels: a list of channel numbers")
    adc = identified(Keysight34970AVolts(o.channel("34970A volts"), chans, float(opts.get("range_v", 10.0))))
    return adc, adc.close


def _open_nidaqmx(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, {"min_v", "max_v", "terminal", "samples", "rate_hz"})
    daq = NIDaqVolts(
        o.spec.resource,
        min_v=float(opts.get("min_v", 0.0)),
        max_v=float(opts.get("max_v", 10.0)),
        terminal=str(opts.get("terminal", "DEFAULT")),
        samples=int(opts.get("samples", 1)),
        rate_hz=float(opts.get("rate_hz", 1000.0)),
    ).open()
    return daq, daq.close


def _open_linuxcnc(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, {"password", "enable_password", "client", "poll_s"})
    link = LinuxCNCLink.open(
        o.spec.resource,
        timeout_s=o.spec.timeout_s,
        password=str(opts.get("password", "EMC")),
        enable_password=str(opts.get("enable_password", "EMCTOO")),
        client=str(opts.get("client", "driftlab")),
        poll_s=float(opts.get("poll_s", 0.2)),
        **({"sleep": _no_sleep, "max_idle_polls": 2} if o.fast else {}),
    )
    return link, link.close


def _open_heidenhain(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, {"axes"})
    axes = opts.get("axes")
    if axes is not None and not isinstance(axes, dict):
        raise ValidationError(f"instruments.{o.role}.options.axes: a mapping of X Y Z A B to the control's axis names")
    tnc = HeidenhainLink.open(
        o.spec.resource,
        timeout_s=o.spec.timeout_s,
        axes={str(k): str(v) for k, v in axes.items()} if axes else None,
    )
    return tnc, tnc.close


def _open_thesis_tc_card(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, {"channels", "tc_type", "calibrations"})
    tc = ThermocoupleCard(
        o.channel("thermocouple card"),
        _channel_map(o.role, opts),
        _calibrations(o.role, opts),
        clock=o.clock,
        tc_type=str(opts.get("tc_type", "E")),
    )
    return tc, tc.close


def _open_laser_export(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, {"format", "axis", "poll_s", "timeout_s", "position_tol"})
    fmt = str(opts.get("format", "renishaw-csv"))
    known = dict(o.readers)
    if fmt not in known:
        raise ValidationError(
            f"instruments.{o.role}.options.format {fmt!r}: one of {', '.join(known) or '(none available here)'}"
        )
    axis = opts.get("axis")
    reader = known[fmt]
    follower = ExportFollower(
        o.spec.resource,
        lambda path: reader(path, axis),
        fmt=fmt,
        poll_s=float(opts.get("poll_s", 1.0)),
        timeout_s=float(opts.get("timeout_s", 600.0)),
        position_tol=float(opts.get("position_tol", 1e-3)),
    )
    follower.rows()  # the file must exist when the rig is opened (the capture software has started)
    return follower, follower.close


def _open_attocube(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, IDS_OPTIONS)
    ids = AttocubeIDS.open(
        o.spec.resource,
        o.spec.timeout_s,
        ids_optics(o.role, opts),
        o.settle(),
        IDSSession(
            api_namespace=str(opts.get("api_namespace", "sen")),
            min_contrast_permille=float(opts.get("min_contrast_permille", 250.0)),
            start_measurement=bool(opts.get("start_measurement", True)),
        ),
    )
    return ids, ids.close


def _open_thesis_laser(o: _Opening) -> Opened:
    _unknown(o.role, o.options, set())
    laser = LaserInterferometer(o.channel("laser"), settle=o.settle(), burst=o.fast)
    return laser, laser.close


def _open_thesis_ad_card(o: _Opening) -> Opened:
    opts = o.options
    _unknown(o.role, opts, {"n_channels"})
    ad = ADCard(o.channel("A/D card"), int(opts.get("n_channels", 16)))
    return ad, ad.close


def _open_thesis_rs232(o: _Opening) -> Opened:
    _unknown(o.role, o.options, set())
    fast: dict[str, Any] = {"sleep": _no_sleep, "max_idle_polls": 2} if o.fast else {}
    link = SerialMachineLink.open(o.spec.resource, timeout_s=o.spec.timeout_s, **fast)
    return link, link.close


#: driver name -> its opener (every name of DRIVERS has one)
_OPENERS: dict[str, Callable[[_Opening], Opened]] = {
    "keysight-34970a": _open_keysight,
    "keysight-34970a-dcv": _open_keysight_dcv,
    "nidaqmx": _open_nidaqmx,
    "linuxcnc": _open_linuxcnc,
    "heidenhain-lsv2": _open_heidenhain,
    "thesis-tc-card": _open_thesis_tc_card,
    "laser-export": _open_laser_export,
    "attocube-ids3010": _open_attocube,
    "thesis-laser": _open_thesis_laser,
    "thesis-ad-card": _open_thesis_ad_card,
    "thesis-rs232": _open_thesis_rs232,
}


def open_instrument(
    role: str,
    spec: InstrumentSpec,
    rm_factory: Callable[[], Any],
    clock: Callable[[], float],
    fast: bool = False,
    readers: Mapping[str, Callable[..., Any]] | None = None,
) -> Opened:
    """Return (driver, close) of one role's instrument, identified and configured; InstrumentError if unreachable.

    ``fast``: a simulated instrument (no waiting between polls and retries). ``readers`` are the
    export-file formats a ``laser-export`` follower can read (format -> reader of a file's rows),
    supplied by the commands from the importers.
    """
    opener = _OPENERS.get(spec.driver)
    if opener is None:  # pragma: no cover - parse_rig refuses an unknown driver
        raise ValidationError(f"driver {spec.driver!r} has no opener")
    return opener(_Opening(role, spec, rm_factory, clock, fast, readers or {}))


def start_simulated(rig: RigSpec, world: Any, clock: Any, roles: list[str]) -> tuple[RigSpec, dict[str, Any]]:
    """Start the virtual machine's instrument for each of ``roles`` and return the rig pointing at them."""
    # the virtual machine's modules are imported here, not at the top: they bring in scipy.signal,
    # measured at 1.1-3.4 s of start-up, which `driftlab rig check` on real instruments does not pay
    from driftlab.daq.sim.instruments import SimADCard, SimLaser, SimThermocoupleCard, serial_url, visa_address
    from driftlab.daq.sim.keysight34970a import Sim34970A
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC

    servers: dict[str, Any] = {}
    specs = dict(rig.instruments)
    try:
        if "machine" in roles and specs["machine"].driver == "heidenhain-lsv2":
            # lazy, as above: the simulators cost start-up that a real rig does not pay (measured)
            from driftlab.daq.sim.heidenhain import SimLSV2, lsv2_resource
            from driftlab.vocabulary import AXES

            names = specs["machine"].options.get("axes") or {}
            tnc = SimLSV2(clock, axes=tuple(str(v) for v in names.values()) or AXES).start()
            servers["machine"] = tnc
            specs["machine"] = specs["machine"].model_copy(update={"resource": lsv2_resource(tnc)})
        elif "machine" in roles:
            m = specs["machine"]
            ctrl: Any = (SimLinuxCNC(world, clock) if m.driver == "linuxcnc" else _sim_controller(world, clock)).start()
            servers["machine"] = ctrl
            specs["machine"] = m.model_copy(update={"resource": serial_url(ctrl)})
        for role in roles:
            spec = specs[role]
            if role == "thermocouples":
                cmap = _channel_map(role, spec.options)
                if spec.driver == "keysight-34970a":
                    srv: Any = Sim34970A(world, clock, cmap)
                else:
                    srv = SimThermocoupleCard(world, clock, cmap)
            elif role == "proximity":
                if spec.driver == "nidaqmx":
                    raise ValidationError("the virtual machine has no NI-DAQmx card: simulate keysight-34970a-dcv")
                srv = Sim34970A(world, clock) if spec.driver == "keysight-34970a-dcv" else SimADCard(clock)
            elif role == "laser":
                if spec.driver == "laser-export":
                    raise ValidationError("the virtual machine has no capture software: simulate attocube-ids3010")
                stage = servers.get("machine")
                if stage is None:
                    # lazy, as above: the simulators cost start-up that a real rig does not pay (measured)
                    from driftlab.daq.sim.instruments import FixedStage

                    stage = FixedStage()
                if spec.driver == "attocube-ids3010":
                    # lazy, as above: the simulators cost start-up that a real rig does not pay (measured)
                    from driftlab.daq.sim.attocube_ids import SimIDS3010, ids_resource

                    head = SimIDS3010(
                        world,
                        clock,
                        stage,
                        api_namespace=str(spec.options.get("api_namespace", "sen")),
                        optics=ids_optics(role, spec.options),
                    )
                    servers[role] = head.start()
                    specs[role] = spec.model_copy(update={"resource": ids_resource(head)})
                    continue
                srv = SimLaser(world, clock, stage)
            else:
                continue
            servers[role] = srv.start()
            specs[role] = spec.model_copy(update={"resource": visa_address(srv)})
    except BaseException:
        for s in servers.values():
            s.close()
        raise
    return rig.model_copy(update={"instruments": specs, "visa_library": "@py"}), servers


def _sim_controller(world: Any, clock: Any) -> Any:
    """Return the simulated machine controller on the virtual machine's world."""
    # lazy, as above: the simulators cost start-up that a real rig does not pay (measured)
    from driftlab.daq.sim.instruments import SimController

    return SimController(world, clock)


def open_rig(
    rig: RigSpec,
    clock: Callable[[], float],
    roles: list[str] | None = None,
    world: Any | None = None,
    sim_clock: Any | None = None,
    simulate_all: bool = False,
    fast: bool = False,
    readers: Mapping[str, Callable[..., Any]] | None = None,
) -> OpenRig:
    """Open the rig's instruments (``roles``, default all), starting simulated ones where asked or named ``sim``."""
    wanted = [r for r in ROLES if r in rig.instruments and (roles is None or r in roles)]
    sim_roles = [r for r in wanted if simulate_all or rig.instruments[r].resource == SIM]
    opened = OpenRig()
    if sim_roles:
        if world is None or sim_clock is None:
            raise ValidationError(
                f"rig {rig.name}: roles {', '.join(sim_roles)} are simulated: give a scenario (--sim)"
            )
        rig, servers = start_simulated(rig, world, sim_clock, sim_roles)
        opened.servers.update(servers)
        opened.closers.extend(s.close for s in servers.values())
    managers: list[Any] = []

    def rm_factory() -> Any:
        if not managers:
            managers.append(visa_resource_manager(rig.visa_library))
            opened.closers.append(managers[0].close)
        return managers[0]

    try:
        for role in wanted:
            driver, close = open_instrument(
                role, rig.instruments[role], rm_factory, clock, fast=fast or role in sim_roles, readers=readers
            )
            opened.instruments[role] = driver
            opened.closers.append(close)
    except BaseException:
        opened.close()
        raise
    return opened


# ----------------------------------------------------------------------------------- checking


@dataclass
class RoleCheck:
    """What ``rig check`` found for one role."""

    role: str
    driver: str
    resource: str
    idn: str | None = None
    reading: dict[str, Any] = field(default_factory=dict)
    error: str | None = None

    def as_json(self) -> dict[str, Any]:
        """Return the check as the ``rig check --json`` entry (NaN readings as null)."""
        out: dict[str, Any] = {
            "role": self.role,
            "driver": self.driver,
            "resource": self.resource,
            "idn": self.idn,
            "reading": {k: finite_or_none(v) if isinstance(v, float) else v for k, v in self.reading.items()},
        }
        if self.error is not None:
            out["error"] = self.error
        return out


def read_once(role: str, driver: Any) -> tuple[str | None, dict[str, Any]]:
    """Return (identification, one reading by name) of an opened instrument."""
    if role == "thermocouples":
        idn = getattr(driver, "idn", None) or _idn(driver)
        scan = driver.scan()
        return idn, dict(scan.values)
    if role == "proximity":
        idn = getattr(driver, "idn", None) or _idn(driver)
        n = int(getattr(driver, "n_channels", 1))
        volts = driver.read_volts(list(range(n)))
        return idn, {f"ch{i}_v": float(v) for i, v in enumerate(volts)}
    if role == "machine":
        idn = driver.identify() if hasattr(driver, "identify") else "thesis RS-232 link"
        return idn, {k: float(v) for k, v in driver.position().items()}
    if role == "laser":
        idn = driver.identify()
        if hasattr(driver, "status"):  # an export follower: what the file holds so far
            return idn, dict(driver.status())
        env = driver.environment()
        return idn, {
            "air_c": float(env.t_c),
            "pressure_pa": float(env.pressure_pa),
            "rh_percent": float(env.rh_percent),
        }
    raise ValidationError(f"no reading for role {role}")  # pragma: no cover


def _idn(driver: Any) -> str | None:
    ident = getattr(driver, "identify", None)
    if callable(ident):
        return str(ident())
    io = getattr(driver, "_io", None)
    if io is not None:
        return str(io.query("*IDN?", lambda t: t))
    return None


def check_rig(
    rig: RigSpec,
    world: Any | None = None,
    sim_clock: Any | None = None,
    simulate_all: bool = False,
    readers: Mapping[str, Callable[..., Any]] | None = None,
) -> list[RoleCheck]:
    """Return, for every role of the rig, what connecting, identifying and one reading gave (errors included)."""
    results: list[RoleCheck] = []
    for role in [r for r in ROLES if r in rig.instruments]:
        spec = rig.instruments[role]
        check = RoleCheck(role, spec.driver, spec.resource)
        results.append(check)
        try:
            opened = open_rig(
                rig,
                time.monotonic,
                [role],
                world=world,
                sim_clock=sim_clock,
                simulate_all=simulate_all,
                readers=readers,
            )
        except DriftlabError as exc:
            check.error = exc.one_line()
            continue
        try:
            check.idn, check.reading = read_once(role, opened.instruments[role])
        except DriftlabError as exc:
            check.error = exc.one_line()
        finally:
            opened.close()
        if check.error is None and role == "thermocouples":
            bad = [k for k, v in check.reading.items() if isinstance(v, float) and not math.isfinite(v)]
            if bad:
                check.error = f"open thermocouple{'s' if len(bad) > 1 else ''}: {', '.join(bad)}"
    return results
