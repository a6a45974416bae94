"""`driftlab plan advise`: the advised plan from a stored campaign, and one-line refusals of bad input."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from driftlab.campaigns.plan import load_plan
from driftlab.campaigns.store import connect
from driftlab.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_advisor import campaign  # noqa: E402  (the small world whose answer is known)


@pytest.fixture(scope="module")
def db(tmp_path_factory) -> str:
    url = f"sqlite:///{tmp_path_factory.mktemp('advise') / 'store.sqlite'}"
    with connect(url) as store:
        store.campaigns.import_bundle(campaign())
    return url


def test_advise_writes_a_plan_the_validator_accepts(db, tmp_path, capsys):
    out = tmp_path / "next.yaml"
    assert main(["plan", "advise", "--campaign", "1", "--hours", "4", "-o", str(out), "--json", "--db", db]) == 0
    report = json.loads(capsys.readouterr().out)
    plan = load_plan(out)  # the daemon's validator
    assert plan.total_s <= 4 * 3600 + 1e-6
    assert report["hours_used"] == pytest.approx(plan.total_s / 3600)
    assert report["stages"] and report["rms_after_um"] < report["rms_before_um"]
    assert [s.name for s in plan.stages][::2] == [r["stage"] for r in report["stages"]]


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--campaign", "99"], "no campaign 99"),
        (["--campaign", "1", "--hours", "0"], "--hours must be a positive"),
        (["--campaign", "1", "--hours", "-2"], "--hours must be a positive"),
        (["--campaign", "1", "--model", "7"], "model"),
    ],
)
def test_bad_input_is_one_line(db, tmp_path, capsys, argv, needle):
    out = tmp_path / "next.yaml"
    assert main(["plan", "advise", *argv, "-o", str(out), "--db", db]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("driftlab: error:") and needle in err
    assert not out.exists()
