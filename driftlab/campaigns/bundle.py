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
import math
import os
import re
import stat
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, Protocol, TypedDict, TypeVar, cast

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, field_validator
from pydantic import ValidationError as PydanticValidationError

from driftlab.errors import ValidationError
from driftlab.physics.geometry import Geometry
from driftlab.vocabulary import AXES, CHANNEL_NAME, TERMS, Axis, valid_channel_name
from driftlab.vocabulary import TRANSLATIONS as TRANSLATION_TERMS

FORMAT = "driftlab-bundle/1"
FORMAT_V2 = "driftlab-bundle/2"
FORMATS = (FORMAT, FORMAT_V2)
ROTARY_AXES = ("A", "B")
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

# Limits of what a bundle may hold (docs/bundle.md, "Limits"): each keeps memory and time bounded
# or keeps a value inside what the store, pandas and the API can represent.
MAX_JSON_BYTES = 1 << 20  # campaign.json: metadata, never bulk data
MAX_JSON_DEPTH = 32  # the deepest valid document nests 5 levels (setups.*.reference.*)
MAX_JSON_NUMBER_CHARS = 40  # longer literals carry no more binary64 precision (and >4300 digits crash int())
MAX_CSV_BYTES = 512 << 20  # per CSV file (read a chunk at a time: staging.stage_bundle)
MAX_LINE_BYTES = 1 << 20  # per CSV line (the scanner reads a line at a time)
CSV_BLOCK_BYTES = 1 << 20  # CSV text read and parsed at a time, in whole lines (a chunk's working set)
MAX_FIELD_CHARS = 256  # per CSV cell: numbers, axis/term/direction/setup names
MAX_NAME_CHARS = 64  # machine id, channel names, setup ids (API path segments), stage names
MAX_TEXT_CHARS = 200  # free text of campaign.json: machine name, channel location and structure
MAX_TIME_S = 1e9  # time_s and stage times: about 31.7 years after started_at
STARTED_AT_RANGE = (datetime(1970, 1, 1, tzinfo=UTC), datetime(2200, 1, 1, tzinfo=UTC))
MAX_LINEAR_POSITION_MM = 1e5  # 100 m: positions and poses of X Y Z (a larger one is a units mistake)

_DIRECTIONS = {"1": 1, "+1": 1, "1.0": 1, "+1.0": 1, "-1": -1, "-1.0": -1}
# ASCII digits only: Python's \d and float() accept full-width and other Unicode digits, pyarrow does not
_NUMBER = re.compile(r"^[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?$")
_NONFINITE = re.compile(r"^[+-]?(nan|inf|infinity)$", re.IGNORECASE)
#: machine ids, channel names and setup ids: what the API accepts as a path segment (api.schemas.ID_PATTERN)
ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,63}$"
_CONTROL = re.compile(r"[\x00-\x1f\x7f\ud800-\udfff]")


_T = TypeVar("_T")


class BundleError(ValidationError):
    """A bundle that does not meet the v1 contract; the message is ``FILE:ROW: problem``."""


# ----------------------------------------------------------------------------- campaign.json


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Machine(_Strict):
    """The machine a campaign was measured on."""

    id: str = Field(min_length=1, max_length=64, pattern=ID_PATTERN)
    name: str = Field(default="", max_length=MAX_TEXT_CHARS)
    resolution_mm: StrictFloat | None = Field(default=None, gt=0, allow_inf_nan=False)
    resolution_deg: StrictFloat | None = Field(default=None, gt=0, allow_inf_nan=False)
    #: optional stated dimensions (table 6.3's physical check); absent = "no geometry"
    geometry: Geometry | None = None
    #: optional travel (soft limits) per axis, (low, high): mm for X Y Z, degrees for A B; a model fitted
    #: on the campaign carries it into its envelope (``models.envelope``, docs/compensate.md)
    travel: dict[Axis, tuple[StrictFloat, StrictFloat]] | None = None

    @field_validator("travel")
    @classmethod
    def _travel(cls, value: dict[str, tuple[float, float]] | None) -> dict[str, tuple[float, float]] | None:
        """Require finite limits, low below high."""
        for axis, (lo, hi) in (value or {}).items():
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"travel of {axis} must be two finite numbers, low < high (got {lo}, {hi})")
        return value


class Channel(_Strict):
    """A thermocouple site: where it is and which structure it sits on."""

    location: str = Field(default="", max_length=MAX_TEXT_CHARS)
    structure: str = Field(default="", max_length=MAX_TEXT_CHARS)


class Stage(_Strict):
    """One stage of the staged single-heat-source plan, as it was run."""

    name: str = Field(min_length=1, max_length=MAX_NAME_CHARS)
    start_s: StrictFloat = Field(ge=0, le=MAX_TIME_S, allow_inf_nan=False)
    end_s: StrictFloat = Field(ge=0, le=MAX_TIME_S, allow_inf_nan=False)
    heat_source: str = Field(min_length=1, max_length=MAX_NAME_CHARS)
    axis: Axis | None = None
    spindle_rpm: StrictFloat = Field(default=0.0, ge=0, allow_inf_nan=False)
    feed_mm_min: StrictFloat = Field(default=0.0, ge=0, allow_inf_nan=False)


class Noise(_Strict):
    """Stated repeatability of the error measurement."""

    length_mm: StrictFloat | None = Field(default=None, ge=0, allow_inf_nan=False)
    angle_rad: StrictFloat | None = Field(default=None, ge=0, allow_inf_nan=False)


class SetupEntry(_Strict):
    """Bundle v2: one instrument setup (what was mounted, the terms it delivers, how it was referenced)."""

    instrument: Literal["laser", "proximity", "probe", "level", "other"]
    optics: str | None = Field(default=None, min_length=1, max_length=64)
    fixture: str | None = Field(default=None, min_length=1, max_length=64)
    axis: Axis | None = None
    terms: list[str] = Field(min_length=1)
    datum: Literal["session", "absolute"] = "session"
    counter_rotating: StrictBool = False
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


class CampaignJson(TypedDict, total=False):
    """campaign.json as plain JSON (:meth:`CampaignMeta.document`; docs/bundle.md): absent optional parts left out."""

    format: str  # always there
    machine: dict[str, object]
    started_at: str  # ISO 8601 with its zone
    channels: dict[str, dict[str, object]]
    room_channels: list[str]
    model_channels: dict[str, list[str]]
    stages: list[dict[str, object]]
    noise: dict[str, float]
    setups: dict[str, dict[str, object]]


class CampaignMeta(_Strict):
    """campaign.json of bundle v1 or v2: machine, channel map, room/model channels, stages, noise (v2: setups)."""

    format: Literal["driftlab-bundle/1", "driftlab-bundle/2"]
    machine: Machine
    started_at: datetime
    channels: dict[str, Channel] = Field(min_length=1)
    room_channels: list[str] = Field(default_factory=list)
    model_channels: dict[Axis, list[str]] | None = None
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
        lo, hi = STARTED_AT_RANGE
        if not lo <= value < hi:
            raise ValueError(f"started_at {value.isoformat()} is outside {lo.year}..{hi.year - 1}")
        return value

    def document(self) -> CampaignJson:
        """Return campaign.json as a JSON-ready dict (absent optional fields left out)."""
        return cast("CampaignJson", self.model_dump(mode="json", exclude_none=True))


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


_JSON_TOKEN = re.compile(r'"(?:[^"\\\n]|\\.)*"|[\[\]{}]|-?Infinity|NaN|-?[0-9][0-9.eE+-]*|\n')


def _prescan_json(text: str, file: str) -> None:
    """Refuse, naming the line and column, what json.loads would crash on or silently accept.

    Nesting deeper than MAX_JSON_DEPTH (RecursionError), number literals longer than
    MAX_JSON_NUMBER_CHARS (int() refuses more than 4300 digits) and a key repeated in one object
    (json.loads keeps the last one silently). Malformed JSON is left to json.loads to describe.
    """
    line, line_start = 1, 0
    keys: list[set[str]] = []
    depth = 0
    for m in _JSON_TOKEN.finditer(text):
        tok, at = m.group(), m.start()
        if tok == "\n":
            line, line_start = line + 1, at + 1
            continue
        where = f"{file}:{line}: column {at - line_start + 1}"
        if tok in "[{":
            depth += 1
            if depth > MAX_JSON_DEPTH:
                raise BundleError(f"{where}: nesting deeper than {MAX_JSON_DEPTH} levels")
            keys.append(set())
        elif tok in "]}":
            depth = max(depth - 1, 0)
            if keys:
                keys.pop()
        elif tok[0] == '"':
            rest = text[m.end() : m.end() + 64].lstrip(" \t\r\n")
            if rest.startswith(":") and keys:
                try:
                    key = json.loads(tok)
                except ValueError:
                    continue  # json.loads reports it
                if key in keys[-1]:
                    raise BundleError(f"{where}: key {_short(key)} appears twice in one object")
                keys[-1].add(key)
        elif tok[-1] in "yN":
            raise BundleError(f"{where}: {tok} is not a finite number (numbers must be finite)")
        elif len(tok) > MAX_JSON_NUMBER_CHARS:
            raise BundleError(f"{where}: number of {len(tok)} characters (at most {MAX_JSON_NUMBER_CHARS})")


def _short(value: object, limit: int = 40) -> str:
    """Return repr(value) cut to ``limit`` characters (messages stay one readable line)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _check_strings(raw: Any, file: str, lines: Mapping[tuple[Any, ...], int], path: tuple[Any, ...] = ()) -> None:
    """Refuse control characters and lone surrogates in any key or string (the store cannot keep them)."""
    if isinstance(raw, dict):
        for key, value in raw.items():
            if _CONTROL.search(key):
                raise _json_fail(file, lines, path + (key,), "control character or lone surrogate in a key")
            _check_strings(value, file, lines, path + (key,))
    elif isinstance(raw, list):
        for k, value in enumerate(raw):
            _check_strings(value, file, lines, path + (k,))
    elif isinstance(raw, str) and _CONTROL.search(raw):
        raise _json_fail(file, lines, path, "control character or lone surrogate in a string")


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a finite number")


def parse_meta(text: str, file: str = CAMPAIGN_FILE) -> CampaignMeta:
    """Return the validated CampaignMeta of a campaign.json text; raise BundleError naming the line."""
    if len(text) > MAX_JSON_BYTES:
        raise BundleError(f"{file}: {len(text)} characters, more than the limit of {MAX_JSON_BYTES}")
    _prescan_json(text, file)
    try:
        raw = json.loads(text, parse_constant=_no_constant)
    except json.JSONDecodeError as exc:
        raise BundleError(f"{file}:{exc.lineno}: invalid JSON: {exc.msg} (column {exc.colno})") from None
    except (ValueError, RecursionError) as exc:  # NaN/Infinity literals; anything the prescan let through
        raise BundleError(f"{file}: invalid JSON: {' '.join(str(exc).split())[:200]}") from None
    lines = _locate_json(text)
    _check_strings(raw, file, lines)
    return _validate_meta(raw, file, lines)


def _validate_meta(raw: Any, file: str, lines: Mapping[tuple[Any, ...], int]) -> CampaignMeta:
    """Validate a decoded campaign.json document, including references between its parts."""
    if isinstance(raw, dict) and "format" in raw and raw["format"] not in FORMATS:
        raise _json_fail(
            file,
            lines,
            ("format",),
            f"unsupported format {_short(raw['format'])}, expected {FORMAT!r} or {FORMAT_V2!r}",
        )
    try:
        meta = CampaignMeta.model_validate(raw)
    except PydanticValidationError as exc:
        err = exc.errors()[0]
        raise _json_fail(file, lines, tuple(err["loc"]), err["msg"]) from None
    for name in meta.channels:
        if not valid_channel_name(name):
            raise _json_fail(
                file,
                lines,
                ("channels", name),
                "channel names start with a letter or digit, then hold only "
                f"letters, digits, '_', '.', '-' (at most {MAX_NAME_CHARS}), and may not be time_s",
            )
    _check_listed(meta.room_channels, meta.channels, file, lines, ("room_channels",), "room channel")
    for axis, names in (meta.model_channels or {}).items():
        _check_listed(names, meta.channels, file, lines, ("model_channels", axis), "model channel")
    _check_setups(meta, file, lines)
    _check_stages(meta, file, lines)
    return meta


def _check_listed(
    names: Sequence[str],
    channels: Mapping[str, Any],
    file: str,
    lines: Mapping[tuple[Any, ...], int],
    at: tuple[Any, ...],
    what: str,
) -> None:
    """Refuse a list of channel names (at ``at`` in the document) naming one not in channels, or one twice."""
    seen: set[str] = set()
    for k, name in enumerate(names):
        if name not in channels:
            raise _json_fail(file, lines, (*at, k), f"{what} {_short(name)} is not in channels")
        if name in seen:
            raise _json_fail(file, lines, (*at, k), f"{what} {_short(name)} listed twice")
        seen.add(name)


def _check_setups(meta: CampaignMeta, file: str, lines: Mapping[tuple[Any, ...], int]) -> None:
    """Refuse setups outside a bundle v2, a v2 without them, a bad setup id, or terms of another axis."""
    if meta.setups is not None and not meta.v2:
        raise _json_fail(file, lines, ("setups",), f"setups belong to {FORMAT_V2!r} bundles")
    if meta.v2 and not meta.setups:
        raise _json_fail(
            file,
            lines,
            ("setups",) if meta.setups is not None else ("format",),
            "a bundle v2 needs setups: the instrument setup of every error reading",
        )
    for sid, entry in (meta.setups or {}).items():
        if not CHANNEL_NAME.match(sid):
            raise _json_fail(
                file, lines, ("setups", sid), "setup ids may hold only letters, digits, '_', '.', '-' (at most 64)"
            )
        if entry.axis is not None and any(not c.startswith(entry.axis + "/") for c in entry.terms):
            raise _json_fail(
                file,
                lines,
                ("setups", sid, "terms"),
                f"setup {_short(sid)} measures the {entry.axis} axis but lists terms of another",
            )


def _check_stages(meta: CampaignMeta, file: str, lines: Mapping[tuple[Any, ...], int]) -> None:
    """Refuse a stage that ends before it starts, overlaps the previous one, or repeats a name."""
    names_seen: set[str] = set()
    previous_end = -math.inf
    for k, stage in enumerate(meta.stages):
        if stage.end_s < stage.start_s:
            raise _json_fail(
                file,
                lines,
                ("stages", k, "end_s"),
                f"stage {_short(stage.name)} ends ({stage.end_s}) before it starts ({stage.start_s})",
            )
        if stage.start_s < previous_end:
            raise _json_fail(
                file,
                lines,
                ("stages", k, "start_s"),
                f"stage {_short(stage.name)} starts at {stage.start_s}, before the "
                f"previous stage ends ({previous_end}): stages must be in order and not overlap",
            )
        if stage.name in names_seen:
            raise _json_fail(file, lines, ("stages", k, "name"), f"stage name {_short(stage.name)} used twice")
        names_seen.add(stage.name)
        previous_end = stage.end_s


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


def _read_header(path: Path, file: str) -> list[str]:
    """Return the header fields of a CSV file, checked for emptiness, length and duplicates."""
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
            raise _fail(file, 1, f"duplicate column {_short(name)}")
        seen.add(name)
    if header[0] != "time_s":
        raise _fail(file, 1, f"first column must be time_s, found {_short(header[0])}")
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
                    if _NONFINITE.match(cell.strip()):
                        return _fail(file, lineno, f"column {name}: {_short(cell)} is not a finite number")
                    if not _NUMBER.match(cell):
                        return _fail(file, lineno, f"column {name}: {_short(cell)} is not a number")
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
            raise _fail(file, 1, f"column {_short(name)} is not a channel of campaign.json")
    missing = [c for c in meta.channels if c not in header]
    if missing:
        raise _fail(file, 1, f"channel {_short(missing[0])} of campaign.json has no column")
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
            raise _fail(file, 1, f"unknown column {_short(name)}: expected some of {','.join(CONDITION_COLUMNS)}")
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
    """Return errors.csv's header: exactly the v1 (or, for a v2 bundle, v2) columns."""
    file = path.name
    header = _read_header(path, file)
    columns = ERROR_COLUMNS_V2 if meta is not None and meta.v2 else ERROR_COLUMNS
    for name in header:
        if name not in columns:
            raise _fail(file, 1, f"unknown column {_short(name)}: expected {','.join(columns)}")
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
            what = "missing" if cell is None else f"{_short(cell)} is not one of {' '.join(vocab)}"
            raise place.fail(k, f"column {name}: {what}")
    k = place.first(~np.isin(direction_text, np.asarray(list(_DIRECTIONS), dtype=object)))
    if k is not None:
        cell = direction_text[k]
        what = "missing" if cell is None else f"{_short(cell)} is not +1 or -1"
        raise place.fail(k, f"column direction: {what}")
    direction = np.fromiter((_DIRECTIONS[d] for d in direction_text), dtype=np.int64, count=len(direction_text))
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
            what = "missing" if sid is None else f"{_short(sid)} is not among campaign.json setups"
            raise place.fail(k, f"column setup: {what}")
        if f"{ax}/{tm}" not in entry.terms:
            raise place.fail(
                k,
                f"column setup: setup {_short(sid)} does not deliver {ax}/{tm} (it delivers {', '.join(entry.terms)})",
            )
    frame["setup"] = pd.array(setup.tolist(), dtype="str")


def _readable(chunks: Iterator[_T], file: str) -> Iterator[_T]:
    """Yield from ``chunks``, turning a read failing half-way (EIO, a file removed under us) into a BundleError."""
    try:
        yield from chunks
    except OSError as exc:
        where = Path(exc.filename).name if exc.filename else file
        raise BundleError(f"{where}: cannot read: {exc.strerror or exc}") from None


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

    @property
    def name(self) -> str:
        """Return the bundle's name (its directory's)."""
        return self.root.resolve().name

    def temperatures(self) -> Iterator[pd.DataFrame]:
        """Yield temperatures.csv: ``time_s`` and one column per channel, in the file's column order."""
        return _readable(_temperature_chunks(self.temperatures_path, self.meta, self.block_bytes), TEMPERATURES_FILE)

    def conditions(self) -> Iterator[pd.DataFrame]:
        """Yield conditions.csv (nothing when the bundle has none)."""
        if self.conditions_path is None:
            return iter(())
        return _readable(_condition_chunks(self.conditions_path, self.block_bytes), CONDITIONS_FILE)

    def errors(self) -> Iterator[pd.DataFrame]:
        """Yield errors.csv with ``direction`` as +1/-1 (and, for v2, the pose and setup columns)."""
        return _readable(_error_chunks(self.errors_path, self.meta, self.block_bytes), ERRORS_FILE)


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
    return BundleFiles(root, parse_meta(text), temp_path, cond_path, err_path, block_bytes)


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
