"""`driftlab demo`: the whole story on a fresh machine, each step the real component (see docs/demo.md).

1. a staged campaign on the virtual machine with a hidden effect, through the daemon;
2. `driftlab fit`, registering a model version;
3. `driftlab export` + `driftlab diagnose` (JSON and HTML reports; the report names the effect);
4. `driftlab serve` on 127.0.0.1 (a free port, a fresh write token);
5. the cutting test of ch. 7.3: uncompensated, with the off-line model fetched from the API (ETag)
   and streamed through the compensator to the simulated controller, and with the on-line model
   updated through the API from probe measurements every 15 minutes;
6. a table on the terminal, demo-report.html and demo-report.json in --out.

Everything lives in --out: the SQLite database (an explicit URL), logs of every command, the
campaign bundle and the reports, so runs are independent.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import secrets
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from driftlab.commands import demo_report as rep
from driftlab.commands.tables import print_table
from driftlab.errors import DriftlabError, InstrumentError, ValidationError
from driftlab.labels import si_text
from driftlab.resources import examples_dir

if TYPE_CHECKING:
    from rich.table import Table

    from driftlab.campaigns.plan import Plan
    from driftlab.daq.sim.scenario import Scenario

log = logging.getLogger(__name__)

EXAMPLES = examples_dir()  # shipped in the package: the demo runs from any directory
DEFAULT_PLAN = EXAMPLES / "plans" / "demo-full.yaml"
DEFAULT_SCENARIO = EXAMPLES / "scenarios" / "demo-full.yaml"
#: the two cutting tests: the campaign's machine as it is, and the same machine after wear (ch. 6.4.3)
CASES = ("thermal", "thermal+wear")


def register(sub: argparse._SubParsersAction) -> None:
    """Register `demo`."""
    p = sub.add_parser(
        "demo",
        help="run the whole pipeline on the virtual machine: campaign, fit, diagnosis, "
        "API, compensated cutting test; write an HTML and JSON report",
    )
    p.add_argument("--out", type=Path, default=Path("demo-out"), help="output directory (default demo-out)")
    p.add_argument(
        "--plan",
        type=Path,
        default=DEFAULT_PLAN,
        help="campaign plan (default examples/plans/demo-full.yaml: all thirty terms)",
    )
    p.add_argument(
        "--scenario",
        type=Path,
        default=DEFAULT_SCENARIO,
        help="virtual-machine scenario with the hidden effect (default examples/scenarios/demo-full.yaml)",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=0.0,
        help="daemon speed: simulated seconds per wall second (0 = as fast as possible)",
    )
    p.add_argument(
        "--passes",
        type=int,
        default=700,
        help="raster passes of the cutting program (700: about 80 min of cutting; at least 99)",
    )
    p.add_argument("--forgetting", type=float, default=0.9, help="on-line forgetting factor lambda (default 0.9)")
    p.add_argument(
        "--age-days",
        type=float,
        default=1.0,
        help="days from the campaign's start to the cutting test (the machine cooled down meanwhile)",
    )
    p.add_argument(
        "--wear-um-per-day",
        type=float,
        default=30.0,
        help="wear of the Z slideways in the thermal+wear cutting test, µm per day since the campaign "
        "started (default 30; catalogue: drift)",
    )
    p.set_defaults(func=_demo)


class _Steps:
    """Runs the demo's commands as subprocesses, logging each to --out/logs and timing it."""

    def __init__(self, out: Path, db_url: str, console: Any) -> None:
        self.out, self.db_url, self.console = out, db_url, console
        self.logs = out / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.done: list[dict[str, Any]] = []

    def cli(self, name: str, *args: str, env: dict[str, str] | None = None) -> str:
        """Run `driftlab ARGS` to completion; return its stdout, or raise with the tail of its log."""
        cmd = [sys.executable, "-m", "driftlab.cli", *args]
        shown = "driftlab " + " ".join(args)
        self.console.print(f"[bold cyan]>[/] {shown}")
        t0 = time.perf_counter()
        # the step's tables are drawn for this terminal's width (COLUMNS), then shown whole; piped, at
        # their natural width (commands.tables), one row a line
        width = {"COLUMNS": str(self.console.width)} if self.console.is_terminal else {}
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env or _env(**width), check=False)
        wall = time.perf_counter() - t0
        (self.logs / f"{name}.log").write_text(f"$ {shown}\n{proc.stdout}\n--- stderr ---\n{proc.stderr}")
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
            raise DriftlabError(
                f"demo step {name} failed (exit {proc.returncode}): {tail}; see {self.logs / (name + '.log')}"
            )
        self.done.append({"name": name, "command": shown, "wall_s": round(wall, 2)})
        for line in proc.stdout.rstrip().splitlines():
            self.console.print(f"  {si_text(line)}", markup=False, highlight=False, crop=False, soft_wrap=True)
        return proc.stdout

    def record(self, name: str, command: str, wall_s: float) -> None:
        """Note an in-process step."""
        self.done.append({"name": name, "command": command, "wall_s": round(wall_s, 2)})


def _env(**extra: str) -> dict[str, str]:
    """Return the environment for the subprocesses (this interpreter's package on the path)."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(extra)
    return env


def free_port() -> int:
    """Return a TCP port free on 127.0.0.1 right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ApiServer:
    """`driftlab serve` in a subprocess on 127.0.0.1 with a write token; stopped on exit."""

    def __init__(self, db_url: str, log_path: Path, token: str) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.token = token
        self._log = open(log_path, "w")  # noqa: SIM115 - closed in stop()
        cmd = [
            sys.executable,
            "-m",
            "driftlab.cli",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(self.port),
            "--db",
            db_url,
            "--no-jobs",
            "--log-level",
            "warning",
        ]
        self.command = "driftlab " + " ".join(cmd[3:])
        self.proc = subprocess.Popen(
            cmd, stdout=self._log, stderr=subprocess.STDOUT, env=_env(DRIFTLAB_API_TOKEN=token)
        )

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Return once /health answers ok; InstrumentError when the server died or never answered."""
        # lazy: this function's imports would add 58 ms to `driftlab --help` (measured)
        import httpx

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise InstrumentError(f"driftlab serve exited with status {self.proc.returncode}")
            try:
                if httpx.get(f"{self.url}/health", timeout=2.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise InstrumentError(f"driftlab serve did not answer on {self.url} within {timeout_s:.0f} s")

    def stop(self) -> None:
        """Terminate the server and wait for it."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


def _demo(args: argparse.Namespace) -> int:
    """Run the demo; 0 when every step ran (the report says whether the ordering held)."""
    # lazy: this function's imports would add 0.9 s to `driftlab --help` (measured)
    from rich.console import Console

    from driftlab.campaigns.plan import load_plan
    from driftlab.daq.sim.scenario import load_scenario

    console = Console(stderr=False, highlight=False)
    _check_options(args)
    plan = load_plan(args.plan)
    scenario = load_scenario(args.scenario)
    out: Path = args.out
    steps = _Steps(out, _fresh_db(out), console)
    t_start = time.perf_counter()
    campaign_id = _run_campaign(args, steps)
    fit_report = _run_fit(steps, campaign_id)
    diag_report = _run_diagnosis(steps, campaign_id)
    tests, model_info = _serve_and_cut(args, steps, scenario, plan.machine.id)
    wall = time.perf_counter() - t_start
    facts = _DemoFacts(args, campaign_id, plan, scenario, fit_report, model_info, wall)
    report, diagnosis = _write_reports(steps, facts, diag_report, tests)
    _print_closing(console, tests, diagnosis, report, out, wall)
    return 0


def _check_options(args: argparse.Namespace) -> None:
    """Refuse out-of-range options before any work (ValidationError, one line)."""
    if args.passes < 99:
        raise ValidationError(f"--passes must be at least 99 (one per CMM row), got {args.passes}")
    if not 0.5 < args.forgetting <= 1.0:
        raise ValidationError(f"--forgetting must be in (0.5, 1], got {args.forgetting}")
    if not 0.0 <= args.age_days <= 365.0:
        raise ValidationError(f"--age-days must be in [0, 365], got {args.age_days}")
    if args.speed < 0:
        raise ValidationError(f"--speed must be >= 0 (0 = as fast as possible), got {args.speed}")
    if not 0.0 < args.wear_um_per_day <= 1000.0:
        raise ValidationError(f"--wear-um-per-day must be in (0, 1000], got {args.wear_um_per_day}")


def _fresh_db(out: Path) -> str:
    """Make ``out``, remove a previous run's SQLite store there, and return the URL of a new one."""
    out.mkdir(parents=True, exist_ok=True)
    db = out / "driftlab.sqlite"
    for stale in (db, db.with_name(db.name + "-wal"), db.with_name(db.name + "-shm")):
        stale.unlink(missing_ok=True)
    return f"sqlite:///{db.resolve()}"


def _stats_path(steps: _Steps) -> Path:
    """Return where the daemon writes its run's figures."""
    return steps.out / "daemon-stats.json"


def _run_campaign(args: argparse.Namespace, steps: _Steps) -> int:
    """Step 1: the staged campaign on the virtual machine, through the daemon; return its id."""
    steps.console.rule("1. staged campaign on the virtual machine, through the daemon")
    stats = _stats_path(steps)
    steps.cli(
        "daemon",
        "daemon",
        "--plan",
        str(args.plan),
        "--sim",
        str(args.scenario),
        "--speed",
        f"{args.speed:g}",
        "--db",
        steps.db_url,
        "--stats-json",
        str(stats),
    )
    return int(json.loads(stats.read_text())["campaign_id"])


def _run_fit(steps: _Steps, campaign_id: int) -> dict[str, Any]:
    """Step 2: fit the model and register it; return the fit report."""
    steps.console.rule("2. fit the model and register it")
    report = steps.out / "fit-report.json"
    steps.cli("fit", "fit", "--campaign", str(campaign_id), "--db", steps.db_url, "--json", str(report))
    return dict(json.loads(report.read_text()))


def _run_diagnosis(steps: _Steps, campaign_id: int) -> dict[str, Any]:
    """Step 3: export the campaign as a bundle and diagnose it; return the diagnosis report."""
    out = steps.out
    steps.console.rule("3. diagnose the campaign")
    bundle = out / "campaign-bundle"
    if bundle.exists():
        shutil.rmtree(bundle)
    steps.cli("export", "export", str(campaign_id), str(bundle), "--db", steps.db_url)
    steps.cli(
        "diagnose",
        "diagnose",
        str(bundle),
        "--json",
        str(out / "diagnosis.json"),
        "--html",
        str(out / "diagnosis.html"),
    )
    return dict(json.loads((out / "diagnosis.json").read_text()))


def _serve_and_cut(
    args: argparse.Namespace, steps: _Steps, scenario: Scenario, machine: str
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Steps 4 and 5: serve the model over the API and run both cutting tests; return them and what was served."""
    console = steps.console
    console.rule("4. serve the model over the API")
    token = secrets.token_urlsafe(24)
    server = ApiServer(steps.db_url, steps.logs / "serve.log", token)
    try:
        t0 = time.perf_counter()
        server.wait_ready()
        steps.record("serve", server.command, time.perf_counter() - t0)
        console.print(f"  API on {server.url}")
        console.rule("5. cutting tests (ch. 7.3) through the streaming compensator")
        tests: dict[str, Any] = {}
        model_info: dict[str, Any] = {}
        for case, machine_case in zip(CASES, (scenario, with_wear(scenario, args.wear_um_per_day))):
            t0 = time.perf_counter()
            console.print(f"  case [bold]{case}[/]")
            tests[case], model_info = _cutting_test(args, machine_case, machine, server, console)
            program = tests[case].program
            steps.record(
                f"cutting test ({case})",
                f"3 runs x {program.pose_written.shape[0]} blocks through the "
                f"machine link ({program.duration_s / 60:.0f} min of cutting each)",
                time.perf_counter() - t0,
            )
    finally:
        server.stop()
    return tests, model_info


@dataclass(frozen=True)
class _DemoFacts:
    """What the report states besides the cutting tests: the options, the campaign, the fit and the API's model."""

    args: argparse.Namespace
    campaign_id: int
    plan: Plan
    scenario: Scenario
    fit_report: dict[str, Any]
    model_info: dict[str, Any]
    wall_s: float


def _write_reports(
    steps: _Steps, facts: _DemoFacts, diag_report: dict[str, Any], tests: dict[str, Any]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Step 6: write demo-report.json and demo-report.html; return the report and the diagnosis summary."""
    out = steps.out
    test = tests["thermal+wear"]
    table = test.table()
    diagnosis = rep.diagnosis_summary(diag_report)
    report = rep.build_report(
        table=table, diagnosis=diagnosis, steps=steps.done, extra=_report_extra(steps, facts, tests)
    )
    rep.write_json(out / "demo-report.json", report)
    figure = rep.surface_figure({k: r.deviation_mm for k, r in test.runs.items()})
    (out / "demo-report.html").write_text(rep.to_html(report, figure), encoding="utf-8")
    return report, diagnosis


def _report_extra(steps: _Steps, facts: _DemoFacts, tests: dict[str, Any]) -> dict[str, Any]:
    """Return the report's figures beyond the table: campaign, coverage, model, program, on-line, both tests."""
    args, plan, fit_report = facts.args, facts.plan, facts.fit_report
    test = tests["thermal+wear"]
    return {
        "wall_s": round(facts.wall_s, 1),
        "campaign": {
            "id": facts.campaign_id,
            "plan": str(args.plan),
            "scenario": str(args.scenario),
            **json.loads(_stats_path(steps).read_text()),
        },
        "planted": [e.model_dump() for e in facts.scenario.hidden],
        # what the campaign measured and what the fitted model holds, of the thirty motion-error terms
        "coverage": {
            "measured": [c for c, st in plan.coverage().items() if st],
            "modelled": sorted({f"{t['axis']}/{t['term']}" for t in fit_report.get("terms", [])}),
        },
        "model": {**facts.model_info, "kept_channels": fit_report.get("kept_channels", [])},
        "program": {
            "blocks": int(test.program.pose_written.shape[0]),
            "passes": test.program.passes,
            "cutting_min": round(test.program.duration_s / 60, 1),
            "spindle_rpm": 10000,
            "feed_mm_min": 2000,
            "rotary_feed_deg_min": 300,
        },
        "online": {**test.table()["online"], "forgetting": args.forgetting, "updates": test.runs["online"].probes},
        # both cutting tests, RMSE of the normal deviation (mm): the campaign's machine, then worn
        "cutting_tests": [_cutting_row(case, t) for case, t in tests.items()],
        "wear_um_per_day": args.wear_um_per_day,
    }


def _cutting_row(case: str, t: Any) -> dict[str, Any]:
    """Return one cutting test's entry of the report: RMSE and max per run, unaligned, predicted spread."""
    tab = t.table()
    return {
        "case": case,
        **{f"{k}_mm": tab[k]["rmse_mm"] for k in rep.RUN_NAMES},
        **{f"{k}_max_mm": tab[k]["max_mm"] for k in rep.RUN_NAMES},
        # before the CMM's alignment on the reference pass: where the surface sits in the machine
        **{f"{k}_unaligned_mm": tab[k]["unaligned_rmse_mm"] for k in rep.RUN_NAMES if "unaligned_rmse_mm" in tab[k]},
        # the off-line model's own predicted spread of this cut (issue 21.4), beside the measured
        **({"offline_predicted": t.offline_predicted} if t.offline_predicted else {}),
    }


def _print_closing(
    console: Any,
    tests: dict[str, Any],
    diagnosis: dict[str, Any],
    report: dict[str, Any],
    out: Path,
    wall: float,
) -> None:
    """Print the cutting tests' table, the predicted spreads, what the diagnosis named and the ordering."""
    print_table(_cutting_table(tests), console)
    for case, ct in tests.items():
        if ct.offline_predicted:
            console.print(f"  {case}: {rep.interval_text(ct.offline_predicted)}")
    named = ", ".join(diagnosis["named"]) or "nothing"
    console.print(f"diagnosis names: [bold]{named}[/]")
    console.print(
        f"ordering uncompensated > off-line > on-line: "
        f"{'[green]holds[/]' if report['ordering_holds'] else report['ordering']}"
    )
    console.print(f"report: {out / 'demo-report.html'} and {out / 'demo-report.json'} ({wall:.0f} s)")


def _cutting_table(tests: dict[str, Any]) -> Table:
    """Return the terminal table of both cutting tests beside the thesis' figures (µm)."""
    # lazy: this function's imports would add 19 ms to `driftlab --help` (measured)
    from rich.table import Table

    t = Table(
        title="Cutting tests, ch. 7.3 (normal deviation of the machined surface, µm; the CMM aligns the part on its "
        "reference pass, 'unaligned' is before that)"
    )
    for col in ("case", "run", "RMSE", "max", "unaligned RMSE", "thesis RMSE", "thesis max", "verdict"):
        t.add_column(col, justify="left" if col in ("case", "run", "verdict") else "right")
    for case, ct in tests.items():
        tab = ct.table()
        figures = {"uncompensated_mm": tab["uncompensated"]["rmse_mm"]}
        if "unaligned_rmse_mm" in tab["uncompensated"]:
            figures["uncompensated_unaligned_mm"] = tab["uncompensated"]["unaligned_rmse_mm"]
        for k in rep.RUN_NAMES:
            figures[f"{k}_mm"] = tab[k]["rmse_mm"]
            if "unaligned_rmse_mm" in tab[k]:
                figures[f"{k}_unaligned_mm"] = tab[k]["unaligned_rmse_mm"]
        if ct.offline_predicted:
            figures["offline_predicted"] = {"inside": ct.offline_predicted.get("inside")}
        for k, name in rep.RUN_NAMES.items():
            words, worse = rep.judge(k, figures)
            t.add_row(
                case if k == "uncompensated" else "",
                name,
                f"{tab[k]['rmse_mm'] * 1e3:.1f}",
                f"{tab[k]['max_mm'] * 1e3:.1f}",
                f"{tab[k]['unaligned_rmse_mm'] * 1e3:.1f}" if "unaligned_rmse_mm" in tab[k] else "",
                f"{rep.THESIS[k]['rmse_mm'] * 1e3:.0f}",
                f"{rep.THESIS[k]['max_mm'] * 1e3:.0f}",
                f"[red]{words}[/]" if worse else words,
            )
    return t


def with_wear(scenario: Scenario, um_per_day: float) -> Scenario:
    """Return ``scenario`` with its Z slideways wearing (catalogue ``drift`` on Z/dz, ch. 6.4.3), nothing else
    changed."""
    # lazy: this function's imports would add 0.3 s to `driftlab --help` (measured)
    from driftlab.daq.sim.scenario import HiddenEffect

    wear = HiddenEffect(kind="drift", axis="Z", term="dz", params={"rate_per_day": um_per_day * 1e-3})
    return scenario.model_copy(update={"hidden": [*scenario.hidden, wear]})


def _cutting_test(
    args: argparse.Namespace, scenario: Any, machine: str, server: ApiServer, console: Any
) -> tuple[Any, dict[str, Any]]:
    """Run the three cutting runs against the API; return the test and what the API served."""
    # lazy: this function's imports would add 1.2 s to `driftlab --help` (measured)
    import httpx

    from driftlab.compensator.cutting_test import ApiRLS, run_cutting_test
    from driftlab.compensator.stream import ApiModel

    sources: list[ApiModel] = []

    def models() -> ApiModel:
        """Return a fresh model source on the API (each run fetches the model, then polls with its ETag)."""
        src = ApiModel(server.url, machine, token=server.token)
        sources.append(src)
        return src

    # each case starts the on-line model afresh, as after maintenance (DELETE /machines/{id}/online)
    reset = httpx.delete(
        f"{server.url}/machines/{machine}/online", timeout=10.0, headers={"Authorization": f"Bearer {server.token}"}
    )
    if reset.status_code not in (204, 404):
        raise DriftlabError(f"the API refused to reset the on-line model: HTTP {reset.status_code}")
    first = models()
    first.refresh()
    if first.document is None:
        raise DriftlabError(f"the API served no model for {machine}")
    document = first.document
    # a second request with the ETag must be answered 304 Not Modified
    probe = httpx.get(
        f"{server.url}/machines/{machine}/model/current", headers={"If-None-Match": first.etag or ""}, timeout=5.0
    )
    info = {
        "version": document.get("version"),
        "etag": first.etag,
        "if_none_match_status": probe.status_code,
        "terms": len(document.get("terms", [])),
    }

    def online() -> ApiRLS:
        """Return a fresh on-line model kept by the API."""
        return ApiRLS(server.url, machine, token=server.token, forgetting=args.forgetting)

    # lazy, as above: kept off the `driftlab --help` path
    from driftlab.progress import progress

    with progress("cutting test", total=3) as bar:

        def done(key: str) -> None:
            """Advance the bar and say which run finished."""
            bar.advance()
            console.print(f"  run {key} done")

        # the session's t = 0 in POSIX time: the campaign's start (the model's time origin) plus its age, so
        # time-dependent terms of the model are evaluated at each block's time on the simulated clock
        origin = document.get("time_origin")
        epoch = (
            None
            if not origin
            else (datetime.fromisoformat(str(origin).replace("Z", "+00:00")).timestamp() + args.age_days * 86400.0)
        )
        test = run_cutting_test(
            scenario, models, online, passes=args.passes, age_s=args.age_days * 86400.0, on_run=done, epoch_s=epoch
        )
    # lazy, as above: kept off the `driftlab --help` path
    from driftlab.compensator.cutting_test import offline_interval

    test.offline_predicted = offline_interval(document, test.runs["offline"], epoch_s=epoch)
    info["loads_per_source"] = [src.reloads for src in sources]  # 1 each: every later poll was a 304
    return test, info
