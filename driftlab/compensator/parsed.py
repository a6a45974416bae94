"""The pieces of a program as the first pass parsed them, kept for the second pass (issues 24, 26.5).

The offline compensator reads a program twice: the first pass checks everything before a byte is
written (syntax, feeds, G91 runaways, subdivision limits, the machine envelope) and learns the
decimals of the whole program; the second pass corrects and writes. Parsing was 40 % of the time
when both passes parsed the text. The first pass now keeps every piece it parsed (``gcode.Program``:
the text and its arrays) in an unnamed temporary file, so memory stays flat in the program's length,
and the second pass reads them back instead of reading and parsing the file again: it also corrects
exactly the bytes the first pass checked, even if the file changes in between.

A kept piece is used as it is only when it reads as the second pass would parse it
(``ParsedPieces.pieces``): in the program's decimals, from the pose the piece before it ends at, with
the time stamps in effect. Otherwise (a piece with fewer decimals than the program, lines before the
program's first time stamp) its kept text is parsed again from the second pass's state.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final

import numpy as np

from driftlab.compensator.gcode import ParserState, Program

#: the arrays of ``Program`` kept, in order, with their shape: (5,), per line (L,), per block (B,), (B, 5).
#: ``num_end`` is kept as the numbers' lengths; integers are kept in the narrowest type that holds them
_FIELDS: Final = (
    ("start_int", "pose"),
    ("line_start", "L"),
    ("line_end", "L"),
    ("has_newline", "L"),
    ("line_time_s", "L"),
    ("block_line", "B"),
    ("incremental", "B"),
    ("rapid", "B"),
    ("insert_at", "B"),
    ("spaced", "B"),
    ("present", "B5"),
    ("target_int", "B5"),
    ("word_int", "B5"),
    ("num_start", "B5"),
    ("num_end", "B5"),
)
#: the types arrays are kept in (a code per array in each piece's header); 0: not kept (no time stamps)
_TYPES: Final = (None, np.bool_, np.int8, np.int16, np.int32, np.int64, np.float64)
#: header: text bytes, decimals (2), first line, end modes (2), lines, blocks, points, then a type code per array
_META = 9
_BIGGEST = 2**31 - 1


def _narrow(a: np.ndarray) -> tuple[int, np.ndarray]:
    """Return (type code, array) of ``a`` in the narrowest kept type that holds it."""
    if a.dtype == np.bool_ or a.dtype == np.float64:
        return _TYPES.index(a.dtype.type), a
    lo, hi = (int(a.min()), int(a.max())) if a.size else (0, 0)
    for narrow in (np.int8, np.int16, np.int32):
        info = np.iinfo(narrow)
        if info.min <= lo and hi <= info.max:
            return _TYPES.index(narrow), a.astype(narrow)
    return _TYPES.index(np.int64), a.astype(np.int64)


@dataclass(frozen=True)
class KeptPiece:
    """A piece read back: the program piece and how many points it subdivides into (counted by the first pass)."""

    program: Program
    points: int | None


class ParsedPieces:
    """The first pass's parsed pieces, in order, in an unnamed temporary file (see module docstring)."""

    def __init__(self) -> None:
        self.fh = tempfile.TemporaryFile()
        self.count = 0

    @staticmethod
    def fits(piece: Program) -> bool:
        """Return whether a piece can be kept (its byte offsets fit 32 bits)."""
        return len(piece.data) < _BIGGEST

    def write(self, piece: Program, points: int) -> None:
        """Append a piece and the number of points it subdivides into."""
        codes, arrays = [], []
        for name, _ in _FIELDS:
            a = getattr(piece, name)
            if name == "num_end":
                a = a - piece.num_start  # the numbers' lengths (0 where no word: both -1)
            if name == "line_time_s" and not np.isfinite(a).any():
                codes.append(0)
                continue
            code, kept = _narrow(np.asarray(a))
            codes.append(code)
            arrays.append(kept)
        head = [len(piece.data), *piece.decimals, piece.first_line, piece.end_motion, piece.end_dist]
        head += [piece.n_lines, piece.n_blocks, points, *codes]
        self.fh.write(np.array(head, dtype=np.int64).data)
        self.fh.write(piece.data)
        for a in arrays:
            self.fh.write(np.ascontiguousarray(a).data)
        self.count += 1

    def read(self, name: str, eol: bytes) -> Iterator[KeptPiece]:
        """Yield the kept pieces in order (named ``name``, lines ending in ``eol``)."""
        self.fh.seek(0)
        for _ in range(self.count):
            head = np.frombuffer(self.fh.read((_META + len(_FIELDS)) * 8), dtype=np.int64).tolist()
            n_data, dec_lin, dec_rot, first_line, end_motion, end_dist, n_lines, n_blocks, points = head[:_META]
            data = self.fh.read(n_data)
            sizes = {"pose": 5, "L": n_lines, "B": n_blocks, "B5": n_blocks * 5}
            got = {field: self._take(code, sizes[shape]) for (field, shape), code in zip(_FIELDS, head[_META:])}
            present, word_int = got["present"].reshape(n_blocks, 5), got["word_int"].reshape(n_blocks, 5)
            num_start, num_len = got["num_start"].reshape(n_blocks, 5), got["num_end"].reshape(n_blocks, 5)
            program = Program(
                data=data,
                name=name,
                decimals=(dec_lin, dec_rot),
                line_start=got["line_start"],
                line_end=got["line_end"],
                has_newline=got["has_newline"],
                eol=eol,
                line_time_s=got["line_time_s"],
                block_line=got["block_line"],
                target_int=got["target_int"].reshape(n_blocks, 5),
                start_int=got["start_int"],
                present=present,
                word_int=word_int,
                num_start=num_start,
                num_end=np.where(num_start >= 0, num_start + num_len, -1),
                incremental=got["incremental"],
                rapid=got["rapid"],
                insert_at=got["insert_at"],
                spaced=got["spaced"],
                first_line=first_line,
                end_motion=end_motion,
                end_dist=end_dist,
            )
            yield KeptPiece(program, points)

    def _take(self, code: int, n: int) -> np.ndarray:
        """Return the next ``n`` values kept as type ``code`` (writable; integers widened to 64 bits as parsed)."""
        dtype = _TYPES[code]
        if dtype is None:  # time stamps not kept: none
            return np.full(n, np.nan)
        size = np.dtype(dtype).itemsize * n
        buf = bytearray(size)
        if self.fh.readinto(buf) != size:
            raise RuntimeError("the kept pieces end early")
        out = np.frombuffer(buf, dtype=dtype)
        return out.astype(np.int64) if np.issubdtype(dtype, np.signedinteger) and dtype is not np.int64 else out

    def close(self) -> None:
        """Drop the file."""
        self.fh.close()


def usable(kept: KeptPiece, state: ParserState, max_points: int | None) -> bool:
    """Return whether a kept piece reads as the second pass parses it from ``state`` (see module docstring)."""
    piece = kept.program
    too_many = max_points is not None and piece.n_lines > 1 and (kept.points is None or kept.points > max_points)
    if piece.decimals != state.decimals or too_many:
        return False
    if state.pose_int is not None and not np.array_equal(piece.start_int, state.pose_int):
        return False
    # lines before the program's first time stamp take it in the second pass, NaN in the first
    return not (np.isfinite(state.time_s) and bool(np.isnan(piece.line_time_s).any()))
