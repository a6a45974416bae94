"""Bundles read a chunk at a time: the same validation and the same data as in one go, all-or-nothing imports,
memory that does not grow with the bundle."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns import ingest
from driftlab.campaigns.bundle import CSV_BLOCK_BYTES, BundleError, load_bundle, open_bundle, write_bundle
from driftlab.campaigns.staging import stage_bundle
from driftlab.campaigns.store import connect
from driftlab.cli import main

from .conftest import error_rows_failing_at, make_bundle, small_frames, small_meta
from .test_bundle_v2 import _v2

ROOT = Path(__file__).resolve().parents[2]
SMALL = 512  # bytes of CSV text per chunk: a few rows, so every file spans many chunks


def test_corrupted_bundle_is_named_the_same_in_small_chunks(bundle_dir: Path, corruption) -> None:
    _, file, mutate, expected = corruption
    mutate(bundle_dir / file)
    with pytest.raises(BundleError) as info:
        load_bundle(bundle_dir, block_bytes=SMALL)
    assert "\n" not in str(info.value) and expected in str(info.value)
    with pytest.raises(BundleError) as staged:
        stage_bundle(bundle_dir, block_bytes=SMALL)
    assert str(staged.value) == str(info.value)


def test_chunks_are_small_and_gather_to_the_whole_file(bundle_dir: Path) -> None:
    files = open_bundle(bundle_dir, block_bytes=SMALL)
    chunks = list(files.errors())
    assert len(chunks) >= 10 and max(len(c) for c in chunks) < 20
    whole = load_bundle(bundle_dir)
    pd.testing.assert_frame_equal(pd.concat(chunks, ignore_index=True), whole.errors, check_exact=True)
    small = load_bundle(bundle_dir, block_bytes=SMALL)
    for name in ("temperatures", "conditions", "errors"):
        pd.testing.assert_frame_equal(getattr(small, name), getattr(whole, name), check_exact=True)


@pytest.mark.parametrize("row", range(3, 60, 2))
def test_a_duplicate_reading_is_found_across_chunks(tmp_path: Path, row: int) -> None:
    """Readings at one time split over two chunks: the repeat is named wherever the chunk boundary falls."""
    temps, cond, _ = small_frames()
    rows = [(10.0 * (k // 6), "Z", ("dx", "dz", "gamma")[k % 3], 100.0 * (k % 6 // 3), 1, 1e-4) for k in range(72)]
    errors = pd.DataFrame(rows, columns=["time_s", "axis", "term", "position", "direction", "value"])
    errors.loc[row - 2, ["term", "position"]] = errors.loc[row - 3, ["term", "position"]].to_numpy()
    bundle = write_bundle(tmp_path / "b", small_meta(), temps, cond, errors)
    for block in (SMALL, 200, 100):
        with pytest.raises(BundleError, match=f"^errors.csv:{row}: duplicate reading"):
            load_bundle(bundle, block_bytes=block)


@pytest.mark.parametrize("row", range(3, 40, 3))
def test_time_order_is_checked_across_chunks(tmp_path: Path, row: int) -> None:
    temps, cond, errors = small_frames()
    temps.loc[row - 2, "time_s"] = temps.loc[row - 3, "time_s"]  # the same time twice: not after the previous
    bundle = write_bundle(tmp_path / "b", small_meta(), temps, cond, errors)
    for block in (SMALL, 256, 100):
        with pytest.raises(BundleError, match=f"^temperatures.csv:{row}: time_s .* is not after the previous row's"):
            load_bundle(bundle, block_bytes=block)


def test_content_hash_is_what_it_always_was(tmp_path: Path) -> None:
    """Hashes of stored campaigns stay valid: the values below were computed before chunked reading."""
    v1 = "cf8e2f9af3cf4d3f82735e0896f2a86e397ce5037f3eb7ca7c38f540a6e62ca1"
    v2 = "3664b85e7af5198d847321e27fd8fdfef3ecb0b293704eab550dbdba9a862fd7"
    for path, want in ((make_bundle(tmp_path / "v1"), v1), (_v2(tmp_path), v2)):
        assert load_bundle(path).content_hash() == want
        assert load_bundle(path, block_bytes=SMALL).content_hash() == want
        with stage_bundle(path, block_bytes=SMALL) as staged:
            assert staged.content_hash() == want


#: each stored table of a campaign, with the key that orders it
TABLES = (
    ("temperature_samples", "channel_id, time_s"),
    ("temperature_rollups", "channel_id, minute"),
    ("condition_samples", "time_s"),
    ("error_samples", "seq"),
    ("channels", "ordinal"),
    ("stages", "ordinal"),
)


def _rows(engine, table: str, key: str, campaign_id: int) -> pd.DataFrame:
    frame = pd.read_sql(f"SELECT * FROM {table} WHERE campaign_id = {campaign_id} ORDER BY {key}", engine)
    return frame.drop(columns=["campaign_id", "channel_id", "id"], errors="ignore")


@pytest.mark.parametrize("how", ["staged", "directory"])
@pytest.mark.parametrize("version", ["v1", "v2"])
def test_an_import_a_chunk_at_a_time_stores_exactly_what_an_import_in_memory_stores(
    store_url: str, tmp_path: Path, version: str, how: str
) -> None:
    """Staged then written, or (``import_directory``, on PostgreSQL) written while the files are read."""
    path = make_bundle(tmp_path / "v1", scans=300, sweeps=9) if version == "v1" else _v2(tmp_path)
    whole = load_bundle(path)
    other = connect(f"sqlite:///{tmp_path / 'memory.sqlite'}")
    store = connect(store_url)
    try:
        cid = _import(store, path, how)
        stored = store.campaigns.load(cid)
        reference = other.campaigns.import_bundle(whole)
        for name in ("temperatures", "conditions", "errors"):
            pd.testing.assert_frame_equal(getattr(stored, name), getattr(whole, name), check_exact=True)
        assert stored.content_hash() == whole.content_hash()
        # every table row for row, rollups and sweep numbers included
        for table, key in TABLES:
            got, want = _rows(store.engine, table, key, cid), _rows(other.engine, table, key, reference)
            assert len(got) > 0, table
            pd.testing.assert_frame_equal(got, want, check_exact=True, check_dtype=False)
        campaign = pd.read_sql(f"SELECT * FROM campaigns WHERE id = {cid}", store.engine).iloc[0]
        assert campaign["content_hash"] == whole.content_hash()
        assert bool(campaign["rollups_complete"])
    finally:
        store.close()
        other.close()


def _import(store, path: Path, how: str) -> int:
    """Import the bundle in ``path`` staged (``campaigns.import_bundle``) or from its directory."""
    if how == "directory":
        with store.campaigns.import_directory(path, block_bytes=SMALL) as imported:
            assert imported.bundle.temperatures.n_rows == len(load_bundle(path).temperatures)
            return imported.campaign_id
    with stage_bundle(path, block_bytes=SMALL) as staged:
        assert staged.temperatures.n_rows == len(load_bundle(path).temperatures)
        return store.campaigns.import_bundle(staged)


def _big_bundle(path: Path, scans: int, bad_last_row: bool = False) -> Path:
    """Write a bundle of 4 channels at 1 Hz (the last temperature row out of range when asked)."""
    t = np.arange(scans, dtype=float)
    rng = np.random.default_rng(0)
    temps = pd.DataFrame(
        {"time_s": t, **{c: np.round(20 + rng.normal(0, 0.1, scans), 3) for c in ("T1", "T2", "T49", "T50")}}
    )
    if bad_last_row:
        temps.loc[scans - 1, "T2"] = 295.4  # kelvin
    _, cond, errors = small_frames()
    return write_bundle(path, small_meta(), temps, cond, errors)


def test_a_bad_last_row_of_a_big_file_leaves_the_store_untouched(store_url: str, tmp_path: Path, capsys) -> None:
    store = connect(store_url)
    try:
        store.campaigns.import_bundle(load_bundle(make_bundle(tmp_path / "first")))
        before = store.table_counts()
        bad = _big_bundle(tmp_path / "bad", 300_000, bad_last_row=True)
        assert (bad / "temperatures.csv").stat().st_size > 8 * CSV_BLOCK_BYTES  # several chunks of the default size
        capsys.readouterr()
        assert main(["import", str(bad), "--db", store_url]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [
            "driftlab: error: temperatures.csv:300001: column T2: 295.4 degC is outside -60.0..250.0: "
            "temperatures must be in degC"
        ]
        assert store.table_counts() == before
    finally:
        store.close()


@pytest.mark.parametrize("how", ["staged", "directory"])
@pytest.mark.parametrize("boom", [RuntimeError("disk on fire"), KeyboardInterrupt()], ids=["error", "ctrl-c"])
def test_a_failure_after_many_chunks_are_written_rolls_all_back(
    store_url: str, tmp_path: Path, monkeypatch, boom, how: str
) -> None:
    """From a staged bundle the errors come last; from a directory on PostgreSQL, first, beside the parse."""
    store = connect(store_url)
    try:
        store.campaigns.import_bundle(load_bundle(make_bundle(tmp_path / "first")))
        before = store.table_counts()
        real = ingest.error_rows
        written: list[int] = []
        path = make_bundle(tmp_path / "second", seed=2, scans=300, sweeps=9)
        with stage_bundle(path, block_bytes=SMALL) as staged:
            assert len(list(staged.errors.chunks())) > 10
        monkeypatch.setattr(ingest, "error_rows", error_rows_failing_at(100, boom, written))
        with pytest.raises(type(boom)):
            _import(store, path, how)
        assert written == [100]
        assert store.table_counts() == before
        monkeypatch.setattr(ingest, "error_rows", real)
        _import(store, path, how)  # nothing was left behind that would block a clean retry
        assert store.table_counts()["campaigns"] == before["campaigns"] + 1
    finally:
        store.close()


def test_cli_import_summary_is_unchanged(store_url: str, bundle_dir: Path, capsys) -> None:
    from driftlab.commands.bundle_io import import_summary

    assert main(["import", str(bundle_dir), "--json", "--db", store_url]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary == import_summary(1, load_bundle(bundle_dir))
    assert (summary["scans"], summary["temperature_readings"], summary["missing_readings"]) == (40, 159, 1)
    assert summary["error_terms"] == ["Z/dx", "Z/dz", "Z/gamma"] and summary["condition_rows"] == 40


# ----------------------------------------------------------------------------- memory

IMPORT_PROBE = r"""
import sys
from driftlab.cli import main
assert main(["import", sys.argv[1], "--db", sys.argv[2]]) == 0
print(int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1]))
"""


def _peak_rss_kb(bundle: Path, db: Path) -> int:
    proc = subprocess.run(
        [sys.executable, "-c", IMPORT_PROBE, str(bundle), f"sqlite:///{db}"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    )
    return int(proc.stdout.split()[-1])


@pytest.mark.slow
def test_import_memory_does_not_grow_with_the_bundle(tmp_path: Path) -> None:
    """Peak RSS (VmHWM) importing 8x the readings is within 40 MB of the smaller bundle (subprocesses)."""
    small = _big_bundle(tmp_path / "small", 100_000)
    big = _big_bundle(tmp_path / "big", 800_000)
    assert (big / "temperatures.csv").stat().st_size > 25 << 20
    rss_small = _peak_rss_kb(small, tmp_path / "small.sqlite")
    rss_big = _peak_rss_kb(big, tmp_path / "big.sqlite")
    assert rss_big - rss_small < 40 * 1024, (rss_small, rss_big)
