"""A throwaway PostgreSQL cluster (initdb + pg_ctl) for tests and benchmarks.

initdb refuses to run as root, so when the effective uid is 0 the server binaries run as the
``postgres`` user through ``runuser`` and the cluster directory is owned by that user.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path

from driftlab.errors import DriftlabError


class PgClusterError(DriftlabError):
    """The throwaway PostgreSQL cluster could not be created or started."""


def pg_binaries_available() -> bool:
    """Return True when initdb and pg_ctl are on PATH (and runuser, when running as root)."""
    needed = ["initdb", "pg_ctl"] + (["runuser"] if os.geteuid() == 0 else [])
    return all(shutil.which(name) for name in needed)


def free_port() -> int:
    """Return a TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class PgCluster:
    """A private PostgreSQL server in a temp directory, on 127.0.0.1 with trust auth."""

    def __init__(self, base_dir: str | Path | None = None, fast: bool = True) -> None:
        """Prepare (not start) a cluster under ``base_dir`` (a fresh temp dir when None)."""
        self.root = Path(tempfile.mkdtemp(prefix="driftlab-pg-", dir=base_dir))
        self.data = self.root / "data"
        self.port = 0
        self.fast = fast
        self._as_postgres = os.geteuid() == 0
        self._started = False
        self._options = ""

    def _run(self, args: list[str]) -> subprocess.CompletedProcess[str]:
        cmd = ["runuser", "-u", "postgres", "--", *args] if self._as_postgres else args
        return subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=self.root)

    def start(self, attempts: int = 3) -> str:
        """Create and start the cluster; return its SQLAlchemy URL (database ``postgres``)."""
        if not pg_binaries_available():
            raise PgClusterError("PostgreSQL server binaries (initdb, pg_ctl) are not on PATH")
        if self._as_postgres:
            pw = pwd.getpwnam("postgres")
            os.chown(self.root, pw.pw_uid, pw.pw_gid)
        init = self._run(["initdb", "-D", str(self.data), "-U", "postgres", "--auth=trust", "-E", "UTF8", "--no-sync"])
        if init.returncode != 0:
            raise PgClusterError(f"initdb failed: {' '.join(init.stderr.split())[:300]}")
        options = f"-c listen_addresses=127.0.0.1 -c unix_socket_directories={self.root}"
        if self.fast:
            options += " -c fsync=off -c synchronous_commit=off -c full_page_writes=off"
        self._options = options
        last = ""
        for _ in range(attempts):
            self.port = free_port()
            proc = self._pg_ctl_start()
            if proc.returncode == 0:
                self._started = True
                return self.url()
            last = " ".join((proc.stderr or proc.stdout).split())[:300]
        raise PgClusterError(f"pg_ctl start failed: {last}")

    def _pg_ctl_start(self) -> subprocess.CompletedProcess[str]:
        """Start the server on ``self.port`` and wait until it accepts connections."""
        log = str(self.root / "server.log")
        return self._run(
            [
                "pg_ctl",
                "-D",
                str(self.data),
                "-l",
                log,
                "-w",
                "-t",
                "60",
                "-o",
                f"-p {self.port} {self._options}",
                "start",
            ]
        )

    def halt(self) -> None:
        """Stop the server (fast shutdown: clients are disconnected) and keep its data, to ``resume`` it."""
        proc = self._run(["pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "stop"])
        if proc.returncode != 0:
            raise PgClusterError(f"pg_ctl stop failed: {' '.join((proc.stderr or proc.stdout).split())[:300]}")

    def resume(self) -> None:
        """Start a halted server again on the same port (what `pg_ctl stop; pg_ctl start` does to clients)."""
        proc = self._pg_ctl_start()
        if proc.returncode != 0:
            raise PgClusterError(f"pg_ctl start failed: {' '.join((proc.stderr or proc.stdout).split())[:300]}")

    def url(self, database: str = "postgres") -> str:
        """Return the SQLAlchemy URL of a database of this cluster."""
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str | None = None, template: str | None = None) -> str:
        """Create a database (optionally copied from ``template``) and return its URL."""
        # lazy: psycopg adds 0.19 s to `import driftlab.testing.pgcluster` (measured); SQLite runs never need it
        import psycopg

        name = name or f"t_{uuid.uuid4().hex[:16]}"
        with psycopg.connect(f"host=127.0.0.1 port={self.port} user=postgres dbname=postgres", autocommit=True) as conn:
            tmpl = f" TEMPLATE {template}" if template else ""
            conn.execute(f'CREATE DATABASE "{name}"{tmpl}')
        return self.url(name)

    def stop(self) -> None:
        """Stop the server (immediately) and delete its directory."""
        if self._started:
            self._run(["pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop"])
            self._started = False
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> PgCluster:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
