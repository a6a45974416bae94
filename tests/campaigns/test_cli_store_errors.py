"""Every command that opens the store: an unreachable, read-only or unwritable database is one line on
stderr and a non-zero exit, never a traceback (``-v`` shows the traceback). The daemon checks it can
write before it starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from driftlab.cli import main

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

#: (id, argv after the command name; --db is appended)
COMMANDS = [
    ("db-upgrade", ["db", "upgrade"]),
    ("db-current", ["db", "current"]),
    ("campaign-list", ["campaign", "list"]),
    ("campaign-status", ["campaign", "status"]),
    ("export", ["export", "1", "{tmp}/out"]),
    ("drift", ["drift", "--machine", "m1", "--axis", "Z", "--term", "dz"]),
    ("fit", ["fit", "--campaign", "1"]),
    ("models-list", ["models", "list"]),
    ("models-show", ["models", "show", "current", "--machine", "m1"]),
    ("diagnose", ["diagnose", "--campaign", "1", "--json", "{tmp}/r.json"]),
    ("import", ["import", "{bundle}"]),
    (
        "daemon",
        [
            "daemon",
            "--plan",
            str(EXAMPLES / "plans" / "demo-z.yaml"),
            "--sim",
            str(EXAMPLES / "scenarios" / "demo-drift.yaml"),
            "--speed",
            "0",
        ],
    ),
]

#: (id, url template): an unreachable PostgreSQL, a SQLite file under a path that cannot exist
STORES = [
    ("pg-unreachable", "postgresql+psycopg://nobody@127.0.0.1:1/driftlab?connect_timeout=2"),
    ("sqlite-unwritable-dir", "sqlite:////proc/driftlab-none/store.sqlite"),
]


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str], str]:
    capsys.readouterr()
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.err.strip().splitlines(), captured.err


@pytest.mark.parametrize("store", STORES, ids=[s[0] for s in STORES])
@pytest.mark.parametrize("command", COMMANDS, ids=[c[0] for c in COMMANDS])
def test_store_failure_is_one_line(command, store, tmp_path: Path, bundle_dir: Path, capsys) -> None:
    _, template = command
    argv = [a.format(tmp=tmp_path, bundle=bundle_dir) for a in template] + ["--db", store[1]]
    code, lines, err = _run(argv, capsys)
    assert code != 0
    assert len(lines) == 1, err
    assert lines[0].startswith("driftlab: error:") and "Traceback" not in err


def test_verbose_shows_the_traceback(capsys) -> None:
    code, lines, err = _run(["-v", "campaign", "list", "--db", STORES[0][1]], capsys)
    assert code == 1
    assert "Traceback (most recent call last)" in err
    assert lines[-1].startswith("driftlab: error: database:")


def test_read_only_sqlite_store_at_a_fresh_start(tmp_path: Path, capsys) -> None:
    """A fresh daemon on a store it cannot write: refused before it starts, in one line."""
    path = tmp_path / "store.sqlite"
    assert main(["db", "upgrade", "--db", f"sqlite:///{path}"]) == 0
    url = f"sqlite:///file:{path}?mode=ro&uri=true"  # read-only even for root (chmod is not)
    code, lines, err = _run(
        [
            "daemon",
            "--plan",
            str(EXAMPLES / "plans" / "demo-z.yaml"),
            "--sim",
            str(EXAMPLES / "scenarios" / "demo-drift.yaml"),
            "--speed",
            "0",
            "--db",
            url,
        ],
        capsys,
    )
    assert code != 0 and len(lines) == 1, err
    assert "cannot write to the store" in lines[0] and "readonly" in lines[0]
    empty = f"sqlite:///file:{tmp_path / 'none.sqlite'}?mode=ro&uri=true"
    code, lines, err = _run(["daemon", "--plan", str(EXAMPLES / "plans" / "demo-z.yaml"), "--db", empty], capsys)
    assert code != 0 and len(lines) == 1 and lines[0].startswith("driftlab: error:"), err


@pytest.mark.postgres
def test_read_only_postgresql_store(pg_cluster, capsys) -> None:
    import psycopg

    url = pg_cluster.create_database()
    assert main(["db", "upgrade", "--db", url]) == 0
    dbname = url.rsplit("/", 1)[1]
    with psycopg.connect(url.replace("postgresql+psycopg://", "postgresql://"), autocommit=True) as conn:
        conn.execute(f'ALTER DATABASE "{dbname}" SET default_transaction_read_only = on')
    code, lines, err = _run(
        [
            "daemon",
            "--plan",
            str(EXAMPLES / "plans" / "demo-z.yaml"),
            "--sim",
            str(EXAMPLES / "scenarios" / "demo-drift.yaml"),
            "--speed",
            "0",
            "--db",
            url,
        ],
        capsys,
    )
    assert code != 0 and len(lines) == 1, err
    assert "cannot write to the store" in lines[0] and "read-only" in lines[0]


def test_unreadable_bundle_file(bundle_dir: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """A file that cannot be opened (PermissionError; simulated, since root reads any file)."""
    import os

    target = bundle_dir / "errors.csv"
    if os.geteuid() != 0:
        target.chmod(0)
    else:
        real_open = Path.open

        def deny(self: Path, *args, **kwargs):
            if self.name == "errors.csv":
                raise PermissionError(13, "Permission denied", str(self))
            return real_open(self, *args, **kwargs)

        monkeypatch.setattr(Path, "open", deny)
    url = f"sqlite:///{tmp_path / 's.sqlite'}"
    code, lines, err = _run(["import", str(bundle_dir), "--db", url], capsys)
    assert code == 2 and lines == ["driftlab: error: errors.csv: cannot read: Permission denied"], err
