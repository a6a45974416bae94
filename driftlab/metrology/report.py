"""HTML pages of the ISO 230-2 and ISO 230-3 reports (plots embedded as PNG)."""

from __future__ import annotations

import base64
import html
import io
from typing import Any

from driftlab.metrology import iso230_2, iso230_3


def _png(fig: Any, alt: str) -> str:
    """Return a matplotlib figure as an embedded base64 PNG <img> tag (and close it)."""
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
    "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}</style>"
)


def iso230_2_html(result: iso230_2.Iso230_2Result, title: str) -> str:
    """Return the ISO 230-2 page: the axis figures, the per-target table and the standard's plot."""
    u = result.unit
    figs = _table(["figure", f"value ({u})"], [[k, f"{result.figures[k]:.6g}"] for k in iso230_2.FIGURES])
    rows = [
        [
            f"{p:g}",
            *(
                f"{v:.6g}"
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
    per = _table(["target", "xbar up", "xbar down", "s up", "s down", "B_j", "R_j"], rows)
    return (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>{_STYLE}</head><body>"
        f"<h1>{html.escape(title)}</h1><p>ISO 230-2:2014, axis {result.axis}, {result.runs} runs per direction, "
        f"{result.targets.size} targets; deviations in {u}.</p>{_png(iso230_2.plot(result), 'ISO 230-2 plot')}"
        f"<h2>Axis figures</h2>{figs}<h2>Per target</h2>{per}</body></html>\n"
    )


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
            rows = [[k, f"{v:.6g}", t.units[k]] for k, v in sorted(t.figures.items())]
            extra = f", room range {t.room_range_degC:.3f} degC" if t.room_range_degC is not None else ""
            parts.append(
                f"<h3>{html.escape(t.stage)} ({(t.end_s - t.start_s) / 3600:.2f} h{extra})</h3>"
                + _table(["figure", "value", "unit"], rows)
                + _png(iso230_3.plot(t), t.stage)
            )
    parts.append("</body></html>\n")
    return "".join(parts)
