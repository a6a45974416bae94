"""Shared parts of the importers: units, directions, and writing readings as a validated bundle."""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from driftlab.campaigns.bundle import (
    ERROR_COLUMNS,
    ERROR_COLUMNS_V2,
    POSE_COLUMNS,
    BundleError,
    load_bundle,
    write_bundle,
)
from driftlab.errors import ValidationError
from driftlab.vocabulary import AXES, ROTATIONS

#: the positioning term of each axis (its own translation or rotation)
POSITIONING_TERM = {"X": "dx", "Y": "dy", "Z": "dz", "A": "alpha", "B": "beta"}
#: factor to the bundle's units (mm for translations and linear positions, rad for rotations, deg for rotary positions)
LENGTH_UNITS = {"mm": 1.0, "um": 1e-3, "µm": 1e-3, "micron": 1e-3, "nm": 1e-6, "m": 1e3, "in": 25.4, "inch": 25.4}
ANGLE_UNITS = {
    "rad": 1.0,
    "mrad": 1e-3,
    "urad": 1e-6,
    "µrad": 1e-6,
    "arcsec": np.pi / 180.0 / 3600.0,
    "deg": np.pi / 180.0,
}
POSITION_UNITS = {**LENGTH_UNITS, "deg": 1.0}
DIRECTIONS = {
    "+": 1,
    "-": -1,
    "1": 1,
    "+1": 1,
    "-1": -1,
    "up": 1,
    "down": -1,
    "forward": 1,
    "backward": -1,
    "forwards": 1,
    "backwards": -1,
    "reverse": -1,
    "pos": 1,
    "neg": -1,
    "positive": 1,
    "negative": -1,
}


class InstrumentFileError(ValidationError):
    """An instrument file that cannot become a bundle; the message is ``FILE:ROW: problem`` where a row is involved."""


def value_factor(unit: str, term: str, where: str) -> float:
    """Return the factor from ``unit`` to the bundle unit of ``term`` (mm or rad)."""
    u = unit.strip().lower().replace("μ", "µ")
    table = ANGLE_UNITS if term in ROTATIONS else LENGTH_UNITS
    if u not in table:
        kind = "an angle" if term in ROTATIONS else "a length"
        raise InstrumentFileError(f"{where}: unit {unit!r} is not {kind} unit ({' '.join(table)})")
    return table[u]


def position_factor(unit: str, axis: str, where: str) -> float:
    """Return the factor from ``unit`` to the bundle unit of positions (mm, or deg for rotary axes)."""
    u = unit.strip().lower().replace("μ", "µ")
    if axis in ("A", "B"):
        if u != "deg":
            raise InstrumentFileError(f"{where}: positions of rotary axis {axis} must be in deg, not {unit!r}")
        return 1.0
    if u not in LENGTH_UNITS:
        raise InstrumentFileError(f"{where}: unit {unit!r} is not a length unit ({' '.join(LENGTH_UNITS)})")
    return LENGTH_UNITS[u]


def parse_direction(cell: Any) -> int | None:
    """Return +1/-1 for a direction cell, None when it is not one."""
    return DIRECTIONS.get(str(cell).strip().lower())


def parse_time(text: str, where: str) -> datetime:
    """Return an aware datetime from ISO 8601 or ``dd/mm/yyyy hh:mm[:ss]`` (UTC when no zone is given)."""
    t = text.strip()
    dt: datetime | None
    try:
        dt = datetime.fromisoformat(t.replace("Z", "+00:00"))
    except ValueError:
        dt = None
        for fmt in ("%d/%m/%Y %H:%M:%S", "%d/%m/%Y %H:%M", "%d/%m/%Y"):
            try:
                dt = datetime.strptime(t, fmt)
                break
            except ValueError:
                continue
        if dt is None:
            raise InstrumentFileError(f"{where}: date {text!r} is neither ISO 8601 nor dd/mm/yyyy hh:mm:ss") from None
    return dt if dt.tzinfo is not None else dt.replace(tzinfo=UTC)


DATE_ORDERS = {
    "dmy": ("%d/%m/%Y %H:%M:%S", "%d/%m/%Y %H:%M", "%d/%m/%Y"),
    "mdy": ("%m/%d/%Y %H:%M:%S", "%m/%d/%Y %H:%M", "%m/%d/%Y"),
    "ymd": ("%Y/%m/%d %H:%M:%S", "%Y/%m/%d %H:%M", "%Y/%m/%d"),
}
_SLASHED = re.compile(r"^\s*(\d{1,2})[/.-](\d{1,2})[/.-]\d{4}")


def parse_date(text: str, where: str, order: str | None = None) -> tuple[datetime, str | None]:
    """Return an aware datetime from ISO 8601 or a slashed date in ``order`` (dmy, mdy, ymd), and the assumption
    made when no order was given and the day and month could be swapped (day first), else None."""
    t = text.strip()
    try:
        dt = datetime.fromisoformat(t.replace("Z", "+00:00"))
        return (dt if dt.tzinfo is not None else dt.replace(tzinfo=UTC)), None
    except ValueError:
        pass
    if order is not None and order not in DATE_ORDERS:
        raise InstrumentFileError(f"{where}: date order {order!r} is not one of {', '.join(DATE_ORDERS)}")
    for fmt in DATE_ORDERS[order or "dmy"]:
        try:
            dt = datetime.strptime(t.replace(".", "/").replace("-", "/"), fmt)
            break
        except ValueError:
            continue
    else:
        raise InstrumentFileError(
            f"{where}: date {text!r} is neither ISO 8601 nor {(order or 'dmy')} with slashes (see --date-order)"
        )
    assumption = None
    m = _SLASHED.match(t)
    if order is None and m and int(m.group(1)) <= 12 and int(m.group(2)) <= 12 and m.group(1) != m.group(2):
        assumption = f"date {t!r} read day first ({dt:%d %B %Y}); it could be month first: give --date-order dmy or mdy"
    return dt.replace(tzinfo=UTC), assumption


@dataclass
class Readings:
    """What an importer extracted: error readings in bundle units, the source row of each, temperatures, metadata."""

    source: str
    errors: pd.DataFrame  # ERROR_COLUMNS
    source_rows: np.ndarray  # (n,) line of each reading in the source file (0 when there is none)
    machine: str = ""
    started_at: datetime | None = None
    temperatures: dict[str, float] = field(default_factory=dict)  # channel -> degC (one scan at time 0)
    temperature_frame: pd.DataFrame | None = None  # or a time series (time_s + channels)
    noise_mm: float | None = None
    #: the instrument's own record (header fields, unit, date order): kept as a bundle v2 setup's reference
    instrument: dict[str, Any] | None = None
    #: what the importer had to assume (said in the import summary)
    assumptions: list[str] = field(default_factory=list)


_ERRORS_ROW = re.compile(r"^errors\.csv:(\d+): (.*)$")
_SAFE = re.compile(r"[^A-Za-z0-9_.\-]+")


def channel_name(text: str) -> str:
    """Return a bundle-safe channel name for an instrument's sensor label."""
    name = _SAFE.sub("_", text.strip()).strip("_") or "sensor"
    return name if name != "time_s" else "time_s_"


def write_readings(
    readings: Readings,
    out: str | Path,
    *,
    machine: str | None = None,
    started_at: datetime | None = None,
    air_temp_degC: float | None = None,
) -> Path:
    """Write the readings as a bundle v1 at ``out`` (validated by the bundle loader first; nothing left on an error)."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InstrumentFileError(f"{out}: exists and is not an empty directory")
    src = readings.source
    errors = readings.errors
    if errors.empty:
        raise InstrumentFileError(f"{src}: no readings")
    machine_id = machine or readings.machine
    if not machine_id:
        raise InstrumentFileError(f"{src}: the file names no machine: give --machine ID")
    when = started_at or readings.started_at
    if when is None:
        raise InstrumentFileError(f"{src}: the file carries no date: give --started-at ISO_TIME")
    temps = _temperatures(readings, air_temp_degC)
    channels = [c for c in temps.columns if c != "time_s"]
    meta: dict[str, Any] = {
        "format": "driftlab-bundle/1",
        "machine": {"id": machine_id},
        "started_at": when.isoformat(),
        "channels": {c: {"location": f"{src} sensor {c}", "structure": "room"} for c in channels},
        "room_channels": channels,
    }
    if readings.noise_mm is not None:
        meta["noise"] = {"length_mm": readings.noise_mm}
    order = np.argsort(errors["time_s"].to_numpy(float), kind="stable")
    frame = errors.iloc[order].reset_index(drop=True)[list(ERROR_COLUMNS)]
    if readings.instrument is not None:
        frame = _as_v2(meta, frame, readings.instrument)
    _write_checked(out, src, readings.source_rows[order], meta, temps, frame)
    return out


def _temperatures(readings: Readings, air_temp_degC: float | None) -> pd.DataFrame:
    """Return the bundle's temperatures: the file's own, else one scan of its stated ones (and ``air_temp_degC``)."""
    if readings.temperature_frame is not None:
        return readings.temperature_frame
    values = dict(readings.temperatures)
    if air_temp_degC is not None:
        values["air"] = float(air_temp_degC)
    if not values:
        raise InstrumentFileError(
            f"{readings.source}: the file records no temperature: give --air-temp DEGC (the room during the test)"
        )
    return pd.DataFrame({"time_s": [0.0], **{k: [v] for k, v in values.items()}})


def _as_v2(meta: dict[str, Any], frame: pd.DataFrame, instrument: dict[str, Any]) -> pd.DataFrame:
    """Make ``meta`` a bundle v2's, with the instrument's record as its setup; return ``frame`` with pose and setup."""
    # bundle v2: the instrument's record travels in campaign.json as its setup's reference
    info = dict(instrument)
    kind = str(info.pop("instrument", "laser"))
    axes = sorted(set(frame["axis"]))
    meta["format"] = "driftlab-bundle/2"
    meta["setups"] = {
        "instrument": {
            "instrument": kind,
            "axis": axes[0] if len(axes) == 1 else None,
            "terms": sorted({f"{a}/{t}" for a, t in zip(frame["axis"], frame["term"])}),
            "reference": {k: v for k, v in info.items() if v not in (None, "")},
        }
    }
    for name in POSE_COLUMNS:
        frame[name] = np.where(frame["axis"] == name.upper(), frame["position"], 0.0)
    frame["setup"] = "instrument"
    return frame[list(ERROR_COLUMNS_V2)]


def _write_checked(
    out: Path, src: str, rows: np.ndarray, meta: dict[str, Any], temps: pd.DataFrame, frame: pd.DataFrame
) -> None:
    """Write the bundle beside ``out``, load it back in full, then move it to ``out``; a bad row names the file's.

    ``rows`` is the instrument file's line of each row of ``frame``.
    """
    tmp = out.with_name(out.name + ".part")
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        write_bundle(tmp, meta, temps, None, frame)
        load_bundle(tmp)  # the bundle contract, in full, before anything appears at ``out``
    except BundleError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        m = _ERRORS_ROW.match(exc.one_line())
        if m:  # name the instrument file's row, not the bundle's
            k = int(m.group(1)) - 2
            row = int(rows[k]) if 0 <= k < rows.size else 0
            raise InstrumentFileError(f"{src}:{row}: {m.group(2)}" if row else f"{src}: {m.group(2)}") from None
        raise InstrumentFileError(f"{src}: {exc.one_line()}") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        out.rmdir()
    tmp.replace(out)


def check_axis(axis: str, where: str) -> str:
    """Return the axis letter upper-cased; InstrumentFileError when it is not one of the bundle's axes."""
    a = str(axis).strip().upper()
    if a not in AXES:
        raise InstrumentFileError(f"{where}: axis {axis!r} is not one of {' '.join(AXES)}")
    return a


def frame(rows: list[tuple[float, str, str, float, int, float]]) -> pd.DataFrame:
    """Return an errors frame from (time_s, axis, term, position, direction, value) tuples."""
    return pd.DataFrame(rows, columns=list(ERROR_COLUMNS))
