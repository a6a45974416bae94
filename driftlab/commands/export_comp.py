"""`driftlab export-comp`: the model's correction of one axis as a controller's compensation table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from driftlab.errors import ValidationError


def register(sub: argparse._SubParsersAction) -> None:
    """Register `export-comp --model VERSION|FILE (--temps CSV | --api URL) --format F --axis X -o FILE`."""
    from driftlab.compensator.exports import FORMATS

    p = sub.add_parser(
        "export-comp",
        help="write the model's correction of an axis as a controller compensation table",
        description="LinuxCNC axis comp file, Siemens 840D LEC/CEC part program, Heidenhain .COM "
        "table, Fanuc pitch error parameter tape (docs/exports.md).",
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
    p.add_argument("--format", required=True, choices=FORMATS, dest="fmt")
    p.add_argument("--axis", required=True, help="X Y Z A B")
    p.add_argument("--range", required=True, metavar="FROM,TO", help="axis travel covered by the table (mm or deg)")
    p.add_argument("--step", type=float, default=None, help="spacing of the table's points (default 10 mm / 5 deg)")
    p.add_argument(
        "--pose", default="0,0,0,0,0", metavar="X,Y,Z,A,B", help="where the other axes stand (mm, deg; default home)"
    )
    p.add_argument("--reference", type=float, default=0.0, help="fanuc: the reference position (a grid point; 0)")
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
    from driftlab.compensator.compensate import ErrorModel

    path = Path(args.model)
    if path.suffix.lower() == ".json" or path.is_file():
        from driftlab.commands.compensate import _model_file

        return _model_file(path, args.machine)
    if not args.machine:
        raise ValidationError("--model VERSION needs --machine ID (or give a model document .json file)")
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
        from driftlab.compensator.compensate import TemperatureTable

        return TemperatureTable.read_csv(args.temps).latest(model.channels)
    from driftlab.compensator.stream import ApiTemperatures
    from driftlab.config import get_settings

    machine = args.machine or model.machine
    if not machine:
        raise ValidationError("--api needs --machine ID")
    return ApiTemperatures(args.api, machine, token=get_settings().api_token or None).read()


def _run(args: argparse.Namespace) -> int:
    """Evaluate the grid, write the table atomically, print the controller settings."""
    from driftlab.compensator.exports import write
    from driftlab.compensator.exports.grid import ROTARY, correction_table, describe, grid_positions
    from driftlab.vocabulary import AXES

    axis = args.axis.upper()
    if axis not in AXES:
        raise ValidationError(f"axis {args.axis!r} is not one of {' '.join(AXES)}")
    lo, hi = _numbers(args.range, 2, "--range")
    pose = _numbers(args.pose, 5, "--pose")
    step = args.step if args.step is not None else (5.0 if axis in ROTARY else 10.0)
    # the grid is checked before the model is loaded: a usage error costs nothing
    grid = grid_positions(lo, hi, step, args.reference if args.fmt == "fanuc" else None)
    if args.fmt == "fanuc" and not (abs(grid - args.reference) < 1e-9 * max(1.0, abs(args.reference))).any():
        raise ValidationError(f"fanuc: the reference position {args.reference:g} is outside {lo:g}..{hi:g}")
    model = _model(args)
    temps = _temperatures(args, model)
    reference = args.reference if args.fmt == "fanuc" else None
    table = correction_table(model, temps, axis, lo, hi, step, pose=pose, reference=reference)
    options: dict[str, Any] = {}
    if args.fmt == "fanuc":
        options = {"reference": args.reference, "detection_unit": args.detection_unit}
    export = write(args.fmt, table, **options)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".part")
    tmp.write_text(export.text, encoding="ascii")
    tmp.replace(args.out)
    summary = {"out": str(args.out), "format": args.fmt, **describe(table), "settings": export.settings}
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"wrote {args.out}: {args.fmt} table of {axis}, {table.positions.size} points "
            f"{table.positions[0]:g}..{table.positions[-1]:g} {table.unit}, model {table.model}; "
            f"largest correction {max(summary['max_forward'], summary['max_reverse']):.6f} {table.unit}"
        )
        for k, v in export.settings.items():
            print(f"  {k} = {v}")
    return 0
