"""A YAML file read for a one-line error: the document, or what went wrong and where, for the caller to word.

Plans, scenarios and instrument mappings are YAML read with PyYAML's ``safe_load``. A syntax error
is a ``yaml.YAMLError``; the marked ones (``MarkedYAMLError``) carry ``problem`` (what is wrong) and
``problem_mark`` (where: a zero-based ``line``), as PyYAML's ``error.py`` defines them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml


@dataclass(frozen=True)
class YamlRead:
    """What ``read_yaml`` found: the document, or the read error, or the syntax error and its line."""

    doc: Any = None
    #: the file could not be read (missing, a directory, no permission)
    unreadable: OSError | None = None
    #: the text is not YAML: PyYAML's problem, and its line (1-based; None when PyYAML gives none)
    problem: str | None = None
    line: int | None = None

    def at(self, form: str) -> str:
        """Return ``form`` with the syntax error's line put in (e.g. ``":{}"``), or "" without a line."""
        return form.format(self.line) if self.line is not None else ""


def read_yaml(path: Path, encoding: str | None = None) -> YamlRead:
    """Return the YAML document of the file ``path``, or why there is none (nothing is raised)."""
    try:
        text = path.read_text(encoding=encoding)
    except OSError as exc:
        return YamlRead(unreadable=exc)
    try:
        return YamlRead(doc=yaml.safe_load(text))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        return YamlRead(problem=f"{getattr(exc, 'problem', exc)}", line=None if mark is None else mark.line + 1)
