"""`driftlab diagnose`: what the simulation gets wrong, which effect causes it, and the held-out gain."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from driftlab.commands.tables import add_csv_option
from driftlab.errors import ValidationError
from driftlab.labels import display_unit, effect_label

if TYPE_CHECKING:
    from rich.table import Table

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Register `diagnose (BUNDLE_DIR | --campaign ID [--db URL]) --json REPORT.json [--html REPORT.html]`."""
    p = sub.add_parser("diagnose", help="diagnose a campaign bundle: simulation vs data, effects, held-out gain")
    p.add_argument(
        "bundle",
        type=Path,
        nargs="?",
        default=None,
        metavar="BUNDLE_DIR",
        help="campaign bundle v1 directory (or --campaign for a stored campaign)",
    )
    p.add_argument("--campaign", type=int, default=None, metavar="ID", help="diagnose a campaign in the store")
    p.add_argument(
        "--db", default=None, metavar="URL", help="store URL (default: DRIFTLAB_DB_URL or the SQLite default)"
    )
    p.add_argument("--json", type=Path, required=True, metavar="REPORT.json", help="write the report v1 here")
    add_csv_option(p)
    p.add_argument("--html", type=Path, default=None, metavar="REPORT.html", help="also write an HTML page")
    p.add_argument(
        "--holdout-fraction",
        type=float,
        default=0.25,
        help="fraction of each (axis, term)'s rows, last in time, held out (default 0.25)",
    )
    p.set_defaults(func=_diagnose)


def _diagnose(args: argparse.Namespace) -> int:
    """Load and validate the bundle, diagnose it, write the report(s); 0 whatever was found."""
    # lazy: this function's imports would add 2.3 s to `driftlab --help` (measured)
    from driftlab.campaigns.bundle import load_bundle
    from driftlab.models.diagnosis import diagnose_bundle
    from driftlab.models.diagnosis_report import to_json_dict as diagnosis_json

    # the API's bounds (api.schemas.HOLDOUT_FRACTION): below 1 % a campaign's last rows round to none held out
    if not 0.01 <= args.holdout_fraction < 0.9:
        raise ValidationError(f"--holdout-fraction must be in [0.01, 0.9), got {args.holdout_fraction}")
    if (args.bundle is None) == (args.campaign is None):
        raise ValidationError("give either a BUNDLE_DIR or --campaign ID, not both or neither")
    if args.campaign is not None:
        # lazy, as above: kept off the `driftlab --help` path
        from driftlab.campaigns.store import connect

        bundle = connect(args.db).campaigns.load(args.campaign)  # NotFoundError for an unknown id
    else:
        bundle = load_bundle(args.bundle)  # BundleError: one line FILE:ROW: problem
    # lazy, as above: kept off the `driftlab --help` path
    from driftlab.progress import progress

    with progress(f"diagnosing {bundle.name}") as _bar:  # a spinner: the search has no known length
        result = diagnose_bundle(bundle, holdout_fraction=args.holdout_fraction)
    doc = diagnosis_json(result)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    if args.html is not None:
        args.html.parent.mkdir(parents=True, exist_ok=True)
        # lazy, as above: kept off the `driftlab --help` path
        from driftlab.models.diagnosis_report import to_html

        args.html.write_text(to_html(result, bundle), encoding="utf-8")  # with the campaign overview
    print_findings(doc, as_csv=args.csv)
    n = len(result.effects)
    print(
        f"diagnosed {bundle.name}: {n} effect{'s' if n != 1 else ''} accepted; report {args.json}"
        + (f", page {args.html}" if args.html is not None else "")
    )
    return 0


def print_findings(doc: dict, as_csv: bool = False) -> None:
    """Print a diagnosis report's findings (effect, cause, held-out gain in µm/µrad) and the baseline per term."""
    # lazy: rich adds to `driftlab --help` (the tables module imports it where it prints)
    from driftlab.commands.tables import Output

    con = Output()
    effects = doc.get("effects", [])
    if effects:
        t, causes = _findings_table(doc, effects)
        con.print(t)
        for line in causes:
            con.print(line, markup=False)
    else:
        con.print("No effect of the catalogue is supported by the data: the baseline model stands.")
    base = doc.get("baseline", [])
    if base:
        con.print(_baseline_table(doc, base))
    left = doc.get("unexplained", [])
    if left:
        con.print(_unexplained_table(left))
    elif base:
        con.print(explained_text(doc))
    con.emit(as_csv)


def explained_text(doc: dict) -> str:
    """Return whether every term is explained, as the figures say: to the noise in training, and held out too.

    "Explained" only when no term's training residual is above 1.5 x its noise (``unexplained`` empty)
    and no term's held-out RMSE (with the findings where they were folded in) is above 1.5 x its
    training RMSE; otherwise the worst held-out term is named, in red.
    """
    ext = {(x.get("axis"), x.get("term")): x for x in doc.get("extended", [])}
    worse = []
    for r in doc.get("baseline", []):
        train = r.get("rmse_train")
        held = ext.get((r.get("axis"), r.get("term")), {}).get("rmse_holdout", r.get("rmse_holdout"))
        if isinstance(train, (int, float)) and isinstance(held, (int, float)) and train > 0 and held > 1.5 * train:
            worse.append((held / train, r, held))
    if not worse:
        return "Every term is explained to its measurement noise, in training and held out (no unexplained residual)."
    ratio, r, held = max(worse, key=lambda w: w[0])
    k, unit = display_unit(str(r.get("term")))
    return (
        f"[red]Not explained held out[/]: no training residual is above 1.5 x the noise, but {len(worse)} "
        f"term(s) are worse held out than in training by more than 1.5 x; the worst, {r.get('axis')}/{r.get('term')}, "
        f"{held * k:.2f} {unit} held out against {r['rmse_train'] * k:.2f} {unit} in training ({ratio:.1f} x)."
    )


def _gain_text(b: float | None, a: float | None) -> str:
    """Return the held-out gain of a finding: "12 % better" (green), "3 % worse" (red), or "-"."""
    if not (b and a is not None):
        return "-"
    return f"[green]{100 * (1 - a / b):.0f} % better[/]" if a <= b else f"[red]{100 * (a / b - 1):.0f} % worse[/]"


def _findings_table(doc: dict, effects: list[dict]) -> tuple[Table, list[str]]:
    """Return the findings' table and each finding's numbered cause."""
    # lazy: this function's imports would add 63 ms to `driftlab --help` (measured)
    from rich.table import Table

    t = Table(
        title=f"Findings: what the standard model misses ({doc.get('holdout', {}).get('method', 'held out')} held out)",
        title_justify="left",
    )
    # the figures and the verdict ("12 % worse") never wrap; the effect wraps between words on a
    # narrow terminal (commands.tables); each finding's cause follows the table as a numbered line
    for col, just in (
        ("#", "right"),
        ("effect", "left"),
        ("on", "left"),
        ("held out before", "right"),
        ("after", "right"),
        ("gain", "right"),
    ):
        t.add_column(
            col,
            justify=just,  # type: ignore[arg-type]  # rich types it as a Literal; ours are its values
            no_wrap=col in ("gain", "held out before", "after"),
        )
    causes = []
    for i, e in enumerate(effects, 1):
        k, unit = display_unit(str(e.get("term")))
        b, a = e.get("rmse_holdout_before"), e.get("rmse_holdout_after")
        where = f"{e.get('axis')}/{e.get('term')}" if e.get("axis") else "temperatures"
        t.add_row(
            str(i),
            effect_label(e),
            where,
            f"{b * k:.2f} {unit}" if b is not None else "-",
            f"{a * k:.2f} {unit}" if a is not None else "-",
            _gain_text(b, a),
        )
        p = f" (p = {e['p_value']:.2g})" if e.get("p_value") is not None else ""
        causes.append(f"{i}. {e.get('cause') or '-'}{p}")
    return t, causes


def _baseline_table(doc: dict, base: list[dict]) -> Table:
    """Return the baseline's held-out RMSE per term (fitted or per-term model), before and after the findings."""
    # lazy: this function's imports would add 63 ms to `driftlab --help` (measured)
    from rich.table import Table

    t = Table(title="Baseline per term: held-out RMSE before and after the findings", title_justify="left")
    for col, just in (
        ("axis/term", "left"),
        ("baseline", "left"),
        ("model thermocouples", "left"),
        ("train", "right"),
        ("held out", "right"),
        ("with findings", "right"),
    ):
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    ext = {(x.get("axis"), x.get("term")): x for x in doc.get("extended", [])}
    for r in base:
        k, unit = display_unit(str(r.get("term")))
        x = ext.get((r.get("axis"), r.get("term")), {})
        fmt = lambda v, k=k, unit=unit: f"{v * k:.2f} {unit}" if isinstance(v, (int, float)) else "-"  # noqa: E731
        ext_txt = fmt(x.get("rmse_holdout"))
        if x.get("holdout_verdict") == "worse":
            ext_txt = f"[red]{ext_txt} worse[/]"
        t.add_row(
            f"{r.get('axis')}/{r.get('term')}",
            "fitted model" if r.get("model") == "fitted" else "per-term model",
            " ".join(r.get("channels") or []),
            fmt(r.get("rmse_train")),
            fmt(r.get("rmse_holdout")),
            ext_txt,
        )
    return t


def _unexplained_table(left: list[dict]) -> Table:
    """Return the terms whose training residual stays above 1.5 x the noise after the findings."""
    # lazy: this function's imports would add 63 ms to `driftlab --help` (measured)
    from rich.table import Table

    t = Table(
        title="Unexplained: residual above the noise after the findings (1.5 x in training, 2 x held out)",
        title_justify="left",
    )
    cols = (("axis/term", "left"), ("shown by", "left"), ("train / noise", "right"), ("held out / noise", "right"))
    for col, just in (*cols, ("hints", "left")):
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    for u in left:
        ho = u.get("holdout_over_noise")
        t.add_row(
            f"{u.get('axis')}/{u.get('term')}",
            str(u.get("part", "training")),
            f"{float(u.get('residual_over_noise', float('nan'))):.1f} x",
            f"[red]{float(ho):.1f} x[/]" if isinstance(ho, (int, float)) else "-",
            "; ".join(u.get("hints") or []),
        )
    return t
