"""`driftlab import` and `driftlab export`: campaign bundles v1 in and out of the store."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from driftlab.commands.db import add_db_option
from driftlab.labels import duration

if TYPE_CHECKING:
    from driftlab.campaigns.bundle import Bundle
    from driftlab.campaigns.staging import StagedBundle


def register(sub: argparse._SubParsersAction) -> None:
    """Register `import BUNDLE_DIR` and `export CAMPAIGN OUT_DIR`."""
    imp = sub.add_parser("import", help="validate a bundle v1 directory and store it as a new campaign")
    imp.add_argument("bundle", type=Path, metavar="BUNDLE_DIR")
    imp.add_argument("--json", action="store_true", help="print what was stored as one JSON object (for scripts)")
    add_db_option(imp)
    imp.set_defaults(func=_import)
    exp = sub.add_parser("export", help="write a stored campaign as a bundle v1 directory")
    exp.add_argument("campaign", type=int, metavar="CAMPAIGN", help="campaign id (see `campaign list`)")
    exp.add_argument("out", type=Path, metavar="OUT_DIR")
    add_db_option(exp)
    exp.set_defaults(func=_export)


def _import(args: argparse.Namespace) -> int:
    """Validate the whole bundle, write it in one transaction, say what was stored (or JSON with --json).

    The bundle is validated and staged a chunk at a time (memory does not grow with its size), in one
    transaction: a bad row anywhere leaves the store as it was (``campaigns.import_pipeline``: on
    PostgreSQL the files are read while the server writes).
    """
    # lazy: this function's imports would add 1.4 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect
    from driftlab.progress import progress

    with progress(f"importing {args.bundle}"):  # a spinner: reading and storing overlap, neither knows its length
        with connect(args.db) as store, store.campaigns.import_directory(args.bundle) as imported:
            summary = import_summary(imported.campaign_id, imported.bundle)
    if args.json:
        print(json.dumps(summary))
        return 0
    _print_import(summary)
    return 0


class ImportSummary(TypedDict):
    """What an import stored (``driftlab import --json``)."""

    campaign_id: int
    name: str
    machine: str
    started_at: str
    channels: int
    room_channels: int
    scans: int
    temperature_readings: int
    missing_readings: int
    condition_rows: int
    error_readings: int
    error_terms: list[str]
    stages: int
    span_s: float


def import_summary(campaign_id: int, bundle: Bundle | StagedBundle) -> ImportSummary:
    """Return what an import stored: machine, channels, readings, time span, stages, error terms.

    ``bundle`` is a Bundle or a StagedBundle: its tables are read a chunk at a time.
    """
    # lazy: this function's imports would add 1.7 s to `driftlab --help` (measured)
    import numpy as np

    from driftlab.campaigns.bundle import as_table

    meta = bundle.meta
    temps, errors = as_table(bundle.temperatures), as_table(bundle.errors)
    chans = [c for c in temps.columns if c != "time_s"]
    present = sum(int((~np.isnan(np.asarray(part, dtype="f8"))).sum()) for c in chans for part in temps.column(c))
    t_min, t_max = np.inf, -np.inf
    for part in temps.column("time_s"):
        if len(part):
            t_min, t_max = min(t_min, float(np.min(part))), max(t_max, float(np.max(part)))
    terms: set[str] = set()
    for chunk in errors.chunks(["axis", "term"]):
        terms.update(f"{a}/{b}" for a, b in set(zip(chunk["axis"], chunk["term"])))
    conditions = None if bundle.conditions is None else as_table(bundle.conditions)
    return {
        "campaign_id": int(campaign_id),
        "name": bundle.name,
        "machine": meta.machine.id,
        "started_at": meta.started_at.isoformat().replace("+00:00", "Z")
        if hasattr(meta.started_at, "isoformat")
        else str(meta.started_at),
        "channels": len(chans),
        "room_channels": len(meta.room_channels),
        "scans": int(temps.n_rows),
        "temperature_readings": present,
        "missing_readings": temps.n_rows * len(chans) - present,
        "condition_rows": 0 if conditions is None else int(conditions.n_rows),
        "error_readings": int(errors.n_rows),
        "error_terms": sorted(terms),
        "stages": len(meta.stages),
        "span_s": t_max - t_min if temps.n_rows else 0.0,
    }


def _print_import(s: ImportSummary) -> None:
    """Print an import's summary as a short table."""
    # lazy: this function's imports would add 76 ms to `driftlab --help` (measured)
    from rich.table import Table

    from driftlab.progress import stdout_console

    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold", justify="right")
    t.add_column()
    t.add_row("stored", f"campaign {s['campaign_id']} ({s['name']}) of machine {s['machine']}")
    t.add_row("started", s["started_at"])
    t.add_row("span", f"{duration(s['span_s'])} in {s['stages']} stage{'s' if s['stages'] != 1 else ''}")
    t.add_row("thermocouples", f"{s['channels']} ({s['room_channels']} in the room air)")
    t.add_row(
        "temperatures",
        f"{s['scans']} scans, {s['temperature_readings']} readings"
        + (f", {s['missing_readings']} missing" if s["missing_readings"] else ""),
    )
    t.add_row("machine state", f"{s['condition_rows']} rows")
    t.add_row("errors", f"{s['error_readings']} readings of {', '.join(s['error_terms']) or 'no term'}")
    stdout_console().print(t)


def _export(args: argparse.Namespace) -> int:
    """Write the campaign's bundle and say where."""
    # lazy: this function's imports would add 3.6 s to `driftlab --help` (measured)
    from driftlab.campaigns.bundle import write_bundle
    from driftlab.campaigns.store import connect

    with connect(args.db) as store:
        b = store.campaigns.load(args.campaign)
    path = write_bundle(args.out, b.meta, b.temperatures, b.conditions, b.errors)
    print(f"wrote {path} ({len(b.temperatures)} scans, {len(b.errors)} error samples)")
    return 0
