"""`driftlab iso230`: ISO 230-2 positioning figures of an axis, ISO 230-3 thermal tests of a campaign's stages."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from driftlab.errors import ValidationError
from driftlab.labels import UM


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
    p.add_argument(
        "--part",
        type=int,
        choices=(2, 3, 4),
        required=True,
        help="2: positioning accuracy; 3: thermal tests; 4: circular test (BUNDLE_DIR is then a circle CSV)",
    )
    p.add_argument("--radius", type=float, default=None, help="part 4: the circle's nominal radius (mm)")
    p.add_argument("--axis", default=None, help="axis for part 2 (X Y Z A B)")
    p.add_argument("--term", default=None, help="part 2: term to evaluate (default the axis' positioning term)")
    p.add_argument("--stage", default=None, help="part 2: only the runs measured during this stage of the campaign")
    win = p.add_mutually_exclusive_group()
    win.add_argument(
        "--per-stage", action="store_true", help="part 2: one evaluation per stage (runs taken while thermally stable)"
    )
    win.add_argument(
        "--window", type=float, default=None, metavar="HOURS", help="part 2: one evaluation per time window"
    )
    p.add_argument("--json", type=Path, default=None, metavar="OUT.json", help="write the figures here")
    p.add_argument("--html", type=Path, default=None, metavar="OUT.html", help="write the report page with its plots")
    p.set_defaults(func=_run)


def _load(args: argparse.Namespace) -> Any:
    if (args.bundle is None) == (args.campaign is None):
        raise ValidationError("give either a BUNDLE_DIR or --campaign ID, not both or neither")
    if args.campaign is not None:
        # lazy: this function's imports would add 1.9 s to `driftlab --help` (measured)
        from driftlab.campaigns.store import connect

        return connect(args.db).campaigns.load(args.campaign)
    # lazy, as above: kept off the `driftlab --help` path
    from driftlab.campaigns.bundle import load_bundle

    return load_bundle(args.bundle)


def _write(path: Path | None, text: str) -> None:
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


def _circle(args: argparse.Namespace) -> int:
    """ISO 230-4: read a circle CSV, print G, H and the findings, write the JSON."""
    # lazy: this function's imports would add 0.2 s to `driftlab --help` (measured)
    from driftlab.metrology import iso230_4

    if args.bundle is None or args.radius is None:
        raise ValidationError("--part 4 needs a circle CSV (angle_deg, direction, deviation_um) and --radius MM")
    res = iso230_4.evaluate(*iso230_4.read_circle_csv(args.bundle), args.radius)
    _write(args.json, json.dumps(res.to_json_dict(), indent=2, allow_nan=False) + "\n")
    g = ", ".join(f"G({k}) {v * 1e3:.2f} {UM}" for k, v in res.G.items())
    print(f"ISO 230-4 {args.bundle.name}, radius {res.radius_mm:g} mm: {g}, H {res.H * 1e3:.2f} {UM}")
    for f in res.findings:
        print(f"  {f['text']}")
    return 0


def _run(args: argparse.Namespace) -> int:
    """Evaluate, print a summary, write the JSON and HTML reports (nothing written on an error)."""
    if args.part == 2 and not args.axis:
        raise ValidationError("--part 2 needs --axis (X Y Z A B)")
    if args.part == 4:
        return _circle(args)
    bundle = _load(args)
    doc, page, lines = _part2(args, bundle) if args.part == 2 else _part3(args, bundle)
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    _write(args.json, text)  # the reports first: a closed stdout loses only the summary
    _write(args.html, page)
    print("\n".join(lines))
    return 0


def _part2(args: argparse.Namespace, bundle: Any) -> tuple[dict[str, Any], str, list[str]]:
    """Return ISO 230-2 of the axis (whole campaign, per stage or per window): the JSON, the HTML, the summary."""
    # lazy: this function's imports would add 0.7 s to `driftlab --help` (measured)
    from driftlab.metrology import iso230_2, report

    errors = bundle.errors
    if args.stage is not None:
        stage = next((s for s in bundle.meta.stages if s.name == args.stage), None)
        if stage is None:
            raise ValidationError(f"{bundle.name}: no stage {args.stage!r} in campaign.json")
        t = errors["time_s"]
        errors = errors[(t >= stage.start_s) & (t <= stage.end_s)]
    if args.window is not None and not args.window > 0:
        raise ValidationError(f"--window must be a positive number of hours, got {args.window:g}")
    res = iso230_2.from_bundle_errors(errors, args.axis, args.term)
    doc: dict[str, Any] = res.to_json_dict()
    doc["drift_between_runs"] = res.drift
    doc["warning"] = res.drift_warning
    t = errors["time_s"]
    conds = report.conditions(bundle, args.axis, args.term, float(t.min()), float(t.max()))
    doc["conditions"] = dict(conds)
    lines: list[str] = []
    wins = None
    if args.per_stage or args.window is not None:
        found = iso230_2.windows(
            errors,
            args.axis,
            args.term,
            window_s=args.window * 3600.0 if args.window is not None else None,
            stages=list(bundle.meta.stages) if args.per_stage else None,
        )
        wins = [(w, report.conditions(bundle, args.axis, args.term, w.start_s, w.end_s)) for w in found]
        doc["windows"] = [
            {
                "label": w.label,
                "start_s": w.start_s,
                "end_s": w.end_s,
                **w.result.to_json_dict(),
                "drift_between_runs": w.result.drift,
                "warning": w.result.drift_warning,
            }
            for w in found
        ]
        lines += [_summary2(f"{bundle.name} {w.label}", w.result) for w in found]
        lines += [f"  warning ({w.label}): {w.result.drift_warning}" for w in found if w.result.drift_warning]
    else:
        lines.append(_summary2(bundle.name, res))
        if res.drift_warning:
            lines.append(f"  warning: {res.drift_warning}")
    page = report.iso230_2_html(res, f"ISO 230-2: {bundle.name}, axis {res.axis}", conds, wins) if args.html else ""
    return doc, page, lines


def _summary2(label: str, r: Any) -> str:
    """Return the one-line summary of an ISO 230-2 result: its figures in the axis' display unit."""
    # lazy: this function's imports would add 0.7 s to `driftlab --help` (measured)
    from driftlab.metrology.iso230_2 import FIGURES, display

    _, u = display(0.0, r.unit)
    figs = " ".join(f"{k} {display(r.figures[k], r.unit)[0]}" for k in FIGURES)
    return f"ISO 230-2 {label} axis {r.axis} ({r.runs} runs, {r.targets.size} targets, {u}): {figs}"


def _part3(args: argparse.Namespace, bundle: Any) -> tuple[dict[str, Any], str, list[str]]:
    """Return ISO 230-3 of every stage: the JSON, the HTML, and the largest figure of each test."""
    # lazy: this function's imports would add 0.7 s to `driftlab --help` (measured)
    from driftlab.metrology import iso230_2, iso230_3, report

    if args.stage is not None:
        raise ValidationError("--stage is for --part 2 (part 3 evaluates every stage)")
    res3 = iso230_3.evaluate_bundle(bundle)
    doc = res3.to_json_dict()
    page = report.iso230_3_html(res3, f"ISO 230-3: {bundle.name}") if args.html else ""
    lines = []
    for kind in ("etve", "spindle", "linear"):
        for t in getattr(res3, kind):
            top = max(t.figures, key=lambda k: t.figures[k] if t.units[k] == "mm" else 0.0)
            value, unit = iso230_2.display(t.figures[top], t.units[top])
            lines.append(f"ISO 230-3 {kind} {t.stage}: largest {top} {value} {unit}")
    return doc, page, lines
