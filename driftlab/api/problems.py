"""RFC 9457 problem details: every error the API returns, declared in the OpenAPI, never a traceback."""

from __future__ import annotations

import json
import logging
import re
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from sqlalchemy.exc import DBAPIError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from driftlab.campaigns.db import read_only_cause
from driftlab.errors import DriftlabError

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"
#: statuses declared as problem responses on every operation (plus 401/403 on writes, 304 where cached)
COMMON_PROBLEMS = (400, 404, 422, 500, 503)
WRITE_PROBLEMS = (401, 403, 409, 413)


def problem_type(status: int) -> str:
    """Return the problem type URI of a status (a stable URN per kind of problem)."""
    try:
        slug = HTTPStatus(status).phrase.lower().replace(" ", "-")
    except ValueError:
        slug = str(status)
    return f"urn:driftlab:problem:{slug}"


def problem_body(status: int, detail: str, instance: str, **extra: object) -> dict[str, object]:
    """Return a problem document (type, title, status, detail, instance, plus extensions)."""
    try:
        title = HTTPStatus(status).phrase
    except ValueError:
        title = "Error"
    return {
        "type": problem_type(status),
        "title": title,
        "status": status,
        "detail": detail,
        "instance": instance,
        **extra,
    }


def problem_response(
    status: int, detail: str, instance: str, headers: dict[str, str] | None = None, **extra: Any
) -> Response:
    """Return a problem+json response."""
    body = json.dumps(problem_body(status, detail, instance, **extra), allow_nan=False, default=str)
    return Response(body, status_code=status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)


def _instance(request: Request) -> str:
    return request.url.path


async def _driftlab_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, DriftlabError)
    status = exc.http_status if 400 <= exc.http_status <= 599 else 400
    return problem_response(status, exc.one_line(), _instance(request))


async def _validation_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, RequestValidationError)
    errors = []
    for e in exc.errors():
        loc = ".".join(str(p) for p in e.get("loc", ()))
        errors.append({"loc": loc, "msg": str(e.get("msg", ""))})
    detail = "; ".join(f"{e['loc']}: {e['msg']}" for e in errors[:5]) or "invalid request"
    # a malformed parameter (query, path, header) is a bad request (400); a body that parses but
    # does not meet its schema is unprocessable content (422)
    in_body = any(tuple(e.get("loc", ()))[:1] == ("body",) for e in exc.errors())
    return problem_response(
        422 if in_body else 400, " ".join(detail.split())[:2000], _instance(request), errors=errors[:20]
    )


def allowed_methods(app: Any, path: str) -> list[str]:
    """Return every method the OpenAPI document declares for the path template matching ``path``."""
    patterns = getattr(app.state, "allow_patterns", None)
    if patterns is None:
        patterns = []
        for template, item in app.openapi().get("paths", {}).items():
            regex = re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(template))
            patterns.append((re.compile(f"^{regex}$"), sorted(m.upper() for m in item)))
        app.state.allow_patterns = patterns
    methods: set[str] = set()
    for regex, ms in patterns:
        if regex.match(path):
            methods.update(ms)
    return sorted(methods)


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        # Starlette names only the methods of the first route matching the path; list them all
        methods = allowed_methods(request.app, request.url.path)
        if methods:
            headers["Allow"] = ", ".join(methods)
    if exc.status_code == 304 or exc.status_code < 400:
        return Response(status_code=exc.status_code, headers=headers)
    detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail, default=str)
    return problem_response(exc.status_code, detail, _instance(request), headers=headers)


def _read_only(request: Request, cause: str) -> Response:
    """Answer a write the store refused because it is read-only: 403, like a server with no token (no retry helps)."""
    log.warning("write refused by a read-only store: %s", cause)
    detail = f"writes are refused: the store is read-only ({cause}); reads still work"
    return problem_response(403, detail, _instance(request))


async def _database_down(request: Request, exc: Exception) -> Response:
    cause = read_only_cause(exc)
    if cause is not None:
        return _read_only(request, cause)
    log.warning("database unavailable: %s", " ".join(str(exc).split())[:300])
    return problem_response(
        503, "the database is unavailable; try again later", _instance(request), headers={"Retry-After": "5"}
    )


async def _database_error(request: Request, exc: Exception) -> Response:
    """A driver error other than an outage: a read-only store (PostgreSQL's 25006) or an unexpected 500."""
    cause = read_only_cause(exc)
    if cause is not None:
        return _read_only(request, cause)
    log.error("unhandled database error on %s %s", request.method, request.url.path, exc_info=exc)
    return problem_response(500, "internal server error; the traceback is in the server log", _instance(request))


def install_handlers(app: FastAPI) -> None:
    """Map driftlab errors, request validation, HTTP errors and database outages to problem+json."""
    app.add_exception_handler(DriftlabError, _driftlab_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(OperationalError, _database_down)
    app.add_exception_handler(DBAPIError, _database_error)


class CatchAllMiddleware:
    """Pure ASGI middleware: an unexpected exception becomes a logged traceback and a 500 problem."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the app; on an unhandled exception answer 500 problem+json (if nothing was sent yet)."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def _send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, _send)
        except ClientDisconnect:
            # the client went away (or was closed for a body that did not arrive in time,
            # api.connections) before its request was read: nobody to answer, nothing to trace
            log.info("client disconnected during %s %s", scope.get("method"), scope.get("path"))
        except Exception:
            log.exception("unhandled error on %s %s", scope.get("method"), scope.get("path"))
            if started:
                raise
            response = problem_response(
                500, "internal server error; the traceback is in the server log", scope.get("path", "")
            )
            await response(scope, receive, send)


PROBLEM_SCHEMA: dict[str, Any] = {
    "title": "Problem",
    "type": "object",
    "description": "RFC 9457 problem details.",
    "required": ["type", "title", "status", "detail"],
    "properties": {
        "type": {"type": "string"},
        "title": {"type": "string"},
        "status": {"type": "integer"},
        "detail": {"type": "string"},
        "instance": {"type": "string"},
        "errors": {"type": "array", "items": {"type": "object"}},
    },
}


WRITE_METHODS = frozenset({"post", "put", "patch", "delete"})


def declare_problems(schema: dict[str, Any]) -> dict[str, Any]:
    """Add the Problem schema and problem+json responses to every operation of an OpenAPI document.

    Every write operation (POST, PUT, PATCH, DELETE) needs the bearer token: 401, 403 and 409 too.
    """
    schema.setdefault("components", {}).setdefault("schemas", {})["Problem"] = PROBLEM_SCHEMA
    ref = {"$ref": "#/components/schemas/Problem"}
    for item in schema.get("paths", {}).values():
        for method, op in item.items():
            if not isinstance(op, dict) or "responses" not in op:
                continue
            statuses = list(COMMON_PROBLEMS)
            if method in WRITE_METHODS:
                statuses += WRITE_PROBLEMS
            for status in statuses:
                entry = {"description": HTTPStatus(status).phrase, "content": {PROBLEM_MEDIA_TYPE: {"schema": ref}}}
                if status == 401:
                    entry["headers"] = {"WWW-Authenticate": {"schema": {"type": "string"}, "description": "Bearer"}}
                op["responses"][str(status)] = entry
    schema.get("components", {}).get("schemas", {}).pop("HTTPValidationError", None)
    schema.get("components", {}).get("schemas", {}).pop("ValidationError", None)
    return schema
