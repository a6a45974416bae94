"""In a real headless Chromium: /live follows a campaign the daemon is running; /docs and /redoc work offline."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from driftlab.campaigns.plan import load_plan
from tests.api.browser import OfflinePage, browser, require_chromium
from tests.api.live_helpers import DEMO_PLAN, serve_process, start_daemon, stop

pytestmark = pytest.mark.slow

SCANS = '[data-live="scans"]'
REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"


def _scans(page) -> int:
    return int(page.inner_text(SCANS))


def test_live_page_follows_a_running_campaign(tmp_path: Path) -> None:
    require_chromium()
    db_url = f"sqlite:///{tmp_path / 'live.sqlite'}"
    stages = [s.name for s in load_plan(DEMO_PLAN).stages]
    with serve_process(db_url) as base, browser() as b:
        view = OfflinePage(b)
        page = view.page
        page.goto(f"{base}/live")
        page.wait_for_selector("#conn[data-state=open]")
        assert "No campaign is running" in page.inner_text("main")
        page.evaluate("window.__sameDocument = true")
        # 25,200 s of campaign at x600: about 42 s if left to run; stopped once the page has followed it a while
        daemon = start_daemon(db_url, 600)
        try:
            page.wait_for_selector(SCANS, timeout=60_000)
            # the campaign appears at its creation; its first scans follow
            page.wait_for_function(f"Number(document.querySelector('{SCANS}').textContent) > 0", timeout=60_000)
            first = _scans(page)
            t_first = float(page.get_attribute('[data-live="latest-time"]', "data-seconds"))
            seen = {first}
            for _ in range(3):
                page.wait_for_function(
                    f"Number(document.querySelector('{SCANS}').textContent) > {max(seen)}", timeout=30_000
                )
                seen.add(_scans(page))
            t_last = float(page.get_attribute('[data-live="latest-time"]', "data-seconds"))
            assert page.inner_text('[data-live="stage"]') in stages
            assert page.inner_text('[data-live="status"]') == "running"
            assert len(page.query_selector_all("[data-structure]")) >= 10  # one chart per structure
            assert page.query_selector('[data-term="Z/dz"] svg path') is not None
            updates = int(page.get_attribute("body", "data-updates"))
            navigations = page.evaluate("performance.getEntriesByType('navigation').length")
            same = page.evaluate("window.__sameDocument === true")
        finally:
            stop(daemon)
        stored = int(httpx.get(f"{base}/live/snapshot").json()["campaigns"][0]["progress"]["scans"])
        view.close()
    assert len(seen) >= 4 and max(seen) <= stored  # the numbers changed, pushed into one document
    assert t_last > t_first
    assert updates >= 3 and navigations == 1 and same
    assert daemon.returncode == 3  # stopped early on SIGTERM, resumable
    assert view.external == [] and view.errors == []


def test_docs_and_redoc_work_with_no_network(tmp_path: Path) -> None:
    require_chromium()
    db_url = f"sqlite:///{tmp_path / 'docs.sqlite'}"
    with serve_process(db_url) as base, browser() as b:
        ops = httpx.get(f"{base}/openapi.json").json()["paths"]
        n_ops = sum(len([m for m in item if m in ("get", "post", "put", "patch", "delete")]) for item in ops.values())
        view = OfflinePage(b)
        page = view.page
        page.goto(f"{base}/docs")
        page.wait_for_selector(".opblock", timeout=30_000)
        page.wait_for_function(f"document.querySelectorAll('.opblock').length >= {n_ops}", timeout=30_000)
        text = page.inner_text("body")
        assert "/machines/{machine_id}/model/current" in text and "/live/snapshot" in text
        assert view.external == []  # Swagger UI asks nothing of the internet
        page.goto(f"{base}/redoc")
        page.wait_for_selector("[data-section-id^='operation/']", timeout=30_000)
        sections = page.evaluate("document.querySelectorAll(\"[data-section-id^='operation/']\").length")
        assert sections >= n_ops
        assert "Running campaigns as the live page shows them" in page.inner_text("body")
        # ReDoc's sidebar credit is an <img> from its vendor's CDN, dropped by ReDoc when it fails to load
        logo = page.evaluate("document.querySelectorAll('img[alt=\"redocly logo\"]').length")
        view.close()
    assert set(view.external) <= {REDOC_LOGO} and logo == 0 and view.errors == []
