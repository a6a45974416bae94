"""driftlab.yamlfile: a YAML file's document, or why there is none (read error, or the syntax error's line)."""

from __future__ import annotations

from driftlab.yamlfile import read_yaml


def test_a_document_is_returned_with_no_failure(tmp_path):
    p = tmp_path / "a.yaml"
    p.write_text("name: demo\nhours: [1, 2]\n")
    got = read_yaml(p)
    assert got.doc == {"name": "demo", "hours": [1, 2]}
    assert got.unreadable is None and got.problem is None and got.at(":{}") == ""


def test_a_syntax_error_names_its_one_based_line(tmp_path):
    p = tmp_path / "b.yaml"
    p.write_text("name: demo\nhours: [1,\n")
    got = read_yaml(p)
    assert got.doc is None and got.unreadable is None
    assert got.line == 3 and got.at(" line {}") == " line 3"
    assert got.problem and "expected" in got.problem


def test_an_unreadable_file_is_reported_not_raised(tmp_path):
    got = read_yaml(tmp_path / "missing.yaml")
    assert isinstance(got.unreadable, FileNotFoundError) and got.problem is None
    assert isinstance(read_yaml(tmp_path).unreadable, IsADirectoryError)


def test_an_empty_file_is_an_empty_document(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("")
    got = read_yaml(p)
    assert got.doc is None and got.unreadable is None and got.problem is None
