"""The command line starts light (issue 24): `driftlab --help` and `--version` load none of the heavy libraries.

A module-set check in a fresh interpreter, not a timing: pandas, statsmodels, FastAPI, SQLAlchemy
(and scipy, numpy) are imported only by the commands that use them, when they run.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("pandas", "statsmodels", "fastapi", "sqlalchemy", "scipy", "numpy", "pydantic", "psycopg", "procrastinate")

PROBE = r"""
import contextlib, io, json, sys
from driftlab.cli import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        code = main(sys.argv[1:])
    except SystemExit as exc:  # argparse's --help and --version exit
        code = exc.code
print(json.dumps({"code": code, "printed": out.getvalue(), "modules": sorted(sys.modules)}))
"""


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["compensate", "--help"], ["worker", "--help"]])
def test_help_and_version_load_no_heavy_library(argv: list[str]) -> None:
    proc = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, check=True)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["code"] == 0 and result["printed"]
    loaded = {m.split(".")[0] for m in result["modules"]}
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_a_command_still_loads_what_it_uses() -> None:
    """The check above can fail: a command that runs does load its libraries."""
    code = "import sys; from driftlab.cli import main; main(['plan', 'check', '/nonexistent.yaml']); "
    code += "print('pydantic' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.stdout.strip().splitlines()[-1] == "True"
