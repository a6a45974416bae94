"""The live page's HTTP side on a real server: the page, its stream, the shared poller, the packaged docs assets."""

from __future__ import annotations

import math
import re
import threading
import time
from pathlib import Path

import httpx
import pytest

from driftlab.api import vendor
from driftlab.api.app import create_app
from driftlab.campaigns.plan import load_plan
from driftlab.daemon.run import run_daemon
from tests.api.live_helpers import CLEAN, events, serving

PLAN = """\
format: driftlab-plan/1
name: live-api
machine: {id: vmc-5ax-01, channels: from scenario}
scan_interval_s: 60
stages:
  - name: warm
    heat: [{kind: spindle, rpm: 10000}]
    axis: Z
    duration_s: 3600
    sweep: {positions: [-250, 0], interval_s: 600, point_s: 6, term: dz}
  - name: cool
    axis: Z
    duration_s: 3600
    sweep: {positions: [-250, 0], interval_s: 600, point_s: 6, term: dz}
"""
STATIC = Path(vendor.__file__).parent / "static"
EXTERNAL = re.compile(r"""(?:src|href)\s*=\s*["']?(?:https?:)?//""", re.I)


def _daemon(store_url: str, plan: Path, commits: int, resume: bool) -> int:
    """Run the daemon in this process on the virtual machine for some commits; return the campaign id."""
    return run_daemon(
        load_plan(plan),
        db_url=store_url,
        scenario_path=CLEAN,
        speed=math.inf,
        resume=resume,
        max_batch=5,
        stop_after_commits=commits,
    ).campaign_id


@pytest.fixture
def plan(tmp_path: Path) -> Path:
    """The plan file."""
    p = tmp_path / "plan.yaml"
    p.write_text(PLAN)
    return p


def test_page_and_assets_are_served_by_the_package_without_a_token(store_url: str) -> None:
    app = create_app(store_url, token="secret-token-0123456789", run_jobs=False)
    with serving(app) as base:
        page = httpx.get(f"{base}/live")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert not EXTERNAL.search(page.text)
        for asset in re.findall(r'(?:src|href)="(/static/[^"]+)"', page.text):
            r = httpx.get(base + asset)
            assert r.status_code == 200 and r.content, asset
        js = httpx.get(f"{base}/static/live.js").text
        for hook in ('"data-live": "stage"', '"data-live": "scans"', '"data-live": "latest-time"'):
            assert hook in js
        assert 'EventSource("/live/events")' in js and "http" not in re.sub(r"http://www\.w3\.org/2000/svg", "", js)
        snap = httpx.get(f"{base}/live/snapshot")
        assert snap.status_code == 200 and snap.json()["campaigns"] == []
        assert httpx.post(f"{base}/live/snapshot").status_code == 405
        assert "/live/snapshot" in httpx.get(f"{base}/openapi.json").json()["paths"]


def test_docs_pages_load_vendored_swagger_ui_and_redoc(store_url: str) -> None:
    assert vendor.verify() == []
    app = create_app(store_url, run_jobs=False)
    with serving(app) as base:
        for path, assets in (
            ("/docs", ("swagger-ui-bundle.js", "swagger-ui.css")),
            ("/redoc", ("redoc.standalone.js",)),
        ):
            html = httpx.get(base + path).text
            assert not EXTERNAL.search(html), path
            assert "fonts.googleapis" not in html and "cdn.jsdelivr" not in html
            for a in assets:
                url = re.search(rf'["\'](/static/vendor/[^"\']*{re.escape(a)})["\']', html).group(1)
                r = httpx.get(base + url)
                assert r.status_code == 200 and len(r.content) > 100_000
                assert r.content == (STATIC / url.removeprefix("/static/")).read_bytes()


def test_vendored_files_are_checked_against_their_manifest(tmp_path: Path, monkeypatch) -> None:
    import shutil

    copy = tmp_path / "vendor"
    shutil.copytree(vendor.VENDOR, copy)
    monkeypatch.setattr(vendor, "VENDOR", copy)
    monkeypatch.setattr(vendor, "MANIFEST", copy / "VENDOR.json")
    assert vendor.verify() == []
    css = copy / "swagger-ui" / "swagger-ui.css"
    css.write_bytes(css.read_bytes() + b"\n")
    (copy / "redoc" / "LICENSE").unlink()
    problems = vendor.verify()
    assert len(problems) == 2 and any("swagger-ui.css differs" in p for p in problems)
    assert any("LICENSE missing" in p for p in problems)


def test_stream_sends_a_snapshot_then_each_commit(store_url: str, plan: Path) -> None:
    import queue

    cid = _daemon(store_url, plan, commits=3, resume=False)
    app = create_app(store_url, run_jobs=False, live_poll_s=0.05)
    inbox: queue.Queue[tuple[str, dict]] = queue.Queue()
    with serving(app) as base, httpx.Client(timeout=20) as client:
        with client.stream("GET", f"{base}/live/events") as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            stream = events(r)
            name, snap = next(stream)
            assert name == "snapshot"
            [camp] = snap["campaigns"]
            assert camp["campaign_id"] == cid and camp["status"] == "running"
            scans0 = camp["progress"]["scans"]
            seq0 = max(camp["errors"]["seq"], default=-1)
            t0 = max(camp["temperatures"]["t"])
            reader = threading.Thread(target=_pump, args=(stream, inbox), daemon=True)
            reader.start()
            _daemon(store_url, plan, commits=4, resume=True)  # meanwhile the page follows
            final = _stored_scans(store_url, cid)
            seen_scans: list[int] = []
            new_seq: list[int] = []
            while not seen_scans or seen_scans[-1] < final:
                name, doc = inbox.get(timeout=20)
                if name != "update":
                    assert name == "campaign"  # the hub's first read of the campaign: whole again
                    continue
                c = doc["campaign"]
                seen_scans.append(c["progress"]["scans"])
                new_seq += c["errors"]["seq"]
                assert min(c["temperatures"]["t"], default=math.inf) > t0 - 60.0 * 1.01
    assert seen_scans == sorted(seen_scans) and seen_scans[-1] == final > scans0
    assert new_seq == sorted(set(new_seq)) and all(s > seq0 for s in new_seq)


def _pump(stream, inbox) -> None:
    """Put each event of the stream in the inbox until the connection is closed."""
    try:
        for ev in stream:
            inbox.put(ev)
    except (httpx.HTTPError, httpx.StreamError):  # closed by the test at its end
        return


def _stored_scans(store_url: str, cid: int) -> int:
    """Return the scans the store holds for the campaign (plain SQL)."""
    from sqlalchemy import create_engine, text

    from driftlab.campaigns.db import normalise_url

    eng = create_engine(normalise_url(store_url))
    try:
        with eng.connect() as c:
            return int(
                c.execute(
                    text("SELECT COUNT(DISTINCT time_s) FROM temperature_samples WHERE campaign_id = :c"), {"c": cid}
                ).scalar()
            )
    finally:
        eng.dispose()


def test_twenty_pages_share_one_poller(tmp_path: Path, plan: Path) -> None:
    store_url = f"sqlite:///{tmp_path / 'live.sqlite'}"
    _daemon(store_url, plan, commits=2, resume=False)
    app = create_app(store_url, run_jobs=False, live_poll_s=0.1)
    hub = app.state.live_hub
    got: list[int] = []
    lock = threading.Lock()

    def page(ready: threading.Barrier) -> None:
        """Follow the stream until the daemon's next commits arrive."""
        with httpx.Client(timeout=30) as c, c.stream("GET", f"{base}/live/events") as r:
            stream = events(r)
            assert next(stream)[0] == "snapshot"
            ready.wait()
            for name, doc in stream:
                if name == "update":
                    with lock:
                        got.append(doc["campaign"]["progress"]["scans"])
                    return

    with serving(app) as base:
        ready = threading.Barrier(21)
        pages = [threading.Thread(target=page, args=(ready,)) for _ in range(20)]
        for t in pages:
            t.start()
        ready.wait()
        assert len(hub.subscribers) == 20
        polls0, t0 = hub.polls, time.monotonic()
        _daemon(store_url, plan, commits=2, resume=True)
        for t in pages:
            t.join(30)
        elapsed = time.monotonic() - t0
        # one read of the store per poll interval, whatever the number of pages
        assert hub.polls - polls0 <= elapsed / 0.1 + 2
    assert len(got) == 20 and len(set(got)) == 1
    time.sleep(0.3)
    assert not hub.subscribers and hub._task is None  # the last page gone: polling stopped
