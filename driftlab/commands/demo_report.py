"""The report of `driftlab demo`: demo-report.json, demo-report.html and the terminal table."""

from __future__ import annotations

import base64
import html
import io
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from driftlab.labels import UM, duration, effect_label, si_text

if TYPE_CHECKING:
    import numpy as np
    from matplotlib.figure import Figure

RUN_NAMES = {"uncompensated": "without compensation", "offline": "off-line model", "online": "off-line + on-line model"}
#: thesis ch. 7.3, mm
THESIS = {
    "uncompensated": {"rmse_mm": 0.060, "max_mm": 0.082},
    "offline": {"rmse_mm": 0.005, "max_mm": 0.015},
    "online": {"rmse_mm": 0.003, "max_mm": 0.012},
}
#: the machine's linear positioning step (ch. 4: the strategy's limit is the resolution, 0.0025 mm); the
#: compensator's ``RESOLUTION_MM``, not imported from it: numpy and pandas would load with `driftlab --help`
#: (tests/test_reports_html.py holds the two equal)
RESOLUTION_MM = 0.0025


def _text(value: object) -> str:
    """Return text for the page: SI unit symbols (µm, µrad, °C) for the ASCII ones, HTML-escaped."""
    return html.escape(si_text(str(value)))


def ordering_holds(table: dict[str, dict[str, Any]]) -> bool:
    """Return whether the thesis' ordering (uncompensated > off-line > on-line in RMSE, ch. 7.3) holds."""
    return bool(table["uncompensated"]["rmse_mm"] > table["offline"]["rmse_mm"] > table["online"]["rmse_mm"])


def ordering_text(table: dict[str, dict[str, Any]]) -> str:
    """Return whether the thesis' ordering (``ordering_holds``) holds, in words.

    When both compensated cuts are within the machine's step, the order between them is below what the
    machine can position and is said so rather than only "does not hold".
    """
    if ordering_holds(table):
        return "holds"
    u, off, on = (float(table[k]["rmse_mm"]) for k in ("uncompensated", "offline", "online"))
    if u > max(off, on) and max(off, on) <= RESOLUTION_MM:
        return (
            f"does not hold between the compensated cuts: off-line {off * 1e3:.1f} µm and on-line {on * 1e3:.1f} µm "
            f"are both within the machine's {RESOLUTION_MM * 1e3:.1f} µm step (ch. 4: the limit of compensation)"
        )
    return "does not hold"


def diagnosis_summary(report: dict[str, Any]) -> dict[str, Any]:
    """Return the findings of a diagnosis report v1: accepted effects with their causes and gains."""
    effects = []
    for e in report.get("effects", []):
        effects.append(
            {
                k: e.get(k)
                for k in (
                    "kind",
                    "axis",
                    "term",
                    "channels",
                    "params",
                    "p_value",
                    "cause",
                    "rmse_holdout_before",
                    "rmse_holdout_after",
                )
            }
        )
    names = [
        f"{e['kind']} {e.get('axis') or ''}/{e.get('term') or ''} {' '.join(e.get('channels') or [])}".strip()
        for e in effects
    ]
    return {
        "effects": effects,
        "named": names,
        "flags": report.get("flags", []),
        "baseline": report.get("baseline", []),
    }


def build_report(
    *, table: dict[str, dict[str, Any]], diagnosis: dict[str, Any], steps: list[dict[str, Any]], extra: dict[str, Any]
) -> dict[str, Any]:
    """Return the demo-report.json document."""
    out: dict[str, Any] = {"format": "driftlab-demo/1"}
    out.update(table)
    out["diagnosis"] = diagnosis
    out["thesis"] = THESIS
    out["ordering_holds"] = ordering_holds(table)
    out["ordering"] = ordering_text(table)
    out["steps"] = steps
    out.update(extra)
    # lazy: this function's imports would add 76 ms to `driftlab --help` (measured)
    from driftlab.jsonsafe import strict_json

    return strict_json(out)


def write_json(path: Path, report: dict[str, Any]) -> Path:
    """Write the report as strict JSON; return the path."""
    path.write_text(json.dumps(report, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path


def surface_figure(deviations: dict[str, np.ndarray]) -> str:
    """Return a PNG (base64) of the machined-surface errors of each run (figs. 7.3, 7.4, 7.6) on one colour scale."""
    # lazy: this function's imports would add 0.6 s to `driftlab --help` (measured)
    import matplotlib.pyplot as plt

    fig = surface_axes(deviations)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def surface_axes(deviations: dict[str, np.ndarray]) -> Figure:
    """Return the matplotlib figure of the surface maps: one symmetric colour scale and one colour bar for all.

    The maps are comparable only on one scale: the compensated runs look as flat as they are, and each map's
    title gives its own range in µm.
    """
    # lazy: this function's imports would add 0.6 s to `driftlab --help` (measured)
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    # lazy, as above: kept off the `driftlab --help` path
    import matplotlib.pyplot as plt

    keys = [k for k in ("uncompensated", "offline", "online") if k in deviations]
    lim = max(float(np.nanmax(np.abs(deviations[k]))) for k in keys) * 1e3 or 1.0
    fig, axes = plt.subplots(1, len(keys), figsize=(4.4 * len(keys) + 1.0, 4.4), sharey=True, constrained_layout=True)
    axes = np.atleast_1d(axes)
    ims = []
    for ax, k in zip(axes, keys):
        um = deviations[k] * 1e3
        im = ax.imshow(
            um,
            aspect="auto",
            origin="lower",
            cmap="coolwarm",
            vmin=-lim,
            vmax=lim,
            extent=(0.5, um.shape[1] + 0.5, 0.5, um.shape[0] + 0.5),
        )
        ax.set_title(f"{RUN_NAMES[k]}\nrange {np.nanmin(um):+.1f} .. {np.nanmax(um):+.1f} {UM}", fontsize=10)
        ax.set_xlabel("across the part (15 CMM points)")
        ims.append(im)
    fig.colorbar(ims[0], ax=list(axes), label=f"normal deviation ({UM}), one scale ±{lim:.1f}", shrink=0.85)
    axes[0].set_ylabel("along the part = machining time (99 CMM points)")
    return fig


def judge(run: str, case: dict[str, Any]) -> tuple[str, bool]:
    """Return the verdict on one run of a cutting test and whether it is worse than its reference.

    Like with like: the uncompensated run is the baseline (the thesis measured another machine); a
    compensated run is judged by how much of the uncompensated error it removes, after the CMM's
    alignment and before it (the unaligned figure keeps what the alignment takes away: a drift the
    model missed). "as much as in the thesis" only when both removals are within 5 points of the
    thesis'; "worse than without compensation" when either RMSE is above the uncompensated one; an
    off-line interval that holds under half of the CMM points is said too.
    """
    t = THESIS
    if run == "uncompensated":
        return f"baseline (the thesis' machine: {t['uncompensated']['rmse_mm'] * 1e3:.0f} {UM})", False
    theirs = 1.0 - t[run]["rmse_mm"] / t["uncompensated"]["rmse_mm"]
    pairs = [(case[f"{run}_mm"], case["uncompensated_mm"])]
    if f"{run}_unaligned_mm" in case and "uncompensated_unaligned_mm" in case:
        pairs.append((case[f"{run}_unaligned_mm"], case["uncompensated_unaligned_mm"]))
    removed = [1.0 - ours / base if base > 0 else float("nan") for ours, base in pairs]
    worst = min(removed)
    words = [f"removes {removed[0]:.0%} of the error"]
    if len(removed) > 1:
        words[0] += f" ({removed[1]:.0%} before the alignment)"
    if any(ours > base for ours, base in pairs):
        words.append("worse than without compensation")
    elif worst >= theirs - 0.05:
        words.append(f"as much as in the thesis ({theirs:.0%})")
    else:
        words.append(f"worse than in the thesis ({theirs:.0%})")
    inside = (case.get("offline_predicted") or {}).get("inside") if run == "offline" else None
    if inside is not None and inside < 0.5:
        words.append(f"only {inside:.0%} of the CMM points inside the predicted interval")
    worse = worst < theirs - 0.05 or any(ours > base for ours, base in pairs) or (inside is not None and inside < 0.5)
    return ", ".join(words), worse


def verdict(run: str, rmse_mm: float, uncompensated_mm: float) -> str:
    """Return the verdict on one run from its aligned RMSE alone (``judge`` weighs the unaligned one too)."""
    return judge(run, {f"{run}_mm": rmse_mm, "uncompensated_mm": uncompensated_mm})[0]


def interval_text(p: dict[str, Any]) -> str:
    """Return the off-line model's predicted interval of a cut beside the measured figure, in words (µm)."""
    return (
        f"off-line model predicted RMSE {p['predicted_rmse_mm'] * 1e3:.1f} {UM} "
        f"({round(100 * (1 - 2 * (1 - _normal_cdf(p['z']))))}% interval +/- {p['mean_half_width_mm'] * 1e3:.1f} {UM} "
        f"on average), measured {p['measured_rmse_mm'] * 1e3:.1f} {UM} before the CMM's alignment; "
        f"{p['inside'] * 100:.0f}% of the CMM points inside their interval"
    )


def _normal_cdf(z: float) -> float:
    """Return the standard normal distribution function at z."""
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))


def _verdict_cell(run: str, case: dict[str, Any]) -> str:
    """Return a run's verdict for the page: the words, in red with the word "worse" when it is."""
    text, worse = judge(run, case)
    return f"<span class='worse'>{html.escape(text)}</span>" if worse else html.escape(text)


def _row(cells: list[str], tag: str = "td") -> str:
    """Return one HTML table row."""
    return "<tr>" + "".join(f"<{tag}>{c}</{tag}>" for c in cells) + "</tr>"


def _planted_text(p: dict[str, Any]) -> str:
    """Return a planted effect of the scenario in words (never as JSON)."""
    where = f" on {p.get('axis')}/{p.get('term')}" if p.get("axis") else ""
    return effect_label(p) + where


def _cutting_rows(cases: list[dict[str, Any]]) -> list[str]:
    """Return the cutting tests' table rows (header first): each case's runs beside the thesis' figures (µm)."""
    e = _text
    head = [
        "case",
        "run",
        f"RMSE ({UM})",
        f"max ({UM})",
        f"unaligned RMSE ({UM})",
        f"thesis RMSE ({UM})",
        f"thesis max ({UM})",
        "verdict",
    ]
    rows = [_row(head, "th")]
    for c in cases:
        for k, name in RUN_NAMES.items():
            t = THESIS[k]
            rows.append(
                _row(
                    [
                        e(c["case"]) if k == "uncompensated" else "",
                        e(name),
                        f"{c[f'{k}_mm'] * 1e3:.1f}",
                        f"{c[f'{k}_max_mm'] * 1e3:.1f}",
                        f"{c[f'{k}_unaligned_mm'] * 1e3:.1f}" if f"{k}_unaligned_mm" in c else "",
                        f"{t['rmse_mm'] * 1e3:.0f}",
                        f"{t['max_mm'] * 1e3:.0f}",
                        _verdict_cell(k, c),
                    ]
                )
            )
    return rows


def _findings_html(diag: dict[str, Any]) -> str:
    """Return the diagnosis' accepted effects as list items: effect, where, cause and held-out gain (µm)."""
    e = _text
    return (
        "".join(
            f"<li><b>{e(effect_label(f))}</b> on {e(str(f.get('axis')))}/{e(str(f.get('term')))}: "
            f"{e(str(f.get('cause') or ''))} (held-out RMSE {1e3 * (f.get('rmse_holdout_before') or 0):.2f} &rarr; "
            f"{1e3 * (f.get('rmse_holdout_after') or 0):.2f} {UM})</li>"
            for f in diag.get("effects", [])
        )
        or "<li>no effect accepted</li>"
    )


def to_html(report: dict[str, Any], figure_png: str | None = None) -> str:
    """Return the demo's HTML page: the cutting-test table (µm), the diagnosis findings in words, the steps."""
    e = _text
    cases = report.get("cutting_tests") or [
        {
            "case": "",
            **{f"{k}_mm": report[k]["rmse_mm"] for k in RUN_NAMES},
            **{f"{k}_max_mm": report[k]["max_mm"] for k in RUN_NAMES},
        }
    ]
    rows = _cutting_rows(cases)
    findings = _findings_html(report.get("diagnosis", {}))
    steps = "".join(
        _row([e(s["name"]), f"<code>{e(s.get('command', ''))}</code>", e(duration(s["wall_s"]))])
        for s in report.get("steps", [])
    )
    fig = (
        (
            f'<p><img style="max-width:100%" alt="machined surface errors of the three runs on one colour '
            f'scale" src="data:image/png;base64,{figure_png}"></p>'
        )
        if figure_png
        else ""
    )
    planted = report.get("planted", [])
    planted_html = "".join(f"<li>{e(_planted_text(p))}</li>" for p in planted) or "<li>nothing hidden</li>"
    ordering = report.get("ordering") or ("holds" if report.get("ordering_holds") else "does NOT hold")
    intervals = "".join(
        f"<p>{e(c['case'])}: {e(interval_text(c['offline_predicted']))}.</p>"
        for c in cases
        if c.get("offline_predicted")
    )
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>driftlab demo</title>
<style>body{{font-family:sans-serif;max-width:70em;margin:2em auto;color:#1d2430}}
.worse{{color:#c0392b;font-weight:bold}}table{{border-collapse:collapse}}
td,th{{border:1px solid #bbb;padding:.25em .6em;text-align:right}}td:first-child,th:first-child{{text-align:left}}
code{{font-size:85%}}</style></head><body>
<h1>driftlab demo</h1>
<p>A staged campaign on the virtual machine through the daemon, a fitted and registered model, its diagnosis,
the model served over the API, and the cutting test of thesis ch. 7.3 streamed through the compensator.
Total wall time {e(duration(report.get("wall_s", 0)))}. Lengths in micrometres ({UM}).</p>
<h2>Cutting tests (ch. 7.3): normal deviation of the machined surface, CMM 15 x 99 points</h2>
<p>As in ch. 7.3, a single pass up the centre of the part is cut first and the CMM aligns the part on it (its height
and pitch); "unaligned" is the deviation before that alignment, where the surface sits in the machine's frame.
"thermal": the campaign's machine, cut cold a day after the campaign started; "thermal+wear": the same cut
with the Z slideways worn ({e(str(report.get("wear_um_per_day", "")))} {UM} a day), which no campaign saw. The maps
below are of the thermal+wear case.</p>
<table>{"".join(rows)}</table>
{intervals}
<p>Ordering uncompensated &gt; off-line &gt; off-line + on-line: <b>{e(ordering)}</b>.</p>
{fig}
<h2>Diagnosis of the campaign</h2>
<ul>{findings}</ul>
<p>Planted in the scenario (the truth, not seen by the pipeline):</p><ul>{planted_html}</ul>
<p>The campaign overview, every finding's plot and the per-term tables: <a href="diagnosis.html">diagnosis.html</a>.</p>
<h2>Steps</h2>
<table>{_row(["step", "command", "wall time"], "th")}{steps}</table>
</body></html>
"""
