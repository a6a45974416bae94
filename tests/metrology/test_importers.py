"""Importers: Renishaw .rtx and CSV export, the generic CSV mapping -> bundles; bad files are one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from driftlab.campaigns.bundle import load_bundle
from driftlab.cli import main
from driftlab.metrology import iso230_2

# ----------------------------------------------------------------------------- files made on the fly


def rtx_bytes(samples: np.ndarray, rate: float = 1000.0, axis: str = "Z", extra: bytes = b"") -> bytes:
    header = (
        f"Owner: CARTO-Capture\r\nVersion no: 4.13\r\nFile Type: rtx\r\nVelocity: 0\r\nSample rate: {rate:g}\r\n"
        f"Sample no: {samples.size}\r\nTrigger point: 0\r\nTrigger interval: {1 / rate:g}\r\n"
        f"Actual sample rate: {rate:g}\r\nFlags: 0 1 2 0 2\r\nMachine: vmc-01\r\nSerial No: 123\r\n"
        f"Date: 10/02/2025 12:58:22\r\nBy: User\r\nAxis: {axis}\r\nLocation: table\r\n"
    ).encode()
    return b"HEADER::\r\n" + header + extra + b"Data:\r\n" + samples.astype("<f8").tobytes() + b"EOF::\r\n"


def renishaw_csv(runs: int = 3, targets=(0.0, 100.0, 200.0, 300.0), axis: str = "X", seed: int = 0) -> tuple[str, list]:
    """Return a CSV export (preamble + table, errors in um) and the readings it holds (target mm, direction,
    error mm)."""
    rng = np.random.default_rng(seed)
    lines = [
        f"Axis,{axis}",
        "Machine,vmc-01",
        "Date,2026-03-02T08:00:00Z",
        "Test,linear",
        "Air temperature,20.4",
        "Material temperature,21.1",
        "",
        "Run,Direction,Target (mm),Error (um)",
    ]
    readings = []
    for r in range(1, runs + 1):
        for d, order in (("+", targets), ("-", targets[::-1])):
            for t in order:
                e_um = 10.0 * t / 300.0 + (2.0 if d == "+" else -2.0) + rng.normal(0, 0.5)
                lines.append(f"{r},{d},{t},{e_um:.4f}")
                readings.append((t, 1 if d == "+" else -1, round(e_um, 4) * 1e-3))
    return "\n".join(lines) + "\n", readings


# ----------------------------------------------------------------------------- Renishaw CSV


def test_renishaw_csv_becomes_a_bundle_and_iso230_2_reads_it(tmp_path, capsys):
    text, readings = renishaw_csv()
    src = tmp_path / "x-linear.csv"
    src.write_text(text)
    out = tmp_path / "bundle"
    assert main(["import-instrument", str(src), "--format", "renishaw-csv", "-o", str(out)]) == 0
    b = load_bundle(out)
    assert b.meta.machine.id == "vmc-01" and set(b.channels) == {"air", "material"}
    assert float(b.temperatures["air"].iloc[0]) == 20.4
    assert len(b.errors) == len(readings) and set(b.errors["term"]) == {"dx"}
    np.testing.assert_allclose(b.errors["value"].to_numpy(), [r[2] for r in readings], rtol=0, atol=1e-15)
    res = iso230_2.from_bundle_errors(b.errors, "X")
    assert res.runs == 3 and res.figures["B"] == pytest.approx(0.004, abs=0.0015)
    assert "wrote bundle" in capsys.readouterr().out


@pytest.mark.parametrize(
    "mutate,needle",
    [
        (lambda t: t.replace("2,+,100.0,", "2,?,100.0,"), "x.csv:18: column Direction: '?' is not + or -"),
        (lambda t: t.replace("1,+,200.0,", "1,+,200.0,abc#"), "x.csv:11: column Error (um): 'abc#"),
        (lambda t: t.replace("Run,Direction,Target (mm),Error (um)", "Run,Dir,Target,Err"), "x.csv: no data table"),
        (lambda t: t.replace("Error (um)", "Error (furlong)"), "x.csv:8: column Error (furlong): unit 'furlong'"),
        (lambda t: t.replace("Axis,X", "Axis,Q"), "axis 'Q' is not one of X Y Z A B"),
        (lambda t: t.replace("Error (um)", "Error (m)"), "mm is implausibly large for a translation"),
        (lambda t: t.replace("Date,2026-03-02T08:00:00Z", "Date,yesterday"), "date 'yesterday' is neither ISO 8601"),
    ],
)
def test_renishaw_csv_bad_files_are_one_line_errors_and_nothing_is_written(tmp_path, capsys, mutate, needle):
    text, _ = renishaw_csv()
    src = tmp_path / "x.csv"
    src.write_text(mutate(text))
    out = tmp_path / "bundle"
    code = main(
        [
            "import-instrument",
            str(src),
            "--format",
            "renishaw-csv",
            "-o",
            str(out),
        ]
    )
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines
    assert not out.exists() and not (tmp_path / "bundle.part").exists()


# ----------------------------------------------------------------------------- .rtx


def test_rtx_capture_becomes_a_drift_record(tmp_path):
    rate = 1000.0
    t = np.arange(12000) / rate  # 12 s at 1 kHz: a slow drift of 0.5 um/s plus vibration
    samples = 0.5 * t + 0.3 * np.sin(2 * np.pi * 50 * t)
    src = tmp_path / "drift.rtx"
    src.write_bytes(rtx_bytes(samples, rate))
    out = tmp_path / "bundle"
    assert (
        main(
            [
                "import-instrument",
                str(src),
                "--format",
                "rtx",
                "-o",
                str(out),
                "--air-temp",
                "20.5",
                "--position",
                "-120",
                "--interval-s",
                "2",
            ]
        )
        == 0
    )
    b = load_bundle(out)
    e = b.errors
    assert len(e) == 6 and set(e["axis"]) == {"Z"} and set(e["term"]) == {"dz"} and set(e["position"]) == {-120.0}
    # 2 s means of 0.5 um/s: 0.5, 1.5, ... um (the 50 Hz vibration averages out), in mm
    np.testing.assert_allclose(e["value"].to_numpy(), (0.5 * e["time_s"].to_numpy()) * 1e-3, atol=1e-9)
    assert b.meta.started_at.isoformat().startswith("2025-02-10T12:58:22")  # dd/mm/yyyy, as the header is written


@pytest.mark.parametrize(
    "make,needle",
    [
        (lambda s: b"HEADR::\r\n" + rtx_bytes(s)[10:], "drift.rtx:1: not a Renishaw .rtx file"),
        (lambda s: rtx_bytes(s)[:-7], "does not end with EOF::"),
        (lambda s: rtx_bytes(s)[:-10] + b"EOF::\r\n", "not a whole number of float64 samples"),
        (
            lambda s: (
                rtx_bytes(s)
                .replace(b"Actual sample rate: 1000", b"Actual sample rate: fast")
                .replace(b"Sample rate: 1000", b"Sample rate: fast")
            ),
            "'Actual sample rate' is missing or not a positive number",
        ),
        (lambda s: rtx_bytes(s, extra=b"garbage line\r\n"), "drift.rtx:18: header line b'garbage line'"),
        (lambda s: rtx_bytes(np.r_[s, np.nan]), "sample 3000 is not a finite number"),
        (lambda s: rtx_bytes(s, axis=""), "axis '' is not one of X Y Z A B"),
    ],
)
def test_rtx_bad_files_are_one_line_errors(tmp_path, capsys, make, needle):
    src = tmp_path / "drift.rtx"
    src.write_bytes(make(np.zeros(3000)))
    out = tmp_path / "bundle"
    code = main(
        [
            "import-instrument",
            str(src),
            "--format",
            "rtx",
            "-o",
            str(out),
            "--air-temp",
            "20",
        ]
    )
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines
    assert not out.exists()


def test_rtx_unit_and_date_order_are_explicit_and_the_header_is_kept(tmp_path, capsys):
    """No --unit: µm is assumed and said; an ambiguous date: day first, said; --date-order mdy reads it month
    first; the header's owner, version, velocity and trigger are in campaign.json."""
    src = tmp_path / "drift.rtx"
    src.write_bytes(rtx_bytes(np.full(4000, 2.0)))
    base = ["import-instrument", str(src), "--format", "rtx", "--air-temp", "20"]
    assert main([*base, "-o", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert "assumed: the header states no unit: the samples are read as µm (give --unit)" in out
    assert "assumed: date '10/02/2025 12:58:22' read day first (10 February 2025)" in out
    a = load_bundle(tmp_path / "a")
    assert a.meta.started_at.month == 2 and a.errors["value"].iloc[0] == pytest.approx(2.0e-3)
    ref = a.meta.setups["instrument"].reference
    assert ref["owner"] == "CARTO-Capture" and ref["version_no"] == "4.13" and ref["velocity"] == "0"
    assert ref["trigger_point"] == "0" and ref["unit"] == "um" and ref["unit_stated"] == "assumed"
    assert a.meta.setups["instrument"].instrument == "laser" and a.meta.setups["instrument"].terms == ["Z/dz"]
    assert main([*base, "-o", str(tmp_path / "b"), "--unit", "nm", "--date-order", "mdy"]) == 0
    out = capsys.readouterr().out
    assert "assumed:" not in out
    b = load_bundle(tmp_path / "b")
    assert b.meta.started_at.month == 10 and b.meta.started_at.day == 2
    assert b.errors["value"].iloc[0] == pytest.approx(2.0e-6)
    assert b.meta.setups["instrument"].reference["date_order"] == "mdy"
    assert b.meta.setups["instrument"].reference["unit_stated"] == "--unit"
    # ISO 230-2's test conditions name the instrument from that record
    from driftlab.metrology import report

    conds = dict(report.conditions(b, "Z", None, 0.0, 4.0))
    assert conds["instrument"].startswith("laser (setup instrument; source Renishaw .rtx capture drift.rtx, owner")
    assert "version no 4.13" in conds["instrument"] and conds["feed"] == "0"


def test_rtx_without_a_temperature_asks_for_one(tmp_path, capsys):
    src = tmp_path / "drift.rtx"
    src.write_bytes(rtx_bytes(np.zeros(2000)))
    assert main(["import-instrument", str(src), "--format", "rtx", "-o", str(tmp_path / "b")]) == 2
    assert "records no temperature: give --air-temp" in capsys.readouterr().err


# ----------------------------------------------------------------------------- generic mapping

MAPPING = {
    "columns": {
        "time_s": "Elapsed",
        "axis": "Achse",
        "term": "Kind",
        "position": "Soll",
        "direction": "Dir",
        "value": "Abw",
    },
    "units": {"time_s": "min", "position": "mm", "value": "um", "angle": "arcsec"},
    "directions": {"V": 1, "R": -1},
    "terms": {"Lin": "dx", "Gier": "gamma"},
    "temperatures": {"room air": "Luft"},
    "machine": "bfz-7",
    "started_at": "2026-05-04T06:00:00+02:00",
    "delimiter": ";",
    "decimal": ",",
}


def generic_csv() -> str:
    rows = ["Elapsed;Achse;Kind;Soll;Dir;Abw;Luft"]
    k = 0
    for run in range(2):
        for d, order in (("V", (0, 50, 100)), ("R", (100, 50, 0))):
            for p in order:
                rows.append(
                    f"{k};X;Lin;{p};{d};{p * 0.02 + (1 if d == 'V' else -1) + run * 0.1:.2f}".replace(".", ",")
                    + f";{20 + k * 0.01:.2f}".replace(".", ",")
                )
                k += 1
                rows.append(
                    f"{k};X;Gier;{p};{d};{0.5:.1f}".replace(".", ",") + f";{20 + k * 0.01:.2f}".replace(".", ",")
                )
                k += 1
    return "\n".join(rows) + "\n"


def test_generic_mapping_with_units_vocabularies_and_temperatures(tmp_path):
    src = tmp_path / "export.csv"
    src.write_text(generic_csv())
    mp = tmp_path / "map.json"
    mp.write_text(json.dumps(MAPPING))
    out = tmp_path / "bundle"
    assert main(["import-instrument", str(src), "--format", "generic", "--mapping", str(mp), "-o", str(out)]) == 0
    b = load_bundle(out)
    e = b.errors
    assert b.meta.machine.id == "bfz-7" and b.channels == ["room_air"] and len(b.temperatures) == 24
    assert set(e["term"]) == {"dx", "gamma"}
    assert e["time_s"].iloc[1] == 60.0  # minutes
    lin = e[e["term"] == "dx"]
    assert lin["value"].iloc[1] == pytest.approx((50 * 0.02 + 1) * 1e-3)  # um -> mm, decimal comma
    gier = e[e["term"] == "gamma"]
    assert gier["value"].iloc[0] == pytest.approx(np.deg2rad(0.5 / 3600))  # arcsec -> rad


@pytest.mark.parametrize(
    "edit,needle",
    [
        (lambda m: m["columns"].update(value="Nope"), "export.csv:1: no column 'Nope' (mapped to value in map.json)"),
        (lambda m: m["directions"].pop("R"), "export.csv:8: column Dir: 'R' is not a direction"),
        (lambda m: m["terms"].pop("Gier"), "export.csv:3: column Kind: 'Gier' is not a term"),
        (lambda m: m.update(colums={}), "map.json: colums: Extra inputs are not permitted"),
        (lambda m: m["columns"].pop("direction"), "map.json: no column or constant for 'direction'"),
        (lambda m: m.update(decimal="."), "export.csv:2: column Abw: '1,00' is not a number"),
    ],
)
def test_generic_mapping_errors_are_one_line(tmp_path, capsys, edit, needle):
    src = tmp_path / "export.csv"
    src.write_text(generic_csv())
    m = json.loads(json.dumps(MAPPING))
    edit(m)
    mp = tmp_path / "map.json"
    mp.write_text(json.dumps(m))
    out = tmp_path / "bundle"
    code = main(
        [
            "import-instrument",
            str(src),
            "--format",
            "generic",
            "--mapping",
            str(mp),
            "-o",
            str(out),
        ]
    )
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines
    assert not out.exists()


def test_existing_output_is_refused(tmp_path, capsys):
    text, _ = renishaw_csv()
    src = tmp_path / "x.csv"
    src.write_text(text)
    out = tmp_path / "bundle"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["import-instrument", str(src), "--format", "renishaw-csv", "-o", str(out)]) == 2
    assert "exists and is not an empty directory" in capsys.readouterr().err
    assert (out / "keep.txt").read_text() == "mine"
