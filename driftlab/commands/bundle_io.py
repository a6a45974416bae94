"""`driftlab import` and `driftlab export`: campaign bundles v1 in and out of the store."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from driftlab.commands.db import add_db_option


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
    """Validate the whole bundle, write it in one transaction, say what was stored (or JSON with --json)."""
    import json

    from driftlab.campaigns.bundle import load_bundle
    from driftlab.campaigns.store import connect
    from driftlab.progress import progress

    with progress(f"validating {args.bundle}") as bar:  # spinners: neither step knows its length in advance
        bundle = load_bundle(args.bundle)
        bar.update(description=f"storing {bundle.name}")
        with connect(args.db) as store:
            campaign_id = store.import_bundle(bundle)
    summary = import_summary(campaign_id, bundle)
    if args.json:
        print(json.dumps(summary))
        return 0
    _print_import(summary)
    return 0


def import_summary(campaign_id: int, bundle: Any) -> dict[str, Any]:
    """Return what an import stored: machine, channels, readings, time span, stages, error terms."""
    meta, temps, errors = bundle.meta, bundle.temperatures, bundle.errors
    chans = [c for c in temps.columns if c != "time_s"]
    t = temps["time_s"]
    terms = sorted({f"{a}/{b}" for a, b in zip(errors["axis"], errors["term"])}) if len(errors) else []
    return {
        "campaign_id": int(campaign_id), "name": bundle.name, "machine": meta.machine.id,
        "started_at": meta.started_at.isoformat().replace("+00:00", "Z") if hasattr(meta.started_at, "isoformat")
        else str(meta.started_at),
        "channels": len(chans), "room_channels": len(meta.room_channels), "scans": int(len(temps)),
        "temperature_readings": int(temps[chans].notna().sum().sum()) if chans else 0,
        "missing_readings": int(temps[chans].isna().sum().sum()) if chans else 0,
        "condition_rows": 0 if bundle.conditions is None else int(len(bundle.conditions)),
        "error_readings": int(len(errors)), "error_terms": terms, "stages": len(meta.stages),
        "span_s": float(t.max() - t.min()) if len(t) else 0.0,
    }


def _print_import(s: dict[str, Any]) -> None:
    """Print an import's summary as a short table."""
    from rich.table import Table

    from driftlab.labels import duration
    from driftlab.progress import stdout_console

    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold", justify="right")
    t.add_column()
    t.add_row("stored", f"campaign {s['campaign_id']} ({s['name']}) of machine {s['machine']}")
    t.add_row("started", s["started_at"])
    t.add_row("span", f"{duration(s['span_s'])} in {s['stages']} stage{'s' if s['stages'] != 1 else ''}")
    t.add_row("thermocouples", f"{s['channels']} ({s['room_channels']} in the room air)")
    t.add_row("temperatures", f"{s['scans']} scans, {s['temperature_readings']} readings"
              + (f", {s['missing_readings']} missing" if s["missing_readings"] else ""))
    t.add_row("machine state", f"{s['condition_rows']} rows")
    t.add_row("errors", f"{s['error_readings']} readings of {', '.join(s['error_terms']) or 'no term'}")
    stdout_console().print(t)


def _export(args: argparse.Namespace) -> int:
    """Write the campaign's bundle and say where."""
    from driftlab.campaigns.bundle import write_bundle
    from driftlab.campaigns.store import connect

    with connect(args.db) as store:
        b = store.load_campaign(args.campaign)
    path = write_bundle(args.out, b.meta, b.temperatures, b.conditions, b.errors)
    print(f"wrote {path} ({len(b.temperatures)} scans, {len(b.errors)} error samples)")
    return 0
