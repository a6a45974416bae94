"""Campaign bundle v1: load (validating everything first) and write, no database involved.

A bundle is a directory with campaign.json, temperatures.csv, errors.csv and an optional
conditions.csv (see docs/bundle.md). Every problem is reported as one line ``FILE:ROW: problem``
with ROW counted as a text editor shows it (the header is line 1).

Large files are parsed by pyarrow's C++ CSV reader with explicit column types (correctly
rounded float parsing, so values round-trip bit-exactly); only when that fast parse fails does
a slow line-by-line scanner run to find the exact row and say what is wrong with it.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
from pydantic import BaseModel, ConfigDict, Field, field_validator
from pydantic import ValidationError as PydanticValidationError

from driftlab.errors import ValidationError

FORMAT = "driftlab-bundle/1"
FORMAT_V2 = "driftlab-bundle/2"
FORMATS = (FORMAT, FORMAT_V2)
AXES = ("X", "Y", "Z", "A", "B")
ROTARY_AXES = ("A", "B")
TERMS = ("alpha", "beta", "gamma", "dx", "dy", "dz")
TRANSLATION_TERMS = ("dx", "dy", "dz")
ERROR_COLUMNS = ("time_s", "axis", "term", "position", "direction", "value")
#: bundle v2 errors.csv: the full commanded pose (mm, degrees) after direction, then the setup id
POSE_COLUMNS = ("x", "y", "z", "a", "b")
ERROR_COLUMNS_V2 = ("time_s", "axis", "term", "position", "direction", *POSE_COLUMNS, "setup", "value")
CONDITION_COLUMNS = ("time_s", "spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b")
CAMPAIGN_FILE = "campaign.json"
TEMPERATURES_FILE = "temperatures.csv"
CONDITIONS_FILE = "conditions.csv"
ERRORS_FILE = "errors.csv"

# Plausibility limits that catch wrong units (kelvin, micrometres, degrees for radians).
TEMP_RANGE_DEGC = (-60.0, 250.0)
MAX_TRANSLATION_MM = 5.0
MAX_ROTATION_RAD = 0.05
MAX_ROTARY_POSITION_DEG = 720.0

_DIRECTIONS = {"1": 1, "+1": 1, "1.0": 1, "+1.0": 1, "-1": -1, "-1.0": -1}
_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
_NONFINITE = re.compile(r"^[+-]?(nan|inf|infinity)$", re.IGNORECASE)
_CHANNEL_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")


class BundleError(ValidationError):
    """A bundle that does not meet the v1 contract; the message is ``FILE:ROW: problem``."""


# ----------------------------------------------------------------------------- campaign.json


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Machine(_Strict):
    """The machine a campaign was measured on."""

    id: str = Field(min_length=1, max_length=64)
    name: str = ""
    resolution_mm: float | None = Field(default=None, gt=0, allow_inf_nan=False)
    resolution_deg: float | None = Field(default=None, gt=0, allow_inf_nan=False)


class Channel(_Strict):
    """A thermocouple site: where it is and which structure it sits on."""

    location: str = ""
    structure: str = ""


class Stage(_Strict):
    """One stage of the staged single-heat-source plan, as it was run."""

    name: str = Field(min_length=1)
    start_s: float = Field(ge=0, allow_inf_nan=False)
    end_s: float = Field(ge=0, allow_inf_nan=False)
    heat_source: str = Field(min_length=1)
    axis: Literal["X", "Y", "Z", "A", "B"] | None = None
    spindle_rpm: float = Field(default=0.0, ge=0, allow_inf_nan=False)
    feed_mm_min: float = Field(default=0.0, ge=0, allow_inf_nan=False)


class Noise(_Strict):
    """Stated repeatability of the error measurement."""

    length_mm: float | None = Field(default=None, ge=0, allow_inf_nan=False)
    angle_rad: float | None = Field(default=None, ge=0, allow_inf_nan=False)


class SetupEntry(_Strict):
    """Bundle v2: one instrument setup (what was mounted, the terms it delivers, how it was referenced)."""

    instrument: Literal["laser", "proximity", "probe", "level", "other"]
    optics: str | None = Field(default=None, min_length=1, max_length=64)
    fixture: str | None = Field(default=None, min_length=1, max_length=64)
    axis: Literal["X", "Y", "Z", "A", "B"] | None = None
    terms: list[str] = Field(min_length=1)
    datum: Literal["session", "absolute"] = "session"
    counter_rotating: bool = False
    reference: dict[str, Any] = Field(default_factory=dict)

    @field_validator("terms")
    @classmethod
    def _cells(cls, value: list[str]) -> list[str]:
        """Require AXIS/term names of the thirty motion-error terms, each once."""
        for c in value:
            ax, _, term = c.partition("/")
            if ax not in AXES or term not in TERMS:
                raise ValueError(f"{c!r} is not AXIS/term (axis X Y Z A B, term dx dy dz alpha beta gamma)")
        if len(set(value)) != len(value):
            raise ValueError("a term is listed twice")
        return value


class CampaignMeta(_Strict):
    """campaign.json of bundle v1 or v2: machine, channel map, room/model channels, stages, noise (v2: setups)."""

    format: Literal["driftlab-bundle/1", "driftlab-bundle/2"]
    machine: Machine
    started_at: datetime
    channels: dict[str, Channel] = Field(min_length=1)
    room_channels: list[str] = Field(default_factory=list)
    model_channels: dict[Literal["X", "Y", "Z", "A", "B"], list[str]] | None = None
    stages: list[Stage] = Field(default_factory=list)
    noise: Noise | None = None
    setups: dict[str, SetupEntry] | None = None

    @property
    def v2(self) -> bool:
        """Return True for a bundle v2 (errors carry the full pose and the setup)."""
        return self.format == FORMAT_V2

    @field_validator("started_at")
    @classmethod
    def _aware(cls, value: datetime) -> datetime:
        """Require a time zone on started_at (wall-clock times are computed from it)."""
        if value.tzinfo is None:
            raise ValueError("started_at needs a time zone, e.g. 2026-03-02T08:00:00Z")
        return value

    def document(self) -> dict[str, Any]:
        """Return campaign.json as a JSON-ready dict (absent optional fields left out)."""
        return self.model_dump(mode="json", exclude_none=True)


def _locate_json(text: str) -> dict[tuple[Any, ...], int]:
    """Return the 1-based line of every value in a valid JSON text, keyed by its path."""
    decoder = json.JSONDecoder()
    ws = re.compile(r"[ \t\n\r]*")
    found: dict[tuple[Any, ...], int] = {}

    def line(i: int) -> int:
        return text.count("\n", 0, i) + 1

    def parse(i: int, path: tuple[Any, ...]) -> int:
        i = ws.match(text, i).end()  # type: ignore[union-attr]
        found[path] = line(i)
        if text[i] == "{":
            i = ws.match(text, i + 1).end()  # type: ignore[union-attr]
            if text[i] == "}":
                return i + 1
            while True:
                i = ws.match(text, i).end()  # type: ignore[union-attr]
                key_line = line(i)
                key, i = json.decoder.scanstring(text, i + 1)  # type: ignore[attr-defined]
                i = ws.match(text, i).end() + 1  # type: ignore[union-attr]  # skip ':'
                i = parse(i, path + (key,))
                found.setdefault(path + (key,), key_line)
                i = ws.match(text, i).end()  # type: ignore[union-attr]
                if text[i] == "}":
                    return i + 1
                i += 1  # ','
        if text[i] == "[":
            i = ws.match(text, i + 1).end()  # type: ignore[union-attr]
            if text[i] == "]":
                return i + 1
            k = 0
            while True:
                i = parse(i, path + (k,))
                k += 1
                i = ws.match(text, i).end()  # type: ignore[union-attr]
                if text[i] == "]":
                    return i + 1
                i += 1
        _, end = decoder.raw_decode(text, i)
        return end

    try:
        parse(0, ())
    except (ValueError, IndexError, AttributeError):  # pragma: no cover - text was valid JSON
        pass
    return found


def _path_text(path: tuple[Any, ...]) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def _json_fail(file: str, lines: Mapping[tuple[Any, ...], int], path: tuple[Any, ...], problem: str) -> BundleError:
    """Return a BundleError naming the line of the nearest located ancestor of ``path``."""
    probe = tuple(path)
    while probe and probe not in lines:
        probe = probe[:-1]
    return BundleError(f"{file}:{lines.get(probe, 1)}: {_path_text(path)}: {problem}")


def parse_meta(text: str, file: str = CAMPAIGN_FILE) -> CampaignMeta:
    """Return the validated CampaignMeta of a campaign.json text; raise BundleError naming the line."""
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BundleError(f"{file}:{exc.lineno}: invalid JSON: {exc.msg} (column {exc.colno})") from None
    lines = _locate_json(text)
    return _validate_meta(raw, file, lines)


def _validate_meta(raw: Any, file: str, lines: Mapping[tuple[Any, ...], int]) -> CampaignMeta:
    """Validate a decoded campaign.json document, including references between its parts."""
    if isinstance(raw, dict) and "format" in raw and raw["format"] not in FORMATS:
        raise _json_fail(file, lines, ("format",), f"unsupported format {raw['format']!r}, expected {FORMAT!r} "
                         f"or {FORMAT_V2!r}")
    try:
        meta = CampaignMeta.model_validate(raw)
    except PydanticValidationError as exc:
        err = exc.errors()[0]
        raise _json_fail(file, lines, tuple(err["loc"]), err["msg"]) from None
    for name in meta.channels:
        if not _CHANNEL_NAME.match(name) or name == "time_s":
            raise _json_fail(
                file, lines, ("channels", name), "channel names may hold only letters, digits, '_', '.', '-' "
                "and may not be time_s"
            )
    seen: set[str] = set()
    for k, name in enumerate(meta.room_channels):
        if name not in meta.channels:
            raise _json_fail(file, lines, ("room_channels", k), f"room channel {name!r} is not in channels")
        if name in seen:
            raise _json_fail(file, lines, ("room_channels", k), f"room channel {name!r} listed twice")
        seen.add(name)
    for axis, names in (meta.model_channels or {}).items():
        seen = set()
        for k, name in enumerate(names):
            if name not in meta.channels:
                raise _json_fail(
                    file, lines, ("model_channels", axis, k), f"model channel {name!r} is not in channels"
                )
            if name in seen:
                raise _json_fail(file, lines, ("model_channels", axis, k), f"model channel {name!r} listed twice")
            seen.add(name)
    if meta.setups is not None and not meta.v2:
        raise _json_fail(file, lines, ("setups",), f"setups belong to {FORMAT_V2!r} bundles")
    if meta.v2 and not meta.setups:
        raise _json_fail(file, lines, ("setups",) if meta.setups is not None else ("format",),
                         "a bundle v2 needs setups: the instrument setup of every error reading")
    for sid, entry in (meta.setups or {}).items():
        if not _CHANNEL_NAME.match(sid) or len(sid) > 64:
            raise _json_fail(file, lines, ("setups", sid), "setup ids may hold only letters, digits, '_', '.', '-' "
                             "(at most 64)")
        if entry.axis is not None and any(not c.startswith(entry.axis + "/") for c in entry.terms):
            raise _json_fail(file, lines, ("setups", sid, "terms"), f"setup {sid!r} measures the {entry.axis} axis "
                             "but lists terms of another")
    names_seen: set[str] = set()
    previous_end = -math.inf
    for k, stage in enumerate(meta.stages):
        if stage.end_s < stage.start_s:
            raise _json_fail(
                file, lines, ("stages", k, "end_s"), f"stage {stage.name!r} ends ({stage.end_s}) before it starts "
                f"({stage.start_s})"
            )
        if stage.start_s < previous_end:
            raise _json_fail(
                file, lines, ("stages", k, "start_s"), f"stage {stage.name!r} starts at {stage.start_s}, before the "
                f"previous stage ends ({previous_end}): stages must be in order and not overlap"
            )
        if stage.name in names_seen:
            raise _json_fail(file, lines, ("stages", k, "name"), f"stage name {stage.name!r} used twice")
        names_seen.add(stage.name)
        previous_end = stage.end_s
    return meta


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


def _hash_floats(h: Any, values: np.ndarray) -> None:
    arr = np.ascontiguousarray(values, dtype="<f8").copy()
    arr[np.isnan(arr)] = np.nan  # one canonical NaN bit pattern
    h.update(arr.tobytes())


def content_hash(
    meta: CampaignMeta, temperatures: pd.DataFrame, conditions: pd.DataFrame | None, errors: pd.DataFrame
) -> str:
    """Return the SHA-256 hex digest identifying a bundle's content."""
    h = hashlib.sha256()
    h.update(json.dumps(meta.document(), sort_keys=True).encode())
    for label, frame in (("temperatures", temperatures), ("conditions", conditions)):
        h.update(f"\0{label}\0".encode())
        if frame is None:
            h.update(b"absent")
            continue
        h.update(",".join(frame.columns).encode())
        for col in frame.columns:
            _hash_floats(h, frame[col].to_numpy(dtype="f8"))
    h.update(b"\0errors\0")
    for col in ("time_s", "position", "value"):
        _hash_floats(h, errors[col].to_numpy(dtype="f8"))
    for col in ("axis", "term"):
        h.update("\n".join(errors[col].astype(str).tolist()).encode())
    h.update(errors["direction"].to_numpy(dtype="<i1").tobytes())
    if meta.v2:  # v1 hashes are unchanged (duplicate imports of v1 bundles are still recognised)
        for col in POSE_COLUMNS:
            _hash_floats(h, errors[col].to_numpy(dtype="f8"))
        h.update("\n".join(errors["setup"].astype(str).tolist()).encode())
    return h.hexdigest()


def _fail(file: str, row: int | None, problem: str) -> BundleError:
    return BundleError(f"{file}:{row}: {problem}" if row is not None else f"{file}: {problem}")


def _read_header(path: Path, file: str) -> list[str]:
    """Return the header fields of a CSV file, checked for emptiness and duplicates."""
    with path.open("r", newline="", encoding="utf-8", errors="strict") as fh:
        try:
            first = fh.readline()
        except UnicodeDecodeError:
            raise _fail(file, 1, "not UTF-8 text") from None
    if not first.strip():
        raise _fail(file, 1, "empty file: expected a header line starting with time_s")
    header = next(csv.reader([first]))
    seen: set[str] = set()
    for name in header:
        if not name.strip():
            raise _fail(file, 1, "empty column name in header")
        if name in seen:
            raise _fail(file, 1, f"duplicate column {name!r}")
        seen.add(name)
    if header[0] != "time_s":
        raise _fail(file, 1, f"first column must be time_s, found {header[0]!r}")
    return header


def _scan_for_problem(path: Path, file: str, header: list[str], kinds: Mapping[str, str]) -> BundleError | None:
    """Return the first row-level problem found by a slow, exact line-by-line scan (or None)."""
    n = len(header)
    with path.open("r", newline="", encoding="utf-8", errors="replace") as fh:
        data = fh.read()
    lines = data.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    for lineno, raw in enumerate(lines[1:], start=2):
        line = raw[:-1] if raw.endswith("\r") else raw
        if not line.strip():
            return _fail(file, lineno, "empty line")
        fields = next(csv.reader([line]))
        if fields == header:
            return _fail(file, lineno, "repeated header line")
        if len(fields) != n:
            hint = " (truncated line?)" if len(fields) < n and lineno == len(lines) else ""
            return _fail(file, lineno, f"expected {n} fields, found {len(fields)}{hint}")
        for name, cell in zip(header, fields, strict=True):
            kind = kinds.get(name, "float")
            if kind == "float":
                if cell == "":
                    continue
                if _NONFINITE.match(cell.strip()):
                    return _fail(file, lineno, f"column {name}: {cell!r} is not a finite number")
                if not _NUMBER.match(cell):
                    return _fail(file, lineno, f"column {name}: {cell!r} is not a number")
    return None


def _read_table(path: Path, file: str, header: list[str], kinds: Mapping[str, str]) -> pa.Table:
    """Return the CSV parsed with explicit types, or raise BundleError naming the bad row."""
    types = {name: (pa.float64() if kinds.get(name, "float") == "float" else pa.string()) for name in header}
    try:
        return pacsv.read_csv(
            path,
            read_options=pacsv.ReadOptions(block_size=1 << 24),
            parse_options=pacsv.ParseOptions(newlines_in_values=False, ignore_empty_lines=False),
            convert_options=pacsv.ConvertOptions(
                column_types=types,
                null_values=[""],
                strings_can_be_null=True,
                quoted_strings_can_be_null=True,
                include_columns=header,
            ),
        )
    except (pa.ArrowInvalid, UnicodeDecodeError) as exc:
        problem = _scan_for_problem(path, file, header, kinds)
        if problem is not None:
            raise problem from None
        raise _fail(file, None, f"cannot parse: {' '.join(str(exc).split())}") from None


def _first(mask: np.ndarray) -> int | None:
    """Return the CSV line number of the first True in a per-row mask (header is line 1)."""
    idx = np.flatnonzero(mask)
    return int(idx[0]) + 2 if idx.size else None


def _check_empty_lines(table: pa.Table, file: str) -> None:
    """Reject empty lines (pyarrow reads them as rows whose every cell is null)."""
    mask = None
    for col in table.columns:
        nulls = col.is_null().to_numpy(zero_copy_only=False)
        mask = nulls if mask is None else mask & nulls
    if mask is not None:
        row = _first(mask)
        if row is not None:
            raise _fail(file, row, "empty line")


def _check_time(file: str, t: np.ndarray, strict: bool) -> None:
    """Check time_s: present, finite, non-negative, in (strictly, for scans) increasing order."""
    row = _first(np.isnan(t))
    if row is not None:
        raise _fail(file, row, "time_s is missing")
    row = _first(~np.isfinite(t))
    if row is not None:
        raise _fail(file, row, "time_s is not a finite number")
    row = _first(t < 0)
    if row is not None:
        raise _fail(file, row, f"time_s {float(t[row - 2])!r} is negative (seconds since started_at)")
    if t.size > 1:
        d = np.diff(t)
        bad = d <= 0 if strict else d < 0
        idx = np.flatnonzero(bad)
        if idx.size:
            k = int(idx[0]) + 1
            what = "not after" if strict else "before"
            raise _fail(file, k + 2, f"time_s {float(t[k])!r} is {what} the previous row's {float(t[k - 1])!r}: rows must be in time order")


def _load_temperatures(path: Path, meta: CampaignMeta) -> pd.DataFrame:
    file = path.name
    header = _read_header(path, file)
    for name in header[1:]:
        if name not in meta.channels:
            raise _fail(file, 1, f"column {name!r} is not a channel of campaign.json")
    missing = [c for c in meta.channels if c not in header]
    if missing:
        raise _fail(file, 1, f"channel {missing[0]!r} of campaign.json has no column")
    table = _read_table(path, file, header, {})
    if table.num_rows == 0:
        raise _fail(file, 2, "no readings (the file has only a header)")
    _check_empty_lines(table, file)
    frame = table.to_pandas()
    t = frame["time_s"].to_numpy()
    _check_time(file, t, strict=True)
    lo, hi = TEMP_RANGE_DEGC
    for name in header[1:]:
        v = frame[name].to_numpy(dtype="f8")
        _check_finite_nan_is_missing(table, file, name)
        with np.errstate(invalid="ignore"):
            row = _first((v < lo) | (v > hi))
        if row is not None:
            raise _fail(
                file, row, f"column {name}: {float(v[row - 2])!r} degC is outside {lo}..{hi}: temperatures must be in degC"
            )
    return frame


def _check_finite_nan_is_missing(table: pa.Table, file: str, name: str) -> None:
    """Reject NaN/inf written in a cell (an empty cell, a null, is the only way to say missing)."""
    col = table.column(name)
    v = col.to_numpy(zero_copy_only=False)
    nulls = col.is_null().to_numpy(zero_copy_only=False)
    bad = ~np.isfinite(v) & ~nulls
    row = _first(bad)
    if row is not None:
        raise _fail(file, row, f"column {name}: {float(v[row - 2])!r} is not a finite number (leave the cell empty if missing)")


def _load_conditions(path: Path) -> pd.DataFrame:
    file = path.name
    header = _read_header(path, file)
    for name in header[1:]:
        if name not in CONDITION_COLUMNS:
            raise _fail(file, 1, f"unknown column {name!r}: expected some of {','.join(CONDITION_COLUMNS)}")
    table = _read_table(path, file, header, {})
    _check_empty_lines(table, file)
    frame = table.to_pandas()
    _check_time(file, frame["time_s"].to_numpy(), strict=True)
    for name in header[1:]:
        _check_finite_nan_is_missing(table, file, name)
        v = frame[name].to_numpy(dtype="f8")
        if name in ("spindle_rpm", "feed_mm_min"):
            with np.errstate(invalid="ignore"):
                row = _first(v < 0)
            if row is not None:
                raise _fail(file, row, f"column {name}: {float(v[row - 2])!r} is negative")
        if name in ("a", "b"):
            with np.errstate(invalid="ignore"):
                row = _first(np.abs(v) > MAX_ROTARY_POSITION_DEG)
            if row is not None:
                raise _fail(file, row, f"column {name}: {float(v[row - 2])!r} is not a rotary position in degrees")
    return frame


def _load_errors(path: Path, meta: CampaignMeta | None = None) -> pd.DataFrame:
    file = path.name
    header = _read_header(path, file)
    v2 = meta is not None and meta.v2
    columns = ERROR_COLUMNS_V2 if v2 else ERROR_COLUMNS
    for name in header:
        if name not in columns:
            raise _fail(file, 1, f"unknown column {name!r}: expected {','.join(columns)}")
    for name in columns:
        if name not in header:
            raise _fail(file, 1, f"missing column {name!r}: expected {','.join(columns)}")
    kinds = {"axis": "str", "term": "str", "direction": "str", **({"setup": "str"} if v2 else {})}
    table = _read_table(path, file, header, kinds)
    if table.num_rows == 0:
        raise _fail(file, 2, "no error samples (the file has only a header)")
    _check_empty_lines(table, file)
    t = table.column("time_s").to_numpy(zero_copy_only=False)
    _check_time(file, t, strict=False)
    axis = np.asarray(table.column("axis").to_pylist(), dtype=object)
    term = np.asarray(table.column("term").to_pylist(), dtype=object)
    direction_text = np.asarray(table.column("direction").to_pylist(), dtype=object)
    for name, values, vocab in (("axis", axis, AXES), ("term", term, TERMS)):
        row = _first(~np.isin(values, np.asarray(vocab, dtype=object)))
        if row is not None:
            cell = values[row - 2]
            what = "missing" if cell is None else f"{cell!r} is not one of {' '.join(vocab)}"
            raise _fail(file, row, f"column {name}: {what}")
    ok = np.isin(direction_text, np.asarray(list(_DIRECTIONS), dtype=object))
    row = _first(~ok)
    if row is not None:
        cell = direction_text[row - 2]
        what = "missing" if cell is None else f"{cell!r} is not +1 or -1"
        raise _fail(file, row, f"column direction: {what}")
    direction = np.fromiter((_DIRECTIONS[d] for d in direction_text), dtype=np.int64, count=len(direction_text))
    position = table.column("position").to_numpy(zero_copy_only=False)
    value = table.column("value").to_numpy(zero_copy_only=False)
    for name, v in (("position", position), ("value", value)):
        nulls = table.column(name).is_null().to_numpy(zero_copy_only=False)
        row = _first(nulls)
        if row is not None:
            raise _fail(file, row, f"column {name}: missing value")
        row = _first(~np.isfinite(v))
        if row is not None:
            raise _fail(file, row, f"column {name}: {float(v[row - 2])!r} is not a finite number")
    is_rot_axis = np.isin(axis, np.asarray(ROTARY_AXES, dtype=object))
    row = _first(is_rot_axis & (np.abs(position) > MAX_ROTARY_POSITION_DEG))
    if row is not None:
        raise _fail(file, row, f"column position: {float(position[row - 2])!r} is not a rotary position in degrees")
    is_trans = np.isin(term, np.asarray(TRANSLATION_TERMS, dtype=object))
    row = _first(is_trans & (np.abs(value) > MAX_TRANSLATION_MM))
    if row is not None:
        raise _fail(
            file, row, f"column value: {float(value[row - 2])!r} mm is implausibly large for a translation: values must be in mm"
        )
    row = _first(~is_trans & (np.abs(value) > MAX_ROTATION_RAD))
    if row is not None:
        raise _fail(
            file, row, f"column value: {float(value[row - 2])!r} rad is implausibly large for a rotation: values must be in rad"
        )
    frame = pd.DataFrame(
        {
            "time_s": t,
            "axis": pd.array(axis.tolist(), dtype="str"),
            "term": pd.array(term.tolist(), dtype="str"),
            "position": position,
            "direction": direction,
            "value": value,
        }
    )
    if v2:
        assert meta is not None
        _load_pose_and_setup(file, table, frame, axis, term, meta)
    dup = frame.duplicated(subset=["time_s", "axis", "term", "position", "direction"]).to_numpy()
    row = _first(dup)
    if row is not None:
        raise _fail(file, row, "duplicate reading: same time_s, axis, term, position and direction as an earlier row")
    return frame


def _load_pose_and_setup(file: str, table: pa.Table, frame: pd.DataFrame, axis: np.ndarray, term: np.ndarray,
                         meta: CampaignMeta) -> None:
    """Add and check v2's pose and setup columns: finite pose, position = the moved axis' pose, known setup."""
    for name in POSE_COLUMNS:
        v = table.column(name).to_numpy(zero_copy_only=False)
        row = _first(table.column(name).is_null().to_numpy(zero_copy_only=False))
        if row is not None:
            raise _fail(file, row, f"column {name}: missing value (a bundle v2 gives the full pose)")
        row = _first(~np.isfinite(v))
        if row is not None:
            raise _fail(file, row, f"column {name}: {float(v[row - 2])!r} is not a finite number")
        frame[name] = v
    pose = frame[list(POSE_COLUMNS)].to_numpy(float)
    moved = pose[np.arange(len(frame)), [AXES.index(a) for a in axis]]
    pos = frame["position"].to_numpy(float)
    row = _first(np.abs(moved - pos) > 1e-9 * np.maximum(1.0, np.abs(pos)))
    if row is not None:
        ax = axis[row - 2]
        raise _fail(file, row, f"column {ax.lower()}: {moved[row - 2]!r} differs from position {pos[row - 2]!r} "
                               f"of the moved axis {ax}")
    setup = np.asarray(table.column("setup").to_pylist(), dtype=object)
    setups = meta.setups or {}
    for r, (sid, ax, tm) in enumerate(zip(setup, axis, term), start=2):
        entry = setups.get(sid) if sid is not None else None
        if entry is None:
            what = "missing" if sid is None else f"{sid!r} is not among campaign.json setups"
            raise _fail(file, r, f"column setup: {what}")
        if f"{ax}/{tm}" not in entry.terms:
            raise _fail(file, r, f"column setup: setup {sid!r} does not deliver {ax}/{tm} "
                                 f"(it delivers {', '.join(entry.terms)})")
    frame["setup"] = pd.array(setup.tolist(), dtype="str")


def load_bundle(path: str | Path) -> Bundle:
    """Return the validated bundle in directory ``path``; raise BundleError (``FILE:ROW: problem``)."""
    root = Path(path)
    if not root.is_dir():
        raise BundleError(f"{root}: not a bundle directory")
    meta_path = root / CAMPAIGN_FILE
    for required in (CAMPAIGN_FILE, TEMPERATURES_FILE, ERRORS_FILE):
        if not (root / required).is_file():
            raise BundleError(f"{required}: file missing from bundle {root}")
    try:
        text = meta_path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise BundleError(f"{CAMPAIGN_FILE}:1: not UTF-8 text") from None
    meta = parse_meta(text)
    temperatures = _load_temperatures(root / TEMPERATURES_FILE, meta)
    cond_path = root / CONDITIONS_FILE
    conditions = _load_conditions(cond_path) if cond_path.is_file() else None
    errors = _load_errors(root / ERRORS_FILE, meta)
    return Bundle(name=root.resolve().name, meta=meta, temperatures=temperatures, conditions=conditions, errors=errors)


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

