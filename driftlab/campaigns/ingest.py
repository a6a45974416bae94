"""Bulk ingest of a validated bundle: one transaction, COPY on PostgreSQL, multi-row INSERTs on SQLite.

The bundle's tables may be frames in memory (``Bundle``) or staged on disk (``StagedBundle``):
either way they are read a chunk at a time (``bundle.ColumnTable``), and every row goes to the
driver as it is made, so memory holds a chunk whatever the bundle's size. What spans chunks
(sweep numbers, per-minute rollups) carries its state from one chunk to the next.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import chain, islice, repeat
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from psycopg.copy import QueuedLibpqWriter
from sqlalchemy import Connection, insert, select, text
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.exc import IntegrityError

from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import POSE_COLUMNS, Bundle, CampaignMeta, ColumnTable, FrameTable, as_table
from driftlab.campaigns.partitions import leaf, start_day
from driftlab.errors import ConflictError

if TYPE_CHECKING:
    from psycopg import Cursor

CONDITION_VALUE_COLUMNS = ("spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b")
TEMPERATURE_COLUMNS = ("campaign_id", "channel_id", "time_s", "value", "campaign_start_day")
TEMPERATURE_TYPES = ("int4", "int4", "float8", "float8", "int4")
#: condition_samples as ``condition_rows`` gives them, and their PostgreSQL types (binary COPY)
CONDITION_ROW_COLUMNS = ("campaign_id", "time_s", *CONDITION_VALUE_COLUMNS, "campaign_start_day")
CONDITION_ROW_TYPES = ("int4", "float8", *["float8"] * len(CONDITION_VALUE_COLUMNS), "int4")
ERROR_COLUMNS = (
    "campaign_id",
    "seq",
    "time_s",
    "axis",
    "term",
    "position",
    "direction",
    "value",
    "sweep",
    "flags",
    "campaign_start_day",
)


class SweepCounter:
    """Sweep numbers of error rows given a chunk at a time: within (axis, term, direction), in time
    order, a new sweep starts when the position repeats or stops moving the same way."""

    def __init__(self) -> None:
        self._state: dict[str, tuple[float, int, float]] = {}  # key -> (last position, sweep, sign)

    def numbers(self, axis: np.ndarray, term: np.ndarray, direction: np.ndarray, position: np.ndarray) -> np.ndarray:
        """Return the sweep number of each row of the next chunk."""
        out = np.zeros(len(position), dtype=np.int64)
        keys = pd.Series(axis).astype(str) + "|" + pd.Series(term).astype(str) + "|" + pd.Series(direction).astype(str)
        positions = np.asarray(position, dtype="f8")
        for key, idx in keys.groupby(keys, sort=False).indices.items():
            p = positions[idx]
            numbers = np.empty(len(idx), dtype=np.int64)
            if key in self._state:
                last, sweep, sign = self._state[key]
                start = 0
            else:
                last, sweep, sign = p[0], 0, 0.0
                numbers[0] = 0
                start = 1
            for k in range(start, len(idx)):
                d = p[k] - last
                step = np.sign(d)
                if d == 0 or (sign != 0 and step != sign):
                    sweep += 1
                    sign = 0.0
                else:
                    sign = step
                numbers[k] = sweep
                last = p[k]
            self._state[key] = (float(last), sweep, float(sign))
            out[idx] = numbers
        return out


def sweep_numbers(errors: pd.DataFrame) -> np.ndarray:
    """Return a sweep number per error row (see SweepCounter) of a whole frame."""
    return SweepCounter().numbers(
        errors["axis"].to_numpy(),
        errors["term"].to_numpy(),
        errors["direction"].to_numpy(),
        errors["position"].to_numpy(),
    )


def _copy_rows(
    conn: Connection,
    table: str,
    columns: Sequence[str],
    types: Sequence[str],
    rows: Iterable[Sequence[Any]],
    queued: bool = False,
) -> None:
    """Stream rows into a PostgreSQL table with binary COPY inside the current transaction (``queued``: see
    ``copy_writer``)."""
    raw = conn.connection.driver_connection
    cols = ", ".join(columns)
    with raw.cursor() as cur:  # type: ignore[union-attr]
        with cur.copy(f"COPY {table} ({cols}) FROM STDIN (FORMAT BINARY)", writer=copy_writer(cur, queued)) as copy:
            copy.set_types(list(types))
            write = copy.write_row
            for row in rows:
                write(row)


def copy_writer(cur: Cursor[Any], queued: bool) -> QueuedLibpqWriter | None:
    """Return the writer of a COPY: with ``queued`` psycopg's QueuedLibpqWriter (psycopg 3 docs, "COPY
    from and to", writer objects), whose thread sends the data while this one encodes the next rows, so
    the server is not left waiting on the encoding (an import: millions of rows); else None, psycopg's
    default writer, which sends in this thread (a daemon's batch: a thread each would cost more)."""
    return QueuedLibpqWriter(cur) if queued else None


def bulk_insert(
    conn: Connection,
    table: str,
    columns: Sequence[str],
    pg_types: Sequence[str],
    rows: Iterable[Sequence[Any]],
    into: str | None = None,
    *,
    queued: bool = False,
) -> None:
    """Insert many rows fast in the connection's transaction: binary COPY or sqlite3 executemany.

    ``into`` names the partition of ``table`` every row belongs to, when known (PostgreSQL);
    ``queued``: see ``copy_writer``.
    """
    if conn.dialect.name == "postgresql":
        _copy_rows(conn, into or table, columns, pg_types, rows, queued)
        return
    raw = conn.connection.driver_connection
    row = f"({', '.join('?' for _ in columns)})"
    cur = raw.cursor()  # type: ignore[union-attr]
    try:
        head = f"INSERT INTO {table} ({', '.join(columns)}) VALUES "
        it = iter(rows)
        while chunk := list(islice(it, SQLITE_CHUNK_ROWS)):
            insert_flat_sqlite(cur, head, row, len(columns), list(chain.from_iterable(chunk)))
    finally:
        cur.close()


#: rows of one multi-row INSERT on SQLite: sqlite3's ``executemany`` resets, binds and steps its
#: statement (and releases and retakes the interpreter lock) once per row, which costs about three
#: times what SQLite itself spends storing a reading; one statement of many rows pays that once per
#: statement (the rows, their order and so the stored file are the same). 128 rows measured as good
#: as 512 and better than 64 (one thread: 0.36 against 1.1 CPU-us a temperature reading).
SQLITE_ROWS_PER_STATEMENT = 128
#: rows of an iterable gathered and flattened at a time (``bulk_insert``): memory holds a chunk
SQLITE_CHUNK_ROWS = 64 * SQLITE_ROWS_PER_STATEMENT


#: a value bound to an SQLite statement
SqlValue = int | float | str | None


def insert_flat_sqlite(cur: sqlite3.Cursor, head: str, row: str, width: int, flat: Sequence[SqlValue]) -> None:
    """Insert rows given as one flat run of parameters (``width`` a row, row after row) in their order.

    ``head`` is ``INSERT INTO t (cols) VALUES `` and ``row`` one row's ``(...)`` with ``width`` marks;
    the rows go in statements of SQLITE_ROWS_PER_STATEMENT rows (one prepared statement over
    ``executemany``), the rest in statements of powers of two rows (the rest's binary digits: 64, 32,
    ..., 1): a few statement texts in all, each prepared once and kept by sqlite3's statement cache.
    The rows per statement are bounded by the connection's limit of bound parameters (999 in SQLite
    before 3.32).
    """
    per = max(1, min(SQLITE_ROWS_PER_STATEMENT, cur.connection.getlimit(sqlite3.SQLITE_LIMIT_VARIABLE_NUMBER) // width))
    step = per * width
    full = len(flat) // step * step
    if full:
        cur.executemany(head + ",".join([row] * per), (flat[i : i + step] for i in range(0, full, step)))
    at, rest = full, (len(flat) - full) // width
    for size in (1 << b for b in reversed(range(rest.bit_length()))):  # rest's binary digits, largest first
        if rest & size:
            cur.execute(head + ",".join([row] * size), flat[at : at + size * width])
            at += size * width


def _nullable(values: np.ndarray, postgres: bool) -> list[Any]:
    """Return floats as a list with NaN as None (SQLite stores a bound NaN as NULL by itself)."""
    if not postgres or not np.isnan(values).any():
        return values.tolist()
    obj = values.astype(object)
    obj[np.isnan(values)] = None
    return obj.tolist()


def insert_temperatures_sqlite(
    conn: Connection, campaign_id: int, day: int, channels: Iterable[tuple[int, Iterable[tuple[Any, Any]]]]
) -> None:
    """Insert readings into temperature_samples on SQLite in the connection's transaction, channel by channel.

    ``channels`` gives per channel id its (times, values) pieces (sequences of floats, NaN or None
    where no value: sqlite stores a bound NaN as NULL). The campaign, the channel and the start day
    are the same for every row of a piece, so they are written into the statement as integer
    literals and each row binds two values instead of five; the rows go in multi-row INSERTs
    (``insert_flat_sqlite``), their times and values interleaved by slice assignment (no tuple a row).
    """
    raw = conn.connection.driver_connection
    head = f"INSERT INTO temperature_samples ({', '.join(TEMPERATURE_COLUMNS)}) VALUES "
    cur = raw.cursor()  # type: ignore[union-attr]
    try:
        for channel_id, pieces in channels:
            row = f"({int(campaign_id)}, {int(channel_id)}, ?, ?, {int(day)})"
            for times, values in pieces:
                flat: list[SqlValue] = [None] * (2 * len(times))
                flat[0::2], flat[1::2] = times, values
                insert_flat_sqlite(cur, head, row, 2, flat)
    finally:
        cur.close()


def _channel_pieces(
    channel_ids: Sequence[int], temperatures: ColumnTable
) -> Iterator[tuple[int, Iterator[tuple[list[float], list[float]]]]]:
    """Return per channel id its (times, values) pieces as Python float lists, for the driver.

    A table in memory (one chunk) has its time column made a list once, for every channel; a staged
    table's times are made again per channel and chunk, so that memory holds a chunk whatever the size.
    """
    names = [c for c in temperatures.columns if c != "time_s"]
    shared = None
    if isinstance(temperatures, FrameTable):
        shared = [np.asarray(t, dtype="f8").tolist() for t in temperatures.column("time_s")]

    def pieces(name: str) -> Iterator[tuple[list[float], list[float]]]:
        times: Iterable[Any] = shared if shared is not None else temperatures.column("time_s")
        for t, v in zip(times, temperatures.column(name), strict=True):
            yield (t if shared is not None else np.asarray(t, dtype="f8").tolist()), np.asarray(v, dtype="f8").tolist()

    return ((channel_id, pieces(name)) for channel_id, name in zip(channel_ids, names, strict=True))


# PostgreSQL binary COPY of temperature rows, encoded by numpy (no Python object per row): the
# file header, then per row a field count and (length, big-endian value) per field, NULL as length -1.
_PG_HEADER = b"PGCOPY\n\xff\r\n\x00" + (0).to_bytes(4, "big") + (0).to_bytes(4, "big")
_PG_TRAILER = (-1).to_bytes(2, "big", signed=True)
_ROW_FIELDS = [
    ("n", ">i2"),
    ("l1", ">i4"),
    ("c", ">i4"),
    ("l2", ">i4"),
    ("ch", ">i4"),
    ("l3", ">i4"),
    ("t", ">f8"),
    ("l4", ">i4"),
    ("v", ">f8"),
    ("l5", ">i4"),
    ("d", ">i4"),
]
_ROW = np.dtype(_ROW_FIELDS)
#: the same without the value (every value NULL: its length -1 and no bytes)
_ROW_NULL = np.dtype([f for f in _ROW_FIELDS if f[0] != "v"])


def _encode_rows(campaign_id: int, channel_id: int, t: np.ndarray, v: np.ndarray | None, start_day: int) -> bytes:
    """Return binary COPY tuples of one channel (v None: every value NULL)."""
    arr = np.empty(len(t), dtype=_ROW if v is not None else _ROW_NULL)
    arr["n"], arr["l1"], arr["c"], arr["l2"], arr["ch"], arr["l3"], arr["t"] = 5, 4, campaign_id, 4, channel_id, 8, t
    arr["l5"], arr["d"] = 4, start_day
    if v is None:
        arr["l4"] = -1
    else:
        arr["l4"], arr["v"] = 8, v
    return arr.tobytes()


def copy_temperatures_pg(
    conn: Connection,
    campaign_id: int,
    channel_ids: Sequence[int],
    temperatures: pd.DataFrame | ColumnTable,
    start_day: int,
    chunk_rows: int = 200_000,
    *,
    queued: bool = False,
    between: Callable[[], None] | None = None,
) -> None:
    """Stream a wide temperature table into temperature_samples with binary COPY, in key order.

    ``start_day`` is the campaign's partition key (``partitions.start_day``); its partition must exist.
    The rows go straight into that partition (every row of a campaign has the same key): no routing
    per row, and PostgreSQL still checks each against the partition's bounds. With ``queued`` the
    rows are sent from a thread of their own while the next chunk is encoded (``copy_writer``).
    ``between`` is called before each channel: what it raises ends the COPY with that error
    (psycopg sends CopyFail; the transaction is then the caller's to roll back).
    """
    target = _into(conn, "temperature_samples", start_day)
    raw = conn.connection.driver_connection
    table = as_table(temperatures)
    names = [c for c in table.columns if c != "time_s"]
    with raw.cursor() as cur:  # type: ignore[union-attr]
        sql = f"COPY {target} ({', '.join(TEMPERATURE_COLUMNS)}) FROM STDIN (FORMAT BINARY)"
        with cur.copy(sql, writer=copy_writer(cur, queued)) as cp:
            cp.write(_PG_HEADER)
            for channel_id, name in zip(channel_ids, names, strict=True):
                if between is not None:
                    between()
                for t_all, v_all in zip(table.column("time_s"), table.column(name), strict=True):
                    t_all, v_all = np.asarray(t_all, dtype="f8"), np.asarray(v_all, dtype="f8")
                    for lo in range(0, len(t_all), chunk_rows):
                        t, v = t_all[lo : lo + chunk_rows], v_all[lo : lo + chunk_rows]
                        missing = np.isnan(v)
                        if not missing.any():
                            cp.write(_encode_rows(campaign_id, channel_id, t, v, start_day))
                            continue
                        # rows keep key order: runs of present and missing values alternate
                        edges = np.flatnonzero(np.diff(missing.astype(np.int8))) + 1
                        for a, b in zip(np.r_[0, edges], np.r_[edges, len(v)], strict=True):
                            cp.write(
                                _encode_rows(campaign_id, channel_id, t[a:b], None if missing[a] else v[a:b], start_day)
                            )
            cp.write(_PG_TRAILER)


ROLLUP_COLUMNS = ("campaign_id", "channel_id", "minute", "n", "n_values", "vmin", "vsum", "vmax")
ROLLUP_S = 60.0
#: rollups are written only where they are at least this many times fewer than the scans
ROLLUP_MIN_SCANS_PER_ROW = 2


def rollups_pay(times: np.ndarray) -> bool:
    """Return True when per-minute rollups would be at least ROLLUP_MIN_SCANS_PER_ROW times fewer rows
    than the readings (scans every 30 s or faster, on average).

    A campaign scanned every 2 minutes (a fleet's monitoring) has one scan per minute at most: its
    rollups would be as many rows as its readings, doubling the import for nothing, and its
    bucketed histories are computed from the readings directly (``rollups_complete`` false).
    """
    t = np.asarray(times, dtype="f8")
    if not len(t):
        return False
    return bool(np.unique(np.floor(t / ROLLUP_S)).size * ROLLUP_MIN_SCANS_PER_ROW <= len(t))


def rollups_pay_chunks(chunks: Iterable[Any]) -> bool:
    """``rollups_pay`` over the time column given a chunk at a time (scans in time order: minutes only grow)."""
    n_rows = n_minutes = 0
    last: int | None = None
    for times in chunks:
        minute = np.floor(np.asarray(times, dtype="f8") / ROLLUP_S).astype(np.int64)
        if not minute.size:
            continue
        n_rows += minute.size
        n_minutes += int(np.count_nonzero(np.diff(minute))) + int(last is None or minute[0] != last)
        last = int(minute[-1])
    return bool(n_rows and n_minutes * ROLLUP_MIN_SCANS_PER_ROW <= n_rows)


def rollup_rows(
    campaign_id: int, channel_ids: Sequence[int], temperatures: pd.DataFrame | ColumnTable
) -> Iterator[tuple[Any, ...]]:
    """Yield per channel and minute (count, present count, min, sum, max) rows of a wide table.

    Scans are in time order, so a minute is a run of consecutive rows; a run cut by the end of a
    chunk is finished with the next chunk's rows (the same sums, in the same order, as in one go).
    """
    for channel_id, r in rollup_arrays(channel_ids, temperatures):
        yield from zip(
            repeat(campaign_id),
            repeat(channel_id),
            r.minute.tolist(),
            r.n.tolist(),
            r.n_values.tolist(),
            _nullable(r.vmin, True),
            _nullable(r.vsum, True),
            _nullable(r.vmax, True),
        )


@dataclass(frozen=True)
class Rollups:
    """Per-minute rollups of whole minutes of one channel, a column each (vmin, vsum, vmax NaN: no value)."""

    minute: np.ndarray
    n: np.ndarray
    n_values: np.ndarray
    vmin: np.ndarray
    vsum: np.ndarray
    vmax: np.ndarray


def rollup_arrays(
    channel_ids: Sequence[int], temperatures: pd.DataFrame | ColumnTable
) -> Iterator[tuple[int, Rollups]]:
    """Yield (channel id, rollups) of a wide table, per channel in order and a piece of minutes at a time."""
    table = as_table(temperatures)
    names = [c for c in table.columns if c != "time_s"]
    for channel_id, name in zip(channel_ids, names, strict=True):
        rest_t, rest_v = np.empty(0), np.empty(0)
        for times, values in zip(table.column("time_s"), table.column(name), strict=True):
            t = np.concatenate([rest_t, np.asarray(times, dtype="f8")])
            v = np.concatenate([rest_v, np.asarray(values, dtype="f8")])
            if not len(t):
                continue
            minute = np.floor(t / ROLLUP_S).astype(np.int64)
            other = np.flatnonzero(minute != minute[-1])
            cut = int(other[-1]) + 1 if other.size else 0  # the last run of a minute may go on in the next chunk
            if cut:
                yield channel_id, _rollups(minute[:cut], v[:cut])
            rest_t, rest_v = t[cut:], v[cut:]
        if len(rest_t):
            yield channel_id, _rollups(np.floor(rest_t / ROLLUP_S).astype(np.int64), rest_v)


def _rollups(minute: np.ndarray, v: np.ndarray) -> Rollups:
    """Return the rollups of whole minutes of one channel (at least one reading)."""
    starts = np.r_[0, np.flatnonzero(np.diff(minute)) + 1]
    n = np.diff(np.r_[starts, len(minute)])
    present = ~np.isnan(v)
    n_values = np.add.reduceat(present.astype(np.int64), starts)
    with np.errstate(invalid="ignore"):
        vmin = np.fmin.reduceat(v, starts)
        vmax = np.fmax.reduceat(v, starts)
    vsum = np.add.reduceat(np.where(present, v, 0.0), starts)
    vsum[n_values == 0] = np.nan
    return Rollups(minute[starts], n, n_values, vmin, vsum, vmax)


#: binary COPY tuples of temperature_rollups (ROLLUP_COLUMNS): five int4, then vmin, vsum, vmax as
#: float8 or, for a minute without a value, all three NULL (length -1, no bytes)
_ROLLUP_INTS = [("n", ">i2"), *[f for k in range(5) for f in ((f"l{k}", ">i4"), (f"i{k}", ">i4"))]]
_ROLLUP = np.dtype(_ROLLUP_INTS + [f for k in range(3) for f in ((f"lf{k}", ">i4"), (f"f{k}", ">f8"))])
_ROLLUP_NULL = np.dtype(_ROLLUP_INTS + [(f"lf{k}", ">i4") for k in range(3)])


def _encode_rollups(campaign_id: int, channel_id: int, r: Rollups, a: int, b: int, present: bool) -> bytes:
    """Return binary COPY tuples of rows a..b of one channel's rollups, all with values or all without."""
    arr = np.empty(b - a, dtype=_ROLLUP if present else _ROLLUP_NULL)
    arr["n"] = len(ROLLUP_COLUMNS)
    ints = (campaign_id, channel_id, r.minute[a:b], r.n[a:b], r.n_values[a:b])
    for k, value in enumerate(ints):
        arr[f"l{k}"], arr[f"i{k}"] = 4, value
    for k, value in enumerate((r.vmin, r.vsum, r.vmax)):
        arr[f"lf{k}"] = 8 if present else -1
        if present:
            arr[f"f{k}"] = value[a:b]
    return arr.tobytes()


def copy_rollups_pg(
    conn: Connection, campaign_id: int, channel_ids: Sequence[int], temperatures: pd.DataFrame | ColumnTable
) -> None:
    """Write the rollups of a wide table into temperature_rollups with binary COPY encoded by numpy (no
    Python object a row), in the order ``rollup_rows`` gives them; sent from psycopg's queued writer."""
    copy_encoded_pg(
        conn, "temperature_rollups", ROLLUP_COLUMNS, encode_rollups_pg(campaign_id, channel_ids, temperatures)
    )


def copy_encoded_pg(conn: Connection, table: str, columns: Sequence[str], tuples: Iterable[bytes]) -> None:
    """COPY binary tuples already encoded (the file header and trailer are added here) into ``table``,
    sent from psycopg's queued writer."""
    raw = conn.connection.driver_connection
    with raw.cursor() as cur:  # type: ignore[union-attr]
        sql = f"COPY {table} ({', '.join(columns)}) FROM STDIN (FORMAT BINARY)"
        with cur.copy(sql, writer=copy_writer(cur, True)) as cp:
            cp.write(_PG_HEADER)
            for piece in tuples:
                cp.write(piece)
            cp.write(_PG_TRAILER)


def encode_rollups_pg(
    campaign_id: int, channel_ids: Sequence[int], temperatures: pd.DataFrame | ColumnTable
) -> Iterator[bytes]:
    """Yield the binary COPY tuples of a wide table's rollups, per channel and run of minutes with or without values."""
    for channel_id, r in rollup_arrays(channel_ids, temperatures):
        empty = r.n_values == 0
        edges = np.flatnonzero(np.diff(empty.astype(np.int8))) + 1  # runs with and without values, in order
        for a, b in zip(np.r_[0, edges], np.r_[edges, len(empty)], strict=True):
            yield _encode_rollups(campaign_id, channel_id, r, int(a), int(b), not empty[a])


def insert_ignoring_duplicates(conn: Connection, table: Any, keys: list[str]) -> Any:
    """Return an INSERT of ``table`` that skips a row whose ``keys`` already exist (both dialects)."""
    if conn.dialect.name == "postgresql":
        return pg_insert(table).on_conflict_do_nothing(index_elements=keys)
    return sqlite_insert(table).on_conflict_do_nothing(index_elements=keys)


def _into(conn: Connection, table: str, day: int) -> str:
    """Return where a campaign's readings of ``table`` are written: on PostgreSQL its partition (no
    routing per row), else the table."""
    if conn.dialect.name != "postgresql":
        return table
    return leaf(conn, table, day) or table


#: the PostgreSQL types of ERROR_COLUMNS (binary COPY)
ERROR_TYPES = ("int4", "int4", "float8", "varchar", "varchar", "float8", "int2", "float8", "int4", "int4", "int4")


def already_stored(name: str, campaign_id: int, content_hash: str) -> ConflictError:
    """Return the refusal of a bundle whose content is stored already, as campaign ``campaign_id``."""
    return ConflictError(
        f"bundle {name!r} is already stored as campaign {campaign_id} (same content hash "
        f"{content_hash[:12]}); nothing imported"
    )


@contextmanager
def concurrent_duplicate_refused(name: str) -> Iterator[None]:
    """Turn the campaigns' unique content hash refusing a row into a ConflictError (an import of the
    same content committed first); any other IntegrityError goes on as it is."""
    try:
        yield
    except IntegrityError as exc:
        if "content_hash" in str(exc.orig):
            raise ConflictError(f"bundle {name!r} was imported concurrently; nothing imported") from None
        raise


def import_bundle(conn: Connection, bundle: Bundle | Any, content_hash: str) -> int:
    """Write a validated bundle (in memory, or staged) in the caller's transaction; return the new campaign id.

    On PostgreSQL the partition of the campaign's start (``partitions.ensure_partitions``) must exist.
    """
    meta = bundle.meta
    postgres = conn.dialect.name == "postgresql"
    day = start_day(meta.started_at)
    ensure_machine(conn, meta)
    temperatures = as_table(bundle.temperatures)
    rollups = rollups_pay_chunks(temperatures.column("time_s"))
    conditions = None if bundle.conditions is None else as_table(bundle.conditions)
    campaign_id = insert_campaign(conn, meta, bundle.name, conditions, content_hash, rollups)
    channel_ids = insert_channels(conn, campaign_id, meta, bundle.channels)

    if postgres:
        copy_temperatures_pg(conn, campaign_id, channel_ids, temperatures, day, queued=True)
    else:
        insert_temperatures_sqlite(conn, campaign_id, day, _channel_pieces(channel_ids, temperatures))

    if rollups:
        write_rollups(conn, campaign_id, channel_ids, temperatures)
    write_conditions(conn, campaign_id, conditions, day)
    write_errors(conn, campaign_id, as_table(bundle.errors), meta, day)
    return int(campaign_id)


def write_rollups(conn: Connection, campaign_id: int, channel_ids: Sequence[int], temperatures: ColumnTable) -> None:
    """Write the per-minute rollups of a campaign's temperatures (binary COPY on PostgreSQL)."""
    if conn.dialect.name == "postgresql":
        copy_rollups_pg(conn, campaign_id, channel_ids, temperatures)
    else:
        bulk_insert(
            conn, "temperature_rollups", ROLLUP_COLUMNS, (), rollup_rows(campaign_id, channel_ids, temperatures)
        )


def write_conditions(conn: Connection, campaign_id: int, conditions: ColumnTable | None, day: int) -> None:
    """Write a campaign's machine-state log (nothing when the bundle has none, or it is empty)."""
    if conditions is None or not conditions.n_rows:
        return
    postgres = conn.dialect.name == "postgresql"
    bulk_insert(
        conn,
        "condition_samples",
        CONDITION_ROW_COLUMNS,
        CONDITION_ROW_TYPES,
        condition_rows(campaign_id, conditions, postgres, day),
        into=_into(conn, "condition_samples", day),
        queued=True,
    )


def write_errors(conn: Connection, campaign_id: int, errors: ColumnTable, meta: CampaignMeta, day: int) -> None:
    """Write a campaign's error readings in file order (bundle v2: with the pose and setup of each)."""
    err_names: tuple[str, ...] = ERROR_COLUMNS
    types: tuple[str, ...] = ERROR_TYPES
    if meta.v2:  # bundle v2: the full commanded pose and the setup of each reading
        err_names += (*POSE_COLUMNS, "setup")
        types += ("float8",) * len(POSE_COLUMNS) + ("varchar",)
    bulk_insert(
        conn,
        "error_samples",
        err_names,
        types,
        error_rows(campaign_id, errors, meta.v2, day),
        into=_into(conn, "error_samples", day),
        queued=True,
    )


def ensure_machine(conn: Connection, meta: CampaignMeta) -> None:
    """Insert the bundle's machine unless it is stored already."""
    machine = conn.execute(select(sc.Machine.id).where(sc.Machine.id == meta.machine.id)).first()
    if machine is None:
        # ON CONFLICT DO NOTHING: two imports of a new machine at once both see no row; the second
        # insert then waits for the first to commit and keeps its row instead of failing on the key
        values = dict(
            id=meta.machine.id,
            name=meta.machine.name,
            resolution_mm=meta.machine.resolution_mm,
            resolution_deg=meta.machine.resolution_deg,
            created_at=sc.utcnow(),
        )
        conn.execute(insert_ignoring_duplicates(conn, sc.Machine.__table__, ["id"]).values(**values))


def insert_campaign(
    conn: Connection,
    meta: CampaignMeta,
    name: str,
    conditions: ColumnTable | None,
    content_hash: str | None,
    rollups: bool,
) -> int:
    """Insert the imported campaign's row and its stages; return its id.

    ``content_hash`` None: set before the commit (``import_pipeline``, which hashes while it writes).
    """
    campaign_id = conn.execute(
        insert(sc.Campaign)
        .values(
            machine_id=meta.machine.id,
            name=name,
            started_at=meta.started_at,
            status="done",
            source="import",
            content_hash=content_hash,
            meta=meta.document(),
            conditions_columns=None if conditions is None else list(conditions.columns),
            rollups_complete=rollups,
            created_at=sc.utcnow(),
        )
        .returning(sc.Campaign.id)
    ).scalar_one()
    if meta.stages:
        conn.execute(
            insert(sc.Stage),
            [
                {
                    "campaign_id": campaign_id,
                    "ordinal": k,
                    "name": s.name,
                    "heat_source": s.heat_source,
                    "axis": s.axis,
                    "spindle_rpm": s.spindle_rpm,
                    "feed_mm_min": s.feed_mm_min,
                    "start_s": s.start_s,
                    "end_s": s.end_s,
                    "status": "done",
                }
                for k, s in enumerate(meta.stages)
            ],
        )
    return int(campaign_id)


def insert_channels(conn: Connection, campaign_id: int, meta: CampaignMeta, names: Sequence[str]) -> list[int]:
    """Insert the bundle's channels (``names``: temperatures.csv order) and return their ids in that order."""
    room = set(meta.room_channels)
    conn.execute(
        insert(sc.Channel),
        [
            {
                "campaign_id": campaign_id,
                "ordinal": k,
                "name": name,
                "location": meta.channels[name].location,
                "structure": meta.channels[name].structure,
                "is_room": name in room,
                "calibration_slope": 1.0,
                "calibration_offset": 0.0,
            }
            for k, name in enumerate(names)
        ],
    )
    ids = dict(conn.execute(select(sc.Channel.name, sc.Channel.id).where(sc.Channel.campaign_id == campaign_id)).all())
    return [ids[name] for name in names]


def condition_rows(campaign_id: int, conditions: ColumnTable, postgres: bool, day: int) -> Iterator[tuple[Any, ...]]:
    """Yield (campaign, time, spindle_rpm, feed_mm_min, x, y, z, a, b, start day) rows, NULL where a column
    is absent."""
    present = [c for c in CONDITION_VALUE_COLUMNS if c in conditions.columns]
    for chunk in conditions.chunks(["time_s", *present]):
        n = len(chunk["time_s"])
        columns = [
            np.asarray(chunk[c], dtype="f8") if c in chunk else np.full(n, np.nan) for c in CONDITION_VALUE_COLUMNS
        ]
        yield from zip(
            repeat(campaign_id, n),
            np.asarray(chunk["time_s"], dtype="f8").tolist(),
            *[_nullable(c, postgres) for c in columns],
            repeat(day, n),
        )


def error_rows(campaign_id: int, errors: ColumnTable, v2: bool, day: int) -> Iterator[tuple[Any, ...]]:
    """Yield error_samples rows in file order: seq counts over the whole file, sweeps carry across chunks."""
    sweeps = SweepCounter()
    seq = 0
    for chunk in errors.chunks():
        n = len(chunk["time_s"])
        axis, term = [str(v) for v in chunk["axis"]], [str(v) for v in chunk["term"]]
        direction = np.asarray(chunk["direction"], dtype="i8")
        numbers = sweeps.numbers(
            np.asarray(axis, dtype=object),
            np.asarray(term, dtype=object),
            direction,
            np.asarray(chunk["position"], dtype="f8"),
        )
        columns: tuple[Any, ...] = (
            repeat(campaign_id, n),
            range(seq, seq + n),
            np.asarray(chunk["time_s"], dtype="f8").tolist(),
            axis,
            term,
            np.asarray(chunk["position"], dtype="f8").tolist(),
            direction.tolist(),
            np.asarray(chunk["value"], dtype="f8").tolist(),
            numbers.tolist(),
            repeat(0, n),
            repeat(day, n),
        )
        if v2:
            columns += (
                *(np.asarray(chunk[c], dtype="f8").tolist() for c in POSE_COLUMNS),
                [str(v) for v in chunk["setup"]],
            )
        yield from zip(*columns)
        seq += n


def refresh_rollups(conn: Connection, campaign_id: int) -> int:
    """Recompute a campaign's per-minute rollups from its stored readings; return the row count."""
    minute = (
        "CAST(FLOOR(time_s / 60.0) AS INTEGER)"
        if conn.dialect.name == "postgresql"
        else ("CAST(time_s / 60.0 AS INTEGER)")
    )  # time_s >= 0: truncation is floor on SQLite
    conn.execute(text("DELETE FROM temperature_rollups WHERE campaign_id = :c"), {"c": campaign_id})
    conn.execute(
        text(
            f"INSERT INTO temperature_rollups ({', '.join(ROLLUP_COLUMNS)}) "
            f"SELECT campaign_id, channel_id, {minute}, COUNT(*), COUNT(value), MIN(value), SUM(value), MAX(value) "
            f"FROM temperature_samples WHERE campaign_id = :c GROUP BY campaign_id, channel_id, {minute}"
        ),
        {"c": campaign_id},
    )
    conn.execute(text("UPDATE campaigns SET rollups_complete = :t WHERE id = :c"), {"c": campaign_id, "t": True})
    return int(
        conn.execute(
            text("SELECT COUNT(*) FROM temperature_rollups WHERE campaign_id = :c"), {"c": campaign_id}
        ).scalar_one()
    )
