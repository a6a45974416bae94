"""Tables a person reads (issue 35.4): no word or number split at any width, piped at natural width, CSV."""

from __future__ import annotations

import csv
import io
import re

import pytest
from rich.console import Console
from rich.table import Table

from driftlab.commands.tables import Output, fit_widths, print_table, tables_csv
from driftlab.labels import si_text

WORDS = ["alpha", "µrad", "6.02e+04", "T1+phi_y+theta_x+T2+phi_z+theta_y", "Y Straightness", "at the noise"]


def _table() -> Table:
    t = Table(title="Per-link models: RMSE of the work-space error (um)", title_justify="left")
    for h in ("axis", "term", "unit", "F", "link", "measurement", "verdict"):
        t.add_column(h)
    for k in range(6):
        t.add_row("X", "alpha", "urad", f"{6.02e4 * (k + 1):.3g}", WORDS[3], "Y Straightness", "[green]at the noise[/]")
    return t


def _render(width: int) -> str:
    out = io.StringIO()
    print_table(_table(), Console(file=out, width=width, force_terminal=True, color_system=None))
    return out.getvalue()


@pytest.mark.parametrize("width", [24, 40, 60, 80, 100, 120, 200])
def test_no_word_or_number_is_split_at_any_width(width: int) -> None:
    text = _render(width)
    if "row 1" not in text:  # drawn: within the width (records are never cut: the terminal wraps them)
        assert all(len(line) <= width for line in text.splitlines()), text
    tokens = set(re.findall(r"[^\s│┃|]+", text))
    for word in ("alpha", "µrad", "6.02e+04", "1.81e+05", WORDS[3], "Straightness"):
        assert word in tokens, (width, word, text)
    assert "urad" not in tokens  # units for people: SI symbols


def test_a_table_too_wide_for_its_words_is_printed_as_records() -> None:
    text = _render(30)
    assert "row 1" in text and f"link: {WORDS[3]}" in text


def test_a_fitted_table_fits_and_one_that_cannot_is_refused() -> None:
    t = _table()
    assert fit_widths(t, 120) and sum(c.width or 0 for c in t.columns) <= 120
    assert not fit_widths(_table(), 30)


def test_piped_tables_print_at_their_natural_width(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("COLUMNS", raising=False)  # a stated width is honoured instead (make and CI may set one)
    print_table(_table())
    lines = capsys.readouterr().out.splitlines()
    body = [ln for ln in lines if ln.startswith("│")]
    assert len(body) == 6  # one row a line: nothing wrapped
    assert "\x1b[" not in "".join(lines)  # no colour in a pipe


def test_csv_is_the_same_table(capsys: pytest.CaptureFixture[str]) -> None:
    out = Output()
    out.print("a line")
    out.print(_table())
    out.emit(as_csv=True)
    text = capsys.readouterr().out
    assert text.startswith("# Per-link models: RMSE of the work-space error (µm)\n")
    rows = list(csv.reader(io.StringIO(text.split("\n", 1)[1])))
    assert rows[0] == ["axis", "term", "unit", "F", "link", "measurement", "verdict"]
    assert rows[1] == ["X", "alpha", "µrad", "6.02e+04", WORDS[3], "Y Straightness", "at the noise"]
    assert len(rows) == 7 and tables_csv([]) == ""


@pytest.mark.parametrize(
    "text, expected",
    [
        ("stated noise 0.5 um, 0.48 urad", "stated noise 0.5 µm, 0.48 µrad"),
        ("2.4e-05 rad/degC, 0.0018 mm/degC", "2.4e-05 rad/°C, 0.0018 mm/°C"),
        ("X/dx residual (um); variance um2", "X/dx residual (µm); variance µm²"),
        ("value_degC, drift_um stay; museum, umbrella", "value_degC, drift_um stay; museum, umbrella"),
    ],
)
def test_si_text(text: str, expected: str) -> None:
    assert si_text(text) == expected
