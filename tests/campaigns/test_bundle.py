"""Bundle v1: the real bundle loads, writing round-trips bit-exactly, every corruption is named."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from driftlab.campaigns.bundle import BundleError, CampaignMeta, load_bundle, write_bundle
from driftlab.errors import ValidationError


def test_corrupted_bundle_is_named(bundle_dir: Path, corruption) -> None:
    _, file, mutate, expected = corruption
    mutate(bundle_dir / file)
    with pytest.raises(BundleError) as info:
        load_bundle(bundle_dir)
    message = str(info.value)
    assert "\n" not in message
    assert expected in message
    assert isinstance(info.value, ValidationError)


def test_no_refusal_shows_a_foreign_files_content(bundle_dir: Path) -> None:
    """A link to /etc/passwd is refused by name: not a byte of the target is in the message."""
    target = Path("/etc/passwd")
    if not target.is_file():  # pragma: no cover - every Linux image has it
        pytest.skip("no /etc/passwd")
    (bundle_dir / "temperatures.csv").unlink()
    (bundle_dir / "temperatures.csv").symlink_to(target)
    with pytest.raises(BundleError) as info:
        load_bundle(bundle_dir)
    first = target.read_text().splitlines()[0]
    assert first not in str(info.value) and "root" not in str(info.value)


def test_a_link_inside_the_bundle_is_followed(bundle_dir: Path) -> None:
    from tests.campaigns.conftest import _link_inside

    before = load_bundle(bundle_dir)
    _link_inside(bundle_dir / "temperatures.csv")
    after = load_bundle(bundle_dir)
    pd.testing.assert_frame_equal(before.temperatures, after.temperatures)


def test_valid_small_bundle_loads(bundle_dir: Path) -> None:
    b = load_bundle(bundle_dir)
    assert b.channels == ["T1", "T2", "T49", "T50"]
    assert np.isnan(b.temperatures.loc[3, "T2"])
    assert b.conditions is not None and b.conditions["z"].isna().all()
    assert set(b.errors["direction"]) == {1, -1}
    assert b.meta.room_channels == ["T49", "T50"]


def test_real_fl_thermal_loads(fl_thermal: Path) -> None:
    b = load_bundle(fl_thermal)
    assert b.meta.machine.id == "fl-thermal"
    assert len(b.temperatures) == 11115
    assert b.channels == [f"t{i}" for i in range(1, 17)]
    assert len(b.errors) == 33345
    assert set(b.errors["term"]) == {"dx", "dy", "dz"}
    assert b.conditions is not None and len(b.conditions) == 11115


def test_write_then_load_and_plain_pandas_round_trip(fl_thermal: Path, tmp_path: Path) -> None:
    b = load_bundle(fl_thermal)
    out = write_bundle(tmp_path / "copy", b.meta, b.temperatures, b.conditions, b.errors)
    c = load_bundle(out)
    pd.testing.assert_frame_equal(c.temperatures, b.temperatures, check_exact=True)
    pd.testing.assert_frame_equal(c.errors, b.errors, check_exact=True)
    assert c.conditions is not None
    pd.testing.assert_frame_equal(c.conditions, b.conditions, check_exact=True)
    assert c.meta == b.meta
    assert c.content_hash() == b.content_hash()
    plain = pd.read_csv(out / "temperatures.csv")
    assert np.array_equal(plain.to_numpy(), b.temperatures.to_numpy(), equal_nan=True)
    plain_err = pd.read_csv(out / "errors.csv")
    assert plain_err["direction"].tolist() == b.errors["direction"].tolist()
    assert np.array_equal(plain_err["value"].to_numpy(), b.errors["value"].to_numpy())


def test_write_accepts_dict_meta_and_validates_it(tmp_path: Path, meta_factory, frames_factory) -> None:
    temps, cond, errors = frames_factory()
    meta = meta_factory()
    meta["room_channels"] = ["T1", "nope"]
    with pytest.raises(BundleError, match=r"room_channels\[1\]"):
        write_bundle(tmp_path / "b", meta, temps, cond, errors)


def test_content_hash_ignores_formatting_but_not_values(bundle_dir: Path, tmp_path: Path) -> None:
    a = load_bundle(bundle_dir)
    path = bundle_dir / "temperatures.csv"
    path.write_text(path.read_text().replace("\n0.0,", "\n0.000,", 1))
    assert load_bundle(bundle_dir).content_hash() == a.content_hash()
    lines = path.read_text().splitlines(keepends=True)
    lines[4] = lines[4].replace(",", ",2", 1)
    path.write_text("".join(lines))
    assert load_bundle(bundle_dir).content_hash() != a.content_hash()


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    temps=st.lists(st.one_of(st.floats(-50, 240, allow_nan=False), st.just(math.nan)), min_size=6, max_size=60),
    values=st.lists(st.floats(-4.9, 4.9, allow_nan=False) | st.just(-0.0) | st.just(5e-324), min_size=1, max_size=20),
    positions=st.lists(finite.filter(lambda x: abs(x) <= 1e5), min_size=1, max_size=20),  # MAX_LINEAR_POSITION_MM
)
def test_floats_round_trip_bit_exactly(tmp_path_factory, meta_factory, temps, values, positions) -> None:
    n = len(temps) // 2
    times = np.cumsum(np.abs(np.asarray(temps[:n], dtype=float)) + 1e-3)
    times = np.nan_to_num(times, nan=1.0).cumsum()
    tf = pd.DataFrame({"time_s": times, "T1": temps[:n], "T2": temps[n : 2 * n], "T49": 20.0, "T50": math.nan})
    k = min(len(values), len(positions))
    ef = pd.DataFrame(
        {
            "time_s": np.arange(k) * 1.5,
            "axis": "X",
            "term": "dx",
            "position": positions[:k],
            "direction": [1 if i % 2 else -1 for i in range(k)],
            "value": values[:k],
        }
    )
    out = write_bundle(tmp_path_factory.mktemp("rt"), meta_factory(), tf, None, ef)
    b = load_bundle(out)
    got, want = b.temperatures.to_numpy(), tf.to_numpy(dtype="f8")
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert got[~np.isnan(got)].tobytes() == want[~np.isnan(want)].tobytes()
    for col in ("time_s", "position", "value"):
        assert b.errors[col].to_numpy().tobytes() == ef[col].to_numpy(dtype="f8").tobytes()
    assert b.conditions is None


def test_campaign_meta_document_round_trips(bundle_dir: Path) -> None:
    b = load_bundle(bundle_dir)
    again = CampaignMeta.model_validate(b.meta.document())
    assert again == b.meta
    assert b.meta.document()["started_at"] == "2026-03-02T08:00:00Z"


@pytest.mark.parametrize(
    ("edits", "expected"),
    [
        # two columns wrong: the first column's problem is named, whatever the rows
        ([(9, "T49", "NaN"), (20, "T1", "295.4")], "temperatures.csv:20: column T1: 295.4 degC is outside"),
        ([(20, "T2", "inf"), (9, "T49", "-80")], "temperatures.csv:20: column T2: inf is not a finite number"),
        # one column wrong twice: a written NaN is named before an earlier value out of range
        ([(20, "T2", "295.4"), (25, "T2", "nan")], "temperatures.csv:25: column T2: nan is not a finite number"),
        # the first of two values out of range, beside a missing reading (an empty cell) in the column
        ([(30, "T2", "-61"), (12, "T2", "251"), (13, "T2", "")], "temperatures.csv:12: column T2: 251.0 degC"),
    ],
    ids=["first-column", "first-column-nonfinite", "nonfinite-before-range", "first-row"],
)
def test_the_first_temperature_problem_is_named(bundle_dir: Path, edits, expected: str) -> None:
    """Checked a chunk at a time in one pass, a temperature file still names the problem a check column by
    column, each column's non-finite cells before its range, meets first."""
    from tests.campaigns.conftest import _edit_cell

    for line, column, value in edits:
        _edit_cell(bundle_dir / "temperatures.csv", line, column, value)
    with pytest.raises(BundleError, match="^" + expected.replace(".", r"\.")):
        load_bundle(bundle_dir)


def _reorder_errors(path: Path, order: list[str]) -> None:
    """Rewrite errors.csv with its columns in ``order`` (the cells' text unchanged)."""
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    rows = [dict(zip(header, line.split(","), strict=True)) for line in lines[1:]]
    path.write_text("\n".join([",".join(order), *(",".join(r[c] for c in order) for r in rows)]) + "\n")


def test_errors_columns_in_any_order(bundle_dir: Path, tmp_path: Path) -> None:
    """docs/bundle.md: errors.csv holds exactly its columns in any order; the data and its identity are the same."""
    canonical = load_bundle(bundle_dir)
    _reorder_errors(bundle_dir / "errors.csv", ["value", "direction", "term", "axis", "position", "time_s"])
    reordered = load_bundle(bundle_dir)
    pd.testing.assert_frame_equal(reordered.errors, canonical.errors, check_exact=True)
    assert reordered.content_hash() == canonical.content_hash()
    # temperatures.csv and conditions.csv still start with time_s
    _reorder_errors(bundle_dir / "errors.csv", ["value", "direction", "term", "axis", "position"])
    with pytest.raises(BundleError, match="errors.csv:1: missing column 'time_s'"):
        load_bundle(bundle_dir)


def test_errors_long_before_the_first_scan_are_refused(tmp_path: Path, meta_factory, frames_factory) -> None:
    """Scans that start 3 h into the campaign, errors from its start: refused in one line, at errors.csv:2."""
    temps, cond, errors = frames_factory()
    temps = temps.assign(time_s=temps["time_s"] + 3 * 3600.0)
    meta = meta_factory()
    meta["stages"] = []
    path = write_bundle(tmp_path / "b", meta, temps, cond, errors)
    with pytest.raises(BundleError) as info:
        load_bundle(path)
    assert str(info.value) == (
        "errors.csv:2: time_s 0.0 is 3 h before the first temperature scan (time_s 10800.0): "
        "errors are measured while the temperatures are scanned"
    )


def test_errors_and_stages_within_the_slack_load(tmp_path: Path, meta_factory, frames_factory) -> None:
    """An error sample and a stage's end up to TIME_SLACK_S after the last scan are kept (a scan or two late)."""
    from driftlab.campaigns.bundle import TIME_SLACK_S

    temps, cond, errors = frames_factory()
    last = float(temps["time_s"].iloc[-1])
    errors.loc[errors.index[-1], "time_s"] = last + TIME_SLACK_S
    meta = meta_factory()
    meta["stages"][-1]["end_s"] = last + TIME_SLACK_S
    b = load_bundle(write_bundle(tmp_path / "b", meta, temps, cond, errors))
    assert b.errors["time_s"].iloc[-1] == last + TIME_SLACK_S
