"""A bundle directory imported into PostgreSQL with its reading and the server's writing overlapped.

`driftlab import` validates every row before the store keeps anything (a bad row at the end of the
last file leaves the store as it was) and holds a chunk of a file, not the file (``staging``).
On SQLite the bundle is staged whole and then written under the store's write lock: SQLite allows
one writer, and it writes in this process, under the interpreter lock the parse also needs. On
PostgreSQL most of an import is the server storing rows, in a process of its own, while this one
waits (a 70 h, 50-channel bundle: about 15 s of server time against 1 s of reading the CSVs and 0.1 s
of hashing). So there the reading runs while the server writes, in one transaction that any failure
rolls back:

1. errors.csv and conditions.csv (the small files) are read and staged;
2. a thread inserts the campaign's row (its content hash not yet known) and COPYs the conditions and
   the errors, while this thread reads and stages temperatures.csv;
3. the channels are inserted and the temperatures COPYed in key order (campaign, channel, time: in
   scan order the server took 1.5x as long, its primary key appended at 50 places instead of one),
   while a thread hashes the staged tables and asks, on a connection of its own, whether a stored
   campaign has that hash (a duplicate is refused a fraction into the write, not after it), and
   another computes the per-minute rollups into a temporary file;
4. the rollups are COPYed from that file, the campaign's hash and rollups flag set (the hash is
   unique: an import of the same content committed meanwhile is refused there), and the transaction
   committed.

A bad row, a duplicate, a server error, an interrupt: the transaction is rolled back, nothing stored.
The rows stored are those ``store.campaigns.import_bundle`` stores for the same bundle (tests hash both).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import BinaryIO

from sqlalchemy import Connection, Engine, select, update

from driftlab.campaigns import ingest, partitions
from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import CSV_BLOCK_BYTES, BundleFiles, open_bundle, table_hash
from driftlab.campaigns.repository import Repository, analyze
from driftlab.campaigns.staging import StagedBundle, StagedTable, stage_bundle, stage_errors, stage_frames


@dataclass
class ImportedBundle:
    """A stored bundle: its campaign id and its staged tables (closed on leaving the ``with``)."""

    campaign_id: int
    bundle: StagedBundle

    def close(self) -> None:
        """Remove the staged tables' temporary files."""
        self.bundle.close()

    def __enter__(self) -> ImportedBundle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def import_directory(
    repo: Repository,
    path: str | Path,
    store_bundle: Callable[[StagedBundle], int],
    block_bytes: int = CSV_BLOCK_BYTES,
    directory: str | None = None,
) -> ImportedBundle:
    """Validate and store the bundle in directory ``path``; return its campaign id with the staged bundle.

    ``store_bundle`` writes a staged bundle (``CampaignRepository.import_bundle``): the path of
    SQLite. BundleError (nothing stored) for a bad bundle, ConflictError for one already stored.
    """
    if repo.engine.dialect.name != "postgresql":
        staged = stage_bundle(path, block_bytes, directory)
        try:
            return ImportedBundle(store_bundle(staged), staged)
        except BaseException:
            staged.close()
            raise
    files = open_bundle(path, block_bytes)
    tables: list[StagedTable] = []
    try:
        conditions = stage_frames(files.conditions(), tables, directory)
        errors = stage_errors(files, tables, directory)
        day = partitions.start_day(files.meta.started_at)
        repo.gate.ensure()
        partitions.ensure_partitions(repo.engine, [day])
        with (
            ingest.concurrent_duplicate_refused(files.name),
            repo.write() as conn,
            ThreadPoolExecutor(2, thread_name_prefix="driftlab-import") as pool,
        ):
            imported = _write_overlapped(conn, pool, files, _Staged(tables, conditions, errors, directory, day))
    except BaseException:
        for table in tables:
            table.close()
        raise
    analyze(repo.engine, day)
    return imported


@dataclass
class _Staged:
    """What is staged before the transaction opens, and where the rest goes."""

    tables: list[StagedTable]
    conditions: StagedTable | None
    errors: StagedTable
    directory: str | None
    day: int


def _write_overlapped(conn: Connection, pool: ThreadPoolExecutor, files: BundleFiles, s: _Staged) -> ImportedBundle:
    """Steps 2-4 of the module docstring, in the caller's transaction."""
    meta = files.meta
    head = pool.submit(_write_head, conn, files, s)
    try:
        temperatures = stage_frames(files.temperatures(), s.tables, s.directory)
    finally:
        wait([head])  # the connection is the head's until it is done, whatever happened here
    campaign_id = head.result()
    assert temperatures is not None  # temperatures() yields at least one chunk or raises
    bundle = StagedBundle(files.name, meta, temperatures, s.conditions, s.errors)
    engine = conn.engine
    hashing = pool.submit(_hash_unless_stored, engine, bundle)
    channel_ids = ingest.insert_channels(conn, campaign_id, meta, bundle.channels)
    rolling = pool.submit(_spool_rollups, campaign_id, channel_ids, temperatures, s.directory)

    def refuse_a_duplicate() -> None:
        if hashing.done():
            _refuse_if_stored(bundle.name, hashing)

    try:
        ingest.copy_temperatures_pg(
            conn, campaign_id, channel_ids, temperatures, s.day, queued=True, between=refuse_a_duplicate
        )
        bundle.hash = _refuse_if_stored(bundle.name, hashing)
    except BaseException:
        rolling.add_done_callback(_close_spool)
        raise
    spooled = rolling.result()
    rollups = spooled is not None
    if spooled is not None:
        with spooled:
            tuples = iter(partial(spooled.read, 1 << 20), b"")
            ingest.copy_encoded_pg(conn, "temperature_rollups", ingest.ROLLUP_COLUMNS, tuples)
    conn.execute(
        update(sc.Campaign)
        .where(sc.Campaign.id == campaign_id)
        .values(content_hash=bundle.hash, rollups_complete=rollups)
    )
    return ImportedBundle(campaign_id, bundle)


def _write_head(conn: Connection, files: BundleFiles, s: _Staged) -> int:
    """Insert the machine (if new), the campaign (no hash yet) and its stages; COPY conditions and errors."""
    ingest.ensure_machine(conn, files.meta)
    campaign_id = ingest.insert_campaign(conn, files.meta, files.name, s.conditions, None, False)
    ingest.write_conditions(conn, campaign_id, s.conditions, s.day)
    ingest.write_errors(conn, campaign_id, s.errors, files.meta, s.day)
    return campaign_id


def _spool_rollups(
    campaign_id: int, channel_ids: list[int], temperatures: StagedTable, directory: str | None
) -> BinaryIO | None:
    """Return the rollups' COPY tuples in a temporary file read from its start (None: they do not pay)."""
    if not ingest.rollups_pay_chunks(temperatures.column("time_s")):
        return None
    spool = tempfile.TemporaryFile(prefix="driftlab-rollups-", dir=directory)
    try:
        for piece in ingest.encode_rollups_pg(campaign_id, channel_ids, temperatures):
            spool.write(piece)
        spool.seek(0)
    except BaseException:
        spool.close()
        raise
    return spool


def _close_spool(future: Future[BinaryIO | None]) -> None:
    """Close the rollups' temporary file of an import that failed before reading it."""
    if future.exception() is None and (spool := future.result()) is not None:
        spool.close()


def _hash_unless_stored(engine: Engine, bundle: StagedBundle) -> tuple[str, int | None]:
    """Return the bundle's content hash and the id of a stored campaign with that hash (None: none)."""
    content_hash = table_hash(bundle.meta, bundle.temperatures, bundle.conditions, bundle.errors)
    with engine.connect() as other:  # not the import's connection: that one is busy with the COPY
        existing = other.execute(select(sc.Campaign.id).where(sc.Campaign.content_hash == content_hash)).scalar()
    return content_hash, existing


def _refuse_if_stored(name: str, hashing: Future[tuple[str, int | None]]) -> str:
    """Return the content hash; ConflictError when a stored campaign has it (the same words as an import of it)."""
    content_hash, existing = hashing.result()
    if existing is not None:
        raise ingest.already_stored(name, existing, content_hash)
    return content_hash
