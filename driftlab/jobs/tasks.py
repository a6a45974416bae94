"""The bodies of the jobs: load through the store, run the pure models, save through the store and registry.

Each body takes a store and a job's parameters and returns the job's JSON result; nothing here
knows how the job was queued. ``execute`` runs one recorded job around its body: it marks the
record running, runs the body, then records the result, or the one-line error and whether a retry
comes. procrastinate's tasks (``driftlab.jobs.queue``, PostgreSQL) and the in-process runner
(``driftlab.jobs.local``, SQLite) both call it, so the same code fits a model whichever way the job
travelled.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, TypeAlias, TypedDict

from driftlab.errors import DriftlabError, ValidationError
from driftlab.jsonsafe import strict_json
from driftlab.models.diagnosis_report import to_json_dict as diagnosis_json

if TYPE_CHECKING:
    from driftlab.campaigns.store import JobInfo, Store
    from driftlab.models.document import ModelDocument
    from driftlab.models.fitting import FitOptions, FitReport, FitResult

log = logging.getLogger(__name__)

FIT = "fit"
DIAGNOSE = "diagnose"
#: the kinds of job a client submits (the API's ``JobKind``)
KINDS: tuple[str, ...] = (FIT, DIAGNOSE)

#: called with a machine id once its new model is registered, before its job reads "done"
OnModel = Callable[[str], None]
#: called with the name of each fitting stage as it ends
OnStage = Callable[[str], None]


def one_line(exc: BaseException) -> str:
    """Return the one-line error a job records: a user error's own text, else the exception's type and text."""
    if isinstance(exc, DriftlabError):
        return exc.one_line()
    return " ".join(f"{type(exc).__name__}: {exc}".split())


# ----------------------------------------------------------------------------- bodies


class DiagnoseJobResult(TypedDict):
    """A diagnosis job's result: the campaign and its diagnosis report v1 (``diagnosis_report.to_json_dict``)."""

    campaign_id: int
    report: Mapping[str, object]


#: a job's JSON result: a fit's report (with the registered ``model_version``) or a diagnosis
JobResult: TypeAlias = "FitReport | DiagnoseJobResult"


def fit_campaigns(
    store: Store,
    campaign_ids: Sequence[int],
    options: FitOptions | None = None,
    progress: OnStage | None = None,
    envelope: Any = None,
) -> tuple[FitResult, ModelDocument]:
    """Fit the stored campaigns, register the model as the machine's current version; return both.

    ``envelope`` (a mapping of ``models.envelope.Envelope``) goes into the document: the compensator's limits.
    """
    # lazy: the fit (statsmodels, scikit-learn) adds 1.7 s to `import driftlab.jobs` (measured); the API imports it
    from driftlab.jobs.registry import register_model
    from driftlab.models.fitting import fit_bundles

    ids = [int(c) for c in campaign_ids]
    if not ids:
        raise ValidationError("give at least one campaign")
    bundles = [store.campaigns.load(c) for c in ids]
    result = fit_bundles(bundles, options, source_campaigns=ids, progress=progress)
    document = result.document
    if envelope is not None:  # a machine file's keys win over the campaigns' travel, axis by axis
        # lazy: the fit (statsmodels, scikit-learn) adds 1.7 s to `import driftlab.jobs` (measured); the API imports it
        from driftlab.models.envelope import envelope_from_mapping, merge

        given = envelope_from_mapping(envelope, "fit envelope")
        document = document.model_copy(update={"envelope": merge(document.envelope, given)})
    doc = register_model(store, document, ids)
    result.document = doc
    return result, doc


def fit_options(params: dict[str, Any], source: str = "fit job") -> FitOptions:
    """Return the fitting options a fit job's parameters ask for (network, diagnosis findings)."""
    # lazy: the fit adds 1.7 s to `import driftlab.jobs` (measured); the API imports it
    from driftlab.models.fitting import FitOptions

    opts = FitOptions(network=bool(params.get("network", True)))
    if params.get("split") is not None:
        opts.split = str(params["split"])
    if params.get("findings"):
        # lazy: the fit adds 1.7 s to `import driftlab.jobs` (measured); the API imports it
        from driftlab.models.findings import parse_findings

        opts.findings = parse_findings(params["findings"], f"{source} findings")
        opts.force_findings = bool(params.get("force_findings", False))
    return opts


def fit_job(
    store: Store, params: dict[str, Any], on_stage: OnStage | None = None, on_model: OnModel | None = None
) -> FitReport:
    """Fit and register a model; return the fit report with the registered ``model_version``."""
    result, doc = fit_campaigns(
        store, params.get("campaigns", []), fit_options(params), progress=on_stage, envelope=params.get("envelope")
    )
    if on_model is not None:
        on_model(doc.machine)
    report = result.report()
    report["model_version"] = doc.version
    return report


def diagnose_job(
    store: Store, params: dict[str, Any], on_stage: OnStage | None = None, on_model: OnModel | None = None
) -> DiagnoseJobResult:
    """Diagnose one stored campaign; return ``{"campaign_id", "report"}`` (diagnosis report v1)."""
    # lazy: the diagnosis adds 1.7 s to `import driftlab.jobs` (measured); the API imports it
    from driftlab.models.diagnosis import diagnose_bundle

    ids = [int(c) for c in params.get("campaigns", [])]
    if len(ids) != 1:
        raise ValidationError("a diagnosis is of exactly one campaign")
    result = diagnose_bundle(store.campaigns.load(ids[0]), holdout_fraction=float(params.get("holdout_fraction", 0.25)))
    return {"campaign_id": ids[0], "report": diagnosis_json(result)}


BODIES: dict[str, Callable[..., JobResult]] = {FIT: fit_job, DIAGNOSE: diagnose_job}


# ----------------------------------------------------------------------------- one recorded job


def execute(
    store: Store,
    job_id: int,
    worker: str,
    *,
    will_retry: Callable[[BaseException, JobInfo], bool],
    only_if_queued: bool = False,
    on_stage: OnStage | None = None,
    on_model: OnModel | None = None,
) -> JobResult | None:
    """Run a recorded job to its end and record how it ended; return its result.

    Returns None when ``only_if_queued`` and the record was not queued (another process has it).
    A failure is recorded (failed, or queued again when ``will_retry(exc, job)``, ``job`` as started:
    ``job.attempts`` counts this run) and then re-raised, so that the queue sees it too.
    """
    job: JobInfo | None = store.jobs.start(job_id, worker, only_if_queued=only_if_queued)
    if job is None:
        return None
    try:
        body = BODIES.get(job.kind)
        if body is None:
            raise ValidationError(f"unknown job kind {job.kind!r}")
        result = strict_json(body(store, dict(job.params), on_stage=on_stage, on_model=on_model))
    except Exception as exc:
        retry = will_retry(exc, job)
        log.log(
            logging.INFO if isinstance(exc, DriftlabError) else logging.WARNING,
            "job %s (%s, attempt %s) failed%s: %s",
            job_id,
            job.kind,
            job.attempts,
            "; it will be retried" if retry else "",
            one_line(exc),
            exc_info=not isinstance(exc, DriftlabError),
        )
        store.jobs.fail(job_id, one_line(exc), retry=retry)
        raise
    store.jobs.finish(job_id, result)
    return result
