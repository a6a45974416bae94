"""`driftlab diagnose`: what the simulation gets wrong, which effect causes it, and the held-out gain."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from driftlab.errors import ValidationError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Register `diagnose (BUNDLE_DIR | --campaign ID [--db URL]) --json REPORT.json [--html REPORT.html]`."""
    p = sub.add_parser("diagnose", help="diagnose a campaign bundle: simulation vs data, effects, held-out gain")
    p.add_argument("bundle", type=Path, nargs="?", default=None, metavar="BUNDLE_DIR",
                   help="campaign bundle v1 directory (or --campaign for a stored campaign)")
    p.add_argument("--campaign", type=int, default=None, metavar="ID", help="diagnose a campaign in the store")
    p.add_argument("--db", default=None, metavar="URL", help="store URL (default: DRIFTLAB_DB_URL or the SQLite default)")
    p.add_argument("--json", type=Path, required=True, metavar="REPORT.json", help="write the report v1 here")
    p.add_argument("--html", type=Path, default=None, metavar="REPORT.html", help="also write an HTML page")
    p.add_argument("--holdout-fraction", type=float, default=0.25,
                   help="fraction of each (axis, term)'s rows, last in time, held out (default 0.25)")
    p.set_defaults(func=_diagnose)


def _diagnose(args: argparse.Namespace) -> int:
    """Load and validate the bundle, diagnose it, write the report(s); 0 whatever was found."""
    from driftlab.campaigns.bundle import load_bundle
    from driftlab.models.diagnosis import diagnose_bundle

    if not 0.0 < args.holdout_fraction < 0.9:
        raise ValidationError(f"--holdout-fraction must be in (0, 0.9), got {args.holdout_fraction}")
    if (args.bundle is None) == (args.campaign is None):
        raise ValidationError("give either a BUNDLE_DIR or --campaign ID, not both or neither")
    if args.campaign is not None:
        from driftlab.campaigns.store import connect

        bundle = connect(args.db).load_campaign(args.campaign)  # NotFoundError for an unknown id
    else:
        bundle = load_bundle(args.bundle)  # BundleError: one line FILE:ROW: problem
    result = diagnose_bundle(bundle, holdout_fraction=args.holdout_fraction)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result.to_json_dict(), indent=2, allow_nan=False) + "\n")
    if args.html is not None:
        args.html.parent.mkdir(parents=True, exist_ok=True)
        args.html.write_text(result.to_html(), encoding="utf-8")
    n = len(result.effects)
    print(f"diagnosed {bundle.name}: {n} effect{'s' if n != 1 else ''} accepted; report {args.json}")
    return 0
