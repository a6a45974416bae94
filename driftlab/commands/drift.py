"""`driftlab drift`: the measured error history of one axis and term across a machine's campaigns."""

from __future__ import annotations

import argparse
import os
import sys
from datetime import UTC, datetime

from driftlab.commands.db import add_db_option
from driftlab.errors import ValidationError
from driftlab.labels import display_unit


def _direction(text: str) -> int:
    """Parse +1 / -1."""
    if text.strip() in ("+1", "1"):
        return 1
    if text.strip() == "-1":
        return -1
    raise argparse.ArgumentTypeError(f"direction must be +1 or -1, not {text!r}")


def _when(text: str) -> datetime:
    """Parse an ISO 8601 time; without a zone it is UTC."""
    try:
        value = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an ISO 8601 time: {text!r}") from None
    return value if value.tzinfo else value.replace(tzinfo=UTC)


def register(sub: argparse._SubParsersAction) -> None:
    """Register `drift`."""
    p = sub.add_parser("drift", help="error history of an axis/term across campaigns, in wall-clock time")
    p.add_argument("--machine", required=True, help="machine id")
    p.add_argument("--axis", required=True, help="X Y Z A B")
    p.add_argument("--term", required=True, help="dx dy dz alpha beta gamma")
    p.add_argument(
        "--position",
        type=float,
        default=None,
        help="at this position: the nearest measured one (or interpolated with --interpolate)",
    )
    p.add_argument("--interpolate", action="store_true", help="interpolate linearly along position in each sweep")
    p.add_argument("--direction", type=_direction, default=None, help="+1 or -1 (default: both)")
    p.add_argument("--from", dest="start", type=_when, default=None, help="ISO 8601 start time (UTC if no zone)")
    p.add_argument("--to", dest="end", type=_when, default=None, help="ISO 8601 end time")
    p.add_argument("--csv", action="store_true", help="CSV instead of a table")
    add_db_option(p)
    p.set_defaults(func=_drift)


def _drift(args: argparse.Namespace) -> int:
    """Print the history as an aligned table or CSV."""
    # lazy: this function's imports would add 1.7 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect

    if args.start and args.end and args.end < args.start:
        raise ValidationError("--to is before --from")
    with connect(args.db) as store:
        frame = store.readings.drift(
            args.machine, args.axis, args.term, args.position, args.direction, args.start, args.end, args.interpolate
        )
    frame = frame.copy()
    frame["time"] = frame["time"].map(lambda t: t.isoformat().replace("+00:00", "Z"))
    if args.csv:
        try:
            frame.to_csv(sys.stdout, index=False, lineterminator="\n")
        except BrokenPipeError:  # e.g. piped into head: not an error
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the flush at exit
        return 0
    if frame.empty:
        print("no measurements")
        return 0

    # for people: the unit beside every value (the CSV keeps the store's mm / rad, exactly)
    factor, unit = display_unit(args.term)
    frame["value"] = frame["value"] * factor
    pos_unit = "deg" if args.axis.upper() in ("A", "B") else "mm"
    frame = frame.rename(columns={"value": f"value ({unit})", "position": f"position ({pos_unit})"})
    print(frame.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    return 0
