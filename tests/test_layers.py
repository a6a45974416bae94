"""The import rules of the layers (issue 11): the store never reaches into the virtual machine.

``campaigns`` (plans, store, bundles, acquisition records) must not import ``daq.sim``; the
compensator reaches the virtual machine only through ``driftlab.daemon`` (the simulated rig and
the machining bench), never directly.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "driftlab"


def imported_modules(path: Path) -> set[str]:
    """Return every module a source file imports, at any depth (function-local imports included)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return out


def _offenders(files: list[Path], forbidden: str) -> list[str]:
    return sorted(
        f"{p.relative_to(PKG.parent)} imports {m}"
        for p in files
        for m in imported_modules(p)
        if m == forbidden or m.startswith(forbidden + ".")
    )


def test_campaigns_never_import_the_virtual_machine():
    files = sorted((PKG / "campaigns").rglob("*.py"))
    assert files
    assert _offenders(files, "driftlab.daq.sim") == []


def test_cutting_test_reaches_the_virtual_machine_only_through_the_daemon():
    path = PKG / "compensator" / "cutting_test.py"
    assert _offenders([path], "driftlab.daq.sim") == []
    assert "driftlab.daemon.machining" in imported_modules(path)


@pytest.mark.parametrize(
    "source,expected",
    [
        ("import driftlab.daq.sim.machine\n", "driftlab.daq.sim.machine"),
        ("def f():\n    from driftlab.daq.sim import truth\n", "driftlab.daq.sim.truth"),
    ],
)
def test_the_import_scan_sees_local_and_from_imports(tmp_path, source, expected):
    p = tmp_path / "m.py"
    p.write_text(source)
    assert expected in imported_modules(p)


#: the pure bottom of the package (docs/architecture.md): physics, the shared words and their units for people
BASE = {
    "driftlab.physics",
    "driftlab.vocabulary",
    "driftlab.labels",
    "driftlab.readings",
    "driftlab.jsonsafe",
    "driftlab.metrics",
    "driftlab.errors",
    "driftlab.yamlfile",  # a YAML file read for a one-line error: PyYAML and the file, nothing of driftlab
}


def _driftlab_imports(files: list[Path]) -> set[str]:
    """Return the driftlab top-level subpackages the files import (``driftlab.x``)."""
    return {".".join(m.split(".")[:2]) for p in files for m in imported_modules(p) if m.startswith("driftlab.")}


def test_metrology_imports_only_campaigns_models_and_the_base():
    files = sorted((PKG / "metrology").rglob("*.py"))
    assert files
    allowed = {"driftlab.metrology", "driftlab.campaigns", "driftlab.models", *BASE}
    assert _driftlab_imports(files) - allowed == set()


def test_compensator_exports_import_only_models_and_the_compensator():
    files = sorted((PKG / "compensator" / "exports").rglob("*.py"))
    assert files
    allowed = {"driftlab.compensator", "driftlab.models", *BASE}
    assert _driftlab_imports(files) - allowed == set()


@pytest.mark.parametrize("package", ["driftlab.metrology", "driftlab.compensator.exports"])
def test_nothing_low_imports_the_bridge(package):
    """Only the bridge itself and the commands reach the ISO reports, importers and controller exports."""
    own = PKG.joinpath(*package.split(".")[1:])
    files = [p for p in PKG.rglob("*.py") if own not in p.parents and PKG / "commands" not in p.parents]
    assert _offenders(files, package) == []
