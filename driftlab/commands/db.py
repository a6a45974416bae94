"""`driftlab db`: bring a campaign store's schema to the current revision."""

from __future__ import annotations

import argparse


def add_db_option(parser: argparse.ArgumentParser) -> None:
    """Add the common ``--db URL`` option (default: DRIFTLAB_DB_URL or the embedded SQLite file)."""
    parser.add_argument("--db", metavar="URL", default=None,
                        help="database URL (default: DRIFTLAB_DB_URL or the embedded SQLite file)")


def register(sub: argparse._SubParsersAction) -> None:
    """Register `db upgrade` and `db current`."""
    dbp = sub.add_parser("db", help="manage the campaign store's schema")
    dbsub = dbp.add_subparsers(dest="db_command", metavar="DBCOMMAND", required=True)
    up = dbsub.add_parser("upgrade", help="bring the database to the newest schema revision")
    add_db_option(up)
    up.add_argument("--revision", default="head", help="target revision (default: head)")
    up.set_defaults(func=_upgrade)
    cur = dbsub.add_parser("current", help="print the database's schema revision")
    add_db_option(cur)
    cur.set_defaults(func=_current)


def _upgrade(args: argparse.Namespace) -> int:
    """Upgrade the schema and print the revision reached."""
    from driftlab.campaigns.store import connect

    with connect(args.db, auto_upgrade=False) as store:
        reached = store.upgrade(args.revision)
        print(f"{store.url}: at revision {reached}")
    return 0


def _current(args: argparse.Namespace) -> int:
    """Print the schema revision (or 'empty')."""
    from driftlab.campaigns.store import connect

    with connect(args.db, auto_upgrade=False) as store:
        print(store.revision() or "empty")
    return 0
