"""`driftlab rig check`: connect to every instrument of a rig file, identify it, read it once.

`driftlab rig check RIG.yaml [--sim SCENARIO.yaml] [--json OUT.json]`

Prints one row per role (driver, resource, identification, reading) and exits 0 when every
instrument answered, 1 otherwise with one line per failure on stderr. ``--sim`` answers every
role with the virtual machine's simulated instrument for the rig's driver (the same command set
the real one speaks); a role whose resource is ``sim`` is simulated even without it (on the
clean scenario). `driftlab rig drivers` lists the drivers and the role each plays.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

from driftlab.resources import examples_dir


def register(sub: argparse._SubParsersAction) -> None:
    """Register `rig check` and `rig drivers`."""
    p = sub.add_parser("rig", help="rig files: which instrument plays each role; check them")
    rs = p.add_subparsers(dest="rig_command", required=True)
    c = rs.add_parser("check", help="connect to every instrument of a rig, identify it, read it once")
    c.add_argument("rig", type=Path, help="rig file (YAML, examples/rigs/)")
    c.add_argument(
        "--sim", type=Path, default=None, metavar="SCENARIO", help="answer every role from the virtual machine"
    )
    c.add_argument("--json", type=Path, default=None, metavar="OUT", help="write the results as JSON")
    c.set_defaults(func=_check)
    d = rs.add_parser("drivers", help="list the instrument drivers and their roles")
    d.set_defaults(func=_drivers)


def export_readers() -> dict[str, Callable[[Path, str | None], list[tuple[str, str, float, int, float]]]]:
    """Return the export-file formats a ``laser-export`` follower reads, from the importers (format -> reader)."""

    def renishaw_csv(path: Path, axis: str | None) -> list[tuple[str, str, float, int, float]]:
        # lazy: this function's imports would add 1.1 s to `driftlab --help` (measured)
        from driftlab.metrology.importers.renishaw import read_renishaw_csv

        e = read_renishaw_csv(path, axis=axis).errors
        return [
            (str(a), str(t), float(p), int(d), float(v))
            for a, t, p, d, v in zip(e["axis"], e["term"], e["position"], e["direction"], e["value"], strict=True)
        ]

    return {"renishaw-csv": renishaw_csv}


def _drivers(args: argparse.Namespace) -> int:
    """Print the drivers a rig file can name."""
    # lazy: this function's imports would add 0.5 s to `driftlab --help` (measured)
    from driftlab.daemon.rigfile import DRIVERS

    for name, (role, what) in DRIVERS.items():
        print(f"{name:22s} {role:14s} {what}")
    return 0


#: the unit of a reading named with it (``air_c``, ``pressure_pa``, ``ch0_v``), as a person reads it
_SUFFIX_UNITS = {"_c": "°C", "_degc": "°C", "_pa": "Pa", "_percent": "%", "_v": "V", "_mm": "mm", "_deg": "deg"}
_ROLE_UNITS = {"thermocouples": "°C"}
_AXIS_UNITS = {"X": "mm", "Y": "mm", "Z": "mm", "A": "deg", "B": "deg"}


def reading_text(role: str, key: str, value: object) -> str:
    """Return one reading with its unit, e.g. "T1 20.0249 °C", "air 20.3770 °C", "A 0.0000 deg"."""
    name, unit = key, _ROLE_UNITS.get(role, "")
    for suffix, u in _SUFFIX_UNITS.items():
        if key.lower().endswith(suffix) and len(key) > len(suffix):
            name, unit = key[: -len(suffix)], u
            break
    else:
        if role == "machine" and key in _AXIS_UNITS:
            unit = _AXIS_UNITS[key]
    if isinstance(value, float):
        text = "open" if value != value else f"{value:.4f}"
        return f"{name} {text}" + (f" {unit}" if unit and text != "open" else "")
    return f"{name} {value}"


def _check(args: argparse.Namespace) -> int:
    """Check every role of the rig and report; 0 when all answered."""
    # lazy: this function's imports would add 2.3 s to `driftlab --help` (measured)
    from driftlab.daemon.rigfile import SIM, check_rig, load_rig

    rig = load_rig(args.rig)
    world = clock = None
    needs_sim = args.sim is not None or any(s.resource == SIM for s in rig.instruments.values())
    if needs_sim:
        # lazy, as above: kept off the `driftlab --help` path
        from driftlab.daq.sim.instruments import ManualClock
        from driftlab.daq.sim.machine import VirtualMachine
        from driftlab.daq.sim.scenario import load_scenario

        scenario = args.sim if args.sim is not None else examples_dir() / "scenarios" / "clean.yaml"
        world, clock = VirtualMachine(load_scenario(scenario)), ManualClock(3600.0)
    results = check_rig(rig, world=world, sim_clock=clock, simulate_all=args.sim is not None, readers=export_readers())
    rows = [("role", "driver", "resource", "identification", "reading")]
    for r in results:
        reading = ", ".join(reading_text(r.role, k, v) for k, v in list(r.reading.items())[:6])
        if len(r.reading) > 6:
            reading += f", ... ({len(r.reading)} values)"
        rows.append((r.role, r.driver, r.resource, r.idn or "-", reading or "-"))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    for row in rows:
        print("  ".join(cell.ljust(widths[i]) if i < 4 else cell for i, cell in enumerate(row)).rstrip())
    if args.json is not None:
        args.json.write_text(json.dumps({"rig": rig.name, "instruments": [r.as_json() for r in results]}) + "\n")
    failed = [r for r in results if r.error is not None]
    for r in failed:
        sys.stderr.write(f"driftlab: rig {rig.name}: {r.role} ({r.driver} at {r.resource}): {r.error}\n")
    if not results:
        sys.stderr.write(f"driftlab: rig {rig.name} names no instruments\n")
        return 1
    return 1 if failed else 0
