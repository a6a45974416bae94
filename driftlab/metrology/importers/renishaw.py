"""Renishaw laser files: the ``.rtx`` capture file and the CSV export of a linear (or angular) test.

``.rtx`` (CARTO capture, e.g. an XL-80 dynamic or drift capture): an ASCII header
``HEADER::\\r\\n`` of ``Key: value\\r\\n`` lines (``Sample rate``, ``Actual sample rate``,
``Sample no``, ``Axis``, ``Machine``, ``Date``, ...), ``Data:\\r\\n``, then the samples as
little-endian float64, and ``EOF::\\r\\n``. The samples are the displacement of the laser reading
at one place over time: the bundle gets them as the axis' positioning term at ``position``,
averaged over ``interval_s`` (a thermal drift record is minutes long, the capture runs at kHz).
The header does not state the samples' unit: it is ``--unit``, else µm is assumed and the summary
says so. Its date is ``dd/mm/yyyy`` or ``mm/dd/yyyy`` depending on the PC that wrote it: ``--date-order``,
else day first, said in the summary when the day and month could be swapped. The header's fields
(owner, version, velocity, trigger, serial number, ...) are kept in campaign.json, as the reference of
the bundle's instrument setup (a bundle v2).

CSV export: a preamble of ``key,value`` lines (``Axis``, ``Machine``, ``Date``, ``Test``
(``linear`` or ``angular``), ``Air temperature``, ``Material temperature``), then the data table
whose header holds ``Run``, ``Direction``, ``Target (<unit>)`` and ``Error (<unit>)`` (and
optionally ``Time (s)``), one row per target of each run. Column names are matched
case-insensitively; units come from the brackets.
"""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from driftlab.metrology.importers.common import (
    POSITIONING_TERM,
    InstrumentFileError,
    Readings,
    channel_name,
    check_axis,
    parse_date,
    parse_direction,
    parse_time,
    position_factor,
    value_factor,
)

RTX_HEADER = b"HEADER::\r\n"
RTX_DATA = b"Data:\r\n"
RTX_EOF = b"EOF::\r\n"


def read_rtx(
    path: str | Path,
    *,
    axis: str | None = None,
    position: float = 0.0,
    unit: str | None = None,
    interval_s: float = 1.0,
    term: str | None = None,
    date_order: str | None = None,
) -> Readings:
    """Return the readings of a ``.rtx`` capture: the samples averaged per ``interval_s``, at one position."""
    path = Path(path)
    src = path.name
    header, samples = _rtx_parts(path)
    rate = _rtx_rate(src, header)
    bad = np.flatnonzero(~np.isfinite(samples))
    if bad.size:
        raise InstrumentFileError(f"{src}: sample {int(bad[0])} is not a finite number")
    ax = check_axis(axis or header.get("Axis") or "", f"{src}: axis (header 'Axis' or --axis)")
    tm = term or POSITIONING_TERM[ax]
    assumptions: list[str] = []
    if unit is None:
        unit = "um" if tm not in ("alpha", "beta", "gamma") else "arcsec"
        shown = "µm" if unit == "um" else unit
        assumptions.append(f"the header states no unit: the samples are read as {shown} (give --unit)")
    scale = value_factor(unit, tm, f"{src}: --unit")
    t, means = _averaged(src, samples, rate, interval_s)
    means = means * scale
    n = len(t)
    errors = pd.DataFrame(
        {"time_s": t, "axis": ax, "term": tm, "position": float(position), "direction": 1, "value": means}
    )
    started = None
    if header.get("Date"):
        started, assumed = parse_date(header["Date"], f"{src}: header 'Date'", date_order)
        assumptions += [assumed] if assumed else []
    record: dict[str, Any] = {
        "instrument": "laser",
        "source": f"Renishaw .rtx capture {src}",
        **{_key(k): v for k, v in header.items() if v},
        "unit": unit,
        "unit_stated": "--unit" if not assumptions or "no unit" not in assumptions[0] else "assumed",
        "date_order": date_order or "dmy (assumed)",
    }
    return Readings(
        src,
        errors,
        np.zeros(n, dtype=np.int64),
        machine=header.get("Machine", ""),
        started_at=started,
        instrument=record,
        assumptions=assumptions,
    )


def _rtx_parts(path: Path) -> tuple[dict[str, str], np.ndarray]:
    """Return the header (key -> value) and the float64 samples of a ``.rtx`` file, each part checked."""
    src = path.name
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InstrumentFileError(f"{src}: {exc.strerror or exc}") from None
    if not raw.startswith(RTX_HEADER):
        raise InstrumentFileError(f"{src}:1: not a Renishaw .rtx file (it does not start with HEADER::)")
    end = raw.find(RTX_DATA)
    if end < 0:
        raise InstrumentFileError(f"{src}: no 'Data:' line after the header")
    header: dict[str, str] = {}
    for lineno, line in enumerate(raw[len(RTX_HEADER) : end].split(b"\r\n"), start=2):
        if not line.strip():
            continue
        key, sep, value = line.decode("latin-1").partition(": ")
        if not sep:
            key, sep, value = line.decode("latin-1").partition(":")
        if not sep:
            raise InstrumentFileError(f"{src}:{lineno}: header line {line[:40]!r} is not 'Key: value'")
        header[key.strip()] = value.strip()
    body = raw[end + len(RTX_DATA) :]
    if not body.endswith(RTX_EOF):
        raise InstrumentFileError(f"{src}: the data block does not end with EOF:: (a truncated file?)")
    body = body[: -len(RTX_EOF)]
    if len(body) % 8:
        raise InstrumentFileError(
            f"{src}: the data block holds {len(body)} bytes, not a whole number of float64 samples"
        )
    samples = np.frombuffer(body, dtype="<f8")
    if samples.size == 0:
        raise InstrumentFileError(f"{src}: the capture holds no samples")
    return header, samples


def _rtx_rate(src: str, header: dict[str, str]) -> float:
    """Return the capture's sample rate (Hz) from its header: the actual rate, else the set one."""
    rate_text = header.get("Actual sample rate") or header.get("Sample rate")
    try:
        rate = float(rate_text) if rate_text is not None else float("nan")
    except ValueError:
        rate = float("nan")
    if not (np.isfinite(rate) and rate > 0):
        raise InstrumentFileError(
            f"{src}: header 'Actual sample rate' is missing or not a positive number ({rate_text!r})"
        )
    return rate


def _averaged(src: str, samples: np.ndarray, rate: float, interval_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the middle time (s) and the mean of each whole ``interval_s`` of the samples taken at ``rate``."""
    if not (np.isfinite(interval_s) and interval_s > 0):
        raise InstrumentFileError(f"{src}: the averaging interval must be positive, got {interval_s!r}")
    per = max(1, int(round(interval_s * rate)))
    n = samples.size // per
    if n == 0:
        raise InstrumentFileError(f"{src}: {samples.size} samples are fewer than one {interval_s:g} s interval")
    means = samples[: n * per].reshape(n, per).mean(axis=1)
    return (np.arange(n) * per + (per - 1) / 2.0) / rate, means  # the middle of each averaging interval


def _key(name: str) -> str:
    """Return a header key as a JSON name: "Version no" -> "version_no"."""
    return re.sub(r"[^a-z0-9]+", "_", name.strip().lower()).strip("_") or "field"


_UNIT = re.compile(r"^\s*([^()\[\]]+?)\s*[\(\[]\s*([^()\[\]]+)\s*[\)\]]\s*$")


def _split_unit(name: str) -> tuple[str, str | None]:
    m = _UNIT.match(name)
    return (m.group(1).strip().lower(), m.group(2).strip()) if m else (name.strip().lower(), None)


def read_renishaw_csv(path: str | Path, *, axis: str | None = None) -> Readings:
    """Return the readings of a Renishaw linear/angular CSV export (preamble + Run/Direction/Target/Error table)."""
    path = Path(path)
    src = path.name
    lines, meta, head, table = _csv_table(path)
    cols: dict[str, tuple[str, str | None]] = {}
    for c in table.columns:
        name, unit = _split_unit(str(c))
        cols[name] = (str(c), unit)
    test = meta.get("test", "linear").strip().lower()
    if test not in ("linear", "angular"):
        raise InstrumentFileError(f"{src}: 'Test' is {meta.get('test')!r}, expected linear or angular")
    ax = check_axis(axis or meta.get("axis", ""), f"{src}: axis (preamble 'Axis' or --axis)")
    term = POSITIONING_TERM[ax]
    if test == "angular" and ax in ("X", "Y", "Z"):
        raise InstrumentFileError(
            f"{src}: an angular test of linear axis {ax}: import it with the generic mapping "
            "(which names the term, e.g. pitch or yaw)"
        )
    t_unit = cols["target"][1] or ("deg" if ax in ("A", "B") else "mm")
    e_unit = cols["error"][1] or ("arcsec" if term in ("alpha", "beta") else "um")
    p_scale = position_factor(t_unit, ax, f"{src}:{head + 1}: column {cols['target'][0]}")
    v_scale = value_factor(e_unit, term, f"{src}:{head + 1}: column {cols['error'][0]}")
    rows_out: list[tuple[float, str, str, float, int, float, int]] = []
    lines_out = []
    for k, row in table.iterrows():
        lineno = head + 2 + int(k)  # the table's header is line head + 1
        cell = {name: str(row[orig]).strip() for name, (orig, _) in cols.items()}
        d, run, numbers = _csv_row(src, lineno, cell, cols)
        t = numbers[2] if "time" in cols else float(len(rows_out))  # measuring order, one second apart
        rows_out.append((t, ax, term, numbers[0] * p_scale, d, numbers[1] * v_scale, run))
        lines_out.append(lineno)
    if not rows_out:
        raise InstrumentFileError(f"{src}: the data table has no rows")
    errors = pd.DataFrame(
        [r[:6] for r in rows_out], columns=["time_s", "axis", "term", "position", "direction", "value"]
    )
    temps = _preamble_temperatures(src, meta, lines)
    started = parse_time(meta["date"], f"{src}: 'Date'") if meta.get("date") else None
    return Readings(
        src, errors, np.array(lines_out), machine=meta.get("machine", ""), started_at=started, temperatures=temps
    )


def _csv_table(path: Path) -> tuple[list[str], dict[str, str], int, pd.DataFrame]:
    """Return the export's lines, its preamble (lower-case key -> value), the table's header line (0-based)
    and the table's cells as text."""
    src = path.name
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InstrumentFileError(f"{src}:1: not UTF-8 text") from None
    except OSError as exc:
        raise InstrumentFileError(f"{src}: {exc.strerror or exc}") from None
    lines = text.splitlines()
    meta: dict[str, str] = {}
    head = None
    for i, line in enumerate(lines):
        cells = [c.strip() for c in line.split(",")]
        names = {_split_unit(c)[0] for c in cells}
        if {"run", "direction", "target", "error"} <= names:
            head = i
            break
        if cells and cells[0]:
            meta[cells[0].lower()] = cells[1] if len(cells) > 1 else ""
    if head is None:
        raise InstrumentFileError(
            f"{src}: no data table: expected a header line with Run, Direction, Target (unit), Error (unit)"
        )
    try:
        table = pd.read_csv(
            io.StringIO("\n".join(lines[head:])), dtype=str, keep_default_na=False, skip_blank_lines=False
        )
    except (pd.errors.ParserError, ValueError) as exc:
        raise InstrumentFileError(f"{src}: cannot parse the data table ({' '.join(str(exc).split())})") from None
    return lines, meta, head, table


def _csv_row(
    src: str, lineno: int, cell: dict[str, str], cols: dict[str, tuple[str, str | None]]
) -> tuple[int, int, list[float]]:
    """Return a table row's direction (+1/-1), run number, and target, error (and time) as finite numbers."""
    if not any(cell.values()):
        raise InstrumentFileError(f"{src}:{lineno}: empty line inside the data table")
    d = parse_direction(cell["direction"])
    if d is None:
        raise InstrumentFileError(
            f"{src}:{lineno}: column Direction: {cell['direction']!r} is not + or - (or forward/backward, up/down)"
        )
    try:
        run = int(cell["run"])
    except ValueError:
        raise InstrumentFileError(f"{src}:{lineno}: column Run: {cell['run']!r} is not a run number") from None
    numbers = []
    for name in ("target", "error", *(("time",) if "time" in cols else ())):
        try:
            v = float(cell[name])
        except ValueError:
            v = float("nan")
        if not np.isfinite(v):
            raise InstrumentFileError(f"{src}:{lineno}: column {cols[name][0]}: {cell[name]!r} is not a number")
        numbers.append(v)
    return d, run, numbers


def _preamble_temperatures(src: str, meta: dict[str, str], lines: list[str]) -> dict[str, float]:
    """Return the preamble's air and material temperatures (degC) as channels, where it states them."""
    temps: dict[str, float] = {}
    for key in ("air temperature", "material temperature"):
        if key in meta and meta[key] != "":
            try:
                temps[channel_name(key.split()[0])] = float(meta[key])
            except ValueError:
                row = next(i for i, ln in enumerate(lines) if ln.lower().startswith(key)) + 1
                raise InstrumentFileError(f"{src}:{row}: {key} {meta[key]!r} is not a number (degC)") from None
    return temps
