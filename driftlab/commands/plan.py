"""`driftlab plan check PLAN [--json]`: what a campaign plan measures, and what the model will lack."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any

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


def plan_report(plan: Plan) -> dict[str, Any]:
    """Return the check report of a valid plan: setups, coverage per term, missing terms, duration."""
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


def format_report(report: dict[str, Any]) -> str:
    """Return the report as a coverage table (axis x term: the first stage measuring it) and a summary."""
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
    from driftlab.campaigns.plan import load_plan

    report = plan_report(load_plan(args.plan))
    print(json.dumps(report) if args.json else format_report(report))
    return 0
