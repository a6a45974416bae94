"""`driftlab iso230`: ISO 230-2 positioning figures of an axis, ISO 230-3 thermal tests of a campaign's stages."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from driftlab.errors import ValidationError


def register(sub: argparse._SubParsersAction) -> None:
    """Register `iso230 (BUNDLE | --campaign ID) --part 2|3 [--axis X] [--json OUT] [--html OUT]`."""
    p = sub.add_parser(
        "iso230",
        help="ISO 230-2 positioning figures of an axis, or ISO 230-3 thermal tests",
        description="ISO 230-2 (--part 2 --axis X): A, B, E, M, R per direction from bidirectional "
        "runs. ISO 230-3 (--part 3): ETVE, spindle-rotation and linear-motion thermal distortion "
        "from the campaign's stages.",
    )
    p.add_argument("bundle", type=Path, nargs="?", default=None, metavar="BUNDLE_DIR", help="campaign bundle directory")
    p.add_argument("--campaign", type=int, default=None, metavar="ID", help="a stored campaign instead of a bundle")
    p.add_argument(
        "--db", default=None, metavar="URL", help="store URL (default: DRIFTLAB_DB_URL or the SQLite default)"
    )
    p.add_argument("--part", type=int, choices=(2, 3), required=True, help="2: positioning accuracy; 3: thermal tests")
    p.add_argument("--axis", default=None, help="axis for part 2 (X Y Z A B)")
    p.add_argument("--term", default=None, help="part 2: term to evaluate (default the axis' positioning term)")
    p.add_argument("--stage", default=None, help="part 2: only the runs measured during this stage of the campaign")
    p.add_argument("--json", type=Path, default=None, metavar="OUT.json", help="write the figures here")
    p.add_argument("--html", type=Path, default=None, metavar="OUT.html", help="write the report page with its plots")
    p.set_defaults(func=_run)


def _load(args: argparse.Namespace) -> Any:
    if (args.bundle is None) == (args.campaign is None):
        raise ValidationError("give either a BUNDLE_DIR or --campaign ID, not both or neither")
    if args.campaign is not None:
        from driftlab.campaigns.store import connect

        return connect(args.db).load_campaign(args.campaign)
    from driftlab.campaigns.bundle import load_bundle

    return load_bundle(args.bundle)


def _write(path: Path | None, text: str) -> None:
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


def _run(args: argparse.Namespace) -> int:
    """Evaluate, print a summary, write the JSON and HTML reports (nothing written on an error)."""
    from driftlab.metrology import iso230_2, iso230_3, report

    if args.part == 2 and not args.axis:
        raise ValidationError("--part 2 needs --axis (X Y Z A B)")
    bundle = _load(args)
    lines: list[str] = []
    if args.part == 2:
        errors = bundle.errors
        if args.stage is not None:
            stage = next((s for s in bundle.meta.stages if s.name == args.stage), None)
            if stage is None:
                raise ValidationError(f"{bundle.name}: no stage {args.stage!r} in campaign.json")
            t = errors["time_s"]
            errors = errors[(t >= stage.start_s) & (t <= stage.end_s)]
        res = iso230_2.from_bundle_errors(errors, args.axis, args.term)
        doc: dict[str, Any] = res.to_json_dict()
        page = report.iso230_2_html(res, f"ISO 230-2: {bundle.name}, axis {res.axis}") if args.html else ""
        lines.append(
            f"ISO 230-2 {bundle.name} axis {res.axis} ({res.unit}, {res.runs} runs, {res.targets.size} "
            "targets): " + " ".join(f"{k} {res.figures[k]:.6g}" for k in iso230_2.FIGURES)
        )
    else:
        if args.stage is not None:
            raise ValidationError("--stage is for --part 2 (part 3 evaluates every stage)")
        res3 = iso230_3.evaluate_bundle(bundle)
        doc = res3.to_json_dict()
        page = report.iso230_3_html(res3, f"ISO 230-3: {bundle.name}") if args.html else ""
        for kind in ("etve", "spindle", "linear"):
            for t in getattr(res3, kind):
                top = max(t.figures, key=lambda k: t.figures[k] if t.units[k] == "mm" else 0.0)
                lines.append(f"ISO 230-3 {kind} {t.stage}: largest {top} {t.figures[top]:.6g} {t.units[top]}")
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    _write(args.json, text)  # the reports first: a closed stdout loses only the summary
    _write(args.html, page)
    print("\n".join(lines))
    return 0
