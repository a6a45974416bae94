"""`driftlab import-instrument`: a laser's or other instrument's export file -> a campaign bundle directory."""

from __future__ import annotations

import argparse
from pathlib import Path

from driftlab.errors import ValidationError
from driftlab.metrology.importers import FORMATS


def register(sub: argparse._SubParsersAction) -> None:
    """Register `import-instrument FILE --format rtx|renishaw-csv|generic [--mapping MAP] -o BUNDLE_DIR`."""
    p = sub.add_parser(
        "import-instrument",
        help="turn a Renishaw .rtx / CSV export, or any CSV with a column mapping, into a campaign bundle",
        description="The bundle is validated in full before it appears; a bad file is one line "
        "FILE:ROW: problem and nothing is written. Import it into the store with `driftlab import`.",
    )
    p.add_argument("file", type=Path, help="the instrument's export file")
    p.add_argument("--format", required=True, choices=FORMATS, dest="fmt")
    p.add_argument("--mapping", type=Path, default=None, help="generic: the column mapping (YAML or JSON)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="BUNDLE_DIR", help="new bundle directory")
    p.add_argument("--machine", default=None, help="machine id (when the file names none, or to override it)")
    p.add_argument("--started-at", default=None, metavar="ISO_TIME", help="when the test started (overrides the file)")
    p.add_argument(
        "--air-temp", type=float, default=None, metavar="DEGC", help="the room temperature, for files that record none"
    )
    p.add_argument("--axis", default=None, help="rtx / renishaw-csv: the axis (overrides the file's)")
    p.add_argument("--position", type=float, default=0.0, help="rtx: where the capture was taken (mm or deg)")
    p.add_argument(
        "--unit",
        default=None,
        help="rtx: unit of the samples, which the header does not state (mm, um, nm, arcsec, urad; µm is assumed)",
    )
    p.add_argument(
        "--date-order",
        choices=("dmy", "mdy", "ymd"),
        default=None,
        help="rtx: order of the header's slashed date (day first is assumed when it could be either)",
    )
    p.add_argument("--interval-s", type=float, default=1.0, help="rtx: average the samples over this (1 s)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    """Read the file, write and validate the bundle, print a one-line summary."""
    # lazy: this function's imports would add 1.0 s to `driftlab --help` (measured)
    from driftlab.metrology.importers import common, generic, renishaw

    if not args.file.is_file():
        raise ValidationError(f"{args.file}: no such file")
    if args.fmt == "generic":
        if args.mapping is None:
            raise ValidationError(
                "--format generic needs --mapping MAP.yaml (columns -> axis, term, position, direction)"
            )
        readings = generic.read_generic(args.file, generic.load_mapping(args.mapping), args.mapping.name)
    elif args.mapping is not None:
        raise ValidationError(f"--mapping is for --format generic, not {args.fmt}")
    elif args.fmt == "rtx":
        readings = renishaw.read_rtx(
            args.file,
            axis=args.axis,
            position=args.position,
            unit=args.unit,
            interval_s=args.interval_s,
            date_order=args.date_order,
        )
    else:
        readings = renishaw.read_renishaw_csv(args.file, axis=args.axis)
    started = common.parse_time(args.started_at, "--started-at") if args.started_at else None
    out = common.write_readings(
        readings, args.out, machine=args.machine, started_at=started, air_temp_degC=args.air_temp
    )
    e = readings.errors
    cells = ", ".join(sorted({f"{a}/{t}" for a, t in zip(e["axis"], e["term"])}))
    print(f"wrote bundle {out}: {len(e)} readings of {cells} from {args.file.name}")
    for note in readings.assumptions:
        print(f"  assumed: {note}")
    if readings.instrument is not None:
        kept = ", ".join(k for k in readings.instrument if k not in ("instrument", "source"))
        print(f"  campaign.json keeps the instrument's record (setup 'instrument'): {kept}")
    return 0
