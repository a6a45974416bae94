"""Fixtures of the campaign tests: small valid bundles made on the fly (never committed)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from driftlab.campaigns import ingest
from driftlab.campaigns.bundle import write_bundle
from driftlab.testing.smallbundle import small_frames, small_meta

FL_THERMAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "fl_thermal"


def make_bundle(
    path: Path,
    seed: int = 0,
    machine: str = "vmc-test-01",
    started_at: str = "2026-03-02T08:00:00Z",
    scans: int = 40,
    sweeps: int = 4,
) -> Path:
    """Write a small valid bundle to ``path`` and return it."""
    temps, cond, errors = small_frames(seed, scans, sweeps)
    return write_bundle(path, small_meta(machine, started_at), temps, cond, errors)


def error_rows_failing_at(row: int, boom: BaseException, written: list[int]):
    """Return ``ingest.error_rows`` that raises ``boom`` at its ``row``-th row (noting it in ``written``)."""
    real = ingest.error_rows

    def failing(campaign_id, errors, v2, day):
        for k, values in enumerate(real(campaign_id, errors, v2, day)):
            if k == row:
                written.append(k)
                raise boom
            yield values

    return failing


@pytest.fixture
def bundle_dir(tmp_path: Path) -> Path:
    """A small valid bundle directory."""
    return make_bundle(tmp_path / "bundle")


@pytest.fixture
def fl_thermal() -> Path:
    """The real FL_THERMAL bundle shipped in shared/data."""
    if not FL_THERMAL.is_dir():
        pytest.skip("shared/data/fl_thermal not present")
    return FL_THERMAL


@pytest.fixture
def bundle_factory(tmp_path: Path):
    """Return a function writing small valid bundles (keyword arguments as make_bundle) under tmp_path."""
    counter = iter(range(10_000))

    def factory(**kwargs) -> Path:
        return make_bundle(tmp_path / f"bundle{next(counter)}", **kwargs)

    return factory


@pytest.fixture
def frames_factory():
    """Return small_frames (temperatures, conditions, errors of a small campaign)."""
    return small_frames


@pytest.fixture
def meta_factory():
    """Return small_meta (a campaign.json document)."""
    return small_meta


# ----------------------------------------------------------------------------- corrupted bundles
# Every test taking a ``corruption`` argument runs once per entry: (id, file, mutation, message).
# Line numbers are as an editor shows them (header = line 1).


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


CORRUPTIONS = [
    ("missing-temperatures", "temperatures.csv", lambda p: p.unlink(), "temperatures.csv: file missing"),
    ("missing-campaign", "campaign.json", lambda p: p.unlink(), "campaign.json: file missing"),
    ("bad-json", "campaign.json", lambda p: _set_line(p, 3, ' "machine" {\n'), "campaign.json:3: invalid JSON"),
    (
        "wrong-format",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(format="driftlab-bundle/3")),
        "campaign.json:2: format: unsupported format 'driftlab-bundle/3'",
    ),
    (
        "v2-without-setups",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(format="driftlab-bundle/2")),
        "campaign.json:2: format: a bundle v2 needs setups",
    ),
    (
        "v1-with-setups",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(setups={"s": {"instrument": "laser", "terms": ["Z/dz"]}})),
        "setups: setups belong to 'driftlab-bundle/2'",
    ),
    (
        "extra-field",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(room_channel=["T49"])),
        "room_channel: Extra inputs are not permitted",
    ),
    (
        "naive-started-at",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(started_at="2026-03-02T08:00:00")),
        "started_at: Value error, started_at needs a time zone",
    ),
    # bundle time rules (issue 36): started_at as ISO 8601 text, errors and stages within the scans
    (
        "numeric-started-at",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(started_at=1772438400)),
        "started_at: Value error, must be an ISO 8601 date and time with its zone, e.g. 2026-03-02T08:00:00Z, "
        "not 1772438400",
    ),
    (
        "digits-started-at",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(started_at="1772438400")),
        "started_at: Value error, must be an ISO 8601 date and time with its zone",
    ),
    (
        "date-only-started-at",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(started_at="2026-03-02")),
        "started_at: Value error, must be an ISO 8601 date and time with its zone",
    ),
    (
        "errors-58-days-after-the-scans",
        "errors.csv",
        lambda p: _edit_cell(p, 121, "time_s", "5011200"),
        "errors.csv:121: time_s 5011200.0 is 58 days after the last temperature scan (time_s 1170.0)",
    ),
    (
        "stage-ends-years-after-the-scans",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["stages"][1].update(end_s=94608000.0)),
        "stages[1].end_s: 94608000.0 s is 1095 days after the last temperature scan (time_s 1170.0)",
    ),
    (
        "room-channel-unknown",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(room_channels=["T49", "T77"])),
        "room_channels[1]: room channel 'T77' is not in channels",
    ),
    (
        "model-channel-unknown",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["model_channels"].update(Z=["T1", "T8"])),
        "model_channels.Z[1]: model channel 'T8' is not in channels",
    ),
    (
        "stage-ends-before-start",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["stages"][1].update(end_s=500)),
        "stages[1].end_s: stage 'cool' ends (500.0) before it starts (600.0)",
    ),
    (
        "stages-overlap",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["stages"][1].update(start_s=300)),
        "stages[1].start_s: stage 'cool' starts at 300.0, before the previous stage ends",
    ),
    (
        "stage-bad-axis",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["stages"][0].update(axis="W")),
        "stages[0].axis: Input should be",
    ),
    (
        "unknown-term",
        "errors.csv",
        lambda p: _edit_cell(p, 7, "term", "dq"),
        "errors.csv:7: column term: 'dq' is not one of alpha beta gamma dx dy dz",
    ),
    (
        "unknown-axis",
        "errors.csv",
        lambda p: _edit_cell(p, 4, "axis", "Q"),
        "errors.csv:4: column axis: 'Q' is not one of X Y Z A B",
    ),
    (
        "direction-zero",
        "errors.csv",
        lambda p: _edit_cell(p, 9, "direction", "0"),
        "errors.csv:9: column direction: '0' is not +1 or -1",
    ),
    (
        "errors-time-backwards",
        "errors.csv",
        lambda p: _swap_rows(p, 5, 30),
        "errors.csv:6: time_s 10.0 is before the previous row's 90.0",
    ),
    (
        "temperatures-not-monotonic",
        "temperatures.csv",
        lambda p: _swap_rows(p, 10, 11),
        "temperatures.csv:11: time_s 240.0 is not after the previous row's 270.0",
    ),
    (
        "temperatures-repeated-time",
        "temperatures.csv",
        lambda p: _edit_cell(p, 7, "time_s", "120.0"),
        "temperatures.csv:7: time_s 120.0 is not after",
    ),
    (
        "text-in-number",
        "temperatures.csv",
        lambda p: _edit_cell(p, 12, "T2", "hot"),
        "temperatures.csv:12: column T2: 'hot' is not a number",
    ),
    (
        "channel-not-in-map",
        "temperatures.csv",
        _extra_channel_column,
        "temperatures.csv:1: column 'T99' is not a channel of campaign.json",
    ),
    (
        "channel-without-column",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["channels"].update(T7={"location": "x", "structure": "y"})),
        "temperatures.csv:1: channel 'T7' of campaign.json has no column",
    ),
    (
        "truncated-last-line",
        "temperatures.csv",
        _truncate_last,
        "temperatures.csv:41: expected 5 fields, found 4 (truncated line?)",
    ),
    ("duplicate-header", "temperatures.csv", _duplicate_header, "temperatures.csv:2: repeated header line"),
    ("duplicate-column", "temperatures.csv", _duplicate_column, "temperatures.csv:1: duplicate column 'T1'"),
    ("empty-errors-file", "errors.csv", lambda p: p.write_text(""), "errors.csv:1: empty file"),
    (
        "errors-header-only",
        "errors.csv",
        lambda p: p.write_text("time_s,axis,term,position,direction,value\n"),
        "errors.csv:2: no error samples",
    ),
    (
        "nan-temperature",
        "temperatures.csv",
        lambda p: _edit_cell(p, 8, "T49", "NaN"),
        "temperatures.csv:8: column T49: nan is not a finite number",
    ),
    (
        "inf-error-value",
        "errors.csv",
        lambda p: _edit_cell(p, 12, "value", "inf"),
        "errors.csv:12: column value: inf is not a finite number",
    ),
    (
        "missing-error-value",
        "errors.csv",
        lambda p: _edit_cell(p, 13, "value", ""),
        "errors.csv:13: column value: missing value",
    ),
    (
        "kelvin",
        "temperatures.csv",
        lambda p: _edit_cell(p, 20, "T1", "295.4"),
        "temperatures.csv:20: column T1: 295.4 degC is outside",
    ),
    (
        "micrometres",
        "errors.csv",
        lambda p: _edit_cell(p, 15, "value", "12.5"),
        "errors.csv:15: column value: 12.5 mm is implausibly large",
    ),
    ("duplicate-reading", "errors.csv", lambda p: _set_line(p, 3, _lines(p)[1]), "errors.csv:3: duplicate reading"),
    ("blank-line", "temperatures.csv", lambda p: _set_line(p, 15, "\n"), "temperatures.csv:15: empty line"),
    (
        "conditions-unknown-column",
        "conditions.csv",
        lambda p: p.write_text(p.read_text().replace("feed_mm_min", "feed_ipm", 1)),
        "conditions.csv:1: unknown column 'feed_ipm'",
    ),
    (
        "conditions-negative-rpm",
        "conditions.csv",
        lambda p: _edit_cell(p, 5, "spindle_rpm", "-100"),
        "conditions.csv:5: column spindle_rpm: -100.0 is negative",
    ),
    (
        "errors-missing-column",
        "errors.csv",
        lambda p: p.write_text(p.read_text().replace("direction", "dir", 1)),
        "errors.csv:1: unknown column 'dir'",
    ),
]


# ----------------------------------------------------------------------------- hostile bundles (issue 13)


def _replace(path: Path, old: str, new: str) -> None:
    text = path.read_text(encoding="utf-8")
    assert old in text, old
    path.write_text(text.replace(old, new, 1), encoding="utf-8")


def _replace_bytes(path: Path, lineno: int, column: str, value: bytes) -> None:
    lines = path.read_bytes().split(b"\n")
    header = lines[0].split(b",")
    fields = lines[lineno - 1].split(b",")
    fields[header.index(column.encode())] = value
    lines[lineno - 1] = b",".join(fields)
    path.write_bytes(b"\n".join(lines))


def _into_dir(path: Path) -> None:
    path.unlink()
    path.mkdir()


def _into_fifo(path: Path) -> None:
    import os

    path.unlink()
    os.mkfifo(path)


def _symlink_loop(path: Path) -> None:
    path.unlink()
    path.symlink_to(path.name)  # a link to itself: ELOOP on open, even for root


def _dangling(path: Path) -> None:
    path.unlink()
    path.symlink_to("nowhere.csv")


def _sparse(size: int):
    def mutate(path: Path) -> None:
        path.unlink()
        with path.open("wb") as fh:
            fh.truncate(size)  # sparse: no disk used, reads as NUL bytes

    return mutate


def _sparse_tail(path: Path, size: int) -> None:
    with path.open("r+b") as fh:
        fh.truncate(path.stat().st_size + size)  # valid rows, then a run of NUL bytes without a line break


def _drop_final_break(path: Path) -> None:
    text = path.read_text()
    path.write_text(text.rstrip("\n")[:-1])  # cut inside the last value: the row still has every field


def _append_column(path: Path, lineno: int, value: str) -> None:
    lines = _lines(path)
    lines[lineno - 1] = lines[lineno - 1].rstrip("\n") + "," + value + "\n"
    path.write_text("".join(lines))


def _with_header(path: Path, header: str) -> None:
    lines = _lines(path)
    lines[0] = header
    path.write_text("".join(lines))


HOSTILE = [
    # campaign.json: what json.loads would crash on or silently accept
    (
        "json-deep-nesting",
        "campaign.json",
        lambda p: p.write_text("[" * 100_000 + "]" * 100_000),
        "campaign.json:1: column 33: nesting deeper than 32 levels",
    ),
    (
        "json-huge-integer",
        "campaign.json",
        lambda p: _replace(p, "8000.0", "1" * 5000),
        "campaign.json:46: column 19: number of 5000 characters (at most 40)",
    ),
    (
        "json-long-fraction",
        "campaign.json",
        lambda p: _replace(p, "0.0025", "0." + "0" * 60 + "1"),
        "campaign.json:6: column 20: number of 63 characters",
    ),
    (
        "json-nan",
        "campaign.json",
        lambda p: _replace(p, "5e-07", "NaN"),
        "campaign.json:61: column 16: NaN is not a finite number",
    ),
    (
        "json-infinity",
        "campaign.json",
        lambda p: _replace(p, "0.0005", "-Infinity"),
        "campaign.json:60: column 16: -Infinity is not a finite number",
    ),
    (
        "json-duplicate-key",
        "campaign.json",
        lambda p: _replace(p, '"started_at"', '"format": "x",\n "started_at"'),
        "campaign.json:9: column 2: key 'format' appears twice in one object",
    ),
    (
        "json-nul-in-string",
        "campaign.json",
        lambda p: _replace(p, "test VMC", "test\\u0000VMC"),
        "campaign.json:5: machine.name: control character or lone surrogate in a string",
    ),
    (
        "json-lone-surrogate",
        "campaign.json",
        lambda p: _replace(p, "spindle nose", "spindle \\ud800nose"),
        "campaign.json:12: channels.T1.location: control character or lone surrogate in a string",
    ),
    (
        "json-bad-utf8",
        "campaign.json",
        lambda p: p.write_bytes(p.read_bytes().replace(b"floor", b"fl\xffor")),
        "campaign.json:24: column 19: not UTF-8 text",
    ),
    (
        "json-bom",
        "campaign.json",
        lambda p: p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes()),
        "campaign.json:1: invalid JSON: Unexpected UTF-8 BOM",
    ),
    (
        "json-top-level-list",
        "campaign.json",
        lambda p: p.write_text("[]\n"),
        "campaign.json:1: (top level): Input should be a valid dictionary",
    ),
    (
        "json-too-large",
        "campaign.json",
        lambda p: p.write_text(p.read_text() + " " * (1 << 20)),
        "campaign.json: 1049554 bytes, more than the limit of 1048576 bytes",
    ),
    ("json-is-directory", "campaign.json", _into_dir, "campaign.json: not a regular file (a directory)"),
    ("json-is-fifo", "campaign.json", _into_fifo, "campaign.json: not a regular file (a FIFO)"),
    (
        "machine-id-slash",
        "campaign.json",
        lambda p: _replace(p, "vmc-test-01", "vmc/test 01"),
        "campaign.json:4: machine.id: String should match pattern",
    ),
    (
        "machine-id-dots",
        "campaign.json",
        lambda p: _replace(p, '"vmc-test-01"', '".."'),
        "campaign.json:4: machine.id: String should match pattern",
    ),
    (
        "machine-id-too-long",
        "campaign.json",
        lambda p: _replace(p, "vmc-test-01", "m" * 65),
        "campaign.json:4: machine.id: String should have at most 64 characters",
    ),
    (
        "machine-name-too-long",
        "campaign.json",
        lambda p: _replace(p, "test VMC", "v" * 201),
        "campaign.json:5: machine.name: String should have at most 200 characters",
    ),
    (
        "channel-name-leading-underscore",
        "campaign.json",
        lambda p: _replace(p, '"T1": {', '"_T1": {'),
        "campaign.json:11: channels._T1: channel names start with a letter or digit",
    ),
    (
        "started-at-after-2262",
        "campaign.json",
        lambda p: _replace(p, "2026-03-02", "2300-03-02"),
        "campaign.json:9: started_at: Value error, started_at 2300-03-02T08:00:00+00:00 is outside 1970..2199",
    ),
    (
        "started-at-before-1970",
        "campaign.json",
        lambda p: _replace(p, "2026-03-02", "1900-03-02"),
        "campaign.json:9: started_at: Value error, started_at 1900-03-02T08:00:00+00:00 is outside 1970..2199",
    ),
    (
        "stage-end-1e300",
        "campaign.json",
        lambda p: _replace(p, "1200.0", "1e300"),
        "campaign.json:52: stages[1].end_s: Input should be less than or equal to 1000000000",
    ),
    (
        "noise-negative",
        "campaign.json",
        lambda p: _replace(p, "0.0005", "-0.0005"),
        "campaign.json:60: noise.length_mm: Input should be greater than or equal to 0",
    ),
    (
        "resolution-zero",
        "campaign.json",
        lambda p: _replace(p, "0.0025", "0"),
        "campaign.json:6: machine.resolution_mm: Input should be greater than 0",
    ),
    (
        "room-channel-twice",
        "campaign.json",
        lambda p: _replace(p, '"T50"\n', '"T49"\n'),
        "campaign.json:30: room_channels[1]: room channel 'T49' listed twice",
    ),
    (
        "stage-name-twice",
        "campaign.json",
        lambda p: _replace(p, '"cool"', '"spindle-8k"'),
        "campaign.json:50: stages[1].name: stage name 'spindle-8k' used twice",
    ),
    (
        "no-channels",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d.update(channels={})),
        "channels: Dictionary should have at least 1 item",
    ),
    # files that are not regular, cannot be read, or are too large
    (
        "temperatures-2gb-sparse",
        "temperatures.csv",
        _sparse(2 << 30),
        "temperatures.csv: 2147483648 bytes, more than the limit of 536870912 bytes",
    ),
    ("errors-sparse-no-newline", "errors.csv", _sparse(3 << 20), "errors.csv:1: line longer than 1048576 bytes"),
    (
        "temperatures-sparse-tail",
        "temperatures.csv",
        lambda p: _sparse_tail(p, 64 << 20),
        "temperatures.csv:42: line longer than 1048576 bytes",
    ),
    ("temperatures-is-fifo", "temperatures.csv", _into_fifo, "temperatures.csv: not a regular file (a FIFO)"),
    ("conditions-is-directory", "conditions.csv", _into_dir, "conditions.csv: not a regular file (a directory)"),
    ("conditions-is-fifo", "conditions.csv", _into_fifo, "conditions.csv: not a regular file (a FIFO)"),
    ("errors-is-directory", "errors.csv", _into_dir, "errors.csv: not a regular file (a directory)"),
    (
        "temperatures-symlink-loop",
        "temperatures.csv",
        _symlink_loop,
        "temperatures.csv: cannot read: Too many levels of symbolic links",
    ),
    ("conditions-dangling-link", "conditions.csv", _dangling, "conditions.csv: a link to a file that does not exist"),
    # CSV rows: exact row and column
    (
        "temperatures-truncated-value",
        "temperatures.csv",
        _drop_final_break,
        "temperatures.csv:41: the last line has no line break (a truncated file?)",
    ),
    (
        "errors-truncated-value",
        "errors.csv",
        lambda p: (_edit_cell(p, 121, "value", "0.00012"), _drop_final_break(p)),
        "errors.csv:121: the last line has no line break (a truncated file?)",
    ),
    (
        "temperatures-bad-utf8",
        "temperatures.csv",
        lambda p: _replace_bytes(p, 12, "T2", b"2\xff.5"),
        "temperatures.csv:12: column T2: not UTF-8 text (byte",
    ),
    (
        "errors-bad-utf8-axis",
        "errors.csv",
        lambda p: _replace_bytes(p, 5, "axis", b"\xc3("),
        "errors.csv:5: column axis: not UTF-8 text",
    ),
    (
        "header-bad-utf8",
        "conditions.csv",
        lambda p: p.write_bytes(p.read_bytes().replace(b"feed", b"f\xe9ed", 1)),
        "conditions.csv:1: column 3: not UTF-8 text",
    ),
    (
        "fullwidth-digits",
        "temperatures.csv",
        lambda p: _edit_cell(p, 9, "T1", "\uff12\uff10.5"),
        "temperatures.csv:9: column T1: '\uff12\uff10.5' is not a number",
    ),
    (
        "field-over-csv-limit",
        "temperatures.csv",
        lambda p: _edit_cell(p, 6, "T1", "x" * 200_000),
        "temperatures.csv:6: column T1: 'xxxxxxxxx",
    ),
    (
        "csv-5000-digit-reading",
        "temperatures.csv",
        lambda p: _edit_cell(p, 5, "T1", "9" * 5000),
        "temperatures.csv:5: column T1: inf is not a finite number",
    ),
    (
        "csv-5000-digit-time",
        "errors.csv",
        lambda p: _edit_cell(p, 5, "time_s", "9" * 5000),
        "errors.csv:5: time_s is not a finite number",
    ),
    (
        "text-cell-too-long",
        "errors.csv",
        lambda p: _edit_cell(p, 4, "axis", "X" * 300),
        "errors.csv:4: column axis: a cell of 300 characters (at most 256)",
    ),
    (
        "header-line-too-long",
        "temperatures.csv",
        lambda p: _with_header(p, "time_s" + ",T" * 600_000 + "\n"),
        "temperatures.csv:1: line longer than 1048576 bytes",
    ),
    (
        "data-line-too-long",
        "errors.csv",
        lambda p: _edit_cell(p, 7, "value", "y" * (2 << 20)),
        "errors.csv:7: line longer than 1048576 bytes",
    ),
    (
        "column-name-too-long",
        "temperatures.csv",
        lambda p: _extra_named_column(p, "T" * 100),
        "temperatures.csv:1: column 6: a column name of 100 characters (at most 64)",
    ),
    (
        "header-bom",
        "temperatures.csv",
        lambda p: p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes()),
        "temperatures.csv:1: starts with a byte-order mark",
    ),
    (
        "header-empty-name",
        "conditions.csv",
        lambda p: _replace(p, ",feed_mm_min,", ",,"),
        "conditions.csv:1: column 3: empty column name in header",
    ),
    (
        "header-first-not-time",
        "conditions.csv",
        lambda p: _replace(p, "time_s,", "t,"),
        "conditions.csv:1: first column must be time_s, found 't'",
    ),
    (
        "nul-bytes-in-cell",
        "temperatures.csv",
        lambda p: _edit_cell(p, 14, "T49", "2\0\0"),
        "temperatures.csv:14: column T49: '2\\x00\\x00' is not a number",
    ),
    ("unbalanced-quote", "errors.csv", lambda p: _edit_cell(p, 8, "term", '"dx'), "errors.csv:8: "),
    (
        "too-many-fields",
        "errors.csv",
        lambda p: _append_column(p, 10, "1"),
        "errors.csv:10: expected 6 fields, found 7",
    ),
    (
        "temperatures-time-1e300",
        "temperatures.csv",
        lambda p: _edit_cell(p, 41, "time_s", "1e300"),
        "temperatures.csv:41: time_s 1e+300 is beyond 1e+09 s",
    ),
    (
        "errors-time-1e300",
        "errors.csv",
        lambda p: _edit_cell(p, 121, "time_s", "1e300"),
        "errors.csv:121: time_s 1e+300 is beyond 1e+09 s",
    ),
    (
        "conditions-time-1e300",
        "conditions.csv",
        lambda p: _edit_cell(p, 41, "time_s", "1e300"),
        "conditions.csv:41: time_s 1e+300 is beyond",
    ),
    (
        "temperatures-time-negative",
        "temperatures.csv",
        lambda p: _edit_cell(p, 2, "time_s", "-1"),
        "temperatures.csv:2: time_s -1.0 is negative",
    ),
    (
        "errors-position-1e300",
        "errors.csv",
        lambda p: _edit_cell(p, 11, "position", "1e300"),
        "errors.csv:11: column position: 1e+300 mm is beyond 100000 mm",
    ),
    (
        "conditions-x-1e12",
        "conditions.csv",
        lambda p: _edit_cell(p, 3, "x", "1e12"),
        "conditions.csv:3: column x: 1000000000000.0 mm is beyond 100000 mm",
    ),
    (
        "conditions-a-degrees",
        "conditions.csv",
        lambda p: _edit_cell(p, 4, "a", "1000"),
        "conditions.csv:4: column a: 1000.0 is not a rotary position in degrees",
    ),
    (
        "rotation-too-large",
        "errors.csv",
        lambda p: _edit_cell(p, 4, "value", "0.1"),
        "errors.csv:4: column value: 0.1 rad is implausibly large",
    ),
    (
        "direction-fraction",
        "errors.csv",
        lambda p: _edit_cell(p, 6, "direction", "+1.5"),
        "errors.csv:6: column direction: '+1.5' is not +1 or -1",
    ),
    ("missing-axis-cell", "errors.csv", lambda p: _edit_cell(p, 3, "axis", ""), "errors.csv:3: column axis: missing"),
    (
        "temperatures-header-only",
        "temperatures.csv",
        lambda p: p.write_text(_lines(p)[0]),
        "temperatures.csv:2: no readings",
    ),
    ("temperatures-empty-file", "temperatures.csv", lambda p: p.write_text(""), "temperatures.csv:1: empty file"),
    (
        "conditions-negative-feed",
        "conditions.csv",
        lambda p: _edit_cell(p, 7, "feed_mm_min", "-5"),
        "conditions.csv:7: column feed_mm_min: -5.0 is negative",
    ),
]


def _extra_named_column(path: Path, name: str) -> None:
    lines = _lines(path)
    out = [lines[0].rstrip("\n") + f",{name}\n"] + [line.rstrip("\n") + ",20.5\n" for line in lines[1:]]
    path.write_text("".join(out))


def _link_out(target: str):
    """Replace the file by a link to ``target`` (relative to the bundle, or absolute)."""

    def mutate(path: Path) -> None:
        if target.startswith("../"):  # a valid copy outside the bundle: following it would succeed
            (path.parent / target).write_bytes(path.read_bytes())
        path.unlink()
        path.symlink_to(target)

    return mutate


def _link_inside(path: Path) -> None:
    """Move the file to a sub-directory of the bundle and link to it (allowed: the link stays inside)."""
    (path.parent / "data").mkdir()
    moved = path.parent / "data" / path.name
    path.rename(moved)
    path.symlink_to(Path("data") / path.name)


# issue 24: campaign.json numbers are strict, and links never lead out of the bundle (nor echo a foreign file)
STRICT_AND_LINKS = [
    (
        "spindle-rpm-boolean",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["stages"][0].update(spindle_rpm=True)),
        "stages[0].spindle_rpm: Input should be a valid number",
    ),
    (
        "resolution-as-string",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["machine"].update(resolution_mm="0.0025")),
        "machine.resolution_mm: Input should be a valid number",
    ),
    (
        "stage-end-as-string",
        "campaign.json",
        lambda p: _edit_json(p, lambda d: d["stages"][1].update(end_s="1200")),
        "stages[1].end_s: Input should be a valid number",
    ),
    (
        "campaign-json-links-out",
        "campaign.json",
        _link_out("../x.json"),
        "campaign.json: a link that leads out of the bundle; refused",
    ),
    (
        "temperatures-links-to-etc-passwd",
        "temperatures.csv",
        _link_out("/etc/passwd"),
        "temperatures.csv: a link that leads out of the bundle; refused",
    ),
    ("errors-links-to-etc-hostname", "errors.csv", _link_out("/etc/hostname"), "errors.csv: a link that leads out"),
]

CORRUPTIONS += HOSTILE
CORRUPTIONS += STRICT_AND_LINKS


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Parametrise tests that take ``corruption`` over every corrupted-bundle case."""
    if "corruption" in metafunc.fixturenames:
        metafunc.parametrize("corruption", CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS])
