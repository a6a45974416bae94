"""Jobs: submit a fit or a diagnosis through driftlab.jobs, poll its state, list the history.

A job is queued on procrastinate when the store is PostgreSQL (run by ``driftlab worker`` processes,
and by this server too unless ``--no-jobs``), and run in a thread of this server on SQLite. Its
record in the store (``jobs``) gives the answers here; while the job is in procrastinate's queue its
state is procrastinate's, mapped to queued / running / done / failed.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Response

from driftlab.api.deps import ApiState, get_state, get_store, require_token
from driftlab.api.schemas import ID_PATTERN, JobKind, JobList, JobOut, JobState, JobSubmit
from driftlab.api.strict import JobId, Limit, Offset, StrictJsonRoute
from driftlab.campaigns.job_repo import JobFilter
from driftlab.campaigns.repository import Page
from driftlab.campaigns.store import JobInfo, Store
from driftlab.errors import ValidationError
from driftlab.jobs import DIAGNOSE, FIT, KINDS
from driftlab.jsonsafe import strict_json

router = APIRouter(tags=["jobs"], route_class=StrictJsonRoute)


def job_out(j: JobInfo) -> JobOut:
    """Return the response model of a job."""
    return JobOut(
        id=j.id,
        kind=j.kind,
        state=j.state,
        params=dict(j.params or {}),
        result=strict_json(j.result),
        error=j.error,
        machine_id=j.machine_id,
        campaign_id=j.campaign_id,
        attempts=j.attempts,
        created_at=j.created_at,
        started_at=j.started_at,
        finished_at=j.finished_at,
    )


@router.post(
    "/jobs",
    response_model=JobOut,
    status_code=202,
    dependencies=[Depends(require_token)],
    summary="Submit a fit or a diagnosis",
)
def submit(body: JobSubmit, state: Annotated[ApiState, Depends(get_state)], response: Response) -> JobOut:
    """Queue a job after checking its machine and campaigns; poll GET /jobs/{id} for its state."""
    ids = list(dict.fromkeys(body.campaign_ids))
    if body.kind == DIAGNOSE and len(ids) != 1:
        raise ValidationError("a diagnosis is of exactly one campaign: give one campaign id")
    if body.kind == FIT and body.machine_id is None and not ids:
        raise ValidationError("a fit needs a machine id or campaign ids")
    ids = state.store.campaigns.job_targets(body.machine_id, ids)
    if body.kind == FIT and not ids:
        raise ValidationError(f"machine {body.machine_id!r} has no campaigns to fit")
    params: dict[str, Any] = {"campaigns": ids}  # a driftlab.jobs fit or diagnosis job's parameters
    if body.kind == DIAGNOSE:
        params["holdout_fraction"] = body.holdout_fraction
    machine = body.machine_id
    if machine is None and ids:
        machine = state.store.campaigns.detail(ids[0]).row.machine_id
    job_id = state.jobs.submit(body.kind, params, machine_id=machine, campaign_id=ids[0] if len(ids) == 1 else None)
    response.headers["Location"] = f"/jobs/{job_id}"
    return job_out(state.store.jobs.get(job_id))


@router.get("/jobs", response_model=JobList, summary="List jobs")
def list_jobs(
    store: Annotated[Store, Depends(get_store)],
    state: JobState | None = None,
    kind: JobKind | None = None,
    machine_id: Annotated[str | None, Query(pattern=ID_PATTERN)] = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> JobList:
    """Return a page of fit and diagnosis jobs, newest first."""
    rows = store.jobs.find(JobFilter(state, kind, machine_id, kinds=KINDS), Page(limit, offset))
    return JobList(items=[job_out(r) for r in rows], limit=limit, offset=offset)


@router.get("/jobs/{job_id}", response_model=JobOut, summary="Poll a job")
def get_job(job_id: JobId, store: Annotated[Store, Depends(get_store)]) -> JobOut:
    """Return a job's state and, when done, its result."""
    return job_out(store.jobs.get(job_id))
