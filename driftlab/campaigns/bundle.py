"""Campaign bundle v1: load (validating everything first) and write, no database involved.

A bundle is a directory with campaign.json, temperatures.csv, errors.csv and an optional
conditions.csv (see docs/bundle.md). Every problem is reported as one line ``FILE:ROW: problem``
with ROW counted as a text editor shows it (the header is line 1).

CSV files are parsed by pyarrow's streaming C++ CSV reader with explicit column types (correctly
rounded float parsing, so values round-trip bit-exactly), a block of text at a time; each chunk
of rows is validated as it comes, with what spans chunks (time order, duplicate readings) carried
from one to the next, so a file is never held whole (``open_bundle``; ``load_bundle`` then
gathers the chunks in memory, ``staging.stage_bundle`` writes them to a temporary file). Only
when the fast parse fails does a slow line-by-line scanner run to find the exact row and say
what is wrong with it.

Before anything is read, every file is checked to be a regular file within its size limit (the
limits table of docs/bundle.md), so a hostile bundle (a FIFO, a directory, a 2 GB sparse file, a
deeply nested JSON document, a number of thousands of digits) is refused in bounded time and
memory: the scanner reads line by line with a bounded line length, never the whole file.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import stat
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv

from driftlab.campaigns.bundle_meta import (
    CAMPAIGN_FILE,
    CONDITION_COLUMNS,
    CONDITIONS_FILE,
    CSV_BLOCK_BYTES,
    DIRECTIONS,
    ERROR_COLUMNS,
    ERROR_COLUMNS_V2,
    ERRORS_FILE,
    MAX_CSV_BYTES,
    MAX_FIELD_CHARS,
    MAX_JSON_BYTES,
    MAX_LINE_BYTES,
    MAX_LINEAR_POSITION_MM,
    MAX_NAME_CHARS,
    MAX_ROTARY_POSITION_DEG,
    MAX_ROTATION_RAD,
    MAX_TIME_S,
    MAX_TRANSLATION_MM,
    NONFINITE_TEXT,
    NUMBER_TEXT,
    POSE_COLUMNS,
    ROTARY_AXES,
    TEMP_RANGE_DEGC,
    TEMPERATURES_FILE,
    BundleError,
    CampaignMeta,
    json_fail,
    parse_meta,
    parse_meta_located,
    short,
)
from driftlab.campaigns.bundle_meta import ID_PATTERN as ID_PATTERN
from driftlab.campaigns.bundle_meta import CampaignJson as CampaignJson  # re-exported: campaign.json's API here
from driftlab.vocabulary import AXES, TERMS
from driftlab.vocabulary import TRANSLATIONS as TRANSLATION_TERMS

_T = TypeVar("_T")


# ----------------------------------------------------------------------------- CSV files


@dataclass(frozen=True)
class Bundle:
    """A validated campaign bundle (v1 or v2) held in memory.

    ``errors`` has the v1 columns; a v2 bundle's also has ``x y z a b`` (the commanded pose, mm and
    degrees) and ``setup`` (a key of ``meta.setups``).
    """

    name: str
    meta: CampaignMeta
    temperatures: pd.DataFrame
    conditions: pd.DataFrame | None
    errors: pd.DataFrame

    @property
    def channels(self) -> list[str]:
        """Return the channel names in temperatures.csv column order."""
        return [c for c in self.temperatures.columns if c != "time_s"]

    def content_hash(self) -> str:
        """Return a SHA-256 over the bundle's values (not its formatting): equal data, equal hash."""
        return content_hash(self.meta, self.temperatures, self.conditions, self.errors)


class ColumnTable(Protocol):
    """A table read a column at a time, each column as a run of arrays in row order (a frame, or staged chunks)."""

    columns: list[str]
    n_rows: int

    def column(self, name: str) -> Iterator[np.ndarray]:
        """Yield the column ``name`` a chunk at a time."""

    def chunks(self, names: Sequence[str] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """Yield runs of consecutive rows as {column: values}."""


class FrameTable:
    """A DataFrame seen as a ColumnTable of one chunk."""

    def __init__(self, frame: pd.DataFrame) -> None:
        self.frame = frame
        self.columns = [str(c) for c in frame.columns]
        self.n_rows = len(frame)

    def column(self, name: str) -> Iterator[np.ndarray]:
        """Yield the whole column."""
        yield self.frame[name].to_numpy()

    def chunks(self, names: Sequence[str] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """Yield every row at once."""
        yield {name: self.frame[name].to_numpy() for name in (names or self.columns)}


def as_table(table: pd.DataFrame | ColumnTable) -> ColumnTable:
    """Return a frame as a ColumnTable (a ColumnTable as it is)."""
    return FrameTable(table) if isinstance(table, pd.DataFrame) else table


def _hash_floats(h: Any, values: np.ndarray) -> None:
    arr = np.ascontiguousarray(values, dtype="<f8").copy()
    arr[np.isnan(arr)] = np.nan  # one canonical NaN bit pattern
    h.update(arr.tobytes())


def _hash_text(h: Any, parts: Iterator[np.ndarray]) -> None:
    """Hash the values of a text column joined by newlines, as one string would be, a chunk at a time."""
    first = True
    for part in parts:
        if len(part) == 0:
            continue
        if not first:
            h.update(b"\n")
        h.update("\n".join(str(v) for v in part).encode())
        first = False


def content_hash(
    meta: CampaignMeta, temperatures: pd.DataFrame, conditions: pd.DataFrame | None, errors: pd.DataFrame
) -> str:
    """Return the SHA-256 hex digest identifying a bundle's content."""
    return table_hash(
        meta, FrameTable(temperatures), None if conditions is None else FrameTable(conditions), FrameTable(errors)
    )


def table_hash(
    meta: CampaignMeta, temperatures: ColumnTable, conditions: ColumnTable | None, errors: ColumnTable
) -> str:
    """Return ``content_hash`` of tables read a chunk at a time: the same bytes, column after column."""
    h = hashlib.sha256()
    h.update(json.dumps(meta.document(), sort_keys=True).encode())
    for label, table in (("temperatures", temperatures), ("conditions", conditions)):
        h.update(f"\0{label}\0".encode())
        if table is None:
            h.update(b"absent")
            continue
        h.update(",".join(table.columns).encode())
        for col in table.columns:
            for part in table.column(col):
                _hash_floats(h, part)
    h.update(b"\0errors\0")
    for col in ("time_s", "position", "value"):
        for part in errors.column(col):
            _hash_floats(h, part)
    for col in ("axis", "term"):
        _hash_text(h, errors.column(col))
    for part in errors.column("direction"):
        h.update(np.asarray(part).astype("<i1").tobytes())
    if meta.v2:  # v1 hashes are unchanged (duplicate imports of v1 bundles are still recognised)
        for col in POSE_COLUMNS:
            for part in errors.column(col):
                _hash_floats(h, part)
        _hash_text(h, errors.column("setup"))
    return h.hexdigest()


def _fail(file: str, row: int | None, problem: str) -> BundleError:
    return BundleError(f"{file}:{row}: {problem}" if row is not None else f"{file}: {problem}")


def _check_file(root: Path, name: str, limit: int, required: bool) -> Path | None:
    """Return the path of a bundle file after checking it is a regular file within ``limit`` bytes.

    None when an optional file is absent. Nothing is opened: a FIFO or a device is refused before
    a read could block or run without end, and a link leading out of the bundle (``-> /etc/passwd``,
    ``-> ../x.json``) before anything of its target could be read or echoed.
    """
    path = root / name
    if os.path.lexists(path):
        # a link may point inside the bundle, never out of it: nothing of a foreign file is read or shown
        try:
            inside = path.resolve().is_relative_to(root.resolve())
        except (OSError, RuntimeError):  # a loop of links: os.stat below names it
            inside = True
        if not inside:
            raise BundleError(f"{name}: a link that leads out of the bundle; refused")
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.lexists(path):
            raise BundleError(f"{name}: a link to a file that does not exist") from None
        if required:
            raise BundleError(f"{name}: file missing from bundle {root}") from None
        return None
    except OSError as exc:
        raise BundleError(f"{name}: cannot read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        kind = (
            "a directory"
            if stat.S_ISDIR(st.st_mode)
            else "a FIFO"
            if stat.S_ISFIFO(st.st_mode)
            else ("a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "a socket")
        )
        raise BundleError(f"{name}: not a regular file ({kind})")
    if st.st_size > limit:
        raise BundleError(f"{name}: {st.st_size} bytes, more than the limit of {limit} bytes")
    return path


def _open(path: Path, file: str) -> Any:
    """Return ``path`` opened for binary reading; BundleError when it cannot be read."""
    try:
        return path.open("rb")
    except OSError as exc:
        raise BundleError(f"{file}: cannot read: {exc.strerror or exc}") from None


def _decode_line(raw: bytes, file: str, lineno: int, header: list[str] | None) -> str:
    """Return a line as text without its line break; BundleError naming row and column if not UTF-8."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        k = raw[: exc.start].count(b",")
        column = header[k] if header is not None and k < len(header) else str(k + 1)
        raise _fail(file, lineno, f"column {column}: not UTF-8 text (byte {exc.start + 1} of the line)") from None
    return text.rstrip("\n").removesuffix("\r")


def _read_line(fh: Any, file: str, lineno: int) -> bytes:
    """Return the next line (b'' at the end) of at most MAX_LINE_BYTES; BundleError on a longer one."""
    raw = fh.readline(MAX_LINE_BYTES + 1)
    if len(raw) > MAX_LINE_BYTES:
        raise _fail(file, lineno, f"line longer than {MAX_LINE_BYTES} bytes")
    return raw


def _split(
    line: str, file: str, lineno: int, header: list[str] | None, kinds: Mapping[str, str] | None = None
) -> list[str]:
    """Return a CSV line's fields; BundleError naming the column of an over-long text field."""
    cells = line.split(",") if '"' not in line else None
    if cells is None:
        try:
            cells = next(csv.reader([line]))
        except csv.Error as exc:
            raise _fail(file, lineno, f"malformed CSV line: {exc}") from None
    for k, cell in enumerate(cells):
        text_column = header is None or k >= len(header) or (kinds or {}).get(header[k], "float") != "float"
        if text_column and len(cell) > MAX_FIELD_CHARS:
            column = header[k] if header is not None and k < len(header) else str(k + 1)
            raise _fail(file, lineno, f"column {column}: a cell of {len(cell)} characters (at most {MAX_FIELD_CHARS})")
    return cells


def _read_header(path: Path, file: str, time_first: bool = True) -> list[str]:
    """Return the header fields of a CSV file, checked for emptiness, length, duplicates (and time_s first)."""
    with _open(path, file) as fh:
        raw = _read_line(fh, file, 1)
    if raw.startswith(b"\xef\xbb\xbf"):
        raise _fail(file, 1, "starts with a byte-order mark: save it as UTF-8 without BOM")
    first = _decode_line(raw, file, 1, None)
    if not first.strip():
        raise _fail(file, 1, "empty file: expected a header line starting with time_s")
    header = _split(first, file, 1, None)
    seen: set[str] = set()
    for k, name in enumerate(header, start=1):
        if not name.strip():
            raise _fail(file, 1, f"column {k}: empty column name in header")
        if len(name) > MAX_NAME_CHARS:
            raise _fail(file, 1, f"column {k}: a column name of {len(name)} characters (at most {MAX_NAME_CHARS})")
        if name in seen:
            raise _fail(file, 1, f"duplicate column {short(name)}")
        seen.add(name)
    if time_first and header[0] != "time_s":
        raise _fail(file, 1, f"first column must be time_s, found {short(header[0])}")
    return header


def _scan_lines(path: Path, file: str) -> Iterator[tuple[int, bytes]]:
    """Yield (line number, raw line) of the data rows, one bounded line at a time."""
    with _open(path, file) as fh:
        _read_line(fh, file, 1)
        lineno = 1
        while True:
            lineno += 1
            raw = _read_line(fh, file, lineno)
            if not raw:
                return
            yield lineno, raw


def _scan_for_problem(path: Path, file: str, header: list[str], kinds: Mapping[str, str]) -> BundleError | None:
    """Return the first row-level problem found by a slow, exact line-by-line scan (or None)."""
    n = len(header)
    try:
        for lineno, raw in _scan_lines(path, file):
            line = _decode_line(raw, file, lineno, header)
            if not line.strip():
                return _fail(file, lineno, "empty line")
            fields = _split(line, file, lineno, header, kinds)
            if fields == header:
                return _fail(file, lineno, "repeated header line")
            if len(fields) != n:
                hint = " (truncated line?)" if len(fields) < n and not raw.endswith(b"\n") else ""
                return _fail(file, lineno, f"expected {n} fields, found {len(fields)}{hint}")
            for name, cell in zip(header, fields, strict=True):
                kind = kinds.get(name, "float")
                if kind == "float":
                    if cell == "":
                        continue
                    if NONFINITE_TEXT.match(cell.strip()):
                        return _fail(file, lineno, f"column {name}: {short(cell)} is not a finite number")
                    if not NUMBER_TEXT.match(cell):
                        return _fail(file, lineno, f"column {name}: {short(cell)} is not a number")
    except BundleError as exc:
        return exc
    return None


def _check_final_line_break(path: Path, file: str, last_line: int) -> None:
    """Refuse a file whose last line has no line break: it may have been cut in the middle of a value."""
    with _open(path, file) as fh:
        fh.seek(0, os.SEEK_END)
        if fh.tell() == 0:
            return
        fh.seek(-1, os.SEEK_END)
        if fh.read(1) != b"\n":
            raise _fail(file, last_line, "the last line has no line break (a truncated file?)")


def _csv_pieces(path: Path, file: str, block_bytes: int) -> Iterator[bytes]:
    """Yield the data lines of a CSV file (after its header) in pieces of whole lines, about ``block_bytes`` each.

    The file is read ``block_bytes`` at a time and cut after the last line break; a line longer
    than MAX_LINE_BYTES is refused as soon as it is seen (the lines before it have been yielded).
    """
    with _open(path, file) as fh:
        _read_line(fh, file, 1)  # the header (checked before)
        lines, rest = 1, b""
        while block := fh.read(block_bytes):
            text = rest + block
            cut = text.rfind(b"\n") + 1
            if cut:
                piece, rest = text[:cut], text[cut:]
                lines += piece.count(b"\n")
                yield piece
            else:
                rest = text
            if len(rest) > MAX_LINE_BYTES:
                raise _fail(file, lines + 1, f"line longer than {MAX_LINE_BYTES} bytes")
        if rest:
            yield rest


def _read_chunks(
    path: Path, file: str, header: list[str], kinds: Mapping[str, str], block_bytes: int = CSV_BLOCK_BYTES
) -> Iterator[tuple[_Rows, pa.Table]]:
    """Yield the CSV as tables of consecutive rows parsed with explicit types, each with its place in the file.

    Each piece of about ``block_bytes`` of whole lines (``_csv_pieces``) is parsed on its own, so
    memory holds a piece and its table, never the file (pyarrow's own streaming reader reads ahead
    of its consumer without bound). When a piece fails to parse, the slow scanner reads the file
    again from the top to name the bad row. After the last piece a final line without a line break
    is refused. At least one table comes, empty for a file with only a header (its columns typed).
    """
    types = {name: (pa.float64() if kinds.get(name, "float") == "float" else pa.string()) for name in header}
    read = pacsv.ReadOptions(column_names=header)
    parse = pacsv.ParseOptions(newlines_in_values=False, ignore_empty_lines=False)
    convert = pacsv.ConvertOptions(
        column_types=types, null_values=[""], strings_can_be_null=True, quoted_strings_can_be_null=True
    )
    rows = 0
    for piece in _csv_pieces(path, file, block_bytes):
        try:
            table = pacsv.read_csv(
                pa.BufferReader(piece), read_options=read, parse_options=parse, convert_options=convert
            )
        except (pa.ArrowInvalid, UnicodeDecodeError) as exc:
            raise _parse_failure(path, file, header, kinds, exc) from None
        del piece
        place = _Rows(file, rows)
        _check_text_lengths(table, place, header, kinds)
        rows += table.num_rows
        yield place, table
    if rows == 0:
        yield _Rows(file, 0), pa.table({name: pa.array([], type=t) for name, t in types.items()})
    _check_final_line_break(path, file, rows + 1)


def _parse_failure(path: Path, file: str, header: list[str], kinds: Mapping[str, str], exc: Exception) -> BundleError:
    """Return the exact row-level problem the scanner finds, or pyarrow's own words when it finds none."""
    problem = _scan_for_problem(path, file, header, kinds)
    if problem is not None:
        return problem
    return _fail(file, None, f"cannot parse: {' '.join(str(exc).split())[:200]}")


def _check_text_lengths(table: pa.Table, place: _Rows, header: list[str], kinds: Mapping[str, str]) -> None:
    """Refuse a text cell longer than MAX_FIELD_CHARS (the store keeps names, not text)."""
    for name in header:
        if kinds.get(name, "float") != "float":
            lengths = pc.utf8_length(table.column(name)).to_numpy(zero_copy_only=False)
            with np.errstate(invalid="ignore"):
                k = place.first(np.nan_to_num(lengths.astype("f8"), nan=0.0) > MAX_FIELD_CHARS)
            if k is not None:
                raise place.fail(
                    k, f"column {name}: a cell of {int(lengths[k])} characters (at most {MAX_FIELD_CHARS})"
                )


@dataclass(frozen=True)
class _Rows:
    """Where a chunk of rows sits in its file: its row k is line ``at + k + 2`` (the header is line 1)."""

    file: str
    at: int

    @staticmethod
    def first(mask: np.ndarray) -> int | None:
        """Return the chunk row of the first True in a per-row mask (None when there is none)."""
        idx = np.flatnonzero(mask)
        return int(idx[0]) if idx.size else None

    def fail(self, k: int, problem: str) -> BundleError:
        """Return a BundleError naming the line of the chunk's row ``k``."""
        return _fail(self.file, self.at + k + 2, problem)


def _check_empty_lines(table: pa.Table, place: _Rows) -> None:
    """Reject empty lines (pyarrow reads them as rows whose every cell is null)."""
    if any(col.null_count == 0 for col in table.columns):
        return  # a column without a null: no row is null throughout
    mask = None
    for col in table.columns:
        nulls = col.is_null().to_numpy(zero_copy_only=False)
        mask = nulls if mask is None else mask & nulls
    if mask is not None:
        k = place.first(mask)
        if k is not None:
            raise place.fail(k, "empty line")


def _check_time(place: _Rows, t: np.ndarray, strict: bool, before: float | None) -> None:
    """Check time_s: present, finite, non-negative, in (strictly, for scans) increasing order.

    ``before`` is the last time of the chunk before (None for the first): order holds across chunks.
    """
    k = place.first(np.isnan(t))
    if k is not None:
        raise place.fail(k, "time_s is missing")
    k = place.first(~np.isfinite(t))
    if k is not None:
        raise place.fail(k, "time_s is not a finite number")
    k = place.first(t < 0)
    if k is not None:
        raise place.fail(k, f"time_s {float(t[k])!r} is negative (seconds since started_at)")
    k = place.first(t > MAX_TIME_S)
    if k is not None:
        raise place.fail(k, f"time_s {float(t[k])!r} is beyond {MAX_TIME_S:.0e} s (about 31 years after started_at)")
    prev = np.concatenate(([before], t[:-1])) if before is not None else t[:-1]
    step = t - prev if before is not None else np.diff(t)
    k = place.first(step <= 0 if strict else step < 0)
    if k is not None:
        row = k if before is not None else k + 1
        what = "not after" if strict else "before"
        raise place.fail(
            row, f"time_s {float(t[row])!r} is {what} the previous row's {float(prev[k])!r}: rows must be in time order"
        )


def _check_finite_nan_is_missing(table: pa.Table, place: _Rows, name: str) -> None:
    """Reject NaN/inf written in a cell (an empty cell, a null, is the only way to say missing)."""
    col = table.column(name)
    v = col.to_numpy(zero_copy_only=False)
    nulls = col.is_null().to_numpy(zero_copy_only=False)
    k = place.first(~np.isfinite(v) & ~nulls)
    if k is not None:
        raise place.fail(k, f"column {name}: {float(v[k])!r} is not a finite number (leave the cell empty if missing)")


def _temperature_header(path: Path, meta: CampaignMeta) -> list[str]:
    """Return temperatures.csv's header: time_s, then exactly the channels of campaign.json."""
    file = path.name
    header = _read_header(path, file)
    for name in header[1:]:
        if name not in meta.channels:
            raise _fail(file, 1, f"column {short(name)} is not a channel of campaign.json")
    missing = [c for c in meta.channels if c not in header]
    if missing:
        raise _fail(file, 1, f"channel {short(missing[0])} of campaign.json has no column")
    return header


def _temperature_chunks(path: Path, meta: CampaignMeta, block_bytes: int = CSV_BLOCK_BYTES) -> Iterator[pd.DataFrame]:
    """Yield temperatures.csv as validated frames of consecutive rows (time order holds across them)."""
    file = path.name
    header = _temperature_header(path, meta)
    last: float | None = None
    for place, table in _read_chunks(path, file, header, {}, block_bytes):
        if table.num_rows == 0:
            continue  # a header alone: refused once the file is read to its end
        _check_empty_lines(table, place)
        frame = table.to_pandas()
        t = frame["time_s"].to_numpy()
        _check_time(place, t, strict=True, before=last)
        _check_temperature_values(table, frame, place, header[1:])
        last = float(t[-1])
        yield frame
    if last is None:
        raise _fail(file, 2, "no readings (the file has only a header)")


def _check_temperature_values(table: pa.Table, frame: pd.DataFrame, place: _Rows, names: list[str]) -> None:
    """Check a chunk's readings: finite where present (``_check_finite_nan_is_missing``) and in degC.

    The problem named is the one a column-by-column check meets first (the first column with one;
    in it a written NaN/inf before a value out of range), found with one pass over the chunk's
    values as a (rows, channels) array instead of a pass per channel and check.
    """
    lo, hi = TEMP_RANGE_DEGC
    v = frame.to_numpy(dtype="f8")[:, 1:]  # time_s first (checked by the header), a null read as NaN
    nonfinite = np.count_nonzero(~np.isfinite(v), axis=0)
    with np.errstate(invalid="ignore"):
        outside = (v < lo) | (v > hi)
    # more non-finite values than nulls in a column: a NaN or inf was written in a cell
    written = nonfinite != np.array([table.column(name).null_count for name in names])
    for j in np.flatnonzero(written | outside.any(axis=0)):
        name = names[j]
        if written[j]:
            _check_finite_nan_is_missing(table, place, name)
        k = place.first(outside[:, j])
        if k is not None:
            raise place.fail(
                k, f"column {name}: {float(v[k, j])!r} degC is outside {lo}..{hi}: temperatures must be in degC"
            )


def _conditions_header(path: Path) -> list[str]:
    """Return conditions.csv's header: time_s, then some of CONDITION_COLUMNS."""
    file = path.name
    header = _read_header(path, file)
    for name in header[1:]:
        if name not in CONDITION_COLUMNS:
            raise _fail(file, 1, f"unknown column {short(name)}: expected some of {','.join(CONDITION_COLUMNS)}")
    return header


def _condition_chunks(path: Path, block_bytes: int = CSV_BLOCK_BYTES) -> Iterator[pd.DataFrame]:
    """Yield conditions.csv as validated frames of consecutive rows (one empty frame for a header alone)."""
    file = path.name
    header = _conditions_header(path)
    last: float | None = None
    for place, table in _read_chunks(path, file, header, {}, block_bytes):
        _check_empty_lines(table, place)
        frame = table.to_pandas()
        if len(frame):
            _check_time(place, frame["time_s"].to_numpy(), strict=True, before=last)
        for name in header[1:]:
            _check_finite_nan_is_missing(table, place, name)
            _check_condition(place, name, frame[name].to_numpy(dtype="f8"))
        if len(frame):
            last = float(frame["time_s"].iat[-1])
        yield frame


def _check_condition(place: _Rows, name: str, v: np.ndarray) -> None:
    """Refuse a negative speed or feed and a position out of range (a units mistake)."""
    with np.errstate(invalid="ignore"):
        if name in ("spindle_rpm", "feed_mm_min"):
            k = place.first(v < 0)
            if k is not None:
                raise place.fail(k, f"column {name}: {float(v[k])!r} is negative")
        if name in ("a", "b"):
            k = place.first(np.abs(v) > MAX_ROTARY_POSITION_DEG)
            if k is not None:
                raise place.fail(k, f"column {name}: {float(v[k])!r} is not a rotary position in degrees")
        if name in ("x", "y", "z"):
            k = place.first(np.abs(v) > MAX_LINEAR_POSITION_MM)
            if k is not None:
                raise place.fail(
                    k,
                    f"column {name}: {float(v[k])!r} mm is beyond {MAX_LINEAR_POSITION_MM:.0f} mm: "
                    "positions must be in mm",
                )


def _errors_header(path: Path, meta: CampaignMeta | None) -> list[str]:
    """Return errors.csv's header: exactly the v1 (or, for a v2 bundle, v2) columns, in any order."""
    file = path.name
    header = _read_header(path, file, time_first=False)
    columns = ERROR_COLUMNS_V2 if meta is not None and meta.v2 else ERROR_COLUMNS
    for name in header:
        if name not in columns:
            raise _fail(file, 1, f"unknown column {short(name)}: expected {','.join(columns)}")
    for name in columns:
        if name not in header:
            raise _fail(file, 1, f"missing column {name!r}: expected {','.join(columns)}")
    return header


#: the columns that identify a reading: a second row with the same values is a duplicate
READING_KEY = ["time_s", "axis", "term", "position", "direction"]


def _error_chunks(
    path: Path, meta: CampaignMeta | None = None, block_bytes: int = CSV_BLOCK_BYTES
) -> Iterator[pd.DataFrame]:
    """Yield errors.csv as validated frames of consecutive rows (order and duplicates checked across them)."""
    file = path.name
    header = _errors_header(path, meta)
    v2 = meta is not None and meta.v2
    kinds = {"axis": "str", "term": "str", "direction": "str", **({"setup": "str"} if v2 else {})}
    last: float | None = None
    tail: pd.DataFrame | None = None  # the readings at the last time so far: a duplicate can only be among them
    for place, table in _read_chunks(path, file, header, kinds, block_bytes):
        if table.num_rows == 0:
            continue  # a header alone: refused once the file is read to its end
        _check_empty_lines(table, place)
        t = table.column("time_s").to_numpy(zero_copy_only=False)
        _check_time(place, t, strict=False, before=last)
        frame = _error_frame(table, place, t)
        if v2:
            assert meta is not None
            _load_pose_and_setup(place, table, frame, meta)
        tail = _check_duplicates(place, frame, tail)
        last = float(t[-1])
        yield frame
    if last is None:
        raise _fail(file, 2, "no error samples (the file has only a header)")


def _finite_column(place: _Rows, table: pa.Table, name: str, missing: str = "missing value") -> np.ndarray:
    """Return a numeric column of a chunk; its first empty or non-finite cell fails with the row."""
    v = table.column(name).to_numpy(zero_copy_only=False)
    k = place.first(table.column(name).is_null().to_numpy(zero_copy_only=False))
    if k is not None:
        raise place.fail(k, f"column {name}: {missing}")
    k = place.first(~np.isfinite(v))
    if k is not None:
        raise place.fail(k, f"column {name}: {float(v[k])!r} is not a finite number")
    return v


def _error_frame(table: pa.Table, place: _Rows, t: np.ndarray) -> pd.DataFrame:
    """Return the v1 columns of a chunk of errors.csv, each checked: vocabulary, direction, finite, plausible."""
    axis = np.asarray(table.column("axis").to_pylist(), dtype=object)
    term = np.asarray(table.column("term").to_pylist(), dtype=object)
    direction_text = np.asarray(table.column("direction").to_pylist(), dtype=object)
    for name, values, vocab in (("axis", axis, AXES), ("term", term, TERMS)):
        k = place.first(~np.isin(values, np.asarray(vocab, dtype=object)))
        if k is not None:
            cell = values[k]
            what = "missing" if cell is None else f"{short(cell)} is not one of {' '.join(vocab)}"
            raise place.fail(k, f"column {name}: {what}")
    k = place.first(~np.isin(direction_text, np.asarray(list(DIRECTIONS), dtype=object)))
    if k is not None:
        cell = direction_text[k]
        what = "missing" if cell is None else f"{short(cell)} is not +1 or -1"
        raise place.fail(k, f"column direction: {what}")
    direction = np.fromiter((DIRECTIONS[d] for d in direction_text), dtype=np.int64, count=len(direction_text))
    position = _finite_column(place, table, "position")
    value = _finite_column(place, table, "value")
    is_rot_axis = np.isin(axis, np.asarray(ROTARY_AXES, dtype=object))
    k = place.first(is_rot_axis & (np.abs(position) > MAX_ROTARY_POSITION_DEG))
    if k is not None:
        raise place.fail(k, f"column position: {float(position[k])!r} is not a rotary position in degrees")
    k = place.first(~is_rot_axis & (np.abs(position) > MAX_LINEAR_POSITION_MM))
    if k is not None:
        raise place.fail(
            k,
            f"column position: {float(position[k])!r} mm is beyond {MAX_LINEAR_POSITION_MM:.0f} mm: "
            "positions must be in mm",
        )
    is_trans = np.isin(term, np.asarray(TRANSLATION_TERMS, dtype=object))
    k = place.first(is_trans & (np.abs(value) > MAX_TRANSLATION_MM))
    if k is not None:
        raise place.fail(
            k, f"column value: {float(value[k])!r} mm is implausibly large for a translation: values must be in mm"
        )
    k = place.first(~is_trans & (np.abs(value) > MAX_ROTATION_RAD))
    if k is not None:
        raise place.fail(
            k, f"column value: {float(value[k])!r} rad is implausibly large for a rotation: values must be in rad"
        )
    return pd.DataFrame(
        {
            "time_s": t,
            "axis": pd.array(axis.tolist(), dtype="str"),
            "term": pd.array(term.tolist(), dtype="str"),
            "position": position,
            "direction": direction,
            "value": value,
        }
    )


def _check_duplicates(place: _Rows, frame: pd.DataFrame, tail: pd.DataFrame | None) -> pd.DataFrame:
    """Refuse a reading repeated from an earlier row; return the readings at the chunk's last time.

    Rows are in time order (checked first), so a reading can only repeat one of the same time_s: the
    rows at the previous chunk's last time are all an earlier chunk can contribute.
    """
    keys = frame[READING_KEY]
    both = keys if tail is None else pd.concat([tail, keys], ignore_index=True)
    dup = both.duplicated().to_numpy()[len(both) - len(keys) :]
    k = place.first(dup)
    if k is not None:
        raise place.fail(k, "duplicate reading: same time_s, axis, term, position and direction as an earlier row")
    t = both["time_s"].to_numpy()
    return both[t == t[-1]].reset_index(drop=True)


def _load_pose_and_setup(place: _Rows, table: pa.Table, frame: pd.DataFrame, meta: CampaignMeta) -> None:
    """Add and check v2's pose and setup columns: finite pose, position = the moved axis' pose, known setup."""
    for name in POSE_COLUMNS:
        v = _finite_column(place, table, name, "missing value (a bundle v2 gives the full pose)")
        bound = MAX_ROTARY_POSITION_DEG if name in ("a", "b") else MAX_LINEAR_POSITION_MM
        k = place.first(np.abs(v) > bound)
        if k is not None:
            raise place.fail(
                k, f"column {name}: {float(v[k])!r} is beyond {bound:.0f} ({'degrees' if name in ('a', 'b') else 'mm'})"
            )
        frame[name] = v
    axis = frame["axis"].to_numpy(dtype=object)
    term = frame["term"].to_numpy(dtype=object)
    pose = frame[list(POSE_COLUMNS)].to_numpy(float)
    moved = pose[np.arange(len(frame)), [AXES.index(a) for a in axis]]
    pos = frame["position"].to_numpy(float)
    k = place.first(np.abs(moved - pos) > 1e-9 * np.maximum(1.0, np.abs(pos)))
    if k is not None:
        ax = axis[k]
        raise place.fail(
            k, f"column {ax.lower()}: {moved[k]!r} differs from position {pos[k]!r} of the moved axis {ax}"
        )
    setup = np.asarray(table.column("setup").to_pylist(), dtype=object)
    setups = meta.setups or {}
    for k, (sid, ax, tm) in enumerate(zip(setup, axis, term)):
        entry = setups.get(sid) if sid is not None else None
        if entry is None:
            what = "missing" if sid is None else f"{short(sid)} is not among campaign.json setups"
            raise place.fail(k, f"column setup: {what}")
        if f"{ax}/{tm}" not in entry.terms:
            raise place.fail(
                k,
                f"column setup: setup {short(sid)} does not deliver {ax}/{tm} (it delivers {', '.join(entry.terms)})",
            )
    frame["setup"] = pd.array(setup.tolist(), dtype="str")


def _readable(chunks: Iterator[_T], file: str) -> Iterator[_T]:
    """Yield from ``chunks``, turning a read failing half-way (EIO, a file removed under us) into a BundleError."""
    try:
        yield from chunks
    except OSError as exc:
        where = Path(exc.filename).name if exc.filename else file
        raise BundleError(f"{where}: cannot read: {exc.strerror or exc}") from None


#: how far outside the temperature scans an error sample, and after the last scan a stage's end, may lie (s):
#: the thermal model reads the temperatures at each error's time, and a stage is a part of the recorded run
TIME_SLACK_S = 3600.0


def _duration(seconds: float) -> str:
    """Return a duration for people: seconds, hours or days."""
    if seconds >= 2 * 86400:
        return f"{seconds / 86400:.0f} days"
    if seconds >= 2 * 3600:
        return f"{seconds / 3600:.0f} h"
    return f"{seconds:.0f} s"


@dataclass(frozen=True)
class Span:
    """The first and last ``time_s`` of a CSV file (its rows are lines 2 .. rows + 1)."""

    first: float
    last: float
    rows: int


@dataclass
class TimeSpans:
    """The spans of temperatures.csv and errors.csv, noted as each is read to its end, checked against each other."""

    temperatures: Span | None = None
    errors: Span | None = None

    def check(self, meta: CampaignMeta, lines: Mapping[tuple[Any, ...], int]) -> None:
        """Refuse errors far outside the scans and stages ending far after the last scan (once both are known)."""
        t = self.temperatures
        if t is None:
            return
        for k, stage in enumerate(meta.stages):
            if stage.end_s > t.last + TIME_SLACK_S:
                raise json_fail(
                    CAMPAIGN_FILE,
                    lines,
                    ("stages", k, "end_s"),
                    f"{stage.end_s!r} s is {_duration(stage.end_s - t.last)} after the last temperature scan "
                    f"(time_s {t.last!r}): a stage lies within the recorded data",
                )
        e = self.errors
        if e is None:
            return
        if e.last > t.last + TIME_SLACK_S:
            raise _fail(
                ERRORS_FILE,
                e.rows + 1,
                f"time_s {e.last!r} is {_duration(e.last - t.last)} after the last temperature scan "
                f"(time_s {t.last!r}): errors are measured while the temperatures are scanned",
            )
        if e.first < t.first - TIME_SLACK_S:
            raise _fail(
                ERRORS_FILE,
                2,
                f"time_s {e.first!r} is {_duration(t.first - e.first)} before the first temperature scan "
                f"(time_s {t.first!r}): errors are measured while the temperatures are scanned",
            )


@dataclass(frozen=True)
class BundleFiles:
    """A bundle directory whose files and campaign.json are checked, its CSVs read a chunk at a time.

    Each of ``temperatures()``, ``conditions()`` and ``errors()`` reads its file afresh and yields
    validated frames of consecutive rows (about ``block_bytes`` of CSV text each), checking what
    spans chunks (time order, duplicate readings) with state carried from one to the next; a problem
    anywhere is a BundleError naming its line. Memory holds a chunk, not the file.
    """

    root: Path
    meta: CampaignMeta
    temperatures_path: Path
    conditions_path: Path | None
    errors_path: Path
    block_bytes: int = CSV_BLOCK_BYTES
    meta_lines: Mapping[tuple[Any, ...], int] = field(default_factory=dict)
    spans: TimeSpans = field(default_factory=lambda: TimeSpans())

    @property
    def name(self) -> str:
        """Return the bundle's name (its directory's)."""
        return self.root.resolve().name

    def temperatures(self) -> Iterator[pd.DataFrame]:
        """Yield temperatures.csv: ``time_s`` and one column per channel, in the file's column order."""
        return _readable(
            self._spanned(_temperature_chunks(self.temperatures_path, self.meta, self.block_bytes)), TEMPERATURES_FILE
        )

    def conditions(self) -> Iterator[pd.DataFrame]:
        """Yield conditions.csv (nothing when the bundle has none)."""
        if self.conditions_path is None:
            return iter(())
        return _readable(_condition_chunks(self.conditions_path, self.block_bytes), CONDITIONS_FILE)

    def errors(self) -> Iterator[pd.DataFrame]:
        """Yield errors.csv with ``direction`` as +1/-1 (and, for v2, the pose and setup columns)."""
        return _readable(
            self._spanned(_error_chunks(self.errors_path, self.meta, self.block_bytes), errors=True), ERRORS_FILE
        )

    def _spanned(self, chunks: Iterator[pd.DataFrame], errors: bool = False) -> Iterator[pd.DataFrame]:
        """Yield the chunks of temperatures.csv or errors.csv; at the file's end note its span and check the times."""
        first: float | None = None
        last = 0.0
        rows = 0
        for frame in chunks:
            t = frame["time_s"]
            if first is None:
                first = float(t.iat[0])
            last = float(t.iat[-1])
            rows += len(frame)
            yield frame
        if first is None:  # pragma: no cover - an empty file is refused by the chunks themselves
            return
        span = Span(first, last, rows)
        if errors:
            self.spans.errors = span
        else:
            self.spans.temperatures = span
        self.spans.check(self.meta, self.meta_lines)


def open_bundle(path: str | Path, block_bytes: int = CSV_BLOCK_BYTES) -> BundleFiles:
    """Return the bundle in directory ``path`` with its files and campaign.json checked; BundleError otherwise."""
    root = Path(path)
    try:
        if not root.is_dir():
            raise BundleError(f"{root}: not a bundle directory")
        # every file is checked (regular, within its size limit) before any is read
        meta_path = _check_file(root, CAMPAIGN_FILE, MAX_JSON_BYTES, required=True)
        temp_path = _check_file(root, TEMPERATURES_FILE, MAX_CSV_BYTES, required=True)
        err_path = _check_file(root, ERRORS_FILE, MAX_CSV_BYTES, required=True)
        cond_path = _check_file(root, CONDITIONS_FILE, MAX_CSV_BYTES, required=False)
        assert meta_path is not None and temp_path is not None and err_path is not None
        with _open(meta_path, CAMPAIGN_FILE) as fh:
            data = fh.read(MAX_JSON_BYTES + 1)
    except OSError as exc:  # a read failing half-way (EIO, a file removed under us)
        where = Path(exc.filename).name if exc.filename else str(root)
        raise BundleError(f"{where}: cannot read: {exc.strerror or exc}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise BundleError(f"{CAMPAIGN_FILE}:{line}: column {column}: not UTF-8 text") from None
    meta, lines = parse_meta_located(text)
    return BundleFiles(root, meta, temp_path, cond_path, err_path, block_bytes, lines)


def _concat(chunks: Iterator[pd.DataFrame]) -> pd.DataFrame:
    """Return the chunks of a file as one frame (index 0..n-1)."""
    frames = list(chunks)
    return frames[0] if len(frames) == 1 else pd.concat(frames, ignore_index=True)


def load_bundle(path: str | Path, block_bytes: int = CSV_BLOCK_BYTES) -> Bundle:
    """Return the validated bundle in directory ``path`` held in memory; raise BundleError (``FILE:ROW: problem``).

    For a bundle too large to hold, ``staging.stage_bundle`` validates the same way a chunk at a time.
    """
    files = open_bundle(path, block_bytes)
    temperatures = _concat(files.temperatures())
    conditions = _concat(files.conditions()) if files.conditions_path is not None else None
    errors = _concat(files.errors())
    return Bundle(name=files.name, meta=files.meta, temperatures=temperatures, conditions=conditions, errors=errors)


# ----------------------------------------------------------------------------- writing


def _as_meta(meta: CampaignMeta | Mapping[str, Any]) -> CampaignMeta:
    if isinstance(meta, CampaignMeta):
        return meta
    text = json.dumps(meta, indent=1, default=str)
    return parse_meta(text)


def _float_text(v: np.ndarray) -> pa.Array:
    """Return shortest round-trip text for floats (integral values keep a '.0'), NaN as null."""
    arr = pa.array(v, type=pa.float64(), from_pandas=True)
    text = pc.cast(arr, pa.string())
    integral = pc.match_substring_regex(text, r"^-?[0-9]+$")
    return pc.if_else(integral, pc.binary_join_element_wise(text, pa.scalar(".0"), ""), text)


def _write_csv(path: Path, frame: pd.DataFrame, columns: list[str], kinds: Mapping[str, str]) -> None:
    """Write columns with shortest round-trip float text; NaN becomes an empty cell."""
    arrays = []
    for name in columns:
        kind = kinds.get(name, "float")
        series = frame[name]
        if kind == "float":
            v = series.to_numpy(dtype="f8")
            if np.isinf(v).any():
                raise BundleError(f"{path.name}: column {name}: infinite values cannot be written")
            arrays.append(_float_text(v))
        elif kind == "int":
            arrays.append(pa.array(series.to_numpy(dtype="i8")))
        else:
            arrays.append(pa.array(series.astype(str).tolist(), type=pa.string()))
    table = pa.table(arrays, names=[f"c{i}" for i in range(len(columns))])
    with path.open("wb") as fh:
        fh.write((",".join(columns) + "\n").encode())
        pacsv.write_csv(table, fh, pacsv.WriteOptions(include_header=False, quoting_style="none"))


def write_bundle(
    path: str | Path,
    meta: CampaignMeta | Mapping[str, Any],
    temperatures: pd.DataFrame,
    conditions: pd.DataFrame | None,
    errors: pd.DataFrame,
) -> Path:
    """Write a bundle directory (v1, or v2 when ``meta`` says so) that load_bundle and pandas read back exactly."""
    root = Path(path)
    meta_obj = _as_meta(meta)
    root.mkdir(parents=True, exist_ok=True)
    channels = [c for c in temperatures.columns if c != "time_s"]
    (root / CAMPAIGN_FILE).write_text(json.dumps(meta_obj.document(), indent=1) + "\n", encoding="utf-8")
    _write_csv(root / TEMPERATURES_FILE, temperatures, ["time_s", *channels], {})
    cond_path = root / CONDITIONS_FILE
    if conditions is not None:
        cols = [c for c in conditions.columns if c in CONDITION_COLUMNS and c != "time_s"]
        _write_csv(cond_path, conditions, ["time_s", *cols], {})
    elif cond_path.exists():
        cond_path.unlink()
    _write_csv(
        root / ERRORS_FILE,
        errors,
        list(ERROR_COLUMNS_V2 if meta_obj.v2 else ERROR_COLUMNS),
        {"axis": "str", "term": "str", "direction": "int", "setup": "str"},
    )
    return root
