"""Headless Chromium (Debian's package) driven by Playwright, with every request off this machine refused."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any
from urllib.parse import urlsplit

import pytest

CHROMIUM = os.environ.get("DRIFTLAB_CHROMIUM", "/usr/bin/chromium")
ARGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    # no name resolves but the loopback: a page that needs the internet fails here as it would offline
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1",
]
LOCAL = {"127.0.0.1", "localhost", "::1"}


def require_chromium() -> str:
    """Return the Chromium binary; skip without it, but fail in CI or under make test (make setup installs it)."""
    path = CHROMIUM if os.path.exists(CHROMIUM) else shutil.which("chromium")
    if path:
        return path
    required = (
        os.environ.get("CI")
        or os.environ.get("DRIFTLAB_REQUIRE_BROWSER") == "1"
        or os.environ.get("DRIFTLAB_REQUIRE_PG") == "1"
    )
    msg = f"no Chromium at {CHROMIUM}: `make setup` installs Debian's chromium"
    if required:
        pytest.fail(msg)
    pytest.skip(msg)


@contextmanager
def browser() -> Iterator[Any]:
    """Yield a Playwright browser on Debian's Chromium."""
    from playwright.sync_api import sync_playwright

    path = require_chromium()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=path, args=ARGS)
        try:
            yield b
        finally:
            b.close()


class OfflinePage:
    """A page whose requests to any host but this machine are refused and recorded."""

    def __init__(self, b: Any, width: int = 1400, height: int = 1000) -> None:
        self.context = b.new_context(viewport={"width": width, "height": height}, service_workers="block")
        self.external: list[str] = []
        self.errors: list[str] = []
        self.context.route("**/*", self._route)
        self.page = self.context.new_page()
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))

    def _route(self, route: Any) -> None:
        """Continue requests to this machine; refuse and record any other."""
        url = route.request.url
        host = urlsplit(url).hostname or ""
        if url.startswith(("data:", "blob:", "file:")) or host in LOCAL:
            route.continue_()
        else:
            self.external.append(url)
            route.abort("internetdisconnected")

    def close(self) -> None:
        """Close the page's context."""
        self.context.close()
