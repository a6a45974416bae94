"""Swagger UI and ReDoc, vendored from their npm packages so that /docs and /redoc work with no network.

``static/vendor/VENDOR.json`` names each package, its version, the registry's integrity hash of its
tarball, and the sha256 of every file taken from it (licences included). ``verify()`` checks the
files against it; ``python -m driftlab.api.vendor refresh`` (``make vendor-docs``) fetches the
tarballs again with ``npm pack``, checks their integrity and copies the files in.
"""

from __future__ import annotations

import base64
import hashlib
import json
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import TypedDict

STATIC = Path(__file__).resolve().parent / "static"
VENDOR = STATIC / "vendor"
MANIFEST = VENDOR / "VENDOR.json"


class VendoredPackage(TypedDict):
    """One vendored npm package in VENDOR.json: version, licence, folder, tarball integrity, files' sha256."""

    version: str
    license: str
    dir: str
    integrity: str  # the registry's "sha512-<base64>" of the tarball
    files: dict[str, str]  # path in the package -> hex sha256 of the copy


class VendorManifest(TypedDict):
    """VENDOR.json: what it is, and the vendored packages by name."""

    about: str
    packages: dict[str, VendoredPackage]


def manifest() -> VendorManifest:
    """Return the vendoring manifest (package -> version, integrity, files with their sha256)."""
    return json.loads(MANIFEST.read_text(encoding="utf-8"))


def _sha256(path: Path) -> str:
    """Return the hex sha256 of a file."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def verify() -> list[str]:
    """Return the problems found (missing or changed files, a package without its licence); [] when intact."""
    problems = []
    for name, pkg in manifest()["packages"].items():
        if not any(Path(f).name.upper().startswith("LICENSE") for f in pkg["files"]):
            problems.append(f"{name}: no licence file vendored")
        for rel, want in pkg["files"].items():
            path = VENDOR / pkg["dir"] / Path(rel).name
            if not path.is_file():
                problems.append(f"{name}: {path.name} missing")
            elif _sha256(path) != want:
                problems.append(f"{name}: {path.name} differs from {rel} of {name}@{pkg['version']}")
    return problems


def refresh() -> None:
    """Fetch each package's tarball with npm, check its integrity, and copy the listed files in."""
    doc = manifest()
    with tempfile.TemporaryDirectory() as tmp:
        for name, pkg in doc["packages"].items():
            spec = f"{name}@{pkg['version']}"
            out = subprocess.run(
                ["npm", "pack", spec, "--json", "--pack-destination", tmp], check=True, capture_output=True, text=True
            ).stdout
            info = json.loads(out)[0]
            tgz = Path(tmp) / info["filename"]
            algo, digest = pkg["integrity"].split("-", 1)
            got = base64.b64encode(hashlib.new(algo, tgz.read_bytes()).digest()).decode()
            if got != digest:
                raise SystemExit(f"{spec}: tarball integrity {algo}-{got} is not the recorded {pkg['integrity']}")
            with tarfile.open(tgz) as tar:
                for rel in pkg["files"]:
                    member = tar.extractfile(f"package/{rel}")
                    if member is None:
                        raise SystemExit(f"{spec}: no {rel} in the package")
                    dest = VENDOR / pkg["dir"] / Path(rel).name
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    dest.write_bytes(member.read())
                    pkg["files"][rel] = _sha256(dest)
    MANIFEST.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def main(argv: list[str]) -> int:
    """`python -m driftlab.api.vendor [verify|refresh]`: 0 when the vendored files are intact."""
    if argv[:1] == ["refresh"]:
        refresh()
    problems = verify()
    for p in problems:
        print(p, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
