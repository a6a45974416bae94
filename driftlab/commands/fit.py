"""`driftlab fit`, `driftlab models list|show`, `driftlab online`: the model registry from the command line."""

from __future__ import annotations

import argparse
import json
import math
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from driftlab.commands.compensate import machine_file_envelope
from driftlab.commands.tables import add_csv_option
from driftlab.errors import ValidationError
from driftlab.labels import ANGLES, coefficient_text, display_unit, effect_label, feature_label

if TYPE_CHECKING:
    from rich.table import Table

    from driftlab.commands.tables import Output

STAGES = (
    "screening",
    "samples",
    "allocation_and_regression",
    "joint_adjustment",
    "validation",
    "network",
    "virtual_sensors",
    "document",
)


def fit_steps(network: bool = True) -> list[str]:
    """Return the steps a fit reports, in order (the neural comparison only with ``network``)."""
    return [s for s in STAGES if network or s != "network"]


def _db(parser: argparse.ArgumentParser) -> None:
    """Add the common ``--db URL`` option."""
    parser.add_argument(
        "--db", metavar="URL", default=None, help="database URL (default: DRIFTLAB_DB_URL or the embedded SQLite file)"
    )


def register(sub: argparse._SubParsersAction) -> None:
    """Register `fit`, `models` and `online`."""
    _register_fit(sub)
    _register_models(sub)
    _register_online(sub)


def _register_fit(sub: argparse._SubParsersAction) -> None:
    """Register `fit --campaign ID ... [--json REPORT] [--findings REPORT] [--enqueue]`."""
    fit = sub.add_parser("fit", help="fit a model from stored campaigns and register it as a new version")
    fit.add_argument(
        "--campaign",
        type=int,
        action="append",
        default=[],
        metavar="ID",
        help="campaign id (repeat for several campaigns of one machine)",
    )
    _db(fit)
    fit.add_argument("--json", type=Path, default=None, metavar="REPORT.json", help="write the fit report here")
    add_csv_option(fit)
    fit.add_argument("--no-network", action="store_true", help="skip the neural-network comparison (ch. 6.6)")
    fit.add_argument(
        "--machine-file",
        type=Path,
        default=None,
        help="machine envelope (JSON or YAML: travel, max_correction, extrapolation_margin_degC) "
        "written into the model document for the compensator (docs/compensate.md)",
    )
    fit.add_argument(
        "--findings",
        type=Path,
        default=None,
        metavar="REPORT.json",
        help="a diagnosis report (driftlab diagnose --json): fold its effects into this fit",
    )
    fit.add_argument(
        "--force-findings",
        action="store_true",
        help="with --findings: force the findings' terms in (default: offer them as candidates)",
    )
    fit.add_argument(
        "--split",
        choices=("stage", "time"),
        default=None,
        help="which points are held out of the fit and scored: 'stage' (default: the last quarter of every "
        "training stage) or 'time' (the last quarter of every measured line: the split of driftlab diagnose, "
        "whose baseline then states the same held-out figures)",
    )
    fit.add_argument(
        "--enqueue",
        action="store_true",
        help="only queue the fit job and print its id (`driftlab worker` runs it on PostgreSQL, "
        "`driftlab serve` on SQLite)",
    )
    fit.set_defaults(func=_fit)


def _register_models(sub: argparse._SubParsersAction) -> None:
    """Register `models list` and `models show VERSION`."""
    models = sub.add_parser("models", help="list or show registered model versions")
    msub = models.add_subparsers(dest="models_command", metavar="MODELSCOMMAND", required=True)
    ls = msub.add_parser("list", help="list model versions")
    ls.add_argument("--machine", default=None)
    ls.add_argument("--json", action="store_true", help="print JSON")
    _db(ls)
    ls.set_defaults(func=_list)
    show = msub.add_parser("show", help="show one model version (the document the compensator consumes)")
    show.add_argument("version", help="version number or 'current'")
    show.add_argument("--machine", required=True)
    show.add_argument("--json", action="store_true", help="print the model document as JSON")
    _db(show)
    show.set_defaults(func=_show)


def _register_online(sub: argparse._SubParsersAction) -> None:
    """Register `online --machine ID --probe FILE.csv`."""
    online = sub.add_parser("online", help="update the on-line model (RLS, eqs. 6.10-6.13) with probe measurements")
    online.add_argument("--machine", required=True)
    online.add_argument(
        "--probe",
        type=Path,
        required=True,
        metavar="FILE.csv",
        help="time_s,x,y,z,a,b,dx,dy,dz plus one column per model channel "
        "(optional measured_at: ISO times of the probings)",
    )
    online.add_argument(
        "--lambda",
        dest="lam",
        type=float,
        default=None,
        help="forgetting factor of a new on-line state (default 0.98; fixed once the state starts)",
    )
    online.add_argument(
        "--start",
        default=None,
        metavar="ISO",
        help="wall-clock time of time_s = 0 (default: the last row was measured now)",
    )
    online.add_argument("--json", action="store_true", help="print the report as JSON")
    _db(online)
    online.set_defaults(func=_online)


def _fit(args: argparse.Namespace) -> int:
    """Queue a fit job and run it here (or only queue it with --enqueue); print the report."""
    # lazy: this function's imports would add 1.2 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect
    from driftlab.jobs import run_until_ended, submit_fit
    from driftlab.progress import stages

    with connect(args.db) as store:
        if not args.campaign:
            raise ValidationError("give --campaign ID")
        findings = None
        if args.findings is not None:
            # lazy, as above: kept off the `driftlab --help` path
            from driftlab.models.findings import load_findings

            findings = load_findings(args.findings)
        elif args.force_findings:
            raise ValidationError("--force-findings needs --findings REPORT.json")

        job_id = submit_fit(
            store,
            args.campaign,
            network=not args.no_network,
            findings=findings,
            force_findings=args.force_findings,
            envelope=machine_file_envelope(args.machine_file),
            split=args.split,
        )
        if args.enqueue:
            print(json.dumps({"job": job_id, "state": "queued"}))
            return 0
        with stages("fitting", fit_steps(network=not args.no_network)) as bar:
            job = run_until_ended(store, job_id, on_stage=bar.done)
        if job.state != "done":
            raise ValidationError(f"fit job {job_id} {job.state}: {job.error or 'no result'}")
        report: dict[str, Any] = dict(job.result or {})
    ref = _reference(store, args.campaign)
    text = json.dumps(report, indent=2)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    _print_summary(report, ref, as_csv=args.csv)
    return 0


def _reference(store: Any, campaign_ids: list[int]) -> dict[str, Any]:
    """Return what the held-out errors are judged against: the campaign's stated noise, else the machine's
    resolution."""
    # lazy: this function's imports would add 0.3 s to `driftlab --help` (measured)
    from driftlab.campaigns.live import campaign_meta

    meta = campaign_meta(store.engine, campaign_ids[0]) if campaign_ids else None
    noise = (meta or {}).get("noise") or {}
    machine = (meta or {}).get("machine") or {}

    res_deg = machine.get("resolution_deg") or 0.001
    return {
        "noise_mm": noise.get("length_mm"),
        "noise_rad": noise.get("angle_rad"),
        "resolution_mm": machine.get("resolution_mm") or 0.0025,
        "resolution_rad": math.radians(res_deg),
    }


def verdict(rmse: float | None, term: str, ref: dict[str, Any]) -> tuple[str, str, str]:
    """Return (ratio text, verdict, style) of a held-out RMSE against the stated noise (or the resolution)."""
    angle = term in ANGLES
    noise = ref["noise_rad"] if angle else ref["noise_mm"]
    basis = "noise"
    if not noise:
        noise, basis = (ref["resolution_rad"] if angle else ref["resolution_mm"]), "resolution"
    if rmse is None or not noise:
        return "-", "no held-out rows", "dim"
    ratio = rmse / noise
    text = f"{ratio:.1f}x {basis}"
    if ratio <= 1.5:
        return text, f"at the {basis}", "green"
    if ratio <= 3.0:
        return text, f"near the {basis}", "yellow"
    return text, "above the noise: run driftlab diagnose" if basis == "noise" else "above the resolution", "red"


_TERM_COLUMNS = (
    ("axis", "left"),
    ("term", "left"),
    ("measurement", "left"),
    ("link", "left"),
    ("form", "left"),
    ("unit", "left"),
    ("RMSE train", "right"),
    ("RMSE held out", "right"),
    ("R2", "right"),
    ("F", "right"),
    ("held out vs", "right"),
    ("verdict", "left"),
)


def _num(v: Any, fmt: str, scale: float = 1.0) -> str:
    """Return a number scaled and formatted, or "-" when there is none."""
    return format(v * scale, fmt) if isinstance(v, (int, float)) else "-"


def _finite_num(v: Any, fmt: str) -> str:
    """Return a finite number formatted, or "-" when there is none (or it is not finite)."""
    return format(v, fmt) if isinstance(v, (int, float)) and math.isfinite(v) else "-"


def _scaled(v: Any, k: float) -> str:
    """Return a finite number times ``k`` with two decimals, or "-"."""
    return f"{v * k:.2f}" if isinstance(v, (int, float)) and math.isfinite(v) else "-"


def _print_summary(report: dict[str, Any], ref: dict[str, Any] | None = None, as_csv: bool = False) -> None:
    """Print the fit as tables 6.1-6.3 do, with units (µm, µrad) and a verdict per row (or its tables as CSV)."""
    # lazy: rich adds to `driftlab --help` (the tables module imports it where it prints)
    from driftlab.commands.tables import Output

    ref = ref or {"noise_mm": None, "noise_rad": None, "resolution_mm": 0.0025, "resolution_rad": 1.7453e-05}
    con = Output()
    kept = report.get("kept_channels", [])
    con.print(
        f"machine {report.get('machine')}: model version {report.get('model_version')} registered; "
        f"{len(kept)} thermocouples kept: {' '.join(kept)}"
    )
    con.print(_terms_table(report, ref))
    _print_physical(con, report)
    _print_findings(con, report)
    for c in report.get("neural_comparison") or []:
        _print_neural(con, c)
    con.emit(as_csv)


def _terms_table(report: dict[str, Any], ref: dict[str, Any]) -> Table:
    """Return the per-link models' table (thesis tables 6.1-6.2), each held-out RMSE judged against ``ref``."""
    # lazy: this function's imports would add 27 ms to `driftlab --help` (measured)
    from rich.table import Table

    stated = []
    if ref.get("noise_mm"):
        stated.append(f"{ref['noise_mm'] * 1e3:.2g} µm")
    if ref.get("noise_rad"):
        stated.append(f"{ref['noise_rad'] * 1e6:.2g} µrad")
    t = Table(
        title="Per-link models (thesis tables 6.1-6.2): RMSE of the work-space error"
        + (
            f"; stated noise {', '.join(stated)}"
            if stated
            else "; no noise stated: judged against the machine's resolution"
        ),
        title_justify="left",
    )
    for col, just in _TERM_COLUMNS:
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    for r in report.get("terms", []):
        k, unit = display_unit(r["term"])
        ratio, word, style = verdict(r.get("rmse_holdout"), r["term"], ref)
        t.add_row(
            r["axis"],
            r["term"],
            str(r.get("measurement", "")),
            " + ".join(str(r["link"]).split("+")),  # spaced: the cell wraps between links, never inside one
            " + ".join(str(r.get("form", "link")).split("+")),
            unit,
            _num(r.get("rmse_train"), ".2f", k),
            _num(r.get("rmse_holdout"), ".2f", k),
            _num(r.get("r2"), ".3f"),
            _num(r.get("f"), ".4g"),
            ratio,
            f"[{style}]{word}[/]",
        )
    return t


def _print_physical(con: Output, report: dict[str, Any]) -> None:
    """Print the regression against physical coefficients (thesis table 6.3), or why there is none."""
    # lazy: this function's imports would add 31 ms to `driftlab --help` (measured)
    from rich.table import Table

    phys = report.get("physical", [])
    check = report.get("physical_check") or {}
    if check and check.get("status") != "compared":
        # no stated geometry: say so instead of comparing with lengths that are not this machine's
        con.print(
            f"Regression against physical coefficients (thesis table 6.3): {check.get('status')}: "
            f"{check.get('note', '')}"
        )
        return
    if not phys:
        return
    pt = Table(
        title="Regression against physical coefficients (thesis table 6.3)"
        + (f"; {check['note']}" if check.get("note") else ""),
        title_justify="left",
    )
    for col in ("coefficient", "regression", "physical", "ratio", "unit", "relationship"):
        pt.add_column(col, justify="right" if col in ("regression", "physical", "ratio") else "left")
    for p in phys:
        elem, _, feat = str(p["term"]).partition(" ")
        status = str(p.get("status", "compared"))
        pt.add_row(
            f"{elem}: {feature_label(feat)}" if feat else feature_label(elem),
            _finite_num(p.get("regression"), ".4g"),
            _finite_num(p.get("physical"), ".4g"),
            _finite_num(p.get("ratio"), ".2f"),
            str(p.get("unit", "")),
            str(p.get("relationship", "")) + ("" if status == "compared" else f" ({status})"),
        )
    con.print(pt)


def _print_findings(con: Output, report: dict[str, Any]) -> None:
    """Print one line per diagnosis finding: folded in (with the terms it entered), substituted, or not."""
    for f in report.get("findings", []):
        what = f"{effect_label(f)} on {f.get('axis')}/{f.get('term')}"
        if not f.get("folded"):
            con.print(f"finding {what}: not folded in ({f.get('note', '')})")
        elif f["kind"] == "sensor_fault":
            con.print(f"finding {what}: {', '.join(f.get('substituted', []))} replaced by its virtual sensor")
        else:
            kept_terms = [f"{feature_label(n)} in {'+'.join(m)}" for n, m in f.get("entered", {}).items() if m]
            con.print(
                f"finding {what}: {'; '.join(kept_terms) or 'no term entered'}{' (forced)' if f.get('forced') else ''}"
            )


def _print_neural(con: Output, c: dict[str, Any]) -> None:
    """Print one target's comparison of least squares and the network on the same inputs (ch. 6.6)."""
    # lazy: this function's imports would add 31 ms to `driftlab --help` (measured)
    from rich.table import Table

    # ch. 6.6: least squares and the network on the same inputs, each extrapolation direction
    if c.get("status") != "compared":
        con.print(f"neural comparison on {c['target']} (ch. 6.6): {c.get('status')}: {c.get('note', '')}")
        return
    k, unit = display_unit(c["target"].partition("/")[2])
    nt = Table(
        title=f"Neural network against least squares on the same inputs, {c['target']} (ch. 6.6; split by "
        f"{c['split']}; {len(c.get('channels', []))} channels)",
        title_justify="left",
    )
    for col in (
        "direction",
        "train",
        "test",
        f"regression test ({unit})",
        f"network test ({unit})",
        f"regression train ({unit})",
        f"network train ({unit})",
        "test beyond range",
    ):
        nt.add_column(col, justify="left" if col in ("direction", "train", "test") else "right")
    for d in c.get("directions", []):
        nt.add_row(
            d["direction"],
            d["train"],
            d["test"],
            _scaled(d["regression_test"], k),
            _scaled(d["network_test"], k),
            _scaled(d["regression_train"], k),
            _scaled(d["network_train"], k),
            f"{d['beyond_range']:.0%}, up to {d['max_excess_degC']:.1f} °C",
        )
    con.print(nt)
    for what, why in (c.get("excluded") or {}).items():
        con.print(f"  not a target: {what}: {why}")


def _list(args: argparse.Namespace) -> int:
    """Print the registry's versions."""
    # lazy: this function's imports would add 1.7 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect
    from driftlab.jobs.registry import list_models

    with connect(args.db) as store:
        rows = list_models(store, args.machine)
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'machine':16} {'version':>7} {'status':8} {'created':26} {'terms':>5} campaigns")
    for r in rows:
        print(
            f"{r['machine']:16} {r['version']:>7} {r['status']:8} {r['created_at'] or '':26} {r['terms']:>5} "
            f"{','.join(str(c) for c in r['source_campaigns'])}"
        )
    return 0


def _show(args: argparse.Namespace) -> int:
    """Print one model document."""
    # lazy: this function's imports would add 1.8 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect
    from driftlab.jobs.registry import get_model
    from driftlab.models.document import document_json

    with connect(args.db) as store:
        doc = get_model(store, args.machine, args.version)
    data = document_json(doc)
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    print(f"machine {doc.machine} version {doc.version} created {doc.created_at} from campaigns {doc.source_campaigns}")
    print(f"inputs: {' '.join(doc.inputs)}")

    for t in doc.terms:  # each coefficient with its unit: µm (µrad) per unit of its feature
        terms = " + ".join(
            f"{coefficient_text(c, t.param, f.kind, f.power, f.label)} × {f.name}"
            for f, c in zip(t.features, t.coefficients)
        )
        print(f"  {t.element}.{t.param} = {terms}")
    return 0


def _online(args: argparse.Namespace) -> int:
    """Run the on-line update and print what it changed."""
    # lazy: this function's imports would add 2.2 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect
    from driftlab.jobs.online import online_update
    from driftlab.models.online import read_probe_csv

    start = None
    if args.start is not None:
        try:
            start = datetime.fromisoformat(args.start.replace("Z", "+00:00"))
        except ValueError:
            raise ValidationError(f"--start: not an ISO 8601 time: {args.start!r}") from None
    probe = read_probe_csv(args.probe)
    with connect(args.db) as store:
        report = online_update(store, args.machine, probe, lam=args.lam, start=start)
    data = report.to_dict()
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    print(f"machine {report.machine}, model version {report.model_version}: {report.n} probe measurements")
    for term, t in report.terms.items():
        print(
            f"  {term}: off-line residual {t['offline_rms_mm']:.4f} mm rms, on-line {t['online_rms_mm']:.4f} mm rms, "
            f"correction now {t['correction_mm']:+.4f} mm"
        )
    return 0
