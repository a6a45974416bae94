"""`driftlab campaign`: stored campaigns."""

from __future__ import annotations

import argparse
import json

from driftlab.commands.db import add_db_option


def register(sub: argparse._SubParsersAction) -> None:
    """Register `campaign list`."""
    camp = sub.add_parser("campaign", help="stored campaigns")
    campsub = camp.add_subparsers(dest="campaign_command", metavar="CAMPAIGNCOMMAND", required=True)
    lst = campsub.add_parser("list", help="list stored campaigns")
    lst.add_argument("--machine", default=None, help="only this machine's campaigns")
    lst.add_argument("--json", action="store_true", help="one JSON array instead of a table")
    add_db_option(lst)
    lst.set_defaults(func=_list)
    from driftlab.commands.daemon import register_status

    register_status(campsub)


def _list(args: argparse.Namespace) -> int:
    """Print the campaigns as a table or JSON."""
    from driftlab.campaigns.store import connect

    with connect(args.db) as store:
        rows = [c.as_dict() for c in store.list_campaigns(args.machine)]
    if args.json:
        print(json.dumps(rows))
        return 0
    header = ("id", "machine_id", "name", "started_at", "status", "source", "channels", "scans", "error_samples")
    table = [header] + [tuple(str(r[k]) for k in header) for r in rows]
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]
    for row in table:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
    return 0
