"""`driftlab fit`, `driftlab models list|show`, `driftlab online`: the model registry from the command line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

STAGES = ("screening", "samples", "allocation_and_regression", "validation", "network", "virtual_sensors", "document")


def _db(parser: argparse.ArgumentParser) -> None:
    """Add the common ``--db URL`` option."""
    parser.add_argument("--db", metavar="URL", default=None,
                        help="database URL (default: DRIFTLAB_DB_URL or the embedded SQLite file)")


def register(sub: argparse._SubParsersAction) -> None:
    """Register `fit`, `models` and `online`."""
    fit = sub.add_parser("fit", help="fit a model from stored campaigns and register it as a new version")
    fit.add_argument("--campaign", type=int, action="append", default=[], metavar="ID",
                     help="campaign id (repeat for several campaigns of one machine)")
    _db(fit)
    fit.add_argument("--json", type=Path, default=None, metavar="REPORT.json", help="write the fit report here")
    fit.add_argument("--no-network", action="store_true", help="skip the neural-network comparison (ch. 6.6)")
    fit.add_argument("--findings", type=Path, default=None, metavar="REPORT.json",
                     help="a diagnosis report (driftlab diagnose --json): fold its effects into this fit")
    fit.add_argument("--force-findings", action="store_true",
                     help="with --findings: force the findings' terms in (default: offer them as candidates)")
    mode = fit.add_mutually_exclusive_group()
    mode.add_argument("--enqueue", action="store_true", help="only queue the fit job and print its id")
    mode.add_argument("--worker", action="store_true", help="run queued fit jobs (a worker process)")
    fit.add_argument("--once", action="store_true", help="with --worker: run at most one job, then exit")
    fit.add_argument("--idle-exit", type=float, default=None, metavar="S",
                     help="with --worker: exit after S seconds without work")
    fit.set_defaults(func=_fit)

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

    online = sub.add_parser("online", help="update the on-line model (RLS, eqs. 6.10-6.13) with probe measurements")
    online.add_argument("--machine", required=True)
    online.add_argument("--probe", type=Path, required=True, metavar="FILE.csv",
                        help="time_s,x,y,z,a,b,dx,dy,dz plus one column per model channel "
                             "(optional measured_at: ISO times of the probings)")
    online.add_argument("--lambda", dest="lam", type=float, default=None,
                        help="forgetting factor of a new on-line state (default 0.98; fixed once the state starts)")
    online.add_argument("--start", default=None, metavar="ISO",
                        help="wall-clock time of time_s = 0 (default: the last row was measured now)")
    online.add_argument("--json", action="store_true", help="print the report as JSON")
    _db(online)
    online.set_defaults(func=_online)


def _fit(args: argparse.Namespace) -> int:
    """Fit (in this process, through the jobs table), queue a fit, or run as a worker."""
    from driftlab.campaigns.store import connect
    from driftlab.errors import ValidationError
    from driftlab.models.fitting import submit_fit, work
    from driftlab.progress import progress

    with connect(args.db) as store:
        if args.worker:
            with progress("fit jobs") as bar:
                done = work(store, once=args.once, idle_exit_s=args.idle_exit, on_stage=lambda _s: bar.advance())
            print(json.dumps({"jobs": done}))
            return 0
        if not args.campaign:
            raise ValidationError("give --campaign ID (or --worker)")
        findings = None
        if args.findings is not None:
            from driftlab.models.findings import load_findings

            findings = load_findings(args.findings)
        elif args.force_findings:
            raise ValidationError("--force-findings needs --findings REPORT.json")
        job_id = submit_fit(store, args.campaign, network=not args.no_network, findings=findings,
                            force_findings=args.force_findings)
        if args.enqueue:
            print(json.dumps({"job": job_id, "state": "queued"}))
            return 0
        with progress("fitting", total=len(STAGES)) as bar:
            work(store, until_job=job_id, on_stage=lambda _s: bar.advance())
        job = store.get_job(job_id)
        if job.state != "done":
            raise ValidationError(f"fit job {job_id} {job.state}: {job.error or 'no result'}")
        report: dict[str, Any] = dict(job.result or {})
    text = json.dumps(report, indent=2)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    _print_summary(report)
    return 0


def _print_summary(report: dict[str, Any]) -> None:
    """Print the fit in the layout of tables 6.1-6.3 (one line each)."""
    out = sys.stdout
    out.write(f"machine {report.get('machine')}: model version {report.get('model_version')}, "
              f"{len(report.get('kept_channels', []))} channels kept: {' '.join(report.get('kept_channels', []))}\n")
    out.write(f"{'axis':4} {'term':6} {'link':28} {'rmse_train':>11} {'rmse_holdout':>12} {'R2':>7} {'F':>10}\n")
    for r in report.get("terms", []):
        def num(v: Any, fmt: str) -> str:
            return format(v, fmt) if isinstance(v, (int, float)) else "-"
        out.write(f"{r['axis']:4} {r['term']:6} {r['link'][:28]:28} {num(r['rmse_train'], '11.3g')} "
                  f"{num(r['rmse_holdout'], '12.3g')} {num(r['r2'], '7.4f')} {num(r['f'], '10.4g')}\n")
    for p in report.get("physical", []):
        out.write(f"  {p['term']}: regression {p['regression']:.4g}, physical {p['physical']:.4g} ({p['relationship']})\n")
    for f in report.get("findings", []):
        where = f"{f['kind']} {f['axis']}/{f['term']} {' '.join(f.get('channels', []))}".rstrip()
        if not f.get("folded"):
            out.write(f"  finding {where}: not folded in ({f.get('note', '')})\n")
        elif f["kind"] == "sensor_fault":
            out.write(f"  finding {where}: {', '.join(f.get('substituted', []))} replaced by its virtual sensor\n")
        else:
            kept = [f"{n} in {'+'.join(m)}" for n, m in f.get("entered", {}).items() if m]
            out.write(f"  finding {where}: {'; '.join(kept) or 'no term entered'}"
                      f"{' (forced)' if f.get('forced') else ''}\n")
    if report.get("extrapolation"):
        e = report["extrapolation"]
        out.write(f"extrapolation: regression {e['regression_mm']:.4f} mm, network {e['network_mm']:.4f} mm\n")


def _list(args: argparse.Namespace) -> int:
    """Print the registry's versions."""
    from driftlab.campaigns.store import connect
    from driftlab.models.registry import list_models

    with connect(args.db) as store:
        rows = list_models(store, args.machine)
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'machine':16} {'version':>7} {'status':8} {'created':26} {'terms':>5} campaigns")
    for r in rows:
        print(f"{r['machine']:16} {r['version']:>7} {r['status']:8} {r['created_at'] or '':26} {r['terms']:>5} "
              f"{','.join(str(c) for c in r['source_campaigns'])}")
    return 0


def _show(args: argparse.Namespace) -> int:
    """Print one model document."""
    from driftlab.campaigns.store import connect
    from driftlab.models.registry import document_json, get_model

    with connect(args.db) as store:
        doc = get_model(store, args.machine, args.version)
    data = document_json(doc)
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    print(f"machine {doc.machine} version {doc.version} created {doc.created_at} from campaigns {doc.source_campaigns}")
    print(f"inputs: {' '.join(doc.inputs)}")
    for t in doc.terms:
        terms = " + ".join(f"{c:.4g}*{f.name}" for f, c in zip(t.features, t.coefficients))
        print(f"  {t.element}.{t.param} = {terms}")
    return 0


def _online(args: argparse.Namespace) -> int:
    """Run the on-line update and print what it changed."""
    from driftlab.campaigns.store import connect
    from driftlab.models.online import online_update, read_probe_csv

    from datetime import datetime

    from driftlab.errors import ValidationError

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
        print(f"  {term}: off-line residual {t['offline_rms_mm']:.4f} mm rms, on-line {t['online_rms_mm']:.4f} mm rms, "
              f"correction now {t['correction_mm']:+.4f} mm")
    return 0
