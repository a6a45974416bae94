"""The header comment of a corrected program: which model, which temperatures, which driftlab, when (issue 35.8).

A corrected program on a control's disk must say where its corrections came from: the model's
machine, version and ETag (or the document's digest when it came from a file), the temperatures
used (their time span, each channel's range), the driftlab version and the date. Written as
parenthesised comments, the form ISO 6983 and every dialect driftlab writes for (Fanuc, LinuxCNC,
SINUMERIK's ISO mode, the simulated controller) reads as a comment: 7-bit ASCII only, no nested
parentheses, lines under 80 characters. A program that starts with its tape start (``%`` alone on
the first line) keeps it first: the header follows it.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable, Mapping, Sequence
from datetime import UTC, datetime
from typing import Any, BinaryIO

import numpy as np

#: the longest header line (a control's comment limit is often 80 characters)
MAX_LINE = 78
_UNSAFE = re.compile(r"[^\x20-\x27\x2a-\x7e]")  # printable 7-bit ASCII without ( and )
#: every header line starts so: an operator (and a test) tells the header from the program's own comments
PREFIX = "driftlab: "


def _comment(text: str) -> str:
    """Return ``text`` as one parenthesised comment of 7-bit ASCII (parentheses and the rest replaced)."""
    text = text.replace("°C", "degC").replace("µm", "um").replace("µrad", "urad")
    return "(" + _UNSAFE.sub("?", PREFIX + text)[: MAX_LINE - 2] + ")"


def document_digest(document: Mapping[str, Any]) -> str:
    """Return the first 16 hex digits of the SHA-256 of a model document's canonical JSON."""
    body = json.dumps(document, sort_keys=True, separators=(",", ":"), default=str).encode()
    return hashlib.sha256(body).hexdigest()[:16]


def temperature_lines(
    values: Mapping[str, Any], time_s: Sequence[float] | np.ndarray | None = None, origin: str = ""
) -> list[str]:
    """Return the lines that name the temperatures used: time span (s), then each channel's range (degC)."""
    lines = []
    if time_s is not None and len(time_s):
        lo, hi = float(np.nanmin(time_s)), float(np.nanmax(time_s))
        lines.append(f"temperatures {origin}scans t = {lo:.0f}..{hi:.0f} s, {len(time_s)} scans".replace("  ", " "))
    else:
        lines.append(f"temperatures {origin}one scan".replace("  ", " "))
    parts = []
    for ch, v in values.items():
        arr = np.atleast_1d(np.asarray(v, float))
        arr = arr[np.isfinite(arr)]
        if arr.size == 0:
            parts.append(f"{ch} -")
        elif np.ptp(arr) < 0.005:
            parts.append(f"{ch} {arr[0]:.2f}")
        else:
            parts.append(f"{ch} {arr.min():.2f}..{arr.max():.2f}")
    line = "degC:"
    for p in parts:
        if len(line) + len(p) + 1 > MAX_LINE - 2 - len(PREFIX):
            lines.append(line)
            line = " "
        line += " " + p
    lines.append(line)
    return lines


def program_header(
    machine: str,
    version: int | None,
    tag: str,
    temperatures: Iterable[str],
    driftlab_version: str,
    when: datetime | None = None,
) -> list[str]:
    """Return the header's comment lines (each ``(...)``, 7-bit ASCII) of a program corrected with a model."""
    stamp = (when or datetime.now(UTC)).astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    lines = [
        f"thermal drift corrected by driftlab {driftlab_version} {stamp}",
        f"model {machine} v{'?' if version is None else version} {tag}",
        *temperatures,
    ]
    return [_comment(" ".join(line.split()) if line.strip() else "-") for line in lines]


class HeaderedOut:
    """A binary stream that writes the header's lines first, after the program's tape start if it has one."""

    def __init__(self, out: BinaryIO, lines: Sequence[str]) -> None:
        self.out = out
        self.header = "".join(f"{line}\n" for line in lines).encode("ascii")
        self._head = b""
        self._done = not lines

    def write(self, data: bytes) -> int:
        """Write ``data``, the header once the first line of the program is known."""
        if self._done:
            return self.out.write(data)
        self._head += data
        end = self._head.find(b"\n")
        if end < 0:
            return len(data)
        first, rest = self._head[: end + 1], self._head[end + 1 :]
        eol = b"\r\n" if first.endswith(b"\r\n") else b"\n"
        header = self.header.replace(b"\n", eol)
        if first.strip() == b"%":  # the tape start stays the first line
            self.out.write(first + header + rest)
        else:
            self.out.write(header + first + rest)
        self._done = True
        return len(data)

    def close(self) -> None:
        """Write what is held (a program of one line without its end) and the header if nothing came."""
        if not self._done:
            self.out.write(self.header + self._head)
            self._done = True
