"""The campaign store: one engine over SQLite or PostgreSQL and one repository per aggregate.

``Store`` holds the engine and its repositories, which share it, its schema gate and
``db.write_transaction`` (``campaigns.repository``):

- ``store.campaigns``: import, export, list, describe and delete campaigns; machines; the
  acquisition scheduler's resume point (``campaign_repo``);
- ``store.readings``: drift across campaigns, histories and their pages, the latest scan
  (``readings_repo``);
- ``store.models``: the model registry (``model_repo``);
- ``store.jobs``: job records (``job_repo``);
- ``store.online``: the machines' on-line (RLS) state and probe measurements (``online_repo``).

Writes happen in one transaction each: an import either lands whole or leaves the database exactly
as it was, whatever interrupts it. The repositories are the store's one API (the names bound on
``Store`` before them are gone, issue 36); ``Store`` itself keeps only what concerns the whole
database (schema, row counts, ping, planner statistics).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from driftlab.campaigns import db, repository
from driftlab.campaigns.campaign_repo import CampaignRepository, CampaignSummary, MachineInfo, ProgressInfo
from driftlab.campaigns.job_repo import QUEUE_STATES, JobInfo, JobRepository, job_info, jobs_select
from driftlab.campaigns.model_repo import ModelRepository, ModelRow, ModelVersionInfo, RefitCandidate
from driftlab.campaigns.online_repo import OnlineStateInfo, OnlineStateRepository, OnlineUpdate, StaleOnlineState
from driftlab.campaigns.readings_repo import ReadingRepository
from driftlab.config import Settings

if TYPE_CHECKING:
    from sqlalchemy import Engine

__all__ = [
    "QUEUE_STATES",
    "CampaignSummary",
    "JobInfo",
    "MachineInfo",
    "ModelRow",
    "ModelVersionInfo",
    "OnlineStateInfo",
    "OnlineUpdate",
    "ProgressInfo",
    "RefitCandidate",
    "StaleOnlineState",
    "Store",
    "connect",
    "job_info",
    "jobs_select",
]


class Store:
    """A campaign store on one database; the schema is brought to head on first use."""

    def __init__(self, engine: Engine, auto_upgrade: bool = True) -> None:
        """Wrap an engine; with ``auto_upgrade`` the schema is upgraded on first use."""
        self.engine = engine
        self.gate = repository.SchemaGate(engine, auto_upgrade)
        self.campaigns = CampaignRepository(self.gate)
        self.readings = ReadingRepository(self.gate)
        self.models = ModelRepository(self.gate)
        self.jobs = JobRepository(self.gate)
        self.online = OnlineStateRepository(self.gate)

    @property
    def url(self) -> str:
        """Return the database URL (password hidden)."""
        return self.engine.url.render_as_string(hide_password=True)

    @property
    def dialect(self) -> str:
        """Return ``sqlite`` or ``postgresql``."""
        return self.engine.dialect.name

    def upgrade(self, revision: str = "head") -> str:
        """Bring the schema to ``revision`` (head by default) and return the revision reached."""
        return self.gate.upgrade(revision)

    def revision(self) -> str | None:
        """Return the database's current schema revision (None when empty)."""
        return db.current_revision(self.engine)

    def ensure_schema(self) -> None:
        """Upgrade the schema to head if it is not there yet (done once per Store)."""
        self.gate.ensure()

    def close(self) -> None:
        """Release the engine's connections."""
        self.engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the whole store

    def analyze(self, start_day: int | None = None) -> None:
        """Refresh the planner statistics of the sample tables (see ``repository.analyze``)."""
        repository.analyze(self.engine, start_day)

    def table_counts(self) -> dict[str, int]:
        """Return the row count of every table (used to prove a failed write changed nothing)."""
        with self.campaigns.read() as conn:
            return repository.table_counts(conn)

    def check_writable(self) -> None:
        """Raise StoreError unless the store is at the head schema and accepts a write now."""
        repository.check_writable(self.gate)

    def ping(self) -> bool:
        """Return True when the database answers."""
        return repository.ping(self.engine)


def connect(url: str | None = None, auto_upgrade: bool = True) -> Store:
    """Return a Store on ``url`` (default: DRIFTLAB_DB_URL or the embedded SQLite file)."""
    return Store(db.make_engine(Settings().resolved_db_url() if url is None else url), auto_upgrade=auto_upgrade)
