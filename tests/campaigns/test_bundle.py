"""Bundle v1: the real bundle loads, writing round-trips bit-exactly, every corruption is named."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from driftlab.campaigns.bundle import BundleError, CampaignMeta, load_bundle, write_bundle
from driftlab.errors import ValidationError


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines(keepends=True)


def _set_line(path: Path, lineno: int, text: str) -> None:
    lines = _lines(path)
    lines[lineno - 1] = text
    path.write_text("".join(lines))


def _edit_cell(path: Path, lineno: int, column: str, value: str) -> None:
    lines = _lines(path)
    header = lines[0].rstrip("\n").split(",")
    fields = lines[lineno - 1].rstrip("\n").split(",")
    fields[header.index(column)] = value
    lines[lineno - 1] = ",".join(fields) + "\n"
    path.write_text("".join(lines))


def _edit_json(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc, indent=1) + "\n")


def _truncate_last(path: Path) -> None:
    text = path.read_text()
    path.write_text(text[: text.rstrip("\n").rfind(",") - 3])


def _duplicate_header(path: Path) -> None:
    lines = _lines(path)
    path.write_text("".join([lines[0], lines[0], *lines[1:]]))


def _duplicate_column(path: Path) -> None:
    lines = _lines(path)
    out = []
    for line in lines:
        fields = line.rstrip("\n").split(",")
        out.append(",".join([*fields, fields[1]]) + "\n")
    path.write_text("".join(out))


def _swap_rows(path: Path, a: int, b: int) -> None:
    lines = _lines(path)
    lines[a - 1], lines[b - 1] = lines[b - 1], lines[a - 1]
    path.write_text("".join(lines))


def _extra_channel_column(path: Path) -> None:
    lines = _lines(path)
    out = [lines[0].rstrip("\n") + ",T99\n"] + [line.rstrip("\n") + ",20.5\n" for line in lines[1:]]
    path.write_text("".join(out))


# (id, file, mutation, expected message fragment). Line numbers: header is line 1.
CORRUPTIONS = [
    ("missing-temperatures", "temperatures.csv", lambda p: p.unlink(), "temperatures.csv: file missing"),
    ("missing-campaign", "campaign.json", lambda p: p.unlink(), "campaign.json: file missing"),
    ("bad-json", "campaign.json", lambda p: _set_line(p, 3, ' "machine" {\n'), "campaign.json:3: invalid JSON"),
    ("wrong-format", "campaign.json", lambda p: _edit_json(p, lambda d: d.update(format="driftlab-bundle/2")),
     "campaign.json:2: format: unsupported format 'driftlab-bundle/2'"),
    ("extra-field", "campaign.json", lambda p: _edit_json(p, lambda d: d.update(room_channel=["T49"])),
     "room_channel: Extra inputs are not permitted"),
    ("naive-started-at", "campaign.json",
     lambda p: _edit_json(p, lambda d: d.update(started_at="2026-03-02T08:00:00")),
     "started_at: Value error, started_at needs a time zone"),
    ("room-channel-unknown", "campaign.json",
     lambda p: _edit_json(p, lambda d: d.update(room_channels=["T49", "T77"])),
     "room_channels[1]: room channel 'T77' is not in channels"),
    ("model-channel-unknown", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["model_channels"].update(Z=["T1", "T8"])),
     "model_channels.Z[1]: model channel 'T8' is not in channels"),
    ("stage-ends-before-start", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["stages"][1].update(end_s=500)),
     "stages[1].end_s: stage 'cool' ends (500.0) before it starts (600.0)"),
    ("stages-overlap", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["stages"][1].update(start_s=300)),
     "stages[1].start_s: stage 'cool' starts at 300.0, before the previous stage ends"),
    ("stage-bad-axis", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["stages"][0].update(axis="W")), "stages[0].axis: Input should be"),
    ("unknown-term", "errors.csv", lambda p: _edit_cell(p, 7, "term", "dq"),
     "errors.csv:7: column term: 'dq' is not one of alpha beta gamma dx dy dz"),
    ("unknown-axis", "errors.csv", lambda p: _edit_cell(p, 4, "axis", "Q"),
     "errors.csv:4: column axis: 'Q' is not one of X Y Z A B"),
    ("direction-zero", "errors.csv", lambda p: _edit_cell(p, 9, "direction", "0"),
     "errors.csv:9: column direction: '0' is not +1 or -1"),
    ("errors-time-backwards", "errors.csv", lambda p: _swap_rows(p, 5, 30),
     "errors.csv:6: time_s 10.0 is before the previous row's 90.0"),
    ("temperatures-not-monotonic", "temperatures.csv", lambda p: _swap_rows(p, 10, 11),
     "temperatures.csv:11: time_s 240.0 is not after the previous row's 270.0"),
    ("temperatures-repeated-time", "temperatures.csv", lambda p: _edit_cell(p, 7, "time_s", "120.0"),
     "temperatures.csv:7: time_s 120.0 is not after"),
    ("text-in-number", "temperatures.csv", lambda p: _edit_cell(p, 12, "T2", "hot"),
     "temperatures.csv:12: column T2: 'hot' is not a number"),
    ("channel-not-in-map", "temperatures.csv", _extra_channel_column,
     "temperatures.csv:1: column 'T99' is not a channel of campaign.json"),
    ("channel-without-column", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["channels"].update(T7={"location": "x", "structure": "y"})),
     "temperatures.csv:1: channel 'T7' of campaign.json has no column"),
    ("truncated-last-line", "temperatures.csv", _truncate_last,
     "temperatures.csv:41: expected 5 fields, found 4 (truncated line?)"),
    ("duplicate-header", "temperatures.csv", _duplicate_header, "temperatures.csv:2: repeated header line"),
    ("duplicate-column", "temperatures.csv", _duplicate_column, "temperatures.csv:1: duplicate column 'T1'"),
    ("empty-errors-file", "errors.csv", lambda p: p.write_text(""), "errors.csv:1: empty file"),
    ("errors-header-only", "errors.csv", lambda p: p.write_text("time_s,axis,term,position,direction,value\n"),
     "errors.csv:2: no error samples"),
    ("nan-temperature", "temperatures.csv", lambda p: _edit_cell(p, 8, "T49", "NaN"),
     "temperatures.csv:8: column T49: nan is not a finite number"),
    ("inf-error-value", "errors.csv", lambda p: _edit_cell(p, 12, "value", "inf"),
     "errors.csv:12: column value: inf is not a finite number"),
    ("missing-error-value", "errors.csv", lambda p: _edit_cell(p, 13, "value", ""),
     "errors.csv:13: column value: missing value"),
    ("kelvin", "temperatures.csv", lambda p: _edit_cell(p, 20, "T1", "295.4"),
     "temperatures.csv:20: column T1: 295.4 degC is outside"),
    ("micrometres", "errors.csv", lambda p: _edit_cell(p, 15, "value", "12.5"),
     "errors.csv:15: column value: 12.5 mm is implausibly large"),
    ("duplicate-reading", "errors.csv", lambda p: _set_line(p, 3, _lines(p)[1]),
     "errors.csv:3: duplicate reading"),
    ("blank-line", "temperatures.csv", lambda p: _set_line(p, 15, "\n"), "temperatures.csv:15: empty line"),
    ("conditions-unknown-column", "conditions.csv",
     lambda p: p.write_text(p.read_text().replace("feed_mm_min", "feed_ipm", 1)),
     "conditions.csv:1: unknown column 'feed_ipm'"),
    ("conditions-negative-rpm", "conditions.csv", lambda p: _edit_cell(p, 5, "spindle_rpm", "-100"),
     "conditions.csv:5: column spindle_rpm: -100.0 is negative"),
    ("errors-missing-column", "errors.csv",
     lambda p: p.write_text(p.read_text().replace("direction", "dir", 1)), "errors.csv:1: unknown column 'dir'"),
]


@pytest.mark.parametrize("case", CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS])
def test_corrupted_bundle_is_named(bundle_dir: Path, case) -> None:
    _, file, mutate, expected = case
    mutate(bundle_dir / file)
    with pytest.raises(BundleError) as info:
        load_bundle(bundle_dir)
    message = str(info.value)
    assert "\n" not in message
    assert expected in message
    assert isinstance(info.value, ValidationError)


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
    _edit_cell(path, 5, "T1", "21.5")
    assert load_bundle(bundle_dir).content_hash() != a.content_hash()


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    temps=st.lists(st.one_of(st.floats(-50, 240, allow_nan=False), st.just(math.nan)), min_size=6, max_size=60),
    values=st.lists(st.floats(-4.9, 4.9, allow_nan=False) | st.just(-0.0) | st.just(5e-324), min_size=1, max_size=20),
    positions=st.lists(finite.filter(lambda x: abs(x) < 1e300), min_size=1, max_size=20),
)
def test_floats_round_trip_bit_exactly(tmp_path_factory, meta_factory, temps, values, positions) -> None:
    n = len(temps) // 2
    times = np.cumsum(np.abs(np.asarray(temps[:n], dtype=float)) + 1e-3)
    times = np.nan_to_num(times, nan=1.0).cumsum()
    tf = pd.DataFrame({"time_s": times, "T1": temps[:n], "T2": temps[n : 2 * n], "T49": 20.0, "T50": math.nan})
    k = min(len(values), len(positions))
    ef = pd.DataFrame(
        {"time_s": np.arange(k) * 1.5, "axis": "X", "term": "dx", "position": positions[:k],
         "direction": [1 if i % 2 else -1 for i in range(k)], "value": values[:k]}
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
