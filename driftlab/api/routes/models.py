"""Model registry: list versions, the current model (ETag, 304), a given version, register/promote/retire.

``GET /machines/{id}/model/current`` is the compensators' polling path: its answer comes from the
in-process cache (serialised bytes and ETag) and touches the database at most once per cache TTL.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Annotated, Any, TypedDict

from fastapi import APIRouter, Depends, Header, Query, Request, Response
from starlette.concurrency import run_in_threadpool
from starlette.types import ASGIApp, Receive, Scope, Send

from driftlab.api.deps import ApiState, get_state, get_store, model_etag, model_out, require_token
from driftlab.api.problems import problem_response
from driftlab.api.routes.machines import MachineId
from driftlab.api.schemas import (
    ID_PATTERN,
    ModelList,
    ModelRegisterIn,
    ModelStatus,
    ModelVersionOut,
)
from driftlab.api.strict import Limit, Offset, StrictJsonRoute, VersionNumber
from driftlab.campaigns.repository import Page
from driftlab.campaigns.store import ModelVersionInfo, Store
from driftlab.errors import ValidationError
from driftlab.jobs import registry as model_registry
from driftlab.jsonsafe import check_json
from driftlab.models import document as documents

if TYPE_CHECKING:
    from driftlab.api.deps import ModelVersionJson

router = APIRouter(tags=["models"], route_class=StrictJsonRoute)

Version = VersionNumber
ETAG_HEADERS = {"ETag": {"description": "hash of the version id and document", "schema": {"type": "string"}}}


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """Return True when an If-None-Match header names this ETag (weak comparison, or ``*``)."""
    if not if_none_match:
        return False
    for tag in if_none_match.split(","):
        tag = tag.strip()
        if tag == "*" or tag.removeprefix("W/") == etag:
            return True
    return False


CURRENT_PATH = re.compile(r"^/machines/([A-Za-z0-9][A-Za-z0-9._:-]{0,63})/model/current$")


class CurrentModelFastPath:
    """Pure ASGI middleware answering cache hits of ``GET /machines/{id}/model/current`` before routing.

    The compensators poll this path; a cached answer is sent as is (same status, headers and body as
    the route's), which skips routing, dependency solving and the thread pool; an expired one is
    refreshed in the background meanwhile. Misses, absent models and every other request go on to
    the application (the route below loads and caches).
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Serve a fresh cached current model, or pass the request on."""
        if scope["type"] == "http" and scope["method"] == "GET":
            m = CURRENT_PATH.match(scope["path"])
            if m is not None:
                entry = scope["app"].state.driftlab.models.servable(m.group(1))
                if entry is not None:
                    inm = next((v for k, v in scope["headers"] if k == b"if-none-match"), None)
                    headers = [(b"etag", entry.etag.encode()), (b"cache-control", b"no-cache")]
                    if inm is not None and etag_matches(inm.decode("latin-1"), entry.etag):
                        await send({"type": "http.response.start", "status": 304, "headers": headers})
                        await send({"type": "http.response.body", "body": b""})
                        return
                    headers = [
                        (b"content-length", str(len(entry.body)).encode()),
                        (b"content-type", b"application/json"),
                        *headers,
                    ]
                    await send({"type": "http.response.start", "status": 200, "headers": headers})
                    await send({"type": "http.response.body", "body": entry.body})
                    return
        await self.app(scope, receive, send)


@router.get("/models", response_model=ModelList, summary="List model versions of every machine")
def list_models(
    store: Annotated[Store, Depends(get_store)],
    machine_id: Annotated[str | None, Query(pattern=ID_PATTERN)] = None,
    status: ModelStatus | None = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> ModelListJson:
    """Return a page of model versions (without documents), by machine then version."""
    return _model_list(store, machine_id, status, Page(limit, offset))


@router.get("/machines/{machine_id}/models", response_model=ModelList, summary="List a machine's model versions")
def machine_models(
    machine_id: MachineId,
    store: Annotated[Store, Depends(get_store)],
    status: ModelStatus | None = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> ModelListJson:
    """Return a page of a machine's model versions, oldest first."""
    return _model_list(store, machine_id, status, Page(limit, offset))


class ModelListJson(TypedDict):
    """A page of model versions as ``schemas.ModelList``'s JSON."""

    items: list[ModelVersionJson]  # without their documents
    limit: int | None
    offset: int


def _model_list(store: Store, machine_id: str | None, status: str | None, page: Page) -> ModelListJson:
    """Return a page of model versions as ModelList's JSON (an unknown machine is a 404)."""
    rows = store.models.versions(machine_id, status, page, known_machine=True)
    return {"items": [model_out(r, with_document=False) for r in rows], "limit": page.limit, "offset": page.offset}


@router.get(
    "/machines/{machine_id}/model/current",
    response_model=ModelVersionOut,
    summary="The machine's current model (ETag; If-None-Match gives 304)",
    responses={200: {"headers": ETAG_HEADERS}, 304: {"description": "Not Modified", "headers": ETAG_HEADERS}},
)
async def current_model(
    request: Request,
    machine_id: MachineId,
    if_none_match: Annotated[str | None, Header(max_length=1000)] = None,
) -> Response:
    """Return the current model document with its ETag, or 304 when the client's copy is current."""
    cache = get_state(request).models
    entry = cache.servable(machine_id)
    if entry is None:
        hit, entry = cache.fresh(machine_id)  # a fresh "no current model" answer
        if not hit:
            entry = await run_in_threadpool(cache.load, machine_id)
    if entry is None:
        return problem_response(404, f"machine {machine_id!r} has no current model", request.url.path)
    headers = {"ETag": entry.etag, "Cache-Control": "no-cache"}
    if etag_matches(if_none_match, entry.etag):
        return Response(status_code=304, headers=headers)
    return Response(entry.body, media_type="application/json", headers=headers)


@router.get(
    "/machines/{machine_id}/models/{version}",
    response_model=ModelVersionOut,
    responses={200: {"headers": ETAG_HEADERS}},
    summary="A given model version",
)
def get_version(
    machine_id: MachineId, version: Version, store: Annotated[Store, Depends(get_store)], response: Response
) -> ModelVersionJson:
    """Return one model version of a machine with its document."""
    row = store.models.version(machine_id, version)
    response.headers["ETag"] = model_etag(row)
    return model_out(row)


@router.post(
    "/machines/{machine_id}/models",
    response_model=ModelVersionOut,
    status_code=201,
    dependencies=[Depends(require_token)],
    summary="Register a new model version (made current)",
)
def register(
    machine_id: MachineId, body: ModelRegisterIn, state: Annotated[ApiState, Depends(get_state)], response: Response
) -> ModelVersionJson:
    """Validate and store a model document as the machine's next version, current from now on."""
    check_json(body.document)
    doc = documents.validate_document(body.document)
    if doc.machine != machine_id:
        raise ValidationError(f"the document is of machine {doc.machine!r}, not {machine_id!r}")
    state.store.campaigns.machine(machine_id)  # 404 for an unknown machine (registry would create it)
    final = model_registry.register_model(state.store, doc, source_campaigns=body.source_campaigns)
    state.models.invalidate(machine_id)
    row = state.store.models.version(machine_id, int(final.version or 0))
    response.headers["Location"] = f"/machines/{machine_id}/models/{row.version}"
    return model_out(row)


def _changed(state: ApiState, row: ModelVersionInfo) -> ModelVersionJson:
    """Return a registry row just changed through this API (its machine's cached current model dropped)."""
    state.models.invalidate(row.machine_id)
    return model_out(row)


#: what the promote and retire routes share: they answer with the version, and need the write token
_VERSION_WRITE: dict[str, Any] = {"response_model": ModelVersionOut, "dependencies": [Depends(require_token)]}


@router.post(
    "/machines/{machine_id}/models/{version}/promote", summary="Make a version the current one", **_VERSION_WRITE
)
def promote(
    machine_id: MachineId, version: Version, state: Annotated[ApiState, Depends(get_state)]
) -> ModelVersionJson:
    """Make a version current (retiring the previous current one); compensators see a new ETag."""
    return _changed(state, state.store.models.promote(machine_id, version))


@router.post("/machines/{machine_id}/models/{version}/retire", summary="Retire a version", **_VERSION_WRITE)
def retire(machine_id: MachineId, version: Version, state: Annotated[ApiState, Depends(get_state)]) -> ModelVersionJson:
    """Retire a version; if it was current the machine has no current model until one is promoted."""
    return _changed(state, state.store.models.retire(machine_id, version))
