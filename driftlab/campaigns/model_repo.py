"""The model registry's repository: model documents stored as numbered versions of their machine.

A machine has at most one current version (a partial unique index); registering or promoting one
retires the previous current one, which stays readable. The writers of one machine's registry are
serialised by its row lock (``repository.lock_machine``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sqlalchemy import Connection, func, insert, select, update

from driftlab.campaigns import schema as sc
from driftlab.campaigns.repository import Page, Repository, lock_machine, machine_exists
from driftlab.errors import ConflictError, NotFoundError

if TYPE_CHECKING:
    from datetime import datetime


@dataclass(frozen=True)
class ModelVersionInfo:
    """A model registry entry."""

    id: int
    machine_id: str
    version: int
    created_at: datetime
    source_campaigns: list[int]
    document: dict[str, Any]
    status: str
    retired_at: datetime | None = None


#: the name the API used for a registry row (the same fields)
ModelRow = ModelVersionInfo


@dataclass(frozen=True)
class RefitCandidate:
    """A machine with finished campaigns newer than its current model: what a refit would fit."""

    machine_id: str
    model_version: int
    campaign_ids: list[int]
    #: the parameters of the fit that made the current model ({} when none is recorded)
    params: dict[str, Any]


def _model(row: Any) -> ModelVersionInfo:
    return ModelVersionInfo(
        id=row.id,
        machine_id=row.machine_id,
        version=row.version,
        created_at=row.created_at,
        source_campaigns=list(row.source_campaigns or []),
        document=dict(row.document or {}),
        status=row.status,
        retired_at=row.retired_at,
    )


def _by_id(conn: Connection, model_id: int) -> ModelVersionInfo:
    return _model(conn.execute(select(sc.ModelVersion.__table__).where(sc.ModelVersion.id == model_id)).one())


def _version_row(conn: Connection, machine_id: str, version: int) -> Any:
    """Return (id, status) of a machine's model version, or raise NotFoundError."""
    mv = sc.ModelVersion
    row = conn.execute(select(mv.id, mv.status).where(mv.machine_id == machine_id, mv.version == version)).first()
    if row is None:
        raise NotFoundError(f"no model version {version} for machine {machine_id!r}")
    return row


def _retire_current(conn: Connection, machine_id: str, now: datetime) -> None:
    """Retire the machine's current version (first: the partial unique index allows one current)."""
    mv = sc.ModelVersion
    conn.execute(
        update(mv).where(mv.machine_id == machine_id, mv.status == "current").values(status="retired", retired_at=now)
    )


class ModelRepository(Repository):
    """The model registry: register, read, list, promote and retire versions; what a refit would fit."""

    def register(
        self, machine_id: str, document: dict[str, Any], source_campaigns: list[int] | None = None
    ) -> ModelVersionInfo:
        """Store a new model version as the machine's current one, retiring the previous current."""
        with self.write() as conn:
            lock_machine(conn, machine_id)
            last = conn.execute(
                select(func.max(sc.ModelVersion.version)).where(sc.ModelVersion.machine_id == machine_id)
            ).scalar()
            now = sc.utcnow()
            _retire_current(conn, machine_id, now)
            new_id = conn.execute(
                insert(sc.ModelVersion)
                .values(
                    machine_id=machine_id,
                    version=(last or 0) + 1,
                    created_at=now,
                    source_campaigns=list(source_campaigns or []),
                    document=document,
                    status="current",
                )
                .returning(sc.ModelVersion.id)
            ).scalar_one()
            return _by_id(conn, new_id)

    def current(self, machine_id: str) -> ModelVersionInfo | None:
        """Return the machine's current model version, or None when it has none."""
        with self.read() as conn:
            row = conn.execute(
                select(sc.ModelVersion.__table__).where(
                    sc.ModelVersion.machine_id == machine_id, sc.ModelVersion.status == "current"
                )
            ).first()
            return None if row is None else _model(row)

    def version(self, machine_id: str, version: int) -> ModelVersionInfo:
        """Return one model version of a machine; NotFoundError when there is no such version."""
        with self.read() as conn:
            return _by_id(conn, _version_row(conn, machine_id, version).id)

    def versions(
        self,
        machine_id: str | None = None,
        status: str | None = None,
        page: Page = Page(),
        *,
        known_machine: bool = False,
    ) -> list[ModelVersionInfo]:
        """Return model versions (of one machine, of one status) ordered by machine then version.

        With ``known_machine`` an unknown machine is NotFoundError (else simply no versions).
        """
        mv = sc.ModelVersion
        with self.read() as conn:
            if machine_id is not None and known_machine:
                machine_exists(conn, machine_id)
            q = select(mv.__table__).order_by(mv.machine_id, mv.version)
            if machine_id is not None:
                q = q.where(mv.machine_id == machine_id)
            if status is not None:
                q = q.where(mv.status == status)
            return [_model(r) for r in conn.execute(page.apply(q)).all()]

    def promote(self, machine_id: str, version: int) -> ModelVersionInfo:
        """Make a version the machine's current one (retiring the previous current) and return it."""
        with self.write() as conn:
            lock_machine(conn, machine_id)
            target = _version_row(conn, machine_id, version)
            if target.status != "current":
                _retire_current(conn, machine_id, sc.utcnow())
                mv = sc.ModelVersion
                conn.execute(update(mv).where(mv.id == target.id).values(status="current", retired_at=None))
            return _by_id(conn, target.id)

    def retire(self, machine_id: str, version: int) -> ModelVersionInfo:
        """Retire a version (the machine has no current model if it was the current one) and return it."""
        with self.write() as conn:
            lock_machine(conn, machine_id)
            target = _version_row(conn, machine_id, version)
            if target.status == "retired":
                raise ConflictError(f"model version {version} of machine {machine_id!r} is already retired")
            mv = sc.ModelVersion
            conn.execute(update(mv).where(mv.id == target.id).values(status="retired", retired_at=sc.utcnow()))
            return _by_id(conn, target.id)

    def machine_ids(self) -> list[str]:
        """Return the id of every machine in the store, in order."""
        with self.read() as conn:
            return [m for (m,) in conn.execute(select(sc.Machine.id).order_by(sc.Machine.id))]

    def refit_candidates(self) -> list[RefitCandidate]:
        """Return the machines whose current model predates finished campaigns of theirs, with what to refit.

        A candidate's campaigns are the current model's sources plus every finished campaign started
        after the newest of them (campaigns the model left out on purpose stay out); ``params`` are
        those of the fit job that made the current model, when one did.
        """
        with self.read() as conn:
            models = conn.execute(
                select(sc.ModelVersion.machine_id, sc.ModelVersion.version, sc.ModelVersion.source_campaigns)
                .where(sc.ModelVersion.status == "current")
                .order_by(sc.ModelVersion.machine_id)
            ).all()
            found = (_refit_candidate(conn, m.machine_id, int(m.version), m.source_campaigns) for m in models)
            return [c for c in found if c is not None]


def _refit_candidate(conn: Connection, machine_id: str, version: int, source_campaigns: Any) -> RefitCandidate | None:
    """Return what a refit of one machine's current model would fit, or None when nothing is new."""
    sources = [int(c) for c in (source_campaigns or [])]
    if not sources:
        return None
    done = conn.execute(
        select(sc.Campaign.id, sc.Campaign.started_at)
        .where(sc.Campaign.machine_id == machine_id, sc.Campaign.status == "done")
        .order_by(sc.Campaign.started_at, sc.Campaign.id)
    ).all()
    started = {int(c.id): c.started_at for c in done}
    newest = max((started[c] for c in sources if c in started), default=None)
    if newest is None:
        return None
    new = [c for c, at in started.items() if c not in sources and at > newest]
    if not new:
        return None
    fits = conn.execute(
        select(sc.Job.params, sc.Job.result)
        .where(sc.Job.machine_id == machine_id, sc.Job.kind == "fit", sc.Job.state == "done")
        .order_by(sc.Job.id.desc())
    ).all()
    params = next((dict(f.params or {}) for f in fits if (f.result or {}).get("model_version") == version), {})
    return RefitCandidate(machine_id, version, [c for c in sources if c in started] + new, params)
