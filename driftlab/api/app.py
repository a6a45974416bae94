"""The FastAPI application factory: store, token, routes, problem responses, model cache, jobs."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import partial
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI
from fastapi.openapi.utils import get_openapi

from driftlab import __version__
from driftlab.api import guard, live, pages, problems
from driftlab.api.deps import ApiState, ModelCache, get_state
from driftlab.api.routes import campaigns, drift, histories, jobs, machines, models, online
from driftlab.api.schemas import Health
from driftlab.campaigns.store import Store, connect
from driftlab.config import Settings
from driftlab.jobs import Jobs

log = logging.getLogger(__name__)

DESCRIPTION = """Campaigns, drift and models of driftlab's campaign store.

Reads are open; every write needs `Authorization: Bearer <DRIFTLAB_API_TOKEN>` (writes are refused
when no token is configured). Errors are RFC 9457 `application/problem+json`.
"""


health_router = APIRouter()


@health_router.get("/health", response_model=Health, tags=["health"], summary="Liveness and database reachability")
def health(st: Annotated[ApiState, Depends(get_state)]) -> Health:
    """Return ok when the database answers."""
    st.store.ping()
    return Health(status="ok", database=st.store.dialect)


def _openapi(app: FastAPI) -> dict[str, Any]:
    """Return the OpenAPI document with the problem+json responses declared on every operation."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        schema = problems.declare_problems(schema)
        # the bearer scheme the front door checks: /docs shows an Authorize button, and writes say they need it
        schema.setdefault("components", {}).setdefault("securitySchemes", {})["bearer"] = {
            "type": "http",
            "scheme": "bearer",
            "description": "the API token (DRIFTLAB_API_TOKEN); reads need none, every write needs it",
        }
        for item in schema.get("paths", {}).values():
            for method, op in item.items():
                if isinstance(op, dict) and method in problems.WRITE_METHODS:
                    op["security"] = [{"bearer": []}]
        app.openapi_schema = schema
    return app.openapi_schema


def create_app(
    db_url: str | None = None,
    token: str | None = None,
    *,
    store: Store | None = None,
    run_jobs: bool = True,
    model_cache_ttl_s: float = 1.0,
    live_poll_s: float = 0.5,
    max_body_bytes: int | None = None,
) -> FastAPI:
    """Return the API over the store at ``db_url`` (default DRIFTLAB_DB_URL) with write token ``token``.

    ``token`` defaults to DRIFTLAB_API_TOKEN; an empty token disables writes. Jobs are submitted
    through driftlab.jobs; with ``run_jobs`` this process also runs them while the application is up
    (a procrastinate worker thread on PostgreSQL, the in-process runner on SQLite). The live
    page's hub polls the store for commits every ``live_poll_s`` while a page is open. A request body
    over ``max_body_bytes`` (default DRIFTLAB_API_MAX_BODY_BYTES, 8 MiB) is refused with 413; a write's
    token is checked before its body is read.
    """
    settings = Settings()
    the_store = store if store is not None else connect(db_url or settings.resolved_db_url())
    models_cache = ModelCache(the_store, ttl_s=model_cache_ttl_s)
    # a fit run in this process drops the machine's cached model before its job reads "done"
    state = ApiState(
        store=the_store,
        token=settings.api_token if token is None else token,
        models=models_cache,
        jobs=Jobs(the_store, run_here=run_jobs, on_model=models_cache.invalidate),
    )
    live_hub = live.LiveHub(the_store.engine, poll_s=live_poll_s)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        the_store.ensure_schema()
        state.jobs.start()
        try:
            yield
        finally:
            await live_hub.stop()
            state.jobs.stop()

    app = FastAPI(
        title="driftlab", version=__version__, description=DESCRIPTION, lifespan=lifespan, docs_url=None, redoc_url=None
    )  # served from packaged assets by `pages`, not from a CDN
    app.state.driftlab = state
    app.state.live_hub = live_hub
    problems.install_handlers(app)
    app.add_middleware(models.CurrentModelFastPath)  # inside the catch-all (the last added is outermost)
    app.add_middleware(problems.CatchAllMiddleware)
    # outermost: a write's token and every body's size are checked before anything reads the body
    limit = settings.api_max_body_bytes if max_body_bytes is None else max_body_bytes
    app.add_middleware(guard.FrontDoorMiddleware, max_body_bytes=limit)
    for module in (machines, campaigns, histories, drift, models, jobs, online):
        app.include_router(module.router)
    app.include_router(live.router)
    pages.install(app)

    app.include_router(health_router)
    app.openapi = partial(_openapi, app)  # type: ignore[method-assign]
    return app
