"""`driftlab export-comp`: the model's correction of one axis as a controller's compensation table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from driftlab.commands.compensate import _model_file
from driftlab.compensator.exports import ALIASES, CONTROLLERS, controller
from driftlab.errors import ValidationError
from driftlab.labels import length_text
from driftlab.vocabulary import AXES


def register(sub: argparse._SubParsersAction) -> None:
    """Register `export-comp --model V (--temps CSV | --api URL) --controller C --axis X --range A,B -o FILE`."""
    p = sub.add_parser(
        "export-comp",
        help="write the model's correction of an axis as a controller compensation table",
        description="LinuxCNC axis comp file, SINUMERIK 840D sl / 828D / 808D LEC and CEC programs, "
        "HEIDENHAIN TNC 640 / TNC 426 .COM table, FANUC 0i / 30i pitch error parameter tape (docs/exports.md).",
    )
    p.add_argument(
        "--model",
        required=True,
        metavar="VERSION|FILE",
        help="a registered model version (number or 'current', with --machine) or a model document JSON",
    )
    p.add_argument("--machine", default=None, help="machine id (for a registered version, and with --api)")
    p.add_argument(
        "--db", default=None, metavar="URL", help="store URL (default: DRIFTLAB_DB_URL or the SQLite default)"
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--temps", type=Path, metavar="CSV", help="temperatures.csv: its latest scan is used")
    src.add_argument("--api", metavar="URL", help="driftlab API base URL: the machine's latest scan")
    p.add_argument(
        "--controller",
        "--format",
        required=True,
        choices=[*CONTROLLERS, *ALIASES],
        dest="controller",
        help="the controller generation: " + ", ".join(CONTROLLERS),
    )
    p.add_argument("--axis", required=True, help="X Y Z A B")
    p.add_argument(
        "--range", required=True, metavar="FROM,TO", help="axis positions the table covers, exactly (mm or deg)"
    )
    p.add_argument(
        "--travel",
        default=None,
        metavar="FROM,TO",
        help="the axis travel the range must lie in (default: the virtual machine's, Tables A.3 and A.4)",
    )
    p.add_argument("--step", type=float, default=None, help="largest spacing of the table's points (10 mm / 5 deg)")
    p.add_argument(
        "--pose", default="0,0,0,0,0", metavar="X,Y,Z,A,B", help="where the other axes stand (mm, deg; default home)"
    )
    p.add_argument("--reference", type=float, default=0.0, help="fanuc: the reference position (a grid point; 0)")
    p.add_argument(
        "--reference-return",
        choices=("+", "-"),
        default="+",
        help="fanuc: the direction of reference position return (No. 3627 is relative to it)",
    )
    p.add_argument("--first-point", type=int, default=None, help="fanuc: first compensation point number")
    p.add_argument("--detection-unit", type=float, default=0.0001, help="fanuc: detection unit (0.0001 mm, IS-C)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="FILE")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    p.set_defaults(func=_run)


def _numbers(text: str, n: int, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != n:
        raise ValidationError(f"{what} must be {n} numbers separated by commas, got {text!r}")
    return values


def _model(args: argparse.Namespace) -> Any:
    """Return the ErrorModel of a model document file or of a registered version."""
    # lazy: this function's imports would add 1.6 s to `driftlab --help` (measured)
    from driftlab.compensator.compensate import ErrorModel

    path = Path(args.model)
    if path.suffix.lower() == ".json" or path.is_file():
        return _model_file(path, args.machine)
    if not args.machine:
        raise ValidationError("--model VERSION needs --machine ID (or give a model document .json file)")
    # lazy, as above: kept off the `driftlab --help` path
    from driftlab.campaigns.store import connect
    from driftlab.jobs.registry import get_model
    from driftlab.models.document import document_json

    store = connect(args.db)
    try:
        doc = get_model(store, args.machine, args.model)
    finally:
        store.close()
    return ErrorModel.from_document(document_json(doc))


def _temperatures(args: argparse.Namespace, model: Any) -> dict[str, float]:
    if args.temps is not None:
        # lazy: this function's imports would add 0.8 s to `driftlab --help` (measured)
        from driftlab.compensator.compensate import TemperatureTable

        return TemperatureTable.read_csv(args.temps).latest(model.channels)
    # lazy, as above: kept off the `driftlab --help` path
    from driftlab.compensator.stream import ApiTemperatures
    from driftlab.config import get_settings

    machine = args.machine or model.machine
    if not machine:
        raise ValidationError("--api needs --machine ID")
    return ApiTemperatures(args.api, machine, token=get_settings().api_token or None).read()


def _travel(args: argparse.Namespace, axis: str, model: Any = None) -> tuple[float, float, str]:
    """Return the axis travel and where it comes from: --travel, the model's envelope, or the virtual machine."""
    if args.travel is not None:
        lo, hi = _numbers(args.travel, 2, "--travel")
        return lo, hi, "--travel"
    envelope = getattr(model, "envelope", None)
    if envelope is not None and axis in envelope.travel:
        lo, hi = envelope.travel[axis]
        return float(lo), float(hi), f"the model's envelope{f' ({envelope.source})' if envelope.source else ''}"
    # lazy: this function's imports would add 0.2 s to `driftlab --help` (measured)
    from driftlab.daq.sim.truth import AXIS_RANGE

    lo, hi = AXIS_RANGE[axis]
    return lo, hi, "the virtual machine's travel (give --travel for another machine)"


def _check_travel(lo: float, hi: float, travel: tuple[float, float, str], axis: str, unit: str) -> None:
    t_lo, t_hi, t_src = travel
    if not (t_lo - 1e-9 <= lo and hi <= t_hi + 1e-9):
        raise ValidationError(
            f"the range {lo:g}..{hi:g} {unit} lies outside the {axis} travel {t_lo:g}..{t_hi:g} {unit} ({t_src})"
        )


def _run(args: argparse.Namespace) -> int:
    """Check the range and grid, evaluate the model there, write the file(s) atomically, print the settings."""
    # lazy: this function's imports would add 0.6 s to `driftlab --help` (measured)
    from driftlab.compensator.exports.grid import ROTARY, controller_grid, correction_table, describe
    from driftlab.compensator.exports.writers import write

    axis = args.axis.upper()
    if axis not in AXES:
        raise ValidationError(f"axis {args.axis!r} is not one of {' '.join(AXES)}")
    ctl = controller(args.controller)
    lo, hi = _numbers(args.range, 2, "--range")
    pose = _numbers(args.pose, 5, "--pose")
    unit = "deg" if axis in ROTARY else "mm"
    if args.travel is not None:  # a usage error costs nothing: checked before the model is loaded
        _check_travel(lo, hi, _travel(args, axis), axis, unit)
    step = args.step if args.step is not None else (5.0 if axis in ROTARY else 10.0)
    # the grid is checked before the model is loaded: a usage error costs nothing
    grid = controller_grid(
        ctl.spacing, ctl.max_points, lo, hi, step, reference=args.reference, unit=args.detection_unit
    )
    model = _model(args)
    travel = _travel(args, axis, model)
    _check_travel(lo, hi, travel, axis, unit)
    t_lo, t_hi, _ = travel
    temps = _temperatures(args, model)
    table = correction_table(model, temps, axis, grid.positions, pose=pose)
    options: dict[str, Any] = {}
    if ctl.family == "fanuc":
        options = {
            "reference": args.reference,
            "detection_unit": args.detection_unit,
            "first_point": args.first_point,
            "reference_return": 1 if args.reference_return == "+" else -1,
        }
    export = write(ctl.name, table, **options)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    written = []
    for suffix, text in export.files.items():
        path = args.out if not suffix else args.out.with_name(args.out.stem + suffix + args.out.suffix)
        tmp = path.with_name(path.name + ".part")
        tmp.write_text(text, encoding="ascii")
        tmp.replace(path)
        written.append(str(path))
    notes = [*grid.notes, *export.notes]
    described = describe(table)
    summary = {
        "out": str(args.out),
        "files": written,
        "controller": ctl.name,
        "format": ctl.name,
        **described,
        "travel": [t_lo, t_hi],
        "settings": export.settings,
        "notes": notes,
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"wrote {', '.join(written)}: {ctl.title} of {axis}, {table.positions.size} points "
            f"{table.positions[0]:g}..{table.positions[-1]:g} {table.unit}, model {table.model}; "
            f"largest correction {length_text(max(described['max_forward'], described['max_reverse']), table.unit)}"
        )
        for note in notes:
            print(f"  note: {note}")
        for k, v in export.settings.items():
            print(f"  {k} = {v}")
    return 0
