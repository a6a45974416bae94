"""Regenerate the screenshots in docs/img/ (`make screenshots`): /live, /docs, /redoc and the diagnosis report.

Everything runs here, offline, in Debian's headless Chromium: a store in a temporary directory, the
daemon on the virtual machine stopped half way through examples/plans/z-axis-demo.yaml (a scenario
whose thermocouple T34 loses its lead two hours in, so the health panel has something to show),
`driftlab serve`, and `driftlab diagnose` on the lag-z scenario.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.api.browser import OfflinePage, browser  # noqa: E402
from tests.api.live_helpers import DEMO_PLAN, serve_process  # noqa: E402

OUT = ROOT / "docs" / "img"
OPEN_T34 = """\
name: open-t34
seed: 3
hours: 8
scan_interval_s: 60
sweep_interval_s: 600
hidden:
  - {kind: sensor_fault, channels: [T34], params: {start_s: 7200, mode: open}}
"""


def cli(*args: str, env_db: str | None = None) -> None:
    """Run a driftlab command, failing loudly."""
    cmd = [sys.executable, "-m", "driftlab.cli", *args]
    if env_db:
        cmd += ["--db", env_db]
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def main() -> int:
    """Write docs/img/{live,docs,redoc,diagnosis-report}.png."""
    OUT.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        db = f"sqlite:///{t / 'store.sqlite'}"
        (t / "open-t34.yaml").write_text(OPEN_T34)
        # about 3.5 h of the 7 h plan, then stopped: the store keeps it 'running' where it stopped
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "driftlab.cli",
                "daemon",
                "--plan",
                str(DEMO_PLAN),
                "--sim",
                str(t / "open-t34.yaml"),
                "--speed",
                "0",
                "--max-batch",
                "10",
                "--stop-after",
                "26",
                "--db",
                db,
            ],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
        )
        assert proc.returncode == 3, proc.returncode
        cli("sim", "campaign", "--scenario", str(ROOT / "examples/scenarios/lag-z.yaml"), "--out", str(t / "lagz"))
        cli("diagnose", str(t / "lagz"), "--json", str(t / "diag.json"), "--html", str(t / "diagnosis.html"))
        with serve_process(db) as base, browser() as b:
            view = OfflinePage(b, width=1400, height=900)
            page = view.page
            page.goto(f"{base}/live")
            page.wait_for_selector('[data-live="scans"]')
            page.wait_for_timeout(500)
            page.screenshot(path=str(OUT / "live.png"), full_page=True)
            page.goto(f"{base}/docs")
            page.wait_for_selector(".opblock")
            page.screenshot(path=str(OUT / "docs.png"))
            page.goto(f"{base}/redoc")
            page.wait_for_selector("[data-section-id^='operation/']")
            page.wait_for_timeout(500)
            page.screenshot(path=str(OUT / "redoc.png"))
            page.set_viewport_size({"width": 1200, "height": 1600})
            page.goto((t / "diagnosis.html").as_uri())
            page.wait_for_timeout(300)
            page.screenshot(path=str(OUT / "diagnosis-report.png"))  # the top: stages and the overview
            assert view.external == [] or all("redoc.ly" in u for u in view.external), view.external
            view.close()
    for p in sorted(OUT.glob("*.png")):
        print(p.relative_to(ROOT))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
