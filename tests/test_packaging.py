"""A non-editable install works from any directory: the wheel carries migrations and examples.

The wheel is built from the checkout (``pip wheel . --no-deps``) and installed with ``pip install
--no-deps --target T`` (its dependencies are those of the project's venv, which this interpreter
already has). It then runs with ``PYTHONPATH=T`` from a directory outside the checkout, so the
installed copy (not the editable one, whose finder comes after the path entries) is imported; the
test checks that it is. Then ``python -m driftlab db upgrade`` on a fresh SQLite file and a short
``driftlab demo`` (its plan and scenario found in the package) must work.
"""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Return the --target directory driftlab's wheel was installed into."""
    wheels = tmp_path_factory.mktemp("wheels")
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(wheels)],
        capture_output=True,
        text=True,
        cwd=wheels,
    )
    if build.returncode != 0:
        pytest.fail(f"pip wheel failed: {build.stderr[-2000:]}")
    [wheel] = wheels.glob("driftlab-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for expected in (
        "driftlab/migrations/env.py",
        "driftlab/migrations/script.py.mako",
        "driftlab/migrations/versions/0001_campaign_store_initial_schema.py",
        "driftlab/migrations/sql/procrastinate-3.10.0.sql",  # the job queue's schema (0006)
        "driftlab/examples/plans/demo-z.yaml",
        "driftlab/examples/scenarios/demo-drift.yaml",
        "driftlab/examples/programs/five_axis_finish.nc",
        "driftlab/__main__.py",
        "driftlab/api/static/vendor/swagger-ui/swagger-ui-bundle.js",
    ):
        assert expected in names, expected
    target = tmp_path_factory.mktemp("site")
    inst = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
        capture_output=True,
        text=True,
        cwd=wheels,
    )
    if inst.returncode != 0:
        pytest.fail(f"pip install failed: {inst.stderr[-2000:]}")
    return target


def _run(target: Path, cwd: Path, *args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(target), "DRIFTLAB_DB_URL": ""}
    env.pop("DRIFTLAB_API_TOKEN", None)
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout)


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_checkout(installed: Path, tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = _run(
        installed,
        elsewhere,
        "-c",
        "import driftlab, driftlab.resources as r; "
        "print(driftlab.__file__); print(r.migrations_dir()); print(r.examples_dir())",
    )
    assert where.returncode == 0, where.stderr
    for line in where.stdout.split():
        assert line.startswith(str(installed)), where.stdout  # the installed copy, not the checkout
    version = _run(installed, elsewhere, "-m", "driftlab", "--version")
    assert version.returncode == 0 and version.stdout.startswith("driftlab "), version.stderr
    db = f"sqlite:///{tmp_path / 'store.sqlite'}"
    up = _run(installed, elsewhere, "-m", "driftlab", "db", "upgrade", "--db", db)
    assert up.returncode == 0, up.stderr
    cur = _run(installed, elsewhere, "-m", "driftlab", "db", "current", "--db", db)
    assert cur.returncode == 0 and cur.stdout.strip(), cur.stderr
    plan = _run(
        installed,
        elsewhere,
        "-c",
        "import driftlab.resources as r, sys; "
        "from driftlab.cli import main; sys.exit(main(['plan', 'check', str(r.examples_dir() / 'plans' / "
        "'demo-z.yaml')]))",
    )
    assert plan.returncode == 0, plan.stderr


@pytest.mark.slow
def test_demo_runs_from_the_wheel_outside_the_checkout(installed: Path, tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    demo = _run(installed, elsewhere, "-m", "driftlab", "demo", "--out", "demo-out", "--passes", "120", timeout=900)
    assert demo.returncode == 0, demo.stderr[-3000:]
    assert (elsewhere / "demo-out" / "demo-report.json").is_file()
