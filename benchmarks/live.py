"""The live page's cost to the daemon and its latency: one JSON line.

A real `driftlab serve` and real `driftlab daemon` processes on one SQLite store (the embedded default):

* ``scans_per_s_0_pages`` / ``scans_per_s_20_pages``: the daemon flat out (``--speed 0``, 50
  thermocouples every 2 s of campaign time, a Z sweep every 15 min) with no page open, and with 20
  pages following /live/events; runs alternate (0, 20, 0, 20, ...) and the medians are reported,
  with ``cost_pct`` = how much slower with 20 pages;
* ``lag_ms_*``: commit (the daemon's ``updated_at``, stored in the same transaction) to the event
  received by a page, the daemon paced at one commit per second; beside it the baseline
  ``baseline_poll_lag_ms_*``: a bare SQL poller at the same interval as the hub (0.5 s), the
  least any polling reader can do;
* ``first_paint_ms``: Chromium opening /live until the campaign's numbers are on screen (when
  Debian's chromium is installed), beside ``baseline_static_page_ms`` (the same browser opening the
  page's HTML as a static file of the same server: no script, no data).
"""

from __future__ import annotations

import _common  # noqa: F401  (first: pins numeric thread pools)

# isort: split

import json
import statistics
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.api.live_helpers import CLEAN, events, serve_process, start_daemon, stop  # noqa: E402

PLAN = """\
format: driftlab-plan/1
name: {name}
machine: {{id: vmc-5ax-01, channels: from scenario}}
scan_interval_s: {scan}
stages:
  - name: spindle
    heat: [{{kind: spindle, rpm: 10000}}]
    axis: Z
    duration_s: {half}
    sweep: &sw {{positions: [-250, -125, 0], interval_s: 900, point_s: 6, term: dz}}
  - name: cool
    axis: Z
    duration_s: {half}
    sweep: *sw
"""
PAGES = 20
ROUNDS = 3


def _plan(tmp: Path, name: str, scan_s: float, hours: float) -> Path:
    """Write a two-stage plan."""
    p = tmp / f"{name}.yaml"
    p.write_text(PLAN.format(name=name, scan=scan_s, half=hours * 1800))
    return p


def _flat_out(db: str, plan: Path, tmp: Path, tag: str) -> float:
    """Run the daemon flat out over the plan; return its scans/s."""
    stats = tmp / f"{tag}.json"
    proc = start_daemon(db, 0, "--stats-json", str(stats), plan=plan, scenario=CLEAN)
    proc.wait()
    assert proc.returncode == 0, proc.stderr.read() if proc.stderr else proc.returncode
    return float(json.loads(stats.read_text())["scans_per_s"])


class Pages:
    """``n`` threads each following /live/events; records (receive time - commit time) of updates."""

    def __init__(self, base: str, n: int) -> None:
        self.lags: list[float] = []
        self.updates = 0
        self._stop = threading.Event()
        self._ready = threading.Barrier(n + 1)
        self._lock = threading.Lock()
        self.threads = [threading.Thread(target=self._follow, args=(base,), daemon=True) for _ in range(n)]
        for t in self.threads:
            t.start()
        self._ready.wait(60)

    def _follow(self, base: str) -> None:
        """Follow the stream until stopped."""
        try:
            with httpx.Client(timeout=None) as c, c.stream("GET", f"{base}/live/events") as r:
                stream = events(r)
                next(stream)
                self._ready.wait(60)
                for name, doc in stream:
                    now = time.time()
                    if name == "update":
                        at = datetime.fromisoformat(doc["campaign"]["updated_at"].replace("Z", "+00:00")).timestamp()
                        with self._lock:
                            self.updates += 1
                            self.lags.append(now - at)
                    if self._stop.is_set():
                        return
        except httpx.HTTPError:
            return

    def close(self) -> None:
        """Stop following (the threads end at their next event or when the server stops)."""
        self._stop.set()


def _poll_baseline(db: str, stop_evt: threading.Event, out: list[float], interval: float = 0.5) -> None:
    """A bare SQL poller of the daemon's commit time at the hub's interval: commit-to-seen lags."""
    from sqlalchemy import create_engine, text

    eng = create_engine(db)
    seen = None
    while not stop_evt.is_set():
        with eng.connect() as c:
            row = c.execute(text("SELECT MAX(updated_at) FROM acquisition_progress")).scalar()
        now = time.time()
        if row is not None and row != seen:
            if seen is not None:
                at = datetime.fromisoformat(str(row))
                out.append(now - (at if at.tzinfo else at.replace(tzinfo=UTC)).timestamp())  # SQLite: naive UTC
            seen = row
        time.sleep(interval)
    eng.dispose()


def _pct(xs: list[float], q: float) -> float | None:
    """Return the q-quantile of xs in ms (None when empty)."""
    if not xs:
        return None
    xs = sorted(xs)
    return round(1e3 * xs[min(len(xs) - 1, int(q * len(xs)))], 1)


def _first_paint(base: str) -> tuple[float | None, float | None]:
    """Return (ms to the campaign's numbers on /live, ms to a static asset) in headless Chromium, or Nones."""
    import os

    if not os.path.exists("/usr/bin/chromium"):
        return None, None
    from tests.api.browser import OfflinePage, browser

    with browser() as b:
        view = OfflinePage(b)
        page = view.page
        page.goto(f"{base}/static/live.html")  # warm the browser process
        best_live, best_static = float("inf"), float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            page.goto(f"{base}/live")
            page.wait_for_selector('[data-live="scans"]')
            best_live = min(best_live, time.perf_counter() - t0)
            t0 = time.perf_counter()
            page.goto(f"{base}/static/live.html")  # the same page as a file: no data, no stream
            best_static = min(best_static, time.perf_counter() - t0)
        view.close()
    return round(best_live * 1e3, 1), round(best_static * 1e3, 1)


def main() -> int:
    """Measure and print one JSON line."""
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        db = f"sqlite:///{tmp / 'store.sqlite'}"
        dense = _plan(tmp, "bench-flat", 2.0, 7.0)  # 12,600 scans of 50 channels, 56 sweep points
        with serve_process(db) as base:
            zero, twenty = [], []
            for i in range(ROUNDS):
                zero.append(_flat_out(db, dense, tmp, f"z{i}"))
                pages = Pages(base, PAGES)
                twenty.append(_flat_out(db, dense, tmp, f"t{i}"))
                pages.close()
                flat_updates = pages.updates
            # latency: one commit per second (60 s scans at x60), 20 pages and a bare poller watching
            paced = _plan(tmp, "bench-paced", 60.0, 0.5)
            pages = Pages(base, PAGES)
            base_lags: list[float] = []
            stop_evt = threading.Event()
            poller = threading.Thread(target=_poll_baseline, args=(db, stop_evt, base_lags), daemon=True)
            poller.start()
            proc = start_daemon(db, 60, "--max-batch", "1", plan=paced, scenario=CLEAN)
            try:
                proc.wait(120)
            finally:
                stop(proc)
            time.sleep(1.0)
            stop_evt.set()
            pages.close()
            lags = list(pages.lags)
            first_paint, static = _first_paint(base)
    z, t = statistics.median(zero), statistics.median(twenty)
    _common.emit(
        {
            "benchmark": "live",
            "scans_per_s_0_pages": round(z, 1),
            "scans_per_s_20_pages": round(t, 1),
            "cost_pct": round(100 * (z - t) / z, 1),
            "runs_0_pages": zero,
            "runs_20_pages": twenty,
            "updates_per_page_flat_out": round(flat_updates / PAGES, 1),
            "lag_ms_p50": _pct(lags, 0.5),
            "lag_ms_p95": _pct(lags, 0.95),
            "lag_ms_max": _pct(lags, 1.0),
            "lag_events": len(lags),
            "baseline_poll_lag_ms_p50": _pct(base_lags, 0.5),
            "baseline_poll_lag_ms_p95": _pct(base_lags, 0.95),
            "first_paint_ms": first_paint,
            "baseline_static_page_ms": static,
            "load_average": _common.load_average(),
        }
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
