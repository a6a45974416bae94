"""Diagnosis report v1 (spec section 4): the JSON document and the self-contained HTML page."""

from __future__ import annotations

import base64
import html
import io
import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from driftlab.models.diagnosis import DiagnosisResult, Effect, TermDiagnosis

FORMAT = "driftlab-diagnosis/1"


def _clean(obj: Any) -> Any:
    """Return ``obj`` with numpy scalars made plain and non-finite floats made null (strict JSON)."""
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def to_json_dict(res: DiagnosisResult) -> dict[str, Any]:
    """Return the report v1 of a diagnosis as a JSON-ready dict (spec keys first, then extras)."""
    frac = res.holdout_fraction
    doc = {
        "format": FORMAT,
        "bundle": res.bundle,
        "holdout": {"method": f"last {frac * 100:g}% of time", "start_s": res.holdout_start_s},
        "simulation": [t.simulation.to_dict() for t in res.terms],
        "baseline": [t.baseline_dict() for t in res.terms],
        "effects": [e.to_dict() for e in res.effects],
        "extended": [t.extended_dict() for t in res.terms],
        "acceptance": {"alpha_family": res.alpha_family, "hypotheses": res.n_hypotheses,
                       "correction": "bonferroni", "min_holdout_gain": res.min_gain,
                       "robust_covariance": "cluster (blocks of whole sweeps)"},
        "flags": [f.to_dict() for f in res.flags],
        "timings_s": res.timings_s,
    }
    return _clean(doc)


# ---------------------------------------------------------------------------------------------
# HTML


def _png(fig: Any) -> str:
    """Return a matplotlib figure as an embedded base64 PNG <img> tag (and close it)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return f'<img alt="plot" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _scale(unit: str) -> tuple[float, str]:
    """Return the display factor and unit (um for mm, urad for rad)."""
    return (1e6, "urad") if unit == "rad" else (1e3, "um")


def _thin(n: int, most: int = 4000) -> slice:
    """Return a stride that keeps at most ``most`` of n points for a scatter plot (the picture is the same)."""
    return slice(None, None, max(1, n // most))


def _effect_plot(eff: Effect, unit: str) -> str:
    """Return the residual plot that shows one finding."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k, lab = _scale(unit)
    sl = _thin(eff.time_s.size)
    th = eff.time_s[sl] / 3600.0
    before = eff.residual_before[sl]
    contrib = eff.contribution[sl]
    train = eff.train[sl]
    position, direction, regressor = eff.position[sl], eff.direction[sl], eff.columns[sl, 0]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4))
    ax = axes[0]
    ax.plot(th, before * k, ".", ms=2, alpha=0.5, label="residual before")
    ax.plot(th, contrib * k, "-", lw=1.2, color="C3", label=f"fitted {eff.kind}")
    hold = th[~train]
    if hold.size:
        ax.axvspan(hold[0], th[-1], color="0.9", zorder=0, label="held out")
    ax.set_xlabel("time (h)")
    ax.set_ylabel(f"{eff.axis}/{eff.term} ({lab})")
    ax.legend(fontsize=7, loc="best")
    ax = axes[1]
    after = before - contrib
    if eff.kind in ("reversal", "screw_expansion"):
        for d, c in ((1, "C0"), (-1, "C1")):
            m = direction == d
            if m.any():
                ax.plot(position[m], before[m] * k, ".", ms=2, color=c, alpha=0.5, label=f"direction {d:+d}")
        ax.set_xlabel("position")
    else:
        ax.plot(regressor, before * k, ".", ms=2, alpha=0.5, label="residual before")
        ax.plot(regressor, after * k, ".", ms=2, alpha=0.5, label="residual after")
        ax.set_xlabel(eff.names[0])
    ax.set_ylabel(lab)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return _png(fig)


def _sim_plots(terms: list[TermDiagnosis]) -> str:
    """Return one figure: the measured errors against the calibrated time-driven law, one panel per term."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(terms)
    ncols = min(3, n)
    nrows = -(-n // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(11, 2.3 * nrows), squeeze=False)
    for ax, t in zip(axes.ravel(), terms):
        k, lab = _scale(t.td.unit)
        sl = _thin(t.td.t.size, 1500)
        th = t.td.t[sl] / 3600.0
        ax.plot(th, t.td.y[sl] * k, ".", ms=1.5, alpha=0.4, label="measured")
        ax.plot(th, t.simulation.predicted[sl] * k, ".", ms=1.5, color="C3", label="Appendix A law")
        ax.set_title(f"{t.td.axis}/{t.td.term} ({lab})", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    axes[0, 0].legend(fontsize=6, loc="best")
    axes[-1, 0].set_xlabel("time (h)", fontsize=8)
    fig.tight_layout()
    return _png(fig)


def _table(rows: list[list[str]], head: list[str]) -> str:
    """Return an HTML table."""
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def to_html(res: DiagnosisResult) -> str:
    """Return the self-contained HTML report: findings with plots and causes, tables, flags."""
    e = html.escape
    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>driftlab diagnosis: {e(res.bundle)}</title>",
           "<style>body{font-family:sans-serif;max-width:1150px;margin:auto}table{border-collapse:collapse}"
           "td,th{border:1px solid #999;padding:2px 6px;font-size:13px}img{max-width:100%}</style></head><body>",
           f"<h1>Diagnosis of {e(res.bundle)}</h1>",
           f"<p>Held out: last {res.holdout_fraction * 100:g}% of each (axis, term) in time "
           f"(from t = {res.holdout_start_s / 3600:.2f} h). Effects are accepted only when significant on the "
           f"training part (Bonferroni over {res.n_hypotheses} hypotheses at family alpha {res.alpha_family}, "
           f"cluster-robust by blocks of sweeps) and lowering the held-out RMSE by at least "
           f"{res.min_gain * 100:g}%.</p>"]
    effects = res.effects
    out.append(f"<h2>Findings ({len(effects)})</h2>")
    if not effects:
        out.append("<p>No effect of the catalogue is supported by the data: the standard model stands.</p>")
    for i, eff in enumerate(effects, 1):
        unit = "rad" if eff.term in ("alpha", "beta", "gamma") else "mm"
        k, lab = _scale(unit)
        params = ", ".join(f"{e(str(a))} = {e(f'{b:.4g}' if isinstance(b, float) else str(b))}"
                           for a, b in eff.params.items())
        out.append(f"<h3>{i}. {e(eff.kind)} on {e(eff.axis)}/{e(eff.term)} {e(', '.join(eff.channels))}</h3>"
                   f"<p><b>Cause.</b> {e(eff.cause)}</p><p>{params}; p = {eff.p_value:.3g}; held-out RMSE "
                   f"{eff.rmse_holdout_before * k:.4g} &rarr; {eff.rmse_holdout_after * k:.4g} {lab} "
                   f"({eff.gain * 100:.0f}% better)</p>{_effect_plot(eff, unit)}")
    rows = []
    for t in res.terms:
        k, lab = _scale(t.td.unit)
        b, x = t.standard.fit, t.extended
        rows.append([e(t.td.axis), e(t.td.term), lab, e(", ".join(t.standard.channels)),
                     e(t.standard.selection.source), f"{b.rmse_train * k:.4g}", f"{b.rmse_holdout * k:.4g}",
                     f"{x.rmse_train * k:.4g}", f"{x.rmse_holdout * k:.4g}", str(len(t.effects))])
    out.append("<h2>Standard model (baseline) and extended model</h2>")
    out.append(_table(rows, ["axis", "term", "unit", "model channels", "channels from", "baseline train",
                             "baseline held-out", "extended train", "extended held-out", "effects"]))
    out.append("<h2>Simulation (Appendix A time-driven laws, calibrated) vs data</h2>")
    rows = []
    for t in res.terms:
        k, lab = _scale(t.td.unit)
        rows.append([e(t.td.axis), e(t.td.term), f"{t.simulation.rmse * k:.4g} {lab}",
                     f"{t.simulation.tau_s / 3600:.2g} h", e(t.simulation.gets_wrong)])
    out.append(_table(rows, ["axis", "term", "RMSE", "tau", "what it gets wrong"]))
    if res.terms:
        out.append(_sim_plots(res.terms))
    out.append("<h2>Flagged data</h2>")
    if res.flags:
        out.append(_table([[e(f.series), str(f.spikes), str(f.out_of_range), str(f.held_scans),
                            e(", ".join(f"{v:g}" for v in f.first_times_s))] for f in res.flags],
                          ["series", "spikes rejected (MAD)", "out of range", "scans held across long gaps",
                           "first flagged times (s)"]))
    else:
        out.append("<p>No spikes, out-of-range readings or long gaps.</p>")
    out.append("</body></html>")
    return "\n".join(out)
