"""Diagnosis report v1 (spec section 4): the JSON document and the self-contained HTML page."""

from __future__ import annotations

import base64
import html
import io
import math
from typing import TYPE_CHECKING, Any

from driftlab.jsonsafe import strict_json
from driftlab.labels import duration, effect_label, feature_label, si_text

if TYPE_CHECKING:
    from driftlab.models.diagnosis import DiagnosisResult, Effect, TermDiagnosis

FORMAT = "driftlab-diagnosis/1"


def _text(value: object) -> str:
    """Return text for the page: SI unit symbols (µm, µrad, °C) for the ASCII ones, HTML-escaped."""
    return html.escape(si_text(str(value)))


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
        "unexplained": [u.to_dict() for u in res.unexplained],
        "acceptance": {
            "alpha_family": res.alpha_family,
            "hypotheses": res.n_hypotheses,
            "correction": "bonferroni",
            "decided_on": "training part only",
            "alpha_per_candidate": res.alpha_each,
            "alpha_per_channel_fault": res.alpha_fault,
            "validation": "rolling origin inside the training part (origins at 2/3 and 5/6), pooled",
            "final_gate": "last training block: the extended model no worse than the baseline and the current model",
            "min_validation_gain": res.min_gain,
            "robust_covariance": "max of HAC (Newey-West) and cluster (blocks of whole sweeps)",
            "sensor_fault": "temperature evidence alone (virtual-sensor departure change point)",
            "sensor_drift": "temperature evidence alone (a ramp of the virtual-sensor departure, peer test)",
            "datum_shift": "a sharp, lasting step of the sweep means (not validated forward: an artefact)",
            "unexplained_ratio": 1.5,
            "unexplained_holdout_ratio": 2.0,
        },
        "flags": [f.to_dict() for f in res.flags],
        "timings_s": res.timings_s,
    }
    return strict_json(doc)


# ---------------------------------------------------------------------------------------------
# HTML


def _png(fig: Any, alt: str = "plot") -> str:
    """Return a matplotlib figure as an embedded base64 PNG <img> tag (and close it)."""
    # lazy: matplotlib adds 0.39 s to this module, and only the HTML report's figures need it (measured)
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _scale(unit: str) -> tuple[float, str]:
    """Return the display factor and unit (µm for mm, µrad for rad)."""
    return (1e6, "µrad") if unit == "rad" else (1e3, "µm")


def _thin(n: int, most: int = 4000) -> slice:
    """Return a stride that keeps at most ``most`` of n points for a scatter plot (the picture is the same)."""
    return slice(None, None, max(1, n // most))


def _effect_plot(eff: Effect, unit: str) -> str:
    """Return the residual plot that shows one finding (axes in words and µm/µrad)."""
    # lazy: matplotlib adds 0.39 s to this module, and only the HTML report's figures need it (measured)
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
    ax.plot(th, before * k, ".", ms=2, alpha=0.5, label="what the standard model leaves")
    ax.plot(th, contrib * k, "-", lw=1.2, color="C3", label=effect_label(eff.to_dict()))
    hold = th[~train]
    if hold.size:
        ax.axvspan(hold[0], th[-1], color="0.9", zorder=0, label="held out")
    ax.set_xlabel("hours since start")
    ax.set_ylabel(f"{eff.axis}/{eff.term} residual ({lab})")
    ax.legend(fontsize=7, loc="best")
    ax = axes[1]
    after = before - contrib
    if eff.kind in ("reversal", "screw_expansion"):
        for d, c in ((1, "C0"), (-1, "C1")):
            m = direction == d
            if m.any():
                ax.plot(position[m], before[m] * k, ".", ms=2, color=c, alpha=0.5, label=f"approach {d:+d}")
        ax.set_xlabel(f"{eff.axis} position ({'deg' if eff.axis in ('A', 'B') else 'mm'})")
    else:
        ax.plot(regressor, before * k, ".", ms=2, alpha=0.5, label="before")
        ax.plot(regressor, after * k, ".", ms=2, alpha=0.5, label="after the finding")
        ax.set_xlabel(feature_label(eff.names[0], eff.params.get("tau_s")) + _feature_unit(eff.names[0]))
    ax.set_ylabel(f"residual ({lab})")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return _png(fig, f"residual of {eff.axis}/{eff.term} with {effect_label(eff.to_dict())}")


def _feature_unit(name: str) -> str:
    """Return the unit suffix of a regressor on an axis label."""
    if name.startswith(("lag", "dT", "fault")):
        return " (°C²)" if name.endswith("^2") else " (°C)"
    if name.startswith("position*"):
        return " (mm °C)"
    return ""


def _sim_plots(terms: list[TermDiagnosis]) -> str:
    """Return one figure: the measured errors against the calibrated time-driven law, one panel per term."""
    # lazy: matplotlib adds 0.39 s to this module, and only the HTML report's figures need it (measured)
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
    axes[-1, 0].set_xlabel("hours since start", fontsize=8)
    fig.tight_layout()
    return _png(fig, "measured errors against the calibrated Appendix A law")


def _overview(bundle: Any) -> str:
    """Return the campaign on one figure: stages, mean temperature per structure, and every error term, over time."""
    # lazy: matplotlib adds 0.39 s to this module, and only the HTML report's figures need it (measured)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta, temps, errors = bundle.meta, bundle.temperatures, bundle.errors
    th = temps["time_s"].to_numpy() / 3600.0
    groups: dict[str, list[str]] = {}
    for name, ch in meta.channels.items():
        if name in temps.columns:
            group = "room" if name in meta.room_channels else (ch.structure or "unspecified")
            groups.setdefault(group, []).append(name)
    keys = sorted({(a, t) for a, t in zip(errors["axis"], errors["term"])})
    fig, axes = plt.subplots(
        2 + len(keys),
        1,
        figsize=(11, 2.0 * (2 + len(keys))),
        sharex=True,
        gridspec_kw={"height_ratios": [0.5, 2] + [1.2] * len(keys)},
    )
    ax = axes[0]
    span = max((st.end_s for st in meta.stages), default=1.0) or 1.0
    for i, st in enumerate(meta.stages):
        ax.axvspan(st.start_s / 3600, st.end_s / 3600, color=f"C{i % 10}", alpha=0.35)
        if (st.end_s - st.start_s) / span < 0.06:
            continue  # too narrow to name: the stage table above has it
        ax.text(
            (st.start_s + st.end_s) / 7200, 0.5, st.name, ha="center", va="center", fontsize=7, rotation=0, clip_on=True
        )
    ax.set_yticks([])
    ax.set_ylabel("stage", fontsize=8)
    ax = axes[1]
    for i, (g, chans) in enumerate(sorted(groups.items())):
        mean = temps[chans].mean(axis=1).to_numpy()
        ax.plot(th, mean, lw=1, color=f"C{i % 10}", label=g.replace("_", " "))
    ax.set_ylabel("mean temperature\nper structure (°C)", fontsize=8)
    ax.legend(fontsize=6, ncol=6, loc="upper left")
    for ax, (axis, term) in zip(axes[2:], keys):
        k, lab = _scale("rad" if term in ("alpha", "beta", "gamma") else "mm")
        rows = errors[(errors["axis"] == axis) & (errors["term"] == term)]
        for d, c in ((1, "C0"), (-1, "C3")):
            m = rows["direction"] == d
            ax.scatter(rows["time_s"][m] / 3600, rows["value"][m] * k, s=3, color=c, label=f"approach {d:+d}")
        ax.set_ylabel(f"{axis}/{term} ({lab})", fontsize=8)
        ax.legend(fontsize=6, loc="upper left")
    axes[-1].set_xlabel("hours since start")
    fig.tight_layout()
    return _png(fig, "campaign overview: stages, temperatures and errors over time")


def _table(rows: list[list[str]], head: list[str]) -> str:
    """Return an HTML table."""
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _params_text(eff: Effect) -> str:
    """Return an effect's parameters in words (durations, times into the campaign), never as JSON."""
    out = []
    for key, value in eff.params.items():
        if key == "tau_s" and isinstance(value, (int, float)):
            out.append(f"time constant {duration(float(value))}")
        elif key == "tau_range_s" and isinstance(value, list) and len(value) == 2:
            lo, hi = (duration(float(v)) for v in value)
            out.append(f"not pinned by the training rows: the mean of the lags over {lo} to {hi}")
        elif key == "start_s" and isinstance(value, (int, float)):
            out.append(f"from {duration(float(value))} into the campaign")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out.append(f"{key.replace('_', ' ')} {value:.4g}")
        elif isinstance(value, (str, bool)):
            out.append(f"{key.replace('_', ' ')}: {value}")
    return "; ".join(html.escape(x) for x in out)


def _html_head(res: DiagnosisResult) -> list[str]:
    """Return the page's head, title and the paragraph on how the findings were decided."""
    e = _text
    return [
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>driftlab diagnosis: {e(res.bundle)}</title>",
        "<style>body{font-family:sans-serif;max-width:1150px;margin:auto;color:#1d2430}table{border-collapse:collapse}"
        "td,th{border:1px solid #999;padding:2px 6px;font-size:13px}img{max-width:100%}"
        ".good{color:#1f7a3a;font-weight:600}.worse{color:#b3261e;font-weight:600}</style></head><body>",
        f"<h1>Diagnosis of {e(res.bundle)}</h1>",
        f"<p>Held out: the last {res.holdout_fraction * 100:g}% of each error term in time "
        f"(from {duration(res.holdout_start_s)} into the campaign). Every decision is made on the training part "
        f"alone: a finding must be significant there (Bonferroni over {res.n_hypotheses} hypotheses at family alpha "
        f"{res.alpha_family}, with inference robust to autocorrelated residuals: HAC and blocks of sweeps) "
        f"and lower "
        f"the error by at least {res.min_gain * 100:g}% in time-ordered validation inside the training part. The "
        f"held-out part is scored once, after the findings are final, and its figures are shown as they came out. "
        f"A faulty thermocouple is decided on the temperatures alone. "
        f"Lengths are in micrometres (µm), angles in microradians (µrad).</p>",
    ]


def _html_campaign(bundle: Any) -> list[str]:
    """Return the campaign's stages and overview (the bundle itself, when the page is given it)."""
    e = _text
    stages = [
        [
            e(st.name),
            e(st.heat_source),
            e(st.axis or "-"),
            f"{st.spindle_rpm:.0f}",
            f"{st.feed_mm_min:.0f}",
            f"{st.start_s / 3600:.2f}",
            f"{st.end_s / 3600:.2f}",
        ]
        for st in bundle.meta.stages
    ]
    return [
        "<h2>The campaign</h2>",
        _table(stages, ["stage", "heat source", "axis", "spindle (rpm)", "feed (mm/min)", "from (h)", "to (h)"]),
        _overview(bundle),
    ]


def _html_finding(i: int, eff: Effect) -> str:
    """Return one finding: its kind and place, cause, parameters, held-out gain or loss (in red) and its plot."""
    e = _text
    unit = "rad" if eff.term in ("alpha", "beta", "gamma") else "mm"
    k, lab = _scale(unit)
    where = f"{e(eff.axis)}/{e(eff.term or '')}" if eff.axis else "the temperatures (no model uses this channel)"
    if math.isfinite(eff.rmse_holdout_before) and math.isfinite(eff.rmse_holdout_after):
        g = eff.gain * 100
        worse = eff.rmse_holdout_after > eff.rmse_holdout_before
        verdict = f"{-g:.0f}% worse" if worse else f"{g:.0f}% better"
        gain = (
            f"held-out RMSE {eff.rmse_holdout_before * k:.2f} &rarr; {eff.rmse_holdout_after * k:.2f} {lab} "
            f"(<span class='{'worse' if worse else 'good'}'>{verdict}</span>)"
        )
    else:
        gain = "no held-out figure (the channel feeds no model, or the fault starts after the last reading)"
    plot = _effect_plot(eff, unit) if eff.time_s.size else ""
    return (
        f"<h3>{i}. {e(effect_label(eff.to_dict()))}, on {where}</h3>"
        f"<p><b>Cause.</b> {e(eff.cause)}</p>"
        f"<p>{_params_text(eff)}; p = {eff.p_value:.3g}; {gain}</p>{plot}"
    )


def _html_models(res: DiagnosisResult) -> list[str]:
    """Return the table of the standard model and the model with the findings, per term (worse in red)."""
    e = _text
    rows = []
    for t in res.terms:
        k, lab = _scale(t.td.unit)
        b, x = t.base, t.ext
        rows.append(
            [
                e(t.td.axis),
                e(t.td.term),
                lab,
                e("fitted model" if b.model == "fitted" else "per-term model"),
                e(", ".join(t.standard.channels)),
                e(t.standard.selection.source),
                f"{b.rmse_train * k:.2f}",
                f"{b.rmse_holdout * k:.2f}",
                f"{x.rmse_train * k:.2f}",
                (
                    f"<span class='worse'>{x.rmse_holdout * k:.2f} (worse)</span>"
                    if t.effects and x.rmse_holdout > b.rmse_holdout
                    else f"{x.rmse_holdout * k:.2f}"
                ),
                str(len(t.effects)),
            ]
        )
    head = ["axis", "term", "unit", "baseline", "model thermocouples", "thermocouples chosen by", "baseline train RMSE"]
    head += ["baseline held-out RMSE", "with findings, train", "with findings, held out", "findings"]
    return [
        "<h2>Baseline (the fitted model, or the per-term model) and the model with the findings</h2>",
        _table(rows, head),
    ]


def _html_unexplained(res: DiagnosisResult) -> list[str]:
    """Return the unexplained terms with their hints (or that every term is explained to its noise)."""
    e = _text
    out = [f"<h2>Unexplained ({len(res.unexplained)})</h2>"]
    if not res.unexplained:
        out.append(
            "<p>Every term is explained to its measurement noise (training residual at most 1.5 x noise, "
            "held-out residual at most 2 x noise).</p>"
        )
        return out
    out.append(
        "<p>Terms whose residual, after the findings above, stays above the measurement noise: 1.5 x in "
        "training, or 2 x on the held-out part (held out shows what training did not; scored after every "
        "decision, it changed none). The hints name the training residual's signature.</p>"
    )
    urows = []
    for u in res.unexplained:
        k, lab = _scale("rad" if u.term in ("alpha", "beta", "gamma") else "mm")
        ho = f"{u.rmse_holdout * k:.2f} {lab}" if math.isfinite(u.rmse_holdout) else "-"
        urows.append(
            [
                e(u.axis),
                e(u.term),
                e(u.part),
                f"<span class='worse'>{u.residual_over_noise:.1f} x</span>",
                f"{u.rmse_train * k:.2f} {lab}",
                f"<span class='worse'>{ho}</span>" if u.part == "held out" else ho,
                f"{u.noise * k:.2f} {lab}",
                e("; ".join(u.hints)),
            ]
        )
    head = ["axis", "term", "shown by", "training residual / noise", "training residual", "held-out residual"]
    out.append(_table(urows, [*head, "noise", "hints"]))
    return out


def _html_simulation(res: DiagnosisResult) -> list[str]:
    """Return the calibrated simulation laws against the data, per term, with their plots."""
    e = _text
    out = ["<h2>Simulation (Appendix A time-driven laws, calibrated) against the data</h2>"]
    rows = []
    for t in res.terms:
        k, lab = _scale(t.td.unit)
        rows.append(
            [
                e(t.td.axis),
                e(t.td.term),
                f"{t.simulation.rmse * k:.2f} {lab}",
                e(duration(t.simulation.tau_s)),
                e(t.simulation.gets_wrong),
            ]
        )
    out.append(_table(rows, ["axis", "term", "RMSE", "time constant", "what it gets wrong"]))
    if res.terms:
        out.append(_sim_plots(res.terms))
    return out


def _html_flags(res: DiagnosisResult) -> list[str]:
    """Return the table of flagged data (spikes, out-of-range readings, held scans)."""
    e = _text
    if not res.flags:
        return ["<h2>Flagged data</h2>", "<p>No spikes, out-of-range readings or long gaps.</p>"]
    rows = [
        [
            e(f.series),
            str(f.spikes),
            str(f.out_of_range),
            str(f.held_scans),
            e(", ".join(duration(v, clock=True) for v in f.first_times_s)),
        ]
        for f in res.flags
    ]
    head = ["series", "spikes rejected (MAD)", "out of range", "scans held across long gaps"]
    head.append("first flagged (h:mm:ss into the campaign)")
    return ["<h2>Flagged data</h2>", _table(rows, head)]


def to_html(res: DiagnosisResult, bundle: Any = None) -> str:
    """Return the self-contained HTML report: an overview of the campaign (with ``bundle``), findings, tables, flags."""
    out = _html_head(res)
    if bundle is not None:
        out += _html_campaign(bundle)
    effects = res.effects
    out.append(f"<h2>Findings ({len(effects)})</h2>")
    if not effects:
        out.append("<p>No effect of the catalogue is supported by the data: the baseline model stands.</p>")
    out += [_html_finding(i, eff) for i, eff in enumerate(effects, 1)]
    out += _html_models(res)
    out += _html_unexplained(res)
    out += _html_simulation(res)
    out += _html_flags(res)
    out.append("</body></html>")
    return "\n".join(out)
