"""Write docs/modules.md, the module map, from the code: `python docs/module_map.py [--check]`.

Each module of the package is listed under its layer, as the layers contract of
``[tool.importlinter]`` in pyproject.toml names them, with the first line of its docstring and the
layers it imports from. ``--check`` writes nothing and exits 1 when docs/modules.md is stale
(the test suite runs it, so the map cannot drift from the code).
"""

from __future__ import annotations

import ast
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "driftlab"
OUT = ROOT / "docs" / "modules.md"


def layers() -> list[list[str]]:
    """Return the layers of the layers contract, top first, each a list of top-level names."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    for c in cfg["tool"]["importlinter"]["contracts"]:
        if c["type"] == "layers":
            return [[p.strip() for p in layer.replace(":", "|").split("|")] for layer in c["layers"]]
    raise SystemExit("no layers contract in pyproject.toml")


def summary(path: Path) -> str:
    """Return the first line of a module's docstring (empty when it has none)."""
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
    return doc.strip().splitlines()[0].strip() if doc else ""


def imported_tops(path: Path) -> set[str]:
    """Return the top-level driftlab names a module imports (any depth, function-local included)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        out.update(n.split(".")[1] for n in names if n.startswith("driftlab.") and n.count(".") >= 1)
    return out


def modules_of(top: str) -> list[Path]:
    """Return the source files of a top-level module or package, in path order."""
    pkg = PKG / top
    if pkg.is_dir():
        return sorted(p for p in pkg.rglob("*.py") if "static" not in p.parts)
    return [PKG / f"{top}.py"]


def render() -> str:
    """Return the text of docs/modules.md."""
    lines = [
        "# Module map",
        "",
        "Generated from the code by `python docs/module_map.py`; `make test` fails when it is stale.",
        "Layers top first, as the import contracts of pyproject.toml enforce them (docs/architecture.md):",
        "a module imports only from layers below its own, and siblings in a layer (`|`) not from each other.",
        "`driftlab.testing` (test support) sits outside the layers: it may import anything, nothing imports it.",
        "",
    ]
    groups = [*layers(), ["testing"]]
    for i, layer in enumerate(groups):
        title = "test support (outside the layers)" if layer == ["testing"] else f"layer {i + 1}"
        lines += [f"## {title}: {' | '.join(layer)}", "", "| module | what it holds | imports from |", "|---|---|---|"]
        for top in layer:
            for path in modules_of(top):
                rel = path.relative_to(ROOT).with_suffix("")
                name = ".".join(rel.parts).removesuffix(".__init__")
                deps = ", ".join(sorted(imported_tops(path) - {top})) or "-"
                lines.append(f"| `{name}` | {summary(path).replace('|', '/')} | {deps} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    """Write the map, or with --check report whether it is current."""
    text = render()
    if "--check" in argv:
        if not OUT.exists() or OUT.read_text(encoding="utf-8") != text:
            print(f"{OUT.relative_to(ROOT)} is stale: run `python docs/module_map.py`", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    print(f"wrote {OUT.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
