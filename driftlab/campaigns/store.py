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
as it was, whatever interrupts it. The names callers used before the repositories
(``store.import_bundle``, ``store.drift``, ``store.get_job``, ...) are the repositories' own
methods, bound once in ``Store.__init__``; new code calls the repositories.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from driftlab.campaigns import db, repository
from driftlab.campaigns.campaign_repo import CampaignRepository, CampaignSummary, MachineInfo, ProgressInfo
from driftlab.campaigns.job_repo import QUEUE_STATES, JobInfo, JobRepository, job_info, jobs_select
from driftlab.campaigns.model_repo import ModelRepository, ModelRow, ModelVersionInfo, RefitCandidate
from driftlab.campaigns.online_repo import OnlineStateInfo, OnlineStateRepository, OnlineUpdate, StaleOnlineState
from driftlab.campaigns.readings_repo import ReadingRepository
from driftlab.config import Settings

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

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
        # the names callers used before the repositories: the repositories' methods themselves
        # (bound, not restated), so that their signatures live in one place
        self.import_bundle = self.campaigns.import_bundle
        self.import_directory = self.campaigns.import_directory
        self.load_campaign = self.campaigns.load
        self.campaign_machine = self.campaigns.machine_of
        self.list_campaigns = self.campaigns.summaries
        self.delete_campaign = self.campaigns.delete
        self.refresh_rollups = self.campaigns.refresh_rollups
        self.save_progress = self.campaigns.save_progress
        self.progress = self.campaigns.progress
        self.drift = self.readings.drift
        self.temperature_history = self.readings.temperature_history
        self.condition_history = self.readings.condition_history
        self.register_model = self.models.register
        self.current_model = self.models.current
        self.machine_ids = self.models.machine_ids
        self.refit_candidates = self.models.refit_candidates
        self.record_job = self.jobs.record
        self.link_queue_job = self.jobs.link_queue_job
        self.start_job = self.jobs.start
        self.finish_job = self.jobs.finish
        self.fail_job = self.jobs.fail
        self.delete_job = self.jobs.delete
        self.jobs_in_state = self.jobs.in_state
        self.last_job_result = self.jobs.last_result
        self.get_job = self.jobs.get
        self.online_state = self.online.get

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

    def model_versions(self, machine_id: str) -> list[ModelVersionInfo]:
        """Return every model version of a machine, oldest first (``models.versions``)."""
        return self.models.versions(machine_id)

    def save_online_state(
        self,
        machine_id: str,
        seen_version: int | None,
        update: OnlineUpdate | None = None,
        probes: Sequence[Mapping[str, Any]] = (),
        **fields: Any,
    ) -> tuple[OnlineStateInfo, list[int]]:
        """Write a new on-line state (``online.save``); the fields of ``OnlineUpdate`` may be given by
        keyword instead of ``update``, as before the repositories."""
        return self.online.save(machine_id, seen_version, update or OnlineUpdate(**fields), probes)


def connect(url: str | None = None, auto_upgrade: bool = True) -> Store:
    """Return a Store on ``url`` (default: DRIFTLAB_DB_URL or the embedded SQLite file)."""
    return Store(db.make_engine(Settings().resolved_db_url() if url is None else url), auto_upgrade=auto_upgrade)
