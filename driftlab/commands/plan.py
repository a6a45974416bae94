"""`driftlab plan check PLAN` and `driftlab plan advise --campaign ID`: what a plan measures, what to measure next.

`driftlab plan advise --campaign ID [--hours H] -o PLAN.yaml`: the next stages that most reduce the
predicted variance of the correction over the work space (``driftlab.models.advisor``), written as
a plan the daemon runs.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from driftlab.errors import NotFoundError, ValidationError

if TYPE_CHECKING:  # the plan machinery (pydantic, the physics) loads only when a plan is checked
    from driftlab.campaigns.plan import Plan


def register(sub: argparse._SubParsersAction) -> None:
    """Register `plan check`."""
    plan = sub.add_parser("plan", help="campaign plans")
    plansub = plan.add_subparsers(dest="plan_command", metavar="PLANCOMMAND", required=True)
    chk = plansub.add_parser(
        "check",
        help="validate a plan (setups deliver their terms, moves within travel and optics range) "
        "and print its coverage of the thirty motion-error terms",
    )
    chk.add_argument("plan", help="plan YAML file")
    chk.add_argument("--json", action="store_true", help="the report as one JSON object")
    chk.set_defaults(func=_check)

    adv = plansub.add_parser(
        "advise",
        help="propose the next stages (setup, heat source, duration) that most reduce the predicted "
        "variance of the correction over the work space, within --hours of machine time",
    )
    adv.add_argument(
        "--campaign",
        type=int,
        action="append",
        default=[],
        metavar="ID",
        required=True,
        help="stored campaign id (repeat for several campaigns of one machine)",
    )
    adv.add_argument(
        "--hours", type=float, default=8.0, help="machine time for the advised stages, cool-downs included (default 8)"
    )
    adv.add_argument(
        "-o", "--output", type=Path, required=True, metavar="PLAN.yaml", help="write the advised plan here"
    )
    adv.add_argument(
        "--model",
        default="current",
        metavar="VERSION",
        help="model version whose terms to pin (default: the machine's current; 'none': structure terms only)",
    )
    adv.add_argument("--json", action="store_true", help="print the advice as one JSON object")
    adv.add_argument(
        "--db", metavar="URL", default=None, help="database URL (default: DRIFTLAB_DB_URL or the embedded SQLite file)"
    )
    adv.set_defaults(func=_advise)


class PlanReport(TypedDict):
    """The check report of a valid plan (``driftlab plan check --json``)."""

    plan: str
    stages: int
    duration_s: float
    sweep_points: int
    setups: dict[str, dict[str, object]]  # campaign.json's ``setups`` entries (bundle v2)
    coverage: dict[str, list[str]]  # per motion-error term, the stages that measure it
    measured: list[str]
    missing: list[str]


def plan_report(plan: Plan) -> PlanReport:
    """Return the check report of a valid plan: setups, coverage per term, missing terms, duration."""
    # lazy: this function's imports would add 87 ms to `driftlab --help` (measured)
    from driftlab.campaigns.setups import all_cells

    cov = plan.coverage()
    return {
        "plan": plan.name,
        "stages": len(plan.stages),
        "duration_s": plan.total_s,
        "sweep_points": len(plan.sweep_points()),
        "setups": {k: s.bundle_entry() for k, s in plan.used_setups().items()},
        "coverage": cov,
        "measured": [c for c in all_cells() if cov[c]],
        "missing": [c for c in all_cells() if not cov[c]],
    }


def format_report(report: PlanReport) -> str:
    """Return the report as a coverage table (axis x term: the first stage measuring it) and a summary."""
    # lazy: this function's imports would add 0.2 s to `driftlab --help` (measured)
    from driftlab.campaigns.setups import TERMS, coverage_table

    table = coverage_table(report["coverage"])
    widths = [max(len(row[i]) for row in table) for i in range(len(TERMS) + 1)]
    lines = [
        f"plan {report['plan']}: {report['stages']} stages, {report['duration_s'] / 3600:.1f} h, "
        f"{report['sweep_points']} sweep points, {len(report['setups'])} setups"
    ]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in table]
    n = len(report["measured"])
    lines.append(
        f"{n}/30 motion-error terms measured"
        + (f"; the model will lack {', '.join(report['missing'])}" if report["missing"] else "")
    )
    return "\n".join(lines)


def _check(args: argparse.Namespace) -> int:
    """Validate the plan and print its coverage; a plan error is one line naming the stage (exit 2)."""
    # lazy: this function's imports would add 0.8 s to `driftlab --help` (measured)
    from driftlab.campaigns.plan import load_plan

    report = plan_report(load_plan(args.plan))
    print(json.dumps(report) if args.json else format_report(report))
    return 0


def _advise(args: argparse.Namespace) -> int:
    """Load the campaigns and their model, advise, check the plan and write it; print the table."""
    # lazy: this function's imports would add 4.3 s to `driftlab --help` (measured)
    import yaml

    from driftlab.campaigns.plan import parse_plan
    from driftlab.campaigns.store import connect
    from driftlab.jobs.registry import get_model
    from driftlab.models.advisor import advise

    if not (math.isfinite(args.hours) and args.hours > 0):
        raise ValidationError(f"--hours must be a positive number of hours, got {args.hours:g}")
    with connect(args.db) as store:
        bundles = [store.campaigns.load(c) for c in args.campaign]
        machines = {b.meta.machine.id for b in bundles}
        if len(machines) != 1:
            raise ValidationError(f"campaigns of different machines: {', '.join(sorted(machines))}")
        machine = machines.pop()
        document = None
        if args.model != "none":
            try:
                document = get_model(store, machine, args.model)
            except NotFoundError:
                if args.model != "current":
                    raise
    name = "c" + "-".join(str(c) for c in args.campaign)
    advice = advise(bundles, document, hours=args.hours, campaign=name)
    doc = advice.plan(name=f"advice-{name}")
    if not doc["stages"]:
        raise ValidationError(
            f"no stage within {args.hours:g} h cuts the predicted variance of the correction by 1 % or more; "
            "nothing to write"
        )
    parse_plan(doc, str(args.output))  # the plan validator the daemon runs
    text = yaml.safe_dump(doc, sort_keys=False, width=120)
    head = f"# {doc['description']}\n# model: {'version ' + str(document.version) if document else 'none'}\n"
    args.output.write_text(head + text, encoding="utf-8")
    if args.json:
        print(json.dumps({**advice.to_dict(), "plan": str(args.output)}))
    else:
        if document is None:
            print("no registered model: advising on the links' recast structure terms alone")
        print(advice.summary())
        print(f"plan: {args.output} (driftlab daemon --plan {args.output})")
    return 0
