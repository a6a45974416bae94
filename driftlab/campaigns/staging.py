"""A bundle staged for import: validated a chunk at a time into temporary files of binary columns.

`driftlab import` of a bundle near the size limit must not hold its tables in memory, and must
still refuse a bad row at the end of the last file without touching the store. So the bundle is
read and validated exactly as ``load_bundle`` does, a chunk at a time (``bundle.open_bundle``),
and each validated chunk is appended to a temporary file, one per table, as contiguous binary
columns (float64; small integer codes for the axis, term and setup names). Only once every file
has been read to its end, and the content hash computed, does the import open its transaction:
it then reads the columns back a chunk at a time (``store.campaigns.import_bundle`` of a ``StagedBundle``).
The store's write lock is held while rows are written, never while text is parsed.

The content hash is computed column after column, as ``bundle.content_hash`` always has (the
hashes of campaigns already stored stay valid); that order is why the rows go to disk first.
The temporary files are anonymous (``tempfile.TemporaryFile``): they vanish when closed, or when
the process ends, however it ends. They take about 8 bytes per value, in ``TMPDIR``.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import pandas as pd

from driftlab.campaigns.bundle import (
    CSV_BLOCK_BYTES,
    POSE_COLUMNS,
    BundleFiles,
    CampaignMeta,
    open_bundle,
    table_hash,
)
from driftlab.vocabulary import AXES, TERMS


@dataclass
class _Chunk:
    """Where one chunk's columns sit in the file: byte offset of each column, and the row count."""

    offsets: dict[str, int]
    rows: int


class StagedTable:
    """A table in a temporary file, appended and read back a chunk at a time.

    Each chunk's columns are stored one after the other, so a column is read (``column``) or a run
    of rows (``chunks``) with one read per column and chunk. Text columns are stored as codes into
    a fixed vocabulary and read back as object arrays of str.
    """

    def __init__(
        self,
        columns: Sequence[str],
        dtypes: Mapping[str, Any],
        vocabularies: Mapping[str, Sequence[str]] | None = None,
        directory: str | None = None,
    ) -> None:
        self.columns = list(columns)
        self._dtypes = {c: np.dtype(dtypes.get(c, "f8")) for c in self.columns}
        self._vocab = {c: np.asarray(list(v), dtype=object) for c, v in (vocabularies or {}).items()}
        for c in self._vocab:
            self._dtypes[c] = np.dtype("i2")
        self._file: BinaryIO = tempfile.TemporaryFile(prefix="driftlab-stage-", dir=directory)
        self._chunks: list[_Chunk] = []
        self._end = 0
        self.n_rows = 0

    def append(self, frame: pd.DataFrame) -> None:
        """Write the table's columns of ``frame`` as the next chunk."""
        n = len(frame)
        if n == 0:
            return
        offsets: dict[str, int] = {}
        self._file.seek(self._end)
        for name in self.columns:
            values = frame[name]
            if name in self._vocab:
                data = pd.Categorical(values.to_numpy(dtype=object), categories=self._vocab[name]).codes
            else:
                data = values.to_numpy(dtype=self._dtypes[name])
            raw = np.ascontiguousarray(data, dtype=self._dtypes[name]).tobytes()
            offsets[name] = self._end
            self._file.write(raw)
            self._end += len(raw)
        self._file.flush()  # read back with os.pread, which does not see the file object's buffer
        self._chunks.append(_Chunk(offsets, n))
        self.n_rows += n

    def _read(self, chunk: _Chunk, name: str) -> np.ndarray:
        """Return one column of one chunk (decoded when it is a text column).

        Read with ``os.pread`` (no shared file position): once appended, a table is read by the
        import and by the content hash at the same time (``import_pipeline``).
        """
        dtype = self._dtypes[name]
        size = chunk.rows * dtype.itemsize
        data = os.pread(self._file.fileno(), size, chunk.offsets[name])
        if len(data) != size:  # the temporary file is ours alone: a short read is the disk failing
            raise OSError(f"staged column {name}: read {len(data)} of {size} bytes")
        values = np.frombuffer(data, dtype=dtype)
        return self._vocab[name][values] if name in self._vocab else values

    def column(self, name: str) -> Iterator[np.ndarray]:
        """Yield the column ``name`` chunk after chunk, in row order."""
        for chunk in self._chunks:
            yield self._read(chunk, name)

    def chunks(self, names: Sequence[str] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """Yield runs of consecutive rows as {column: values} (every column unless ``names``)."""
        for chunk in self._chunks:
            yield {name: self._read(chunk, name) for name in (names or self.columns)}

    def close(self) -> None:
        """Remove the temporary file."""
        self._file.close()


@dataclass
class StagedBundle:
    """A validated bundle whose tables wait in temporary files (see module docstring); close it when done."""

    name: str
    meta: CampaignMeta
    temperatures: StagedTable
    conditions: StagedTable | None
    errors: StagedTable
    hash: str = field(default="")

    @property
    def channels(self) -> list[str]:
        """Return the channel names in temperatures.csv column order."""
        return [c for c in self.temperatures.columns if c != "time_s"]

    def content_hash(self) -> str:
        """Return the SHA-256 of the bundle's values, the same as ``Bundle.content_hash`` of it in memory."""
        return self.hash

    def close(self) -> None:
        """Remove the temporary files."""
        for table in (self.temperatures, self.conditions, self.errors):
            if table is not None:
                table.close()

    def __enter__(self) -> StagedBundle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def stage_errors(files: BundleFiles, tables: list[StagedTable], directory: str | None) -> StagedTable:
    """Return errors.csv validated and staged (the table put in ``tables`` first, to be closed on failure)."""
    errors = _error_table(files.meta, directory)
    tables.append(errors)
    for frame in files.errors():
        errors.append(frame)
    return errors


def _error_table(meta: CampaignMeta, directory: str | None) -> StagedTable:
    """Return an empty table for errors.csv: names stored as codes into their fixed vocabularies."""
    columns = ["time_s", "axis", "term", "position", "direction", "value"]
    vocab: dict[str, Sequence[str]] = {"axis": AXES, "term": TERMS}
    if meta.v2:
        columns += [*POSE_COLUMNS, "setup"]
        vocab["setup"] = sorted(meta.setups or {})
    return StagedTable(columns, {"direction": "i1"}, vocab, directory)


def stage_frames(
    frames: Iterable[pd.DataFrame], tables: list[StagedTable], directory: str | None
) -> StagedTable | None:
    """Return a table of the chunks ``frames``, made at the first (and put in ``tables``); None when there are none."""
    table: StagedTable | None = None
    for frame in frames:
        if table is None:
            table = StagedTable(list(frame.columns), {}, None, directory)
            tables.append(table)
        table.append(frame)
    return table


def stage_bundle(path: str | Path, block_bytes: int = CSV_BLOCK_BYTES, directory: str | None = None) -> StagedBundle:
    """Return the bundle in directory ``path`` validated and staged; BundleError (nothing staged) otherwise."""
    files = open_bundle(path, block_bytes)
    tables: list[StagedTable] = []
    try:
        temperatures = stage_frames(files.temperatures(), tables, directory)
        conditions = stage_frames(files.conditions(), tables, directory)
        errors = stage_errors(files, tables, directory)
        assert temperatures is not None  # temperatures() yields at least one chunk or raises
        staged = StagedBundle(files.name, files.meta, temperatures, conditions, errors)
        staged.hash = table_hash(files.meta, temperatures, conditions, errors)
    except BaseException:
        for table in tables:
            table.close()
        raise
    return staged
