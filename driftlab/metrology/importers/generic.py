"""Any instrument's CSV through a column mapping (YAML or JSON): which columns hold axis, term, position, direction.

Example mapping (docs/metrology.md):

.. code-block:: yaml

    columns: {time_s: Elapsed, position: Nominal, direction: Dir, value: Deviation}
    constants: {axis: X, term: dx}       # when the file has no such column
    units: {time_s: s, position: mm, value: um, angle: arcsec}   # value: translations; angle: rotations
    directions: {"F": 1, "R": -1}        # the file's own direction words (+ - forward backward ... by default)
    terms: {Linear: dx, Pitch: beta}     # the file's own term names, if it has a term column
    temperatures: {air: AirTemp}         # optional: bundle channel -> column (degC), one per reading
    machine: vmc-01
    started_at: "2026-03-02T08:00:00Z"
    delimiter: ";"                       # optional, default ","
    decimal: ","                         # optional, default "."
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field
from pydantic import ValidationError as PydanticValidationError

from driftlab.metrology.importers.common import (
    InstrumentFileError,
    Readings,
    channel_name,
    parse_direction,
    parse_time,
    position_factor,
    value_factor,
)
from driftlab.vocabulary import AXES, TERMS
from driftlab.yamlfile import read_yaml

FIELDS = ("time_s", "axis", "term", "position", "direction", "value")
TIME_UNITS = {"s": 1.0, "min": 60.0, "h": 3600.0, "ms": 1e-3}


class Mapping(BaseModel):
    """A column mapping: bundle field -> CSV column, constants for fields the file lacks, units, vocabularies."""

    model_config = ConfigDict(extra="forbid")

    columns: dict[str, str] = Field(default_factory=dict)
    constants: dict[str, Any] = Field(default_factory=dict)
    units: dict[str, str] = Field(default_factory=dict)
    directions: dict[str, int] = Field(default_factory=dict)
    terms: dict[str, str] = Field(default_factory=dict)
    temperatures: dict[str, str] = Field(default_factory=dict)
    machine: str = ""
    started_at: str | None = None
    delimiter: str = Field(default=",", min_length=1, max_length=1)
    decimal: str = Field(default=".", min_length=1, max_length=1)


def load_mapping(path: str | Path) -> Mapping:
    """Return the validated mapping of a YAML/JSON file; one-line InstrumentFileError naming the field otherwise."""
    path = Path(path)
    got = read_yaml(path, encoding="utf-8")
    if got.unreadable is not None:
        raise InstrumentFileError(f"{path.name}: {got.unreadable.strerror or got.unreadable}")
    if got.problem is not None:
        raise InstrumentFileError(f"{path.name}:{got.line or 1}: not YAML/JSON ({got.problem})")
    raw = got.doc
    try:
        m = Mapping.model_validate(raw if raw is not None else {})
    except PydanticValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"]) or "mapping"
        raise InstrumentFileError(f"{path.name}: {loc}: {err['msg']}") from None
    for f in list(m.columns) + list(m.constants):
        if f not in FIELDS:
            raise InstrumentFileError(f"{path.name}: {f!r} is not a bundle field ({' '.join(FIELDS)})")
    for f in ("axis", "term", "position", "value"):
        if f not in m.columns and f not in m.constants:
            raise InstrumentFileError(f"{path.name}: no column or constant for {f!r}")
    if "direction" not in m.columns and "direction" not in m.constants:
        raise InstrumentFileError(f"{path.name}: no column or constant for 'direction' (ISO 230-2 runs need it)")
    bad = [v for v in m.directions.values() if v not in (1, -1)]
    if bad:
        raise InstrumentFileError(f"{path.name}: directions map to +1 or -1, not {bad[0]}")
    bad_t = [v for v in m.terms.values() if v not in TERMS]
    if bad_t:
        raise InstrumentFileError(f"{path.name}: terms map to one of {' '.join(TERMS)}, not {bad_t[0]!r}")
    return m


def read_generic(path: str | Path, mapping: Mapping, mapping_name: str = "mapping") -> Readings:
    """Return the readings of a CSV file read through ``mapping`` (rows in file order)."""
    path = Path(path)
    src = path.name
    rows = _Rows(src, _read_table(path, mapping, mapping_name), mapping)
    axis, term, direction = _vocabulary(rows)
    position = rows.numbers("position")
    value = rows.numbers("value")
    _apply_units(mapping, mapping_name, axis, term, position, value)
    time_s = _times(rows, mapping_name)
    errors = pd.DataFrame(
        {
            "time_s": time_s,
            "axis": axis,
            "term": term.astype(str),
            "position": position,
            "direction": direction.astype(int),
            "value": value,
        }
    )
    temps = _temperatures(rows, time_s) if mapping.temperatures else None
    started = parse_time(mapping.started_at, f"{mapping_name}: started_at") if mapping.started_at else None
    return Readings(src, errors, rows.lines, machine=mapping.machine, started_at=started, temperature_frame=temps)


def _read_table(path: Path, mapping: Mapping, mapping_name: str) -> pd.DataFrame:
    """Return the CSV's cells as text, with every mapped column present, at least one row and no empty line."""
    src = path.name
    try:
        table = pd.read_csv(
            path, dtype=str, keep_default_na=False, sep=mapping.delimiter, skip_blank_lines=False, encoding="utf-8-sig"
        )
    except FileNotFoundError:
        raise InstrumentFileError(f"{src}: no such file") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InstrumentFileError(f"{src}: not a CSV file ({' '.join(str(exc).split())})") from None
    wanted = {**mapping.columns, **{f"temperature {k}": v for k, v in mapping.temperatures.items()}}
    for field, col in wanted.items():
        if col not in table.columns:
            raise InstrumentFileError(f"{src}:1: no column {col!r} (mapped to {field} in {mapping_name})")
    if table.empty:
        raise InstrumentFileError(f"{src}:2: no rows (the file has only a header)")
    empty = np.flatnonzero((table.astype(str).apply(lambda c: c.str.strip()) == "").all(axis=1).to_numpy())
    if empty.size:
        raise InstrumentFileError(f"{src}:{empty[0] + 2}: empty line")
    return table


class _Rows:
    """The CSV's rows seen through the mapping: a field's cells (a column, or the mapping's constant)."""

    def __init__(self, src: str, table: pd.DataFrame, mapping: Mapping) -> None:
        self.src, self.table, self.mapping = src, table, mapping
        self.n = len(table)
        self.lines = np.arange(self.n) + 2  # the file's line of each row (the header is line 1)

    def cells(self, field: str) -> np.ndarray:
        """Return the field's text per row, stripped."""
        if field in self.mapping.columns:
            return self.table[self.mapping.columns[field]].astype(str).str.strip().to_numpy()
        return np.full(self.n, str(self.mapping.constants[field]))

    def fail(self, i: int, field: str, what: str) -> InstrumentFileError:
        """Return the one-line error of row ``i``'s cell of ``field``."""
        col = self.mapping.columns.get(field, f"constant {field}")
        return InstrumentFileError(f"{self.src}:{self.lines[i]}: column {col}: {what}")

    def numbers(self, field: str) -> np.ndarray:
        """Return the field as finite numbers (the mapping's decimal mark); the first other cell fails."""
        text = self.cells(field)
        if self.mapping.decimal != ".":
            text = np.char.replace(text.astype(str), self.mapping.decimal, ".")
        v = np.array(pd.to_numeric(pd.Series(text), errors="coerce").to_numpy(float))  # a writable copy
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise self.fail(int(bad[0]), field, f"{self.cells(field)[bad[0]]!r} is not a number")
        return v


def _vocabulary(rows: _Rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return each row's axis, term (through the mapping's ``terms``) and direction (+1/-1, ``directions``)."""
    mapping = rows.mapping
    axis = np.char.upper(rows.cells("axis").astype(str))
    bad = np.flatnonzero(~np.isin(axis, AXES))
    if bad.size:
        raise rows.fail(int(bad[0]), "axis", f"{rows.cells('axis')[bad[0]]!r} is not one of {' '.join(AXES)}")
    term_text = rows.cells("term")
    term = np.array([mapping.terms.get(t, t) for t in term_text], dtype=object)
    bad = np.flatnonzero(~np.isin(term, TERMS))
    if bad.size:
        raise rows.fail(int(bad[0]), "term", f"{term_text[bad[0]]!r} is not a term (map it under 'terms')")
    dir_text = rows.cells("direction")
    direction = np.array(
        [mapping.directions[d] if d in mapping.directions else parse_direction(d) for d in dir_text], dtype=object
    )
    bad = np.flatnonzero(np.array([d is None for d in direction]))
    if bad.size:
        raise rows.fail(
            int(bad[0]), "direction", f"{dir_text[bad[0]]!r} is not a direction (map it under 'directions')"
        )
    return axis, term, direction


def _apply_units(
    mapping: Mapping, mapping_name: str, axis: np.ndarray, term: np.ndarray, position: np.ndarray, value: np.ndarray
) -> None:
    """Scale ``position`` and ``value`` in place to mm / deg and mm / rad from the mapping's ``units``."""
    p_unit = mapping.units.get("position")
    v_unit = mapping.units.get("value")  # translations (default mm)
    a_unit = mapping.units.get("angle")  # rotations (default rad)
    for i in range(len(term)):  # units differ per term (lengths, angles) and per axis (linear, rotary)
        rotation = term[i] in ("alpha", "beta", "gamma")
        unit = a_unit if rotation else v_unit
        if unit is not None:
            value[i] *= value_factor(unit, term[i], f"{mapping_name}: units.{'angle' if rotation else 'value'}")
        if p_unit is not None:
            position[i] *= position_factor(p_unit, axis[i], f"{mapping_name}: units.position")


def _times(rows: _Rows, mapping_name: str) -> np.ndarray:
    """Return each row's time (s): the mapped ``time_s`` in its unit, else the measuring order a second apart."""
    mapping = rows.mapping
    if "time_s" in mapping.columns or "time_s" in mapping.constants:
        t_unit = mapping.units.get("time_s", "s")
        if t_unit not in TIME_UNITS:
            raise InstrumentFileError(f"{mapping_name}: units.time_s {t_unit!r} is not one of {' '.join(TIME_UNITS)}")
        return rows.numbers("time_s") * TIME_UNITS[t_unit]
    return np.arange(rows.n, dtype=float)  # measuring order, one second apart


def _temperatures(rows: _Rows, time_s: np.ndarray) -> pd.DataFrame:
    """Return the mapped thermocouple columns (degC; an empty cell is a missing reading) by time, once per time."""
    table, mapping = rows.table, rows.mapping
    cols = {}
    for ch, col in mapping.temperatures.items():
        v = pd.to_numeric(table[col].str.replace(mapping.decimal, ".", regex=False), errors="coerce")
        bad_rows = np.flatnonzero(v.isna().to_numpy() & (table[col].str.strip() != "").to_numpy())
        if bad_rows.size:
            raise InstrumentFileError(
                f"{rows.src}:{rows.lines[bad_rows[0]]}: column {col}: "
                f"{table[col].iat[bad_rows[0]]!r} is not a number (degC)"
            )
        cols[channel_name(ch)] = v.to_numpy(float)
    temps = pd.DataFrame({"time_s": time_s, **cols}).drop_duplicates("time_s").reset_index(drop=True)
    return temps.sort_values("time_s", kind="stable").reset_index(drop=True)
