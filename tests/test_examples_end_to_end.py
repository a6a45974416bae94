"""The shop's task on the shipped files alone (issue 35.1): simulate, import, fit, compensate every program.

`sim campaign` writes the virtual machine's travel into campaign.json, the fit carries it into the
model's envelope, and each program in examples/programs lies inside it: no machine file is needed.
The shipped machine file states the same travel, and a model without travel is refused with a line
that says what is missing.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from driftlab.cli import main
from driftlab.daq.sim.truth import AXIS_RANGE

#: the checkout's examples (an editable install elsewhere would point importlib.resources at its own)
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PROGRAMS = sorted((EXAMPLES / "programs").glob("*.nc"))
SCENARIO = """\
name: e2e
seed: 4
hours: 8
scan_interval_s: 120
sweep_interval_s: 900
hidden: []
"""


def test_the_shipped_machine_file_states_the_virtual_machines_travel() -> None:
    body = yaml.safe_load((EXAMPLES / "machines" / "virtual-machine.yaml").read_text())
    assert {a: tuple(v) for a, v in body["travel"].items()} == dict(AXIS_RANGE)
    assert set(body["max_correction"]) == set(AXIS_RANGE)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """Simulate, import and fit through the command line; return (model document, temperatures, db URL)."""
    tmp = tmp_path_factory.mktemp("e2e")
    scen = tmp / "e2e.yaml"
    scen.write_text(SCENARIO)
    db = f"sqlite:///{tmp / 's.sqlite'}"
    assert main(["sim", "campaign", "--scenario", str(scen), "--out", str(tmp / "bundle")]) == 0
    meta = json.loads((tmp / "bundle" / "campaign.json").read_text())
    assert meta["machine"]["travel"]["Z"] == [-254.0, 0.0]
    assert main(["import", str(tmp / "bundle"), "--db", db]) == 0
    assert main(["fit", "--campaign", "1", "--db", db, "--no-network"]) == 0
    return tmp, tmp / "bundle" / "temperatures.csv", db


def test_every_shipped_program_compensates_with_the_fitted_model_alone(
    fitted: tuple[Path, Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    tmp, temps, db = fitted
    capsys.readouterr()
    assert main(["models", "show", "--machine", "vmc-5ax-01", "1", "--json", "--db", db]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["envelope"]["travel"]["X"] == [0.0, 254.0]
    model = tmp / "model.json"
    model.write_text(json.dumps(doc))
    assert len(PROGRAMS) >= 2
    for program in PROGRAMS:
        out = tmp / program.name
        code = main(["compensate", str(program), "--model", str(model), "--temps", str(temps), "-o", str(out)])
        captured = capsys.readouterr()
        assert code == 0, (program.name, captured.err)
        assert out.exists() and out.stat().st_size > 0


def test_a_model_without_travel_is_refused_with_what_is_missing(
    fitted: tuple[Path, Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    tmp, temps, db = fitted
    capsys.readouterr()
    assert main(["models", "show", "--machine", "vmc-5ax-01", "1", "--json", "--db", db]) == 0
    doc = json.loads(capsys.readouterr().out)
    doc.pop("envelope")
    model = tmp / "bare.json"
    model.write_text(json.dumps(doc))
    out = tmp / "refused.nc"
    code = main(["compensate", str(PROGRAMS[0]), "--model", str(model), "--temps", str(temps), "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and not out.exists()
    assert "carries no machine travel (its campaigns state no machine.travel" in err[0]
    assert "fitted before the envelope" not in err[0]
    # the shipped machine file is the fix it names
    machine = EXAMPLES / "machines" / "virtual-machine.yaml"
    assert "examples/machines/virtual-machine.yaml" in err[0]
    args = ["compensate", str(PROGRAMS[0]), "--model", str(model), "--temps", str(temps), "-o", str(out)]
    assert main([*args, "--machine-file", str(machine)]) == 0
