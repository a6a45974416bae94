"""Strict inputs of the API: integers in paths and queries as plain decimal digits, JSON bodies as written.

A path or query integer is read by pydantic's lax rules unless told otherwise: ``1.0``, ``+1``, ``" 1"``
(``%201``) and ``01`` would all name campaign 1 and ``1_0`` campaign 10 (Python's ``int()`` reads
underscores). Every integer parameter here must be written as decimal digits with no sign, point,
space, underscore or leading zero; anything else is 400 before the route runs.

A JSON body is parsed by the standard library, which keeps the last of duplicate keys and reads the
non-standard ``NaN``/``Infinity``: RFC 8259 section 4 leaves duplicate names' meaning undefined, so a body
naming a key twice is refused (422) rather than silently half-read, and so are the non-JSON constants.
The bodies' models themselves are strict (``schemas._In``): no string for a number, no ``true`` for 1.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import BeforeValidator

#: the largest row id (PostgreSQL INTEGER)
MAX_ID = 2**31 - 1
_DECIMAL = re.compile(r"0|[1-9][0-9]*")


def plain_decimal(value: object) -> object:
    """Return the value unchanged when it is not text or is text of plain decimal digits; else raise ValueError."""
    if isinstance(value, str) and not _DECIMAL.fullmatch(value):
        raise ValueError(f"must be plain decimal digits (no sign, point, space, underscore), not {value[:30]!r}")
    return value


_Decimal = BeforeValidator(plain_decimal)

CampaignId = Annotated[int, Path(ge=1, le=MAX_ID, description="campaign id"), _Decimal]
VersionNumber = Annotated[int, Path(ge=1, le=MAX_ID, description="model version number"), _Decimal]
JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="job id"), _Decimal]
Limit = Annotated[int, Query(ge=1, le=1000, description="items per page"), _Decimal]
Offset = Annotated[int, Query(ge=0, le=10**9, description="items to skip"), _Decimal]
RowLimit = Annotated[int, Query(ge=1, le=10000, description="rows per page"), _Decimal]
RowOffset = Annotated[int, Query(ge=0, le=10**9, description="rows to skip (or use cursor)"), _Decimal]
Buckets = Annotated[int | None, Query(ge=1, le=10000, description="downsample to this many time buckets"), _Decimal]


class _Refused(ValueError):
    """A JSON body that parses but is not plain JSON (a key given twice, NaN, Infinity)."""


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: dict[str, Any] = {}
    for key, value in pairs:
        if key in seen:
            raise _Refused(f"the key {key[:60]!r} is given twice")
        seen[key] = value
    return seen


def _constant(name: str) -> float:
    raise _Refused(f"{name} is not a JSON number")


def json_problem(body: bytes) -> str | None:
    """Return why a JSON body is refused (a duplicate key, NaN or Infinity), or None (plain JSON, or not JSON at all).

    Malformed JSON is left to FastAPI's own parser and its usual answer.
    """
    try:
        json.loads(body, object_pairs_hook=_pairs, parse_constant=_constant)
    except _Refused as exc:
        return str(exc)
    except (ValueError, RecursionError):
        return None
    return None


def _is_json(content_type: str | None) -> bool:
    media = (content_type or "").split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


class StrictJsonRoute(APIRoute):
    """A route whose JSON body is refused (422) when it names a key twice or holds NaN/Infinity."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        """Return FastAPI's handler, preceded by the duplicate-key check when the route takes a body."""
        handler = super().get_route_handler()
        if self.body_field is None:
            return handler

        async def checked(request: Request) -> Response:
            body = await request.body()  # cached on the request: FastAPI's handler reads the same bytes
            if body and _is_json(request.headers.get("content-type")):
                problem = json_problem(body)
                if problem is not None:
                    raise RequestValidationError([{"type": "json_invalid", "loc": ("body",), "msg": problem}])
            return await handler(request)

        return checked
