"""Tables a person reads on a terminal or in a pipe, never with a word or a number split, and as CSV.

rich fits a table to the console by narrowing its widest columns, below their longest word if it
must: at 80 columns `alpha` printed as `alph|a`, `6.02e+04` as `6.0|2e+|04` (issue 35.4). Here the
widths are chosen before rich sees the table: each column gets at least its longest word (or
number), the room left goes first to the columns that need least to stop wrapping, and each column's
width is then fixed, so rich wraps cells only between words. When even the longest words do not fit
the terminal, the rows are printed as records (``header: value`` lines), readable at any width.
Piped (not a terminal), a table is printed at its natural width (one row a line, nothing wrapped,
no colour), or fitted to ``COLUMNS`` when that is set. ``--csv`` prints the same tables as CSV
instead (``# title`` before each).

Units are shown as SI symbols (µm, µrad, °C): cells and titles pass through ``labels.si_text``,
as the modelling core's messages still spell them in ASCII.
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import sys
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from driftlab.labels import si_text

if TYPE_CHECKING:  # rich is imported where a table is printed: `driftlab --help` does not pay for it
    from rich.console import Console
    from rich.table import Table


def add_csv_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--csv``: print the command's tables as CSV (``# title`` before each) instead of drawn."""
    parser.add_argument(
        "--csv", action="store_true", help="print the tables as CSV (a '# title' line before each) instead of drawn"
    )


def _si_cell(cell: Any) -> Any:
    """Return a cell with SI unit symbols (a styled Text whose length would change is left as it is)."""
    from rich.text import Text

    if isinstance(cell, str):
        return si_text(cell)
    if isinstance(cell, Text):
        plain = si_text(cell.plain)
        if plain == cell.plain:
            return cell
        if not cell.spans or len(plain) == len(cell.plain):
            out = Text(plain, style=cell.style, justify=cell.justify, no_wrap=cell.no_wrap)
            out.spans = list(cell.spans)
            return out
    return cell


def si_table(table: Table) -> Table:
    """Return ``table`` with SI unit symbols in its title, headers and cells (changed in place)."""
    if isinstance(table.title, str):
        table.title = si_text(table.title)
    if isinstance(table.caption, str):
        table.caption = si_text(table.caption)
    for col in table.columns:
        col.header = _si_cell(col.header)
        col._cells = [_si_cell(c) for c in col._cells]
    return table


def _measure(table: Table) -> tuple[list[int], list[int], int]:
    """Return each column's (longest word, natural width) and the table's padding and borders, in cells."""
    from rich.console import Console
    from rich.measure import Measurement

    console = Console(width=100_000, no_color=True)
    options = console.options
    lows, highs = [], []
    for col in table.columns:
        cells: list[Any] = [col.header] if table.show_header else []
        cells.extend(col.cells)
        if table.show_footer:
            cells.append(col.footer)
        lo = hi = 1
        for cell in cells:
            m = Measurement.get(console, options, cell)
            lo, hi = max(lo, m.minimum), max(hi, m.maximum)
        lows.append(hi if col.no_wrap else lo)  # a column that must not wrap needs its whole text
        highs.append(hi)
    overhead = table._extra_width + sum(table._get_padding_width(i) for i in range(len(table.columns)))
    return lows, highs, overhead


def fit_widths(table: Table, width: int) -> bool:
    """Fix each column's width so the table fits ``width`` with no word split; False when it cannot."""
    if not table.columns:
        return True
    lows, highs, overhead = _measure(table)
    room = width - overhead
    if sum(lows) > room:
        return False
    widths = list(lows)
    spare = room - sum(lows)
    # the room goes first to the columns that need least of it to stop wrapping: fewest wrapped rows
    for i in sorted(range(len(widths)), key=lambda k: highs[k] - lows[k]):
        give = min(spare, highs[i] - widths[i])
        widths[i] += give
        spare -= give
    for col, w in zip(table.columns, widths):
        col.width, col.min_width, col.max_width = w, None, None
    return True


def _columns() -> int | None:
    """Return the width the COLUMNS variable asks for (20 or more), or None."""
    try:
        width = int(os.environ.get("COLUMNS", ""))
    except ValueError:
        return None
    return width if width >= 20 else None


def natural_width(table: Table) -> int:
    """Return the width at which ``table`` prints with nothing wrapped."""
    _, highs, overhead = _measure(table)
    return sum(highs) + overhead


def _plain(cell: Any) -> str:
    """Return a cell's text without markup or style."""
    from rich.text import Text

    if isinstance(cell, Text):
        return cell.plain
    if isinstance(cell, str):
        try:
            return Text.from_markup(cell).plain
        except Exception:  # rich.errors.MarkupError: a cell that merely contains brackets
            return cell
    return str(cell)


def rows(table: Table) -> tuple[list[str], list[list[str]]]:
    """Return (headers, rows) of ``table`` as plain strings (newlines in headers become spaces)."""
    headers = [" ".join(_plain(c.header).split()) for c in table.columns]
    columns = [[_plain(c) for c in col.cells] for col in table.columns]
    return headers, [list(r) for r in zip(*columns)] if columns else []


def records(table: Table) -> str:
    """Return the rows of ``table`` as records, one ``header: value`` line per cell (any width)."""
    headers, body = rows(table)
    lines = [_plain(table.title)] if table.title else []
    for n, row in enumerate(body, 1):
        lines.append(f"  row {n}")
        lines.extend(f"    {h or '-'}: {' '.join(v.split())}" for h, v in zip(headers, row))
    return "\n".join(lines)


def tables_csv(tables: Iterable[Table]) -> str:
    """Return the tables as CSV blocks: ``# title``, the header row, the rows; a blank line between."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    for k, table in enumerate(tables):
        si_table(table)
        if k:
            out.write("\n")
        if table.title:
            out.write(f"# {' '.join(_plain(table.title).split())}\n")
        headers, body = rows(table)
        if any(headers):
            writer.writerow(headers)
        writer.writerows([[" ".join(v.split()) for v in row] for row in body])
    return out.getvalue()


def print_table(table: Table, console: Console | None = None) -> None:
    """Print ``table`` readable at the console's width (or at its natural width when piped)."""
    from rich.console import Console

    si_table(table)
    if console is None:
        console = Console() if sys.stdout.isatty() else Console(no_color=True)
    if not console.is_terminal:
        # piped: the width COLUMNS asks for (the demo draws its steps' tables for its terminal), else
        # the table's natural width, one row a line
        width = _columns() or max(natural_width(table), 40)
        console = Console(file=console.file, width=width, no_color=True)
    if fit_widths(table, console.width):
        console.print(table)
    else:
        console.print(records(table), markup=False, highlight=False, soft_wrap=True)


def print_text(line: str, console: Console | None = None) -> None:
    """Print one line of text for a person, with SI unit symbols, never cut at the console's width."""
    from driftlab.progress import stdout_console

    (console or stdout_console()).print(si_text(line), markup=False, highlight=False, soft_wrap=True)


class Output:
    """A command's output for a person: lines and tables in order, printed together (drawn or ``--csv``).

    ``print(x)`` takes a line of text (rich markup allowed) or a ``Table``, as ``Console.print`` does,
    so a command's printing functions take one or the other.
    """

    def __init__(self) -> None:
        self.items: list[Any] = []

    def print(self, item: Any, *_: Any, markup: bool = True, **__: Any) -> None:
        """Keep a line (rich markup unless ``markup=False``) or a table for ``emit``."""
        self.items.append((item, markup))

    def emit(self, as_csv: bool = False, console: Console | None = None) -> None:
        """Print everything kept: tables drawn to fit (lines with SI units), or only the tables as CSV."""
        from rich.table import Table

        from driftlab.progress import stdout_console

        tables = [t for t, _ in self.items if isinstance(t, Table)]
        if as_csv:
            sys.stdout.write(tables_csv(tables))
            return
        con = console or stdout_console()
        for item, markup in self.items:
            if isinstance(item, Table):
                print_table(item, con)
            else:
                text = si_text(item if isinstance(item, str) else _plain(item))
                con.print(text, markup=markup, highlight=False, soft_wrap=True)
