"""The API's front door (pure ASGI): the bearer token of a write and the size of a body, checked first.

A write (POST, PUT, PATCH, DELETE on a declared write operation) without a valid token is answered
401/403 before a byte of its body is read, so an unauthenticated client cannot make the server buffer
or parse anything. Every body is capped: a ``Content-Length`` over the limit is 413 at once, and a
body streamed without one (chunked) is counted as it arrives and refused with 413 when it passes the
limit. Both answers are RFC 9457 problem documents like every other error of the API.
"""

from __future__ import annotations

import hmac
import json
from typing import Any

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from driftlab.api.problems import PROBLEM_MEDIA_TYPE, allowed_methods, problem_body

WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: the largest request body accepted (a model document is tens of kilobytes; a probe post is one line)
MAX_BODY_BYTES = 8 << 20


def token_problem(expected: str, authorization: str | None) -> tuple[int, str, dict[str, str]] | None:
    """Return (status, detail, headers) refusing a write, or None when the bearer token is right."""
    if not expected:
        return 403, "writes are disabled: no API token is configured (DRIFTLAB_API_TOKEN)", {}
    header = authorization or ""
    scheme, _, given = header.partition(" ")
    if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), expected.encode()):
        reason = "missing bearer token" if not header else "invalid bearer token"
        return (
            401,
            f"{reason}: writes need Authorization: Bearer <DRIFTLAB_API_TOKEN>",
            {"WWW-Authenticate": 'Bearer realm="driftlab"'},
        )
    return None


async def _answer(send: Send, status: int, detail: str, path: str, headers: dict[str, str] | None = None) -> None:
    body = json.dumps(problem_body(status, detail, path)).encode()
    raw = [
        (b"content-type", PROBLEM_MEDIA_TYPE.encode()),
        (b"content-length", str(len(body)).encode()),
        (b"connection", b"close"),
    ]
    raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


class FrontDoorMiddleware:
    """Check a write's bearer token before its body is read; refuse bodies over ``max_body_bytes`` (413)."""

    def __init__(self, app: ASGIApp, max_body_bytes: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Answer 401/403/413/400 without reading the body, or pass the request on with a counted body."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path: str = scope.get("path", "")
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        method = scope.get("method", "GET")
        app: Any = scope.get("app")
        if method in WRITE_METHODS and app is not None and method in allowed_methods(app, path):
            refused = token_problem(app.state.driftlab.token, headers.get("authorization"))
            if refused is not None:
                await _answer(send, refused[0], refused[1], path, refused[2])
                return
        length = headers.get("content-length")
        if length is not None:
            if not length.isdigit() or len(length) > 18:
                await _answer(send, 400, f"Content-Length {length[:30]!r} is not a byte count", path)
                return
            if int(length) > self.max_body_bytes:
                await _answer(
                    send,
                    413,
                    f"request body of {int(length)} bytes is larger than the limit of {self.max_body_bytes} bytes",
                    path,
                )
                return
        received = 0
        limit = self.max_body_bytes

        async def counted() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    # FastAPI passes an HTTPException raised while reading the body through unchanged:
                    # the problem handler turns it into the 413 document
                    raise HTTPException(413, f"request body larger than the limit of {limit} bytes")
            return message

        await self.app(scope, counted, send)
