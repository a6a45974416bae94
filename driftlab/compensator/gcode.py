"""Five-axis motion code: vectorised parse, subdivision of long segments, byte-exact emission.

Accepted language (one block per line, ISO 6983 style, as the thesis' controller took it):

* words ``X Y Z`` (mm) and ``A B`` (deg) on ``G0``/``G1`` (modal), ``G90``/``G91`` (modal,
  absolute by default), ``G21``; ``G4`` dwell (with ``P``); harmless modal codes
  ``G17 G18 G19 G40 G49 G54 G61 G64 G80 G94`` pass through;
* pass-through words ``N`` (line number), ``M``, ``F``, ``S``, ``T``, ``P``, ``O``, ``H``, ``D``;
* comments ``( ... )`` and ``; ...``, a ``%`` line as program start/end; a comment ``(T=123.0)``
  stamps the block with a time (s) used to pick its temperatures.

Refused with a one-line ``PROGRAM:LINE: problem``: tool length offsets ``G43``/``G44``, ``G10``, macro and
subprogram calls ``G65``/``G66``/``M97``/``M98``/``M99`` (their effect on the axes is not in the program's
coordinates: issue 34), ``G20`` (inch), ``G2``/``G3`` arcs (and their
``I J K R`` words), other G-codes, axes the machine does not have, malformed numbers, feeds ``F``
that are not positive.

Program coordinates are taken as the joint coordinates ``q`` of the kinematic chain.
Positions are held as exact integers in units of ``10**-decimals`` (mm for X, Y, Z; deg for A, B),
so words that receive no correction are written back byte for byte.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from driftlab.errors import ValidationError
from driftlab.vocabulary import AXES

ROTARY: np.ndarray = np.array([False, False, False, True, True])
MAX_DECIMALS = 9
_W = 16  # widest number word accepted (characters after the letter)

# byte classes
_OTHER, _LETTER, _NUM, _WS, _SPECIAL = 0, 1, 2, 3, 4
_CLS = np.zeros(256, dtype=np.uint8)
_CLS[ord("A") : ord("Z") + 1] = _LETTER
_CLS[ord("a") : ord("z") + 1] = _LETTER
_CLS[ord("0") : ord("9") + 1] = _NUM
for _c in b".+-":
    _CLS[_c] = _NUM
for _c in b" \t\r\n":
    _CLS[_c] = _WS
for _c in b"();%":
    _CLS[_c] = _SPECIAL

# word kinds: 0..4 axes, then G, passthrough, arc words, foreign axes, unknown
_K_G, _K_PASS, _K_ARC, _K_FOREIGN, _K_UNKNOWN = 5, 6, 7, 8, 9
_KIND = np.full(256, _K_UNKNOWN, dtype=np.int8)
for _i, _a in enumerate("XYZAB"):
    _KIND[ord(_a)] = _i
_KIND[ord("G")] = _K_G
for _w in "NMFSTPOHD":
    _KIND[ord(_w)] = _K_PASS
for _w in "IJKR":
    _KIND[ord(_w)] = _K_ARC
for _w in "CUVW":
    _KIND[ord(_w)] = _K_FOREIGN

# G codes times ten
_G_MOTION = {0: 0, 10: 1}
_G_DIST = {900: 0, 910: 1}
_G_OK = {40, 170, 180, 190, 210, 400, 490, 540, 610, 640, 800, 940}
#: codes whose effect on the axes the compensator cannot see (issue 34): tool length offsets shift Z by a
#: length the envelope does not know, subprogram calls run moves that are neither checked nor corrected
_G_UNSEEN = {
    430: "G43 applies a tool length offset",
    440: "G44 applies a tool length offset",
    100: "G10 sets offsets",
    650: "G65 calls a macro",
    660: "G66 calls a macro",
}
_M_UNSEEN = {
    97: "M97 calls a local subprogram",
    98: "M98 calls a subprogram",
    99: "M99 returns from or loops a subprogram",
}


@dataclass(frozen=True)
class Program:
    """A parsed program: the original bytes plus vectorised blocks (one per line that moves)."""

    data: bytes
    name: str
    #: decimals of the integer position units, (linear, rotary)
    decimals: tuple[int, int]
    #: (L,) byte offset where each line starts; (L,) offset after its content (before ``\\n``)
    line_start: np.ndarray
    line_end: np.ndarray
    #: (L,) True where the line carries its ``\\n``; the file's line terminator
    has_newline: np.ndarray
    eol: bytes
    #: (L,) time stamp (s) in effect on each line, NaN when the program carries no times
    line_time_s: np.ndarray
    #: (B,) line index of each block (0-based)
    block_line: np.ndarray
    #: (B, 5) exact target of each block in units of 10**-decimals (mm / deg)
    target_int: np.ndarray
    #: (5,) start pose in the same units (the machine's position before the program)
    start_int: np.ndarray
    #: (B, 5) word present on the block; (B, 5) its value as written, in the same units
    present: np.ndarray
    word_int: np.ndarray
    #: (B, 5) byte span of each present word's number (start, end), -1 where absent
    num_start: np.ndarray
    num_end: np.ndarray
    #: (B,) G91 in effect; G0 in effect; where new words go; whether the line separates words
    incremental: np.ndarray
    rapid: np.ndarray
    insert_at: np.ndarray
    spaced: np.ndarray
    #: line number (0-based) of this text's first line in the whole program (a piece of a streamed program)
    first_line: int = 0
    #: modal motion (-1 none yet, 0 G0, 1 G1) and distance (0 G90, 1 G91) modes in effect after the last line
    end_motion: int = -1
    end_dist: int = 0
    #: for each of (linear, rotary): (largest |value|, residual |v*10**d - rint(v*10**d)| for d = least..9)
    residuals: tuple[tuple[float, np.ndarray], tuple[float, np.ndarray]] | None = None

    @property
    def n_lines(self) -> int:
        """Return the number of lines."""
        return int(self.line_start.shape[0])

    @property
    def n_blocks(self) -> int:
        """Return the number of motion blocks."""
        return int(self.block_line.shape[0])

    @property
    def scale(self) -> np.ndarray:
        """Return (5,) size of one integer unit per axis (mm for X, Y, Z; deg for A, B)."""
        lin, rot = self.decimals
        return np.where(ROTARY, 10.0**-rot, 10.0**-lin)

    @property
    def start_int_blocks(self) -> np.ndarray:
        """Return (B, 5) pose at the start of each block (the previous target)."""
        out = np.empty_like(self.target_int)
        out[0:1] = self.start_int
        out[1:] = self.target_int[:-1]
        return out

    def to_q(self, pose_int: np.ndarray) -> np.ndarray:
        """Return joint coordinates (N, 5) in mm and rad for integer poses (N, 5)."""
        q = pose_int * self.scale
        q[:, 3:] = np.deg2rad(q[:, 3:])
        return q

    def line_number(self, block: int) -> int:
        """Return the line number (1-based, in the whole program) of block ``block`` of this text."""
        return int(self.block_line[block]) + self.first_line + 1

    def block_time_s(self) -> np.ndarray:
        """Return (B,) time stamp of each block (NaN when the program carries none)."""
        return self.line_time_s[self.block_line]

    def next_state(self, state: ParserState) -> ParserState:
        """Return the state these lines, parsed from ``state``, leave for the lines after them."""
        return replace(
            state,
            pose_int=self.target_int[-1] if self.n_blocks else self.start_int,
            motion=self.end_motion,
            dist=self.end_dist,
            time_s=float(self.line_time_s[-1]) if self.n_lines else state.time_s,
            line_offset=self.first_line + self.n_lines,
        )


def _fail(name: str, errors: list[tuple[int, str]], line_offset: int = 0) -> None:
    """Raise the first error (by line; on a line, G-code problems first) as one line ``NAME:LINE: problem``."""
    if errors:
        line, msg = min(errors, key=lambda e: (e[0], not e[1].startswith(("G", "unsupported G"))))
        raise ValidationError(f"{name}:{line + line_offset + 1}: {msg}; program not accepted")


def _show(byte: int) -> str:
    """Return a printable rendering of one byte for an error message."""
    ch = chr(byte)
    return repr(ch) if ch.isprintable() and byte < 128 else f"byte 0x{byte:02x}"


@dataclass(frozen=True, eq=False)
class ParserState:
    """What the lines before a text leave for it, so that a piece of a longer program reads as in the whole.

    A whole program is parsed from the default state. The pieces of a streamed program
    (``compensate.parse_pieces``) each start from the state the piece before leaves (``Program.next_state``).
    """

    #: decimals of the integer units (linear, rotary), fixed: the whole program's; None: chosen from this text
    decimals: tuple[int, int] | None = None
    #: the pose before the first line in those units; None: ``parse_program``'s ``start``
    pose_int: np.ndarray | None = None
    #: modal motion (-1 none yet, 0 G0, 1 G1) and distance (0 G90, 1 G91) modes in effect
    motion: int = -1
    dist: int = 0
    #: the time stamp (s) in effect (NaN: none yet)
    time_s: float = math.nan
    #: the file's line terminator; None: taken from this text's first line
    eol: bytes | None = None
    #: lines before this text in the whole program (``Program.first_line``, error messages)
    line_offset: int = 0


_FRESH = ParserState()


@dataclass(frozen=True)
class _Lines:
    """Where the lines of a text are: newlines, starts, ends (before ``\\n``), which carry a newline."""

    nl: np.ndarray
    start: np.ndarray
    end: np.ndarray
    has_newline: np.ndarray
    eol: bytes

    @property
    def n(self) -> int:
        """Return the number of lines."""
        return int(self.start.shape[0])


def _split_lines(buf: np.ndarray, eol: bytes | None) -> _Lines:
    """Return the lines of ``buf``; the line terminator is the first line's unless ``eol`` is given."""
    n = buf.shape[0]
    nl = np.flatnonzero(buf == 10)
    line_start = np.concatenate(([0], nl + 1)).astype(np.int64)
    if line_start[-1] >= n:
        line_start = line_start[:-1]
    n_lines = line_start.shape[0]
    line_end = np.empty(n_lines, dtype=np.int64)
    line_end[: nl.shape[0]] = nl[:n_lines]
    if nl.shape[0] < n_lines:
        line_end[-1] = n
    has_newline = np.zeros(n_lines, dtype=bool)
    has_newline[: nl.shape[0]] = True
    if eol is None:
        eol = b"\r\n" if nl.shape[0] and nl[0] > 0 and buf[nl[0] - 1] == 13 else b"\n"
    return _Lines(nl, line_start, line_end, has_newline, eol)


def _strip_comments(
    data: bytes,
    work: bytearray,
    selected: np.ndarray,
    lines: _Lines,
    errors: list[tuple[int, str]],
    times: dict[int, float],
) -> None:
    """Blank comments and ``%`` markers of the ``selected`` lines in ``work``; collect times and errors."""
    for li in selected.tolist():
        a, b = int(lines.start[li]), int(lines.end[li])
        text = data[a:b]
        i, n = 0, len(text)
        code_chars = []
        while i < n:
            ch = text[i]
            if ch == 0x28:  # (
                j = text.find(b")", i + 1)
                if j < 0:
                    errors.append((li, "unterminated comment '('"))
                    break
                if text.find(b"(", i + 1, j) >= 0:
                    errors.append((li, "nested comment '('"))
                    break
                _time_comment(text[i + 1 : j].strip(), li, errors, times)
                work[a + i : a + j + 1] = b" " * (j + 1 - i)
                i = j + 1
            elif ch == 0x29:  # )
                errors.append((li, "')' without '('"))
                break
            elif ch == 0x3B:  # ;
                work[a + i : b] = b" " * (n - i)
                break
            else:
                if ch not in b" \t\r":
                    code_chars.append(i)
                i += 1
        pct = [k for k in code_chars if text[k] == 0x25]
        if pct:
            if len(code_chars) != 1:
                errors.append((li, "'%' must stand alone on its line"))
            else:
                work[a + pct[0]] = 0x20


def _time_comment(body: bytes, li: int, errors: list[tuple[int, str]], times: dict[int, float]) -> None:
    """Record the time stamp of a comment ``(T=123.0)`` on line ``li`` (other comments say nothing)."""
    if body[:1] in (b"T", b"t") and body[1:].lstrip().startswith(b"="):
        value = body[1:].lstrip()[1:].strip()
        try:
            t = float(value)
        except ValueError:
            t = math.nan
        if not math.isfinite(t):
            errors.append((li, f"bad time comment ({body.decode('ascii', 'replace')})"))
        else:
            times[li] = t


def _class_counts(cls: np.ndarray) -> dict[int, int]:
    """Return whether bytes of the classes that need attention occur (the lowest and highest classes)."""
    if cls.shape[0] == 0:
        return {_OTHER: 0, _SPECIAL: 0}
    return {_OTHER: int(cls.min() == _OTHER), _SPECIAL: int(cls.max() == _SPECIAL)}


def _code_bytes(
    data: bytes, lines: _Lines, errors: list[tuple[int, str]]
) -> tuple[np.ndarray, np.ndarray, dict[int, float]]:
    """Return the bytes with comments blanked, their classes and the lines' time stamps; note stray characters."""
    buf = np.frombuffer(data, dtype=np.uint8)
    times: dict[int, float] = {}
    cls = np.take(_CLS, buf)  # (a take of a 256-entry table: about twice as fast as indexing)
    counts = _class_counts(cls)
    if counts[_SPECIAL]:
        work = bytearray(data)
        selected = np.unique(np.searchsorted(lines.nl, np.flatnonzero(cls == _SPECIAL)))
        _strip_comments(data, work, selected, lines, errors, times)
        buf = np.frombuffer(bytes(work), dtype=np.uint8)
        cls = np.take(_CLS, buf)
        counts = _class_counts(cls)
    if counts[_OTHER] or counts[_SPECIAL]:
        other = np.flatnonzero((cls == _OTHER) | (cls == _SPECIAL))
        for p in other[:1000].tolist():
            errors.append((int(np.searchsorted(lines.nl, p)), f"unexpected character {_show(int(buf[p]))}"))
    return buf, cls, times


@dataclass(frozen=True)
class _Words:
    """The words of a text: a letter and the run of number characters right after it."""

    #: (W,) byte offset of the letter; length of its number; line; letter (upper case); kind (``_KIND``)
    pos: np.ndarray
    runlen: np.ndarray
    lid: np.ndarray
    letter: np.ndarray
    kind: np.ndarray
    #: (W,) the number parsed; whether it did
    valid: np.ndarray
    value: np.ndarray
    #: bytes that are not number characters (the rest belong to words, or stand alone)
    n_nonnum: int


def _words(buf: np.ndarray, cls: np.ndarray) -> _Words:
    """Return the words of ``buf``: each ends at the next byte that is not part of a number."""
    nonnum = np.flatnonzero(cls != _NUM)
    widx = np.flatnonzero(cls[nonnum] == _LETTER)
    pos = nonnum[widx]
    runlen = np.append(nonnum, buf.shape[0])[widx + 1] - pos - 1
    lid = np.cumsum(buf[nonnum] == 10)[widx]  # newlines before each letter
    letter = buf[pos] & 0xDF
    valid = (runlen > 0) & (runlen < _W)
    value = _numbers(buf, pos, runlen, valid)
    return _Words(pos, runlen, lid, letter, _KIND[letter], valid, value, nonnum.shape[0])


def _numbers(buf: np.ndarray, pos: np.ndarray, runlen: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Return the numbers after the letters at ``pos`` (NaN where none); clear ``valid`` where malformed."""
    value = np.full(pos.shape[0], np.nan)
    padded = np.concatenate((buf, np.zeros(_W, dtype=np.uint8)))
    win = np.lib.stride_tricks.sliding_window_view(padded, _W)
    cols = np.arange(_W)
    step = 1 << 18
    todo = np.flatnonzero(valid)
    for s in range(0, todo.shape[0], step):
        sel = todo[s : s + step]
        m = win[pos[sel] + 1]
        m *= cols[None, :] < runlen[sel, None]  # the window is a copy: blank what follows the number
        strings = m.view(f"S{_W}").ravel()
        try:
            value[sel] = strings.astype(np.float64)
        except ValueError:  # numpy's parser takes exactly [+-]digits[.digits]: find the bad ones
            for k, txt in zip(sel.tolist(), strings.tolist()):
                try:
                    value[k] = float(txt)
                except ValueError:
                    valid[k] = False
    return value


def _word_errors(w: _Words, buf: np.ndarray, cls: np.ndarray, lines: _Lines, errors: list[tuple[int, str]]) -> None:
    """Note words without a valid number, numbers without a letter, words of no accepted kind, bad feeds."""
    for i in np.flatnonzero(~w.valid)[:1000].tolist():
        ltr = chr(w.letter[i])
        if w.runlen[i] == 0:
            errors.append((int(w.lid[i]), f"word '{ltr}' has no value"))
        elif w.runlen[i] >= _W:
            errors.append((int(w.lid[i]), f"number after '{ltr}' is too long"))
        else:
            errors.append((int(w.lid[i]), f"malformed number '{ltr}{_number_text(w, buf, i)}'"))
    if int(w.runlen.sum()) != buf.shape[0] - w.n_nonnum:  # every number character belongs to a word
        per_line = np.bincount(np.searchsorted(lines.nl, np.flatnonzero(cls == _NUM)), minlength=lines.n)
        covered = np.bincount(w.lid, weights=w.runlen, minlength=lines.n)
        for li in np.flatnonzero(per_line != covered)[:1000].tolist():
            errors.append((int(li), "number without a letter"))
    for i in np.flatnonzero(w.kind >= _K_ARC)[:1000].tolist():
        ltr = chr(w.letter[i])
        if w.kind[i] == _K_ARC:
            msg = f"word '{ltr}' belongs to arcs, which are not supported (linearise G2/G3 first)"
        elif w.kind[i] == _K_FOREIGN:
            msg = f"axis '{ltr}' is not on this machine (X Y Z A B)"
        else:
            msg = f"unsupported word '{ltr}'"
        errors.append((int(w.lid[i]), msg))
    # subprogram calls: the moves they run are neither checked against the envelope nor corrected
    mi = np.flatnonzero((w.letter == ord("M")) & w.valid)
    for j in mi[np.isin(w.value[mi], list(_M_UNSEEN))][:1000].tolist():
        errors.append(
            (
                int(w.lid[j]),
                f"{_M_UNSEEN[int(w.value[j])]} the compensator cannot see: refused (expand it into the program)",
            )
        )
    # feeds: F0 stalls the controller and a negative feed is no feed; both are refused here, not mid-run
    fi = np.flatnonzero((w.letter == ord("F")) & w.valid)
    for j in fi[~(w.value[fi] > 0)][:1000].tolist():
        errors.append((int(w.lid[j]), f"feed 'F{_number_text(w, buf, j)}' must be positive"))


def _number_text(w: _Words, buf: np.ndarray, i: int) -> str:
    """Return the number of word ``i`` as written."""
    return bytes(buf[w.pos[i] + 1 : w.pos[i] + 1 + w.runlen[i]]).decode("ascii")


def _modes(w: _Words, n_lines: int, errors: list[tuple[int, str]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the G codes of each line: motion (-1 none, 0 G0, 1 G1), distance (-1, 0 G90, 1 G91), dwell."""
    gi = np.flatnonzero((w.kind == _K_G) & w.valid)
    g10 = np.rint(w.value[gi] * 10.0)
    g_exact = np.abs(w.value[gi] * 10.0 - g10) < 1e-6
    g10 = g10.astype(np.int64)
    motion_line = np.full(n_lines, -1, dtype=np.int8)
    dist_line = np.full(n_lines, -1, dtype=np.int8)
    dwell_line = np.zeros(n_lines, dtype=bool)
    for codes, per_line in ((_G_MOTION, motion_line), (_G_DIST, dist_line)):
        for code, mode in codes.items():
            per_line[w.lid[gi[(g10 == code) & g_exact]]] = mode
    dwell_line[w.lid[gi[(g10 == 40) & g_exact]]] = True
    known = np.isin(g10, list(_G_MOTION) + list(_G_DIST) + list(_G_OK)) & g_exact
    for j in np.flatnonzero(~known)[:1000].tolist():
        text = f"G{w.value[gi[j]]:g}"
        if g_exact[j] and int(g10[j]) in _G_UNSEEN:
            msg = f"{_G_UNSEEN[int(g10[j])]} the envelope cannot account for: refused (apply it in the program)"
        elif g_exact[j] and g10[j] in (20, 30):
            msg = f"{text}: circular interpolation is not supported (linearise arcs into G1 first)"
        elif g_exact[j] and g10[j] == 200:
            msg = "G20: inch units are not supported (the program must be in mm, G21)"
        else:
            msg = f"unsupported G-code {text}"
        errors.append((int(w.lid[gi[j]]), msg))
    for codes, what in ((_G_MOTION, "motion codes G0/G1"), (_G_DIST, "distance modes G90/G91")):
        kinds = [np.bincount(w.lid[gi[(g10 == c) & g_exact]], minlength=n_lines) > 0 for c in codes]
        for li in np.flatnonzero(np.sum(kinds, axis=0) > 1)[:1000].tolist():
            errors.append((int(li), f"conflicting {what} on one block"))
    return motion_line, dist_line, dwell_line


@dataclass(frozen=True)
class _AxisWords:
    """The axis words of a text, in byte order: index among the words, axis, line, value in integer units."""

    index: np.ndarray
    axis: np.ndarray
    lid: np.ndarray
    value_int: np.ndarray
    decimals: tuple[int, int]
    residuals: tuple[tuple[float, np.ndarray], tuple[float, np.ndarray]] | None


def _axis_words(
    w: _Words,
    n_lines: int,
    min_decimals: tuple[int, int],
    state: ParserState,
    residuals: bool,
    errors: list[tuple[int, str]],
) -> _AxisWords:
    """Return the axis words in integer units of the decimals chosen (``state.decimals`` when fixed)."""
    ai = np.flatnonzero((w.kind < 5) & w.valid)
    a_axis = w.kind[ai].astype(np.int64)
    a_lid = w.lid[ai]
    per_key = np.bincount(a_lid * 5 + a_axis, minlength=5 * n_lines)
    for k in np.flatnonzero(per_key > 1)[:1000].tolist():
        errors.append((int(k // 5), f"repeated word '{AXES[k % 5]}'"))
    rot = ROTARY[a_axis]
    lin_values, rot_values = w.value[ai[~rot]], w.value[ai[rot]]
    need = None
    if residuals:
        need = (_residuals(lin_values, min_decimals[0]), _residuals(rot_values, min_decimals[1]))
    if state.decimals is not None:
        dec_lin, dec_rot = state.decimals
    elif need is not None:  # the same residuals decide (``decimals_of`` of one piece is ``_decimals``)
        dec_lin, dec_rot = decimals_of([need[0]], min_decimals[0]), decimals_of([need[1]], min_decimals[1])
    else:
        dec_lin, dec_rot = _decimals(lin_values, min_decimals[0]), _decimals(rot_values, min_decimals[1])
    if state.decimals is None:
        for dec, values, lids in ((dec_lin, lin_values, a_lid[~rot]), (dec_rot, rot_values, a_lid[rot])):
            if dec > MAX_DECIMALS:
                bad = np.flatnonzero(~_whole(values * 10.0**MAX_DECIMALS))[0]
                errors.append((int(lids[bad]), f"more than {MAX_DECIMALS} decimals"))
        dec_lin, dec_rot = min(dec_lin, MAX_DECIMALS), min(dec_rot, MAX_DECIMALS)
    a_val = w.value[ai] * np.where(rot, 10.0**dec_rot, 10.0**dec_lin)
    big = ~(np.abs(a_val) < 2.0**52)
    for j in np.flatnonzero(big)[:1000].tolist():
        errors.append((int(a_lid[j]), f"value of '{AXES[a_axis[j]]}' out of range"))
    a_int = np.rint(np.where(big, 0.0, a_val)).astype(np.int64)
    return _AxisWords(ai, a_axis, a_lid, a_int, (dec_lin, dec_rot), need)


def _carry(per_line: np.ndarray, initial: int | float) -> np.ndarray:
    """Return the value in effect on each line: the last one given on it or before, else ``initial``."""
    idx = np.arange(per_line.shape[0])
    last = np.maximum.accumulate(np.where(per_line >= 0, idx, -1))
    return np.where(last >= 0, per_line[np.maximum(last, 0)], initial)


@dataclass(frozen=True)
class _Blocks:
    """The per-block arrays of ``Program`` (see there) that come from the axis words."""

    block_line: np.ndarray
    present: np.ndarray
    word_int: np.ndarray
    num_start: np.ndarray
    num_end: np.ndarray
    insert_at: np.ndarray
    spaced: np.ndarray


def _blocks(w: _Words, axes: _AxisWords, buf: np.ndarray) -> _Blocks:
    """Return the blocks (lines with axis words): which words each has, their values and where they are."""
    # words are in byte order, so lines of axis words are sorted
    new_block = np.diff(axes.lid, prepend=-1) != 0
    block_line = axes.lid[new_block]
    n_blocks = block_line.shape[0]
    flat = (np.cumsum(new_block) - 1) * 5 + axes.axis  # (block, axis) of each axis word
    present = np.zeros((n_blocks, 5), dtype=bool)
    word_int = np.zeros((n_blocks, 5), dtype=np.int64)
    num_start = np.full((n_blocks, 5), -1, dtype=np.int64)
    num_end = np.full((n_blocks, 5), -1, dtype=np.int64)
    a_start = w.pos[axes.index] + 1
    a_end = a_start + w.runlen[axes.index]
    present.reshape(-1)[flat] = True
    word_int.reshape(-1)[flat] = axes.value_int
    num_start.reshape(-1)[flat] = a_start
    num_end.reshape(-1)[flat] = a_end
    # a block's last axis word is the one before the next block's first
    last = np.append(np.flatnonzero(new_block)[1:], new_block.shape[0])[:n_blocks] - 1
    spaced = buf[np.maximum(a_start[last] - 2, 0)] == 32
    return _Blocks(block_line, present, word_int, num_start, num_end, a_end[last], spaced)


def block_targets(
    present: np.ndarray, word_int: np.ndarray, incremental: np.ndarray, start_int: np.ndarray
) -> np.ndarray:
    """Return (B, 5) the target of each block: absolute words set it, G91 words add to the one before.

    ``present`` and ``word_int`` (B, 5): the blocks' axis words and their values; ``incremental`` (B,):
    G91 in effect; ``start_int`` (5,): the pose before the first block (all in integer units).
    """
    n_blocks = present.shape[0]
    target = np.empty((n_blocks, 5), dtype=np.int64)
    ar = np.arange(n_blocks)
    for k in range(5):
        reset = present[:, k] & ~incremental
        inc = np.where(present[:, k] & incremental, word_int[:, k], 0)
        csum = np.cumsum(inc)
        r = np.maximum.accumulate(np.where(reset, ar, -1))
        base = np.where(r >= 0, word_int[np.maximum(r, 0), k] - csum[np.maximum(r, 0)], start_int[k])
        target[:, k] = base + csum
    return target


def _line_times(times: dict[int, float], n_lines: int, initial_time_s: float) -> np.ndarray:
    """Return (L,) the time stamp in effect on each line (the lines before the first stamp take ``initial_time_s``)."""
    line_time = np.full(n_lines, initial_time_s)
    if times:
        tl = np.array(sorted(times))
        line_time[tl] = [times[t] for t in tl.tolist()]
        stamped = np.zeros(n_lines, dtype=bool)
        stamped[tl] = True
        last = np.maximum.accumulate(np.where(stamped, np.arange(n_lines), -1))
        # lines before the first stamp take the time in effect (a whole program: its first stamp)
        before = initial_time_s if math.isfinite(initial_time_s) else line_time[tl[0]]
        line_time = np.where(last >= 0, line_time[np.maximum(last, 0)], before)
    return line_time


def parse_program(
    data: bytes | str,
    name: str = "<program>",
    start: tuple[float, ...] | np.ndarray | None = None,
    min_decimals: tuple[int, int] = (4, 3),
    *,
    state: ParserState = _FRESH,
    residuals: bool = False,
) -> Program:
    """Return the parsed program; raise ValidationError naming the first bad line otherwise.

    ``start`` is the machine's pose before the first block (X, Y, Z mm; A, B deg; default home).
    ``min_decimals`` sets the finest position unit (linear, rotary); it grows to the program's.

    A piece of a longer program (streaming, see ``compensate.parse_pieces``) is parsed with the
    ``state`` the lines before it leave (``ParserState``: the decimals of the whole program, the pose,
    modal modes, time stamp, line terminator and line number). ``residuals`` records what choosing the
    decimals of the whole program needs (``Program.residuals``).
    """
    if isinstance(data, str):
        data = data.encode("utf-8")
    lines = _split_lines(np.frombuffer(data, dtype=np.uint8), state.eol)
    errors: list[tuple[int, str]] = []
    buf, cls, times = _code_bytes(data, lines, errors)
    words = _words(buf, cls)
    _word_errors(words, buf, cls, lines, errors)
    motion_line, dist_line, dwell_line = _modes(words, lines.n, errors)
    axes = _axis_words(words, lines.n, min_decimals, state, residuals, errors)
    motion = _carry(motion_line, state.motion)
    dist = _carry(dist_line, state.dist)
    blocks = _blocks(words, axes, buf)
    for li in blocks.block_line[dwell_line[blocks.block_line]][:1000].tolist():
        errors.append((int(li), "G4 dwell with axis words"))
    for li in blocks.block_line[motion[blocks.block_line] < 0][:1000].tolist():
        errors.append((int(li), "axis words before any G0/G1"))
    _fail(name, errors, state.line_offset)

    incremental = dist[blocks.block_line] == 1
    start_int = _start_int(start, *axes.decimals) if state.pose_int is None else np.asarray(state.pose_int, np.int64)
    return Program(
        data=data,
        name=name,
        decimals=axes.decimals,
        line_start=lines.start,
        line_end=lines.end,
        has_newline=lines.has_newline,
        eol=lines.eol,
        line_time_s=_line_times(times, lines.n, state.time_s),
        block_line=blocks.block_line,
        target_int=block_targets(blocks.present, blocks.word_int, incremental, start_int),
        start_int=start_int,
        present=blocks.present,
        word_int=blocks.word_int,
        num_start=blocks.num_start,
        num_end=blocks.num_end,
        incremental=incremental,
        rapid=motion[blocks.block_line] == 0,
        insert_at=blocks.insert_at,
        spaced=blocks.spaced,
        first_line=state.line_offset,
        end_motion=int(motion[-1]) if lines.n else state.motion,
        end_dist=int(dist[-1]) if lines.n else state.dist,
        residuals=axes.residuals,
    )


def _whole(x: np.ndarray) -> np.ndarray:
    """Return where ``x`` is a whole number (to the precision a parsed decimal keeps)."""
    return np.abs(x - np.rint(x)) <= 1e-6 * np.maximum(1.0, np.abs(x) * 1e-9)


def _decimals(values: np.ndarray, least: int) -> int:
    """Return the fewest decimals (at least ``least``) that write every value exactly; > 9 when none do."""
    if values.shape[0] == 0:
        return least
    tol = 1e-6 * max(1.0, float(np.abs(values).max()) * 10.0**MAX_DECIMALS * 1e-9)
    for d in range(least, MAX_DECIMALS + 1):
        x = values * 10.0**d
        if float(np.abs(x - np.rint(x)).max()) <= tol:
            return d
    return MAX_DECIMALS + 1


def _residuals(values: np.ndarray, least: int) -> tuple[float, np.ndarray]:
    """Return (largest |value|, worst residual at each of least..9 decimals): what ``_decimals`` decides on."""
    if values.shape[0] == 0:
        return 0.0, np.zeros(MAX_DECIMALS + 1 - least)
    res = []
    for d in range(least, MAX_DECIMALS + 1):
        x = values * 10.0**d
        res.append(float(np.abs(x - np.rint(x)).max()))
    return float(np.abs(values).max()), np.array(res)


def decimals_of(pieces: list[tuple[float, np.ndarray]], least: int) -> int:
    """Return what ``_decimals`` gives for the values of all pieces together (> 9 when none do)."""
    if not pieces:
        return least
    biggest = max(p[0] for p in pieces)
    worst = np.max(np.vstack([p[1] for p in pieces]), axis=0)
    tol = 1e-6 * max(1.0, biggest * 10.0**MAX_DECIMALS * 1e-9)
    fits = np.flatnonzero(worst <= tol)
    return least + int(fits[0]) if fits.shape[0] else MAX_DECIMALS + 1


def _start_int(start: tuple[float, ...] | np.ndarray | None, dec_lin: int, dec_rot: int) -> np.ndarray:
    """Return the start pose (X, Y, Z mm; A, B deg) in integer units."""
    if start is None:
        return np.zeros(5, dtype=np.int64)
    s = np.asarray(start, dtype=float).reshape(-1)
    if s.shape != (5,) or not np.all(np.isfinite(s)):
        raise ValidationError("start pose must be five finite numbers X, Y, Z (mm), A, B (deg)")
    return np.rint(s * np.where(ROTARY, 10.0**dec_rot, 10.0**dec_lin)).astype(np.int64)


@dataclass(frozen=True)
class Points:
    """The poses a program visits after subdivision: one or more points per block, in order."""

    #: (P,) block of each point (non-decreasing; a block's last point is its target)
    block: np.ndarray
    #: (P, 5) nominal pose in the program's integer units
    nominal_int: np.ndarray

    @property
    def n(self) -> int:
        """Return the number of points."""
        return int(self.block.shape[0])


def _pieces(
    program: Program, max_mm: float, max_deg: float, b0: int, b1: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (start, end, pieces) of blocks b0..b1: their poses and how many points each becomes."""
    if not (max_mm > 0 and max_deg > 0):
        raise ValidationError("subdivision lengths must be positive")
    end = program.target_int[b0:b1]
    start = np.empty_like(end)
    if b1 > b0:
        start[0] = program.start_int if b0 == 0 else program.target_int[b0 - 1]
        start[1:] = end[:-1]
    delta = (end - start) * program.scale
    lin = np.sqrt((delta[:, :3] ** 2).sum(axis=1))
    rot = np.abs(delta[:, 3:]).max(axis=1) if delta.shape[0] else np.zeros(0)
    pieces = np.maximum(np.ceil(np.maximum(lin / max_mm, rot / max_deg) - 1e-9), 1).astype(np.int64)
    pieces[program.rapid[b0:b1]] = 1
    if pieces.shape[0] and int(pieces.max()) > 100_000:
        b = b0 + int(np.argmax(pieces))
        raise ValidationError(
            f"{program.name}:{program.line_number(b)}: segment would need more than "
            "100000 subdivisions; raise the subdivision length"
        )
    return start, end, pieces


def count_points(program: Program, max_mm: float = 5.0, max_deg: float = 5.0) -> int:
    """Return how many points ``subdivide`` makes of the program (without making them)."""
    return int(_pieces(program, max_mm, max_deg, 0, program.n_blocks)[2].sum())


def subdivide(
    program: Program,
    max_mm: float = 5.0,
    max_deg: float = 5.0,
    blocks: slice = slice(None),
    count: int | None = None,
) -> Points:
    """Return the points of ``blocks``: G1 segments longer than max_mm / max_deg split evenly (ch. 7.2).

    Rapid (G0) moves are not cut: they are not cutting moves. Points follow the controller's
    joint-space linear interpolation, so the correction tracks the kinematic error along the
    segment rather than only at its ends. ``count``: how many points all the program's blocks make
    (``count_points`` with these lengths, when already known): one a block needs no measuring.
    """
    b0, b1, _ = blocks.indices(program.n_blocks)
    if count is not None and count == program.n_blocks and (b0, b1) == (0, program.n_blocks):
        return Points(block=np.arange(b0, b1), nominal_int=program.target_int.copy())
    start, end, pieces = _pieces(program, max_mm, max_deg, b0, b1)
    block = np.repeat(np.arange(b0, b1), pieces)
    if block.shape[0] == end.shape[0]:
        return Points(block=block, nominal_int=end.copy())
    first = np.cumsum(pieces) - pieces
    j = np.arange(block.shape[0]) - np.repeat(first, pieces) + 1
    frac = (j / np.repeat(pieces, pieces))[:, None]
    rel = block - b0
    nominal = start[rel] + np.rint((end[rel] - start[rel]) * frac).astype(np.int64)
    return Points(block=block, nominal_int=nominal)


_LUT4 = np.array([list(f"{i:04d}".encode()) for i in range(10000)], dtype=np.uint8)


def _digits(a: np.ndarray, k: int) -> np.ndarray:
    """Return the (M, k) ASCII digits of non-negative integers ``a`` < 10**k, zero-padded."""
    groups = -(-k // 4)
    out = np.empty((a.shape[0], 4 * groups), dtype=np.uint8)
    rest = a
    for j in range(groups - 1, -1, -1):
        rest, r = np.divmod(rest, 10000)
        out[:, 4 * j : 4 * j + 4] = _LUT4[r]
    return out[:, 4 * groups - k :]


def format_fixed(values: np.ndarray, decimals: int) -> tuple[np.ndarray, np.ndarray]:
    """Return (bytes, lengths) of integers ``values`` (units 10**-decimals) written as decimals.

    Always one digit before and at least one after the point (``-0.5``, ``12.0``): a bare
    integer means a count of least increments on some controllers.
    """
    chars, start, length = _fixed_rows(values, decimals)
    cols = np.arange(chars.shape[1])[None, :]
    return chars[(cols >= start[:, None]) & (cols < (start + length)[:, None])], length


def _fixed_rows(values: np.ndarray, decimals: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (chars (M, W), start (M,), length (M,)): value k written as ``format_fixed`` writes it is
    ``chars[k, start[k] : start[k] + length[k]]`` (the sign stands just before the first digit written)."""
    v = np.asarray(values, dtype=np.int64)
    m = v.shape[0]
    neg = v < 0
    a = np.abs(v)
    ip, fp = np.divmod(a, 10**decimals)
    n_int = len(str(int(ip.max(initial=0))))
    idig = _digits(ip, n_int)
    nz = idig != 48
    first = np.where(nz.any(axis=1), np.argmax(nz, axis=1), n_int - 1)
    fd = max(decimals, 1)
    fdig = _digits(fp, decimals) if decimals else np.full((m, 1), 48, dtype=np.uint8)
    keep_f = np.maximum(fd - np.argmax(fdig[:, ::-1] != 48, axis=1), 1)
    keep_f[~(fdig != 48).any(axis=1)] = 1
    width = 1 + n_int + 1 + fd
    chars = np.empty((m, width), dtype=np.uint8)
    chars[:, 0] = 45
    chars[:, 1 : 1 + n_int] = idig
    chars[:, 1 + n_int] = 46
    chars[:, 2 + n_int :] = fdig
    chars[np.flatnonzero(neg), first[neg]] = 45  # over a leading zero, or the first column
    return chars, 1 + first - neg, neg + (n_int - first) + 1 + keep_f


def _concat_pieces(sources: np.ndarray, start: np.ndarray, length: np.ndarray) -> bytes:
    """Return the concatenation of slices ``sources[start:start+length]`` in order."""
    keep = length > 0
    start, length = start[keep], length[keep]
    total = int(length.sum())
    if total == 0:
        return b""
    off = np.cumsum(length) - length
    # index = running count of ones, jumping at each piece to the piece's source offset
    itype = np.int32 if sources.shape[0] < 2**31 - 1 else np.int64
    step = np.ones(total, dtype=itype)
    step[off] = start - np.concatenate(([0], start[:-1] + length[:-1] - 1))
    return sources[np.cumsum(step, dtype=itype)].tobytes()


@dataclass(frozen=True)
class _Edits:
    """Edits of a program's text in byte order: each writes a prefix (``_PREFIXES``) and a number at ``pos``.

    ``end`` is where the text resumes after the edit (past the old number a replacement covers, else ``pos``).
    """

    pos: np.ndarray
    end: np.ndarray
    prefix: np.ndarray
    value: np.ndarray
    axis: np.ndarray  # -1: no number (a line end)
    #: the sort key within one byte position (insertions at one place keep their order)
    key: np.ndarray

    @classmethod
    def join(cls, parts: list[_Edits]) -> _Edits:
        """Return the edits of ``parts`` together, in byte order."""
        pos, end, prefix, value, axis, key = (
            np.concatenate([getattr(p, f) for p in parts]).astype(np.int64, copy=False) for f in _EDIT_FIELDS
        )
        if np.any(pos[1:] < pos[:-1]) or any(p.pos.shape[0] for p in parts[1:]):
            # edits are made in runs already in byte order, so a stable sort of one key is nearly free
            order = np.argsort(pos * (1 << 20) + np.minimum(key, (1 << 20) - 1), kind="stable")
            pos, end, prefix, value, axis, key = (a[order] for a in (pos, end, prefix, value, axis, key))
        return cls(pos, end, prefix, value, axis, key)


_EDIT_FIELDS = ("pos", "end", "prefix", "value", "axis", "key")


def _point_lines(program: Program, points: Points, resume: bool) -> tuple[np.ndarray, np.ndarray]:
    """Return (P,) whether each point is its block's first (on the block's own line), and its number in the block."""
    blk = points.block
    first = np.ones(points.n, dtype=bool)
    first[1:] = blk[1:] != blk[:-1]
    first[0] = not resume
    starts = first.copy()
    starts[0] = True  # a resumed block counts its points from the first one given
    fidx = np.flatnonzero(starts)
    sub = np.arange(points.n) - np.repeat(fidx, np.diff(np.append(fidx, points.n))) + int(resume)
    return first, sub


def _word_edits(program: Program, fb: np.ndarray, fval: np.ndarray, moved: np.ndarray) -> list[_Edits]:
    """Return the edits of the blocks' own lines: changed words replaced, words for axes that move inserted."""
    present = program.present[fb]
    r_b, r_a = np.nonzero(present & (fval != program.word_int[fb]))
    replace_words = _Edits(
        program.num_start[fb[r_b], r_a],
        program.num_end[fb[r_b], r_a],
        np.zeros_like(r_b),
        fval[r_b, r_a],
        r_a,
        np.zeros_like(r_b),
    )
    i_b, i_a = np.nonzero(~present & moved)
    at = program.insert_at[fb[i_b]]
    prefix = 1 + i_a + 5 * program.spaced[fb[i_b]]
    return [replace_words, _Edits(at, at, prefix, fval[i_b, i_a], i_a, 1 + i_a)]


def _new_line_edits(
    program: Program, blk: np.ndarray, gen: np.ndarray, value: np.ndarray, sub: np.ndarray
) -> list[_Edits]:
    """Return the lines of points after a block's first: their words and line ends, after the block's line.

    A newline goes before them when the block's line is the last of a text without a final newline.
    """
    after = np.append(program.line_start[1:], len(program.data))
    g_p, g_a = np.nonzero(gen)
    at = after[program.block_line[blk[g_p]]]
    lead = np.ones(g_p.shape[0], dtype=bool)
    lead[1:] = g_p[1:] != g_p[:-1]
    words = _Edits(at, at, 1 + g_a + 5 * ~lead, value[g_p, g_a], g_a, sub[g_p] * 8 + g_a)
    gp = np.unique(g_p)
    gpl = program.block_line[blk[gp]]
    ends = after[gpl]
    none = np.full(gp.shape[0], -1)
    line_ends = _Edits(ends, ends, np.full(gp.shape[0], 11), np.zeros_like(none), none, sub[gp] * 8 + 6)
    bare = np.unique(gpl[~program.has_newline[gpl]])
    at = program.line_end[bare]
    nobare = np.full(bare.shape[0], -1)
    return [
        words,
        line_ends,
        _Edits(at, at, np.full(bare.shape[0], 11), np.zeros_like(nobare), nobare, np.full(bare.shape[0], 7)),
    ]


def _splice(program: Program, edits: _Edits, lo: int, hi: int) -> bytes:
    """Return the text from byte ``lo`` to ``hi`` with ``edits`` made (numbers written in the program's decimals)."""
    data = np.frombuffer(program.data, dtype=np.uint8)
    pos, ax, endp = edits.pos, edits.axis, edits.end
    num_start = np.zeros(pos.shape[0], dtype=np.int64)
    num_len = np.zeros(pos.shape[0], dtype=np.int64)
    pools = []
    pool_off = 0
    for axes_sel, dec in (((ax >= 0) & (ax < 3), program.decimals[0]), (ax >= 3, program.decimals[1])):
        sel = np.flatnonzero(axes_sel)
        if sel.shape[0]:
            chars, first, lens = _fixed_rows(edits.value[sel], dec)
            num_len[sel] = lens
            num_start[sel] = pool_off + np.arange(sel.shape[0]) * chars.shape[1] + first
            pools.append(chars.ravel())
            pool_off += chars.size
    prefix_text = [b""] + [a.encode() for a in AXES] + [b" " + a.encode() for a in AXES] + [program.eol]
    ptab = np.frombuffer(b"".join(prefix_text), dtype=np.uint8)
    plen = np.array([len(p) for p in prefix_text], dtype=np.int64)
    poff = np.cumsum(plen) - plen
    base_pool = data.shape[0] + ptab.shape[0]
    sources = np.concatenate([data, ptab] + pools)
    kept_from = np.empty(pos.shape[0], dtype=np.int64)
    kept_from[0] = lo
    kept_from[1:] = endp[:-1]
    e = pos.shape[0]
    starts = np.empty((e, 3), dtype=np.int64)
    lens = np.empty((e, 3), dtype=np.int64)
    starts[:, 0], lens[:, 0] = kept_from, pos - kept_from
    starts[:, 1], lens[:, 1] = data.shape[0] + poff[edits.prefix], plen[edits.prefix]
    starts[:, 2], lens[:, 2] = base_pool + num_start, num_len
    starts = np.append(starts.ravel(), endp[-1])
    lens = np.append(lens.ravel(), hi - endp[-1])
    return _concat_pieces(sources, starts, lens)


def emit(
    program: Program,
    points: Points | None = None,
    sent_int: np.ndarray | None = None,
    prev_sent: np.ndarray | None = None,
    lines: slice = slice(None),
    resume: bool = False,
) -> bytes:
    """Return the program text of ``lines`` with ``points`` commanded at ``sent_int`` (integer units).

    Words whose commanded value equals the value written are kept byte for byte; changed
    words get new numbers; axes that must move but have no word get one (after the block's
    last axis word); points after a block's first go on new lines after it. In G91 blocks
    the written value is the increment from the previous commanded pose. ``prev_sent`` is
    the commanded pose before the first point (default: the program's start pose). With no
    points, the lines come back unchanged. ``points`` must cover exactly the blocks of ``lines``;
    with ``resume`` the first point continues a block whose line was emitted before (``lines``
    then starts right after that block's line) and only gets a new line of its own.
    """
    l0, l1, _ = lines.indices(program.n_lines)
    lo = int(program.line_start[l0]) if l0 < program.n_lines else len(program.data)
    hi = int(program.line_start[l1]) if l1 < program.n_lines else len(program.data)
    if points is None or points.n == 0:
        return program.data[lo:hi]
    sent_int = np.asarray(points.nominal_int if sent_int is None else sent_int, dtype=np.int64)
    blk = points.block
    lines_of = program.block_line[blk]
    first_line = l0 - 1 if resume else l0
    if lines_of[0] < first_line or lines_of[-1] >= max(l1, first_line + 1):
        raise ValueError("points outside the emitted lines")
    first, sub = _point_lines(program, points, resume)
    prev = np.empty_like(sent_int)
    prev[0] = program.start_int if prev_sent is None else prev_sent
    prev[1:] = sent_int[:-1]
    value = np.where(program.incremental[blk][:, None], sent_int - prev, sent_int)
    moved = sent_int != prev
    parts = _word_edits(program, blk[first], value[first], moved[first])
    parts += _new_line_edits(program, blk, moved & ~first[:, None], value, sub)
    edits = _Edits.join(parts)
    if edits.pos.shape[0] == 0:
        return program.data[lo:hi]
    return _splice(program, edits, lo, hi)


def emit_program(
    program: Program,
    points: Points | None = None,
    sent_int: np.ndarray | None = None,
    chunk_lines: int = 1 << 15,
) -> bytes:
    """Return the whole program with ``points`` commanded at ``sent_int`` (see ``emit``).

    Works through the program in runs of lines so that the working arrays stay small.
    """
    if points is None or points.n == 0:
        return program.data
    if sent_int is None:
        sent_int = points.nominal_int
    point_line = program.block_line[points.block]
    out = []
    for l0 in range(0, program.n_lines, chunk_lines):
        l1 = min(program.n_lines, l0 + chunk_lines)
        p0, p1 = np.searchsorted(point_line, [l0, l1])
        prev = program.start_int if p0 == 0 else sent_int[p0 - 1]
        sub = Points(block=points.block[p0:p1], nominal_int=points.nominal_int[p0:p1])
        out.append(emit(program, sub, sent_int[p0:p1], prev_sent=prev, lines=slice(l0, l1)))
    return b"".join(out)
