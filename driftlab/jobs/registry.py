"""The model registry: model documents stored as versions of their machine.

This joins the two layers below it: ``models.document`` (what a document is) and the store's
``model_versions`` table (``campaigns.store``). A new version becomes current and retires the old
one, which stays readable.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, TypedDict

from driftlab.errors import NotFoundError, ValidationError
from driftlab.models.document import ModelDocument, document_json, validate_document

if TYPE_CHECKING:
    from driftlab.campaigns.store import ModelVersionInfo, Store


def register_model(
    store: Store, document: Mapping[str, Any] | ModelDocument, source_campaigns: Sequence[int] = ()
) -> ModelDocument:
    """Store a document as its machine's new current version (the old one retired, still readable); return it."""
    doc = validate_document(document)
    if not doc.terms:  # made current it would compensate nothing while the shop believes it compensates
        raise ValidationError(f"model document of machine {doc.machine!r} has no terms (terms: []): not registered")
    stored = document_json(doc.model_copy(update={"version": None}))
    try:
        info = store.models.register(doc.machine, stored, [int(c) for c in source_campaigns])
    except NotFoundError:
        raise NotFoundError(f"no machine {doc.machine!r} in the store: import one of its campaigns first") from None
    return document_of(info)


def document_of(info: ModelVersionInfo) -> ModelDocument:
    """Return the document of a registry row with its version number and source campaigns filled in."""
    doc = validate_document(info.document)
    return doc.model_copy(
        update={"version": int(info.version), "source_campaigns": list(info.source_campaigns) or doc.source_campaigns}
    )


class ModelRow(TypedDict):
    """One stored model version as ``driftlab models list`` shows it."""

    machine: str
    version: int
    status: str
    created_at: str | None
    source_campaigns: list[int]
    terms: int
    kept_channels: int


def list_models(store: Store, machine: str | None = None) -> list[ModelRow]:
    """Return one summary row per stored version (machine, version, status, created, campaigns, size)."""
    machines = [machine] if machine else store.models.machine_ids()
    rows = [r for m in machines for r in store.models.versions(m)]
    return [
        {
            "machine": r.machine_id,
            "version": r.version,
            "status": r.status,
            "created_at": r.created_at.isoformat() if r.created_at else None,
            "source_campaigns": list(r.source_campaigns or []),
            "terms": len((r.document or {}).get("terms", [])),
            "kept_channels": len((r.document or {}).get("kept_channels", [])),
        }
        for r in rows
    ]


def get_model(store: Store, machine: str, version: int | str = "current") -> ModelDocument:
    """Return a stored document: a version number or ``current``; NotFoundError when there is none."""
    if str(version) == "current":
        info = store.models.current(machine)
        if info is None:
            raise NotFoundError(f"machine {machine} has no current model: run `driftlab fit` first")
        return document_of(info)
    try:
        v = int(version)
    except ValueError:
        raise ValidationError(f"model version must be a number or 'current', got {version!r}") from None
    for info in store.models.versions(machine):
        if info.version == v:
            return document_of(info)
    raise NotFoundError(f"no model version {v} for machine {machine}")
