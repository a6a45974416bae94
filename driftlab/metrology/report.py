"""HTML pages of the ISO 230-2 and ISO 230-3 reports (plots embedded as PNG)."""

from __future__ import annotations

import base64
import html
import io
from datetime import timedelta
from typing import Any

from driftlab.metrology import iso230_2, iso230_3


def _png(fig: Any, alt: str) -> str:
    """Return a matplotlib figure as an embedded base64 PNG <img> tag (and close it)."""
    # lazy: matplotlib adds 0.54 s to `import driftlab.metrology.report` (measured); only plots need it
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _table(head: list[str], rows: list[list[str]]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


_STYLE = (
    "<style>body{font-family:sans-serif;max-width:70em;margin:1em auto}table{border-collapse:collapse}"
    "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
    ".warning{background:#fff3cd;border:1px solid #e0b000;padding:.5em}img{max-width:100%}</style>"
)


def conditions(bundle: Any, axis: str, term: str | None, start_s: float, end_s: float) -> list[tuple[str, str]]:
    """Return the test conditions of runs measured in [start_s, end_s]: date, temperatures, feed, instrument,
    compensation state, as far as the campaign records them ("not recorded" otherwise)."""
    meta = bundle.meta
    term = term or iso230_2.POSITIONING_TERM.get(axis.upper(), "")
    t0 = meta.started_at
    when = (
        f"{(t0 + timedelta(seconds=start_s)):%Y-%m-%d %H:%M} to {(t0 + timedelta(seconds=end_s)):%Y-%m-%d %H:%M} "
        f"{t0:%Z}".strip()
    )
    out = [("date", when), ("duration", f"{(end_s - start_s) / 3600:.1f} h")]
    temps = getattr(bundle, "temperatures", None)
    if temps is not None and len(temps):
        t = temps["time_s"].to_numpy(float)
        rows = temps[(t >= start_s) & (t <= end_s)]
        room = [c for c in meta.room_channels if c in rows]
        if room and len(rows):
            air = rows[room].mean(axis=1)
            out.append(
                (
                    "air temperature",
                    f"{air.min():.1f} to {air.max():.1f} °C (range {air.max() - air.min():.2f} °C, {', '.join(room)})",
                )
            )
        else:
            out.append(("air temperature", "not recorded (no room channel)"))
        chans = [c for c in rows.columns if c != "time_s" and c not in room]
        if chans and len(rows):
            rise = (rows[chans].max() - rows[chans].min()).max()
            out.append(("machine temperatures", f"largest change of one sensor {rise:.2f} °C ({len(chans)} sensors)"))
    setups = [(name, st) for name, st in (meta.setups or {}).items() if f"{axis.upper()}/{term}" in st.terms]
    if setups:
        name, st = setups[0]
        what = (
            st.instrument + (f", {st.optics} optics" if st.optics else "") + (f", {st.fixture}" if st.fixture else "")
        )
        ref = st.reference or {}
        keys = ("source", "owner", "version", "version_no", "serial_no")
        extra = ", ".join(f"{k.replace('_', ' ')} {ref[k]}" for k in keys if ref.get(k))
        out.append(("instrument", f"{what} (setup {name}{'; ' + extra if extra else ''})"))
        feed = ref.get("velocity") or ref.get("feed")
        out.append(("feed", str(feed) if feed else "not recorded in campaign.json"))
        comp = ref.get("compensation")
        out.append(("compensation", str(comp) if comp else "not recorded in campaign.json"))
    else:
        out.append(("instrument", "not recorded in campaign.json"))
        out.append(("feed", "not recorded in campaign.json"))
        out.append(("compensation", "not recorded in campaign.json"))
    stages = [s.name for s in meta.stages if s.start_s < end_s and s.end_s > start_s]
    if stages:
        out.append(("stages", ", ".join(stages[:8]) + (f" and {len(stages) - 8} more" if len(stages) > 8 else "")))
    return out


def _figures_table(result: iso230_2.Iso230_2Result) -> str:
    names = {"B_mean": "B̄ (mean reversal value)"}
    rows = []
    for k in iso230_2.FIGURES:
        v, u = iso230_2.display(result.figures[k], result.unit)
        rows.append([names.get(k, k), v, u])
    return _table(["figure", "value", "unit"], rows)


def _per_target(result: iso230_2.Iso230_2Result) -> str:
    _, u = iso230_2.display(0.0, result.unit)
    rows = [
        [
            f"{p:g}",
            *(
                iso230_2.display(float(v), result.unit)[0]
                for v in (
                    result.xbar_up[j],
                    result.xbar_down[j],
                    result.s_up[j],
                    result.s_down[j],
                    result.reversal[j],
                    result.R_j[j],
                )
            ),
        ]
        for j, p in enumerate(result.targets)
    ]
    head = ["target", "x̄ ↑", "x̄ ↓", "s ↑", "s ↓", "B_j", "R_j"]
    return _table([*head[:1], *(f"{h} ({u})" for h in head[1:])], rows)


def _section(result: iso230_2.Iso230_2Result, conds: list[tuple[str, str]] | None, alt: str) -> str:
    warn = result.drift_warning
    parts = []
    if warn:
        parts.append(f"<p class='warning'><b>Warning:</b> {html.escape(warn)}</p>")
    if conds:
        parts.append("<h3>Test conditions</h3>" + _table(["condition", "value"], [list(c) for c in conds]))
    parts.append(_png(iso230_2.plot(result), alt))
    parts.append("<h3>Axis figures</h3>" + _figures_table(result))
    parts.append("<h3>Per target</h3>" + _per_target(result))
    return "".join(parts)


def iso230_2_html(
    result: iso230_2.Iso230_2Result,
    title: str,
    conds: list[tuple[str, str]] | None = None,
    windows: list[tuple[iso230_2.Window, list[tuple[str, str]]]] | None = None,
) -> str:
    """Return the ISO 230-2 page: conditions, the standard's plot, the axis figures and the per-target table;
    with ``windows``, one such section per stage or time window."""
    head = (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>{_STYLE}</head><body>"
        f"<h1>{html.escape(title)}</h1>"
    )
    if windows:
        body = [
            f"<p>ISO 230-2:2014, axis {windows[0][0].result.axis}: {len(windows)} evaluations of the runs taken "
            "within one stage or time window each.</p>"
        ]
        for w, wc in windows:
            body.append(f"<h2>{html.escape(w.label)}</h2>" + _section(w.result, wc, f"ISO 230-2 plot {w.label}"))
        return head + "".join(body) + "</body></html>\n"
    _, u = iso230_2.display(0.0, result.unit)
    intro = (
        f"<p>ISO 230-2:2014, axis {result.axis}, {result.runs} runs per direction, {result.targets.size} targets; "
        f"deviations in {u}.</p>"
    )
    return head + intro + _section(result, conds, "ISO 230-2 plot") + "</body></html>\n"


def iso230_3_html(result: iso230_3.Iso230_3Result, title: str) -> str:
    """Return the ISO 230-3 page: one section per test, its figures and plot."""
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>{_STYLE}</head>"
        f"<body><h1>{html.escape(title)}</h1>"
    ]
    names = {
        "etve": "Environmental temperature variation error (ETVE)",
        "spindle": "Spindle rotation",
        "linear": "Moving linear axes",
    }
    for kind in ("etve", "spindle", "linear"):
        tests = getattr(result, kind)
        if not tests:
            continue
        parts.append(f"<h2>{names[kind]}</h2>")
        for t in tests:
            rows = [[k, *iso230_2.display(v, t.units[k])] for k, v in sorted(t.figures.items())]
            extra = f", room range {t.room_range_degC:.2f} °C" if t.room_range_degC is not None else ""
            if t.extra.get("follows_heat"):
                extra += "; follows a heated stage: the drift includes the machine cooling down"
            parts.append(
                f"<h3>{html.escape(t.stage)} ({(t.end_s - t.start_s) / 3600:.2f} h{extra})</h3>"
                + _table(["figure", "value", "unit"], rows)
                + _png(iso230_3.plot(t), t.stage)
            )
    parts.append("</body></html>\n")
    return "".join(parts)
