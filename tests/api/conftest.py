"""Fixtures of the API tests: a store seeded with a small bundle and a model, apps and HTTP clients."""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import httpx
import pytest

from driftlab.api.app import create_app
from driftlab.campaigns.store import Store, connect
from tests.api.helpers import TOKEN, Seeded, seed


@pytest.fixture
def seeded(store_url: str, tmp_path: Path) -> Seeded:
    """A database at the head schema (SQLite and PostgreSQL) with one campaign and one current model and
    nothing else (``store_url``: emptied or copied, cheaper than a new database and its migrations)."""
    return seed(store_url, tmp_path)


@pytest.fixture
def store(seeded: Seeded) -> Iterator[Store]:
    """A store on the seeded database (to look behind the API)."""
    with connect(seeded.url) as s:
        yield s


@pytest.fixture
async def client(seeded: Seeded) -> AsyncIterator[httpx.AsyncClient]:
    """An httpx client on the app (ASGI transport, lifespan run, jobs executed in the background)."""
    app = create_app(seeded.url, TOKEN)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            c.app = app  # type: ignore[attr-defined]
            yield c


@pytest.fixture
def anyio_backend() -> str:
    """Run the async tests on asyncio."""
    return "asyncio"
