"""Jobs: submit a fit or a diagnosis (a row of the store's jobs table), poll its state; the runner.

The API server runs queued jobs itself in one background thread (``JobRunner``) unless told not to:
fits through the fitting pipeline's job runner (``driftlab.models.fitting.run_fit_job``, the same
jobs ``driftlab fit --enqueue`` queues and ``driftlab fit --worker`` runs), diagnoses here. Any
other worker claiming from the same table works alongside it (claims are atomic).
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Response

from driftlab.api.deps import ApiState, get_state, get_store, require_token
from driftlab.api.schemas import ID_PATTERN, MAX_ID, JobKind, JobList, JobOut, JobState, JobSubmit
from driftlab.campaigns import api_queries
from driftlab.campaigns.store import JobInfo, Store
from driftlab.errors import DriftlabError, ValidationError

log = logging.getLogger(__name__)

router = APIRouter(tags=["jobs"])

FIT_JOB = "fit"  # driftlab.models.fitting.FIT_JOB (imported when a job runs: the pipeline is heavy)
DIAGNOSE_JOB = "diagnose"
JOB_KINDS = (FIT_JOB, DIAGNOSE_JOB)


def _finite(obj: Any) -> Any:
    """Return ``obj`` with non-finite floats as None (JSON columns and responses are strict JSON)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def job_out(j: Any) -> JobOut:
    """Return the response model of a job (a JobInfo or a jobs row)."""
    return JobOut(id=j.id, kind=j.kind, state=j.state, params=dict(j.params or {}), result=_finite(j.result),
                  error=j.error, machine_id=j.machine_id, campaign_id=j.campaign_id, attempts=j.attempts,
                  created_at=j.created_at, started_at=j.started_at, finished_at=j.finished_at)


def run_diagnosis(store: Store, job: JobInfo) -> dict[str, Any]:
    """Run a claimed diagnosis job and return its JSON result (DriftlabError when it cannot run)."""
    from driftlab.models.diagnosis import diagnose_bundle

    ids = [int(c) for c in job.params.get("campaigns", [])]
    if len(ids) != 1:
        raise ValidationError("a diagnosis is of exactly one campaign")
    result = diagnose_bundle(store.load_campaign(ids[0]),
                             holdout_fraction=float(job.params.get("holdout_fraction", 0.25)))
    return _finite({"campaign_id": ids[0], "report": result.to_json_dict()})


class _InvalidatingStore:
    """The store, except that marking a job done first drops the machine's cached current model.

    A fit registers its model and then marks its job done; a client that sees "done" must already
    get the new model, so the cache goes before the job's state changes.
    """

    def __init__(self, store: Store, invalidate: Any) -> None:
        self._store = store
        self._invalidate = invalidate

    def __getattr__(self, name: str) -> Any:
        return getattr(self._store, name)

    def finish_job(self, job_id: int, worker: str, result: dict[str, Any]) -> None:
        """Invalidate, then record the job done."""
        self._invalidate()
        self._store.finish_job(job_id, worker, result)


class JobRunner(threading.Thread):
    """A background thread that claims and runs fit/diagnosis jobs, one at a time, with heartbeats."""

    def __init__(self, state: ApiState, poll_s: float = 2.0, heartbeat_s: float = 15.0,
                 stale_s: float = 600.0) -> None:
        super().__init__(name="driftlab-jobs", daemon=True)
        self.state = state
        self.poll_s = poll_s
        self.heartbeat_s = heartbeat_s
        self.stale_s = stale_s
        self.worker = f"api-{socket.gethostname()}-{os.getpid()}-{id(self):x}"
        self.wake = threading.Event()
        self.stopping = threading.Event()
        self.ran = 0

    def stop(self, timeout_s: float = 30.0) -> None:
        """Ask the thread to finish after its current job and wait for it."""
        self.stopping.set()
        self.wake.set()
        if self.is_alive():
            self.join(timeout_s)

    def run(self) -> None:
        """Claim and run jobs until stopped; sleep on the wake event when the queue is empty."""
        store = self.state.store
        try:
            store.requeue_stale(self.stale_s)
        except Exception:
            log.exception("job runner: cannot requeue stale jobs")
        while not self.stopping.is_set():
            try:
                job = store.claim_job(self.worker, kinds=list(JOB_KINDS))
            except Exception:
                log.exception("job runner: cannot claim a job")
                job = None
            if job is None:
                self.wake.wait(self.poll_s)
                self.wake.clear()
                continue
            self._execute(job)

    def _execute(self, job: JobInfo) -> None:
        """Run one job with a heartbeat beside it; record its result or its one-line error."""
        store = self.state.store
        done = threading.Event()

        def beat() -> None:
            while not done.wait(self.heartbeat_s):
                try:
                    store.heartbeat(job.id, self.worker)
                except Exception:
                    log.warning("job %s: heartbeat failed", job.id)

        beater = threading.Thread(target=beat, name=f"job-{job.id}-heartbeat", daemon=True)
        beater.start()
        try:
            if job.kind == FIT_JOB:
                from driftlab.models import fitting

                # records done (with the fit report) or failed itself, then re-raises a failure
                machine = job.machine_id
                fitting.run_fit_job(_InvalidatingStore(store, lambda: self.state.models.invalidate(machine)),
                                    job, self.worker)
            else:
                store.finish_job(job.id, self.worker, run_diagnosis(store, job))
        except Exception as exc:
            log.log(logging.INFO if isinstance(exc, DriftlabError) else logging.ERROR,
                    "job %s (%s) failed", job.id, job.kind, exc_info=not isinstance(exc, DriftlabError))
            if store.get_job(job.id).state == "running":
                text = exc.one_line() if isinstance(exc, DriftlabError) else f"{type(exc).__name__}: {exc}"
                store.fail_job(job.id, self.worker, text)
        finally:
            done.set()
            beater.join(1.0)
            self.ran += 1
            if job.kind == FIT_JOB and job.machine_id:
                self.state.models.invalidate(job.machine_id)


@router.post("/jobs", response_model=JobOut, status_code=202, dependencies=[Depends(require_token)],
             summary="Submit a fit or a diagnosis")
def submit(body: JobSubmit, state: Annotated[ApiState, Depends(get_state)], response: Response) -> JobOut:
    """Queue a job after checking its machine and campaigns; poll GET /jobs/{id} for its state."""
    ids = list(dict.fromkeys(body.campaign_ids))
    if body.kind == "diagnose" and len(ids) != 1:
        raise ValidationError("a diagnosis is of exactly one campaign: give one campaign id")
    if body.kind == "fit" and body.machine_id is None and not ids:
        raise ValidationError("a fit needs a machine id or campaign ids")
    ids = api_queries.check_job_targets(state.store, body.machine_id, ids)
    if body.kind == "fit" and not ids:
        raise ValidationError(f"machine {body.machine_id!r} has no campaigns to fit")
    params: dict[str, Any] = {"campaigns": ids}  # the fitting pipeline's job parameters
    if body.kind == DIAGNOSE_JOB:
        params["holdout_fraction"] = body.holdout_fraction
    machine = body.machine_id
    if machine is None and ids:
        machine = api_queries.campaign_detail(state.store, ids[0])[0].machine_id
    job_id = state.store.submit_job(body.kind, params, machine_id=machine, campaign_id=ids[0] if len(ids) == 1 else None)
    if state.jobs is not None:
        state.jobs.wake.set()
    response.headers["Location"] = f"/jobs/{job_id}"
    return job_out(state.store.get_job(job_id))


@router.get("/jobs", response_model=JobList, summary="List jobs")
def list_jobs(store: Annotated[Store, Depends(get_store)],
              state: JobState | None = None, kind: JobKind | None = None,
              machine_id: Annotated[str | None, Query(pattern=ID_PATTERN)] = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              offset: Annotated[int, Query(ge=0, le=10**9)] = 0) -> JobList:
    """Return a page of fit and diagnosis jobs, newest first."""
    rows = api_queries.list_jobs(store, state, kind, machine_id, limit, offset, kinds=JOB_KINDS)
    return JobList(items=[job_out(r) for r in rows], limit=limit, offset=offset)


@router.get("/jobs/{job_id}", response_model=JobOut, summary="Poll a job")
def get_job(job_id: Annotated[int, Path(ge=1, le=MAX_ID)], store: Annotated[Store, Depends(get_store)]) -> JobOut:
    """Return a job's state and, when done, its result."""
    return job_out(store.get_job(job_id))
