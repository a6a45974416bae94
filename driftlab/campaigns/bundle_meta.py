"""campaign.json of a bundle (v1, v2): its model, its parser naming the line of a problem, and the bundle's limits.

The limits (docs/bundle.md, "Limits") and file names are shared with the CSV files' reader
(``campaigns.bundle``), which re-exports what callers use (``CampaignMeta``, ``BundleError``).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from typing import Any, Literal, TypedDict, cast

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, field_validator
from pydantic import ValidationError as PydanticValidationError

from driftlab.errors import ValidationError
from driftlab.physics.geometry import Geometry
from driftlab.vocabulary import AXES, CHANNEL_NAME, TERMS, Axis, valid_channel_name

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

DIRECTIONS = {"1": 1, "+1": 1, "1.0": 1, "+1.0": 1, "-1": -1, "-1.0": -1}
# ASCII digits only: Python's \d and float() accept full-width and other Unicode digits, pyarrow does not
NUMBER_TEXT = re.compile(r"^[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?$")
NONFINITE_TEXT = re.compile(r"^[+-]?(nan|inf|infinity)$", re.IGNORECASE)
#: machine ids, channel names and setup ids: what the API accepts as a path segment (api.schemas.ID_PATTERN)
ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,63}$"
_CONTROL = re.compile(r"[\x00-\x1f\x7f\ud800-\udfff]")
#: started_at as campaign.json gives it: ISO 8601 date and time (seconds and fraction optional) and a zone
_ISO_DATETIME = re.compile(
    r"[0-9]{4}-[0-9]{2}-[0-9]{2}T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\.[0-9]{1,9})?)?(Z|[+-][0-9]{2}:?[0-9]{2})?"
)


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

    @field_validator("started_at", mode="before")
    @classmethod
    def _iso_text(cls, value: object) -> object:
        """Require ISO 8601 text with its zone (pydantic would read a number, or digits, as a Unix time)."""
        if isinstance(value, datetime):
            return value  # built in Python (the daemon, write_bundle): checked for its zone below
        if not isinstance(value, str) or not _ISO_DATETIME.fullmatch(value):
            raise ValueError(
                f"must be an ISO 8601 date and time with its zone, e.g. 2026-03-02T08:00:00Z, not {short(value)}"
            )
        return value

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


def json_fail(file: str, lines: Mapping[tuple[Any, ...], int], path: tuple[Any, ...], problem: str) -> BundleError:
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
                    raise BundleError(f"{where}: key {short(key)} appears twice in one object")
                keys[-1].add(key)
        elif tok[-1] in "yN":
            raise BundleError(f"{where}: {tok} is not a finite number (numbers must be finite)")
        elif len(tok) > MAX_JSON_NUMBER_CHARS:
            raise BundleError(f"{where}: number of {len(tok)} characters (at most {MAX_JSON_NUMBER_CHARS})")


def short(value: object, limit: int = 40) -> str:
    """Return repr(value) cut to ``limit`` characters (messages stay one readable line)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _check_strings(raw: Any, file: str, lines: Mapping[tuple[Any, ...], int], path: tuple[Any, ...] = ()) -> None:
    """Refuse control characters and lone surrogates in any key or string (the store cannot keep them)."""
    if isinstance(raw, dict):
        for key, value in raw.items():
            if _CONTROL.search(key):
                raise json_fail(file, lines, path + (key,), "control character or lone surrogate in a key")
            _check_strings(value, file, lines, path + (key,))
    elif isinstance(raw, list):
        for k, value in enumerate(raw):
            _check_strings(value, file, lines, path + (k,))
    elif isinstance(raw, str) and _CONTROL.search(raw):
        raise json_fail(file, lines, path, "control character or lone surrogate in a string")


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


def parse_meta_located(text: str, file: str = CAMPAIGN_FILE) -> tuple[CampaignMeta, dict[tuple[Any, ...], int]]:
    """Return ``parse_meta(text)`` and the line of each of its values (for problems found later, against the data)."""
    return parse_meta(text, file), _locate_json(text)


def _validate_meta(raw: Any, file: str, lines: Mapping[tuple[Any, ...], int]) -> CampaignMeta:
    """Validate a decoded campaign.json document, including references between its parts."""
    if isinstance(raw, dict) and "format" in raw and raw["format"] not in FORMATS:
        raise json_fail(
            file,
            lines,
            ("format",),
            f"unsupported format {short(raw['format'])}, expected {FORMAT!r} or {FORMAT_V2!r}",
        )
    try:
        meta = CampaignMeta.model_validate(raw)
    except PydanticValidationError as exc:
        err = exc.errors()[0]
        raise json_fail(file, lines, tuple(err["loc"]), err["msg"]) from None
    for name in meta.channels:
        if not valid_channel_name(name):
            raise json_fail(
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
            raise json_fail(file, lines, (*at, k), f"{what} {short(name)} is not in channels")
        if name in seen:
            raise json_fail(file, lines, (*at, k), f"{what} {short(name)} listed twice")
        seen.add(name)


def _check_setups(meta: CampaignMeta, file: str, lines: Mapping[tuple[Any, ...], int]) -> None:
    """Refuse setups outside a bundle v2, a v2 without them, a bad setup id, or terms of another axis."""
    if meta.setups is not None and not meta.v2:
        raise json_fail(file, lines, ("setups",), f"setups belong to {FORMAT_V2!r} bundles")
    if meta.v2 and not meta.setups:
        raise json_fail(
            file,
            lines,
            ("setups",) if meta.setups is not None else ("format",),
            "a bundle v2 needs setups: the instrument setup of every error reading",
        )
    for sid, entry in (meta.setups or {}).items():
        if not CHANNEL_NAME.match(sid):
            raise json_fail(
                file, lines, ("setups", sid), "setup ids may hold only letters, digits, '_', '.', '-' (at most 64)"
            )
        if entry.axis is not None and any(not c.startswith(entry.axis + "/") for c in entry.terms):
            raise json_fail(
                file,
                lines,
                ("setups", sid, "terms"),
                f"setup {short(sid)} measures the {entry.axis} axis but lists terms of another",
            )


def _check_stages(meta: CampaignMeta, file: str, lines: Mapping[tuple[Any, ...], int]) -> None:
    """Refuse a stage that ends before it starts, overlaps the previous one, or repeats a name."""
    names_seen: set[str] = set()
    previous_end = -math.inf
    for k, stage in enumerate(meta.stages):
        if stage.end_s < stage.start_s:
            raise json_fail(
                file,
                lines,
                ("stages", k, "end_s"),
                f"stage {short(stage.name)} ends ({stage.end_s}) before it starts ({stage.start_s})",
            )
        if stage.start_s < previous_end:
            raise json_fail(
                file,
                lines,
                ("stages", k, "start_s"),
                f"stage {short(stage.name)} starts at {stage.start_s}, before the "
                f"previous stage ends ({previous_end}): stages must be in order and not overlap",
            )
        if stage.name in names_seen:
            raise json_fail(file, lines, ("stages", k, "name"), f"stage name {short(stage.name)} used twice")
        names_seen.add(stage.name)
        previous_end = stage.end_s
