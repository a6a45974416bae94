"""`driftlab import` and `driftlab export`: campaign bundles v1 in and out of the store."""

from __future__ import annotations

import argparse
from pathlib import Path

from driftlab.commands.db import add_db_option


def register(sub: argparse._SubParsersAction) -> None:
    """Register `import BUNDLE_DIR` and `export CAMPAIGN OUT_DIR`."""
    imp = sub.add_parser("import", help="validate a bundle v1 directory and store it as a new campaign")
    imp.add_argument("bundle", type=Path, metavar="BUNDLE_DIR")
    add_db_option(imp)
    imp.set_defaults(func=_import)
    exp = sub.add_parser("export", help="write a stored campaign as a bundle v1 directory")
    exp.add_argument("campaign", type=int, metavar="CAMPAIGN", help="campaign id (see `campaign list`)")
    exp.add_argument("out", type=Path, metavar="OUT_DIR")
    add_db_option(exp)
    exp.set_defaults(func=_export)


def _import(args: argparse.Namespace) -> int:
    """Validate the whole bundle, write it in one transaction, print the new campaign id."""
    from driftlab.campaigns.bundle import load_bundle
    from driftlab.campaigns.store import connect

    bundle = load_bundle(args.bundle)
    with connect(args.db) as store:
        campaign_id = store.import_bundle(bundle)
    print(campaign_id)
    return 0


def _export(args: argparse.Namespace) -> int:
    """Write the campaign's bundle and say where."""
    from driftlab.campaigns.bundle import write_bundle
    from driftlab.campaigns.store import connect

    with connect(args.db) as store:
        b = store.load_campaign(args.campaign)
    path = write_bundle(args.out, b.meta, b.temperatures, b.conditions, b.errors)
    print(f"wrote {path} ({len(b.temperatures)} scans, {len(b.errors)} error samples)")
    return 0
