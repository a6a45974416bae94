"""The ISO 230-2 and demo reports in Chromium: every plot shown whole at the page's width, the ISO 230-2 legend
clear of the data, the figures line inside the picture, the demo's three maps on one colour scale."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from driftlab.commands import demo_report
from driftlab.metrology import iso230_2, report
from tests.api.browser import OfflinePage, browser


def _runs(n_runs: int = 6, seed: int = 4) -> iso230_2.Iso230_2Result:
    """Bidirectional runs over 11 targets with a 6 um reversal, a slope and noise (mm)."""
    rng = np.random.default_rng(seed)
    targets = np.linspace(0.0, 250.0, 11)
    pos, d, x = [], [], []
    for _ in range(n_runs):
        for direction, order in ((1, targets), (-1, targets[::-1])):
            pos += list(order)
            d += [direction] * order.size
            x += list(2e-5 * order + 0.003 * direction + rng.normal(0, 0.0008, order.size))
    return iso230_2.evaluate(np.array(pos), np.array(d), np.array(x))


def test_iso230_2_plot_keeps_its_legend_off_the_data_and_its_figures_inside() -> None:
    import matplotlib.pyplot as plt

    fig = iso230_2.plot(_runs())
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    [ax] = fig.axes
    legend = ax.get_legend().get_window_extent(renderer)
    plot_area = ax.get_window_extent(renderer)
    assert legend.x0 >= plot_area.x1  # beside the plot, never over a curve
    [figures] = [t for t in ax.texts if "B̄ =" in t.get_text()]
    assert figures.get_fontsize() >= 9 and "µm" in figures.get_text() and "e-" not in figures.get_text()
    box = figures.get_window_extent(renderer)
    assert box.y1 <= plot_area.y0  # beneath the plot, not over it
    # what the page embeds (bbox_inches="tight") holds the legend and the figures line whole
    tight = fig.get_tightbbox(renderer)
    assert tight.x1 * fig.dpi >= legend.x1 - 1 and tight.y0 * fig.dpi <= box.y0 + 1
    plt.close(fig)


def _shown_whole(page, tmp_path, name: str) -> list[dict]:
    """Return every <img> of the loaded page with its size, after a full-page screenshot."""
    shot = tmp_path / f"{name}.png"
    page.screenshot(path=str(shot), full_page=True)
    assert Image.open(shot).size[0] == 1100
    imgs = page.eval_on_selector_all(
        "img",
        "els => els.map(e => ({w: e.naturalWidth, shown: e.getBoundingClientRect().width,"
        " right: e.getBoundingClientRect().right, alt: e.alt}))",
    )
    width = page.evaluate("document.documentElement.clientWidth")
    assert page.evaluate("document.documentElement.scrollWidth") <= width  # nothing runs off to the side
    for img in imgs:
        assert img["w"] > 0 and 0 < img["shown"] and img["right"] <= width  # decoded, and inside the page
    return imgs


def test_reports_render_whole_in_chromium(tmp_path) -> None:
    drifting = _runs(n_runs=8)
    iso = tmp_path / "iso.html"
    iso.write_text(report.iso230_2_html(drifting, "ISO 230-2: test, axis X", [("date", "2026-03-02")]))
    rng = np.random.default_rng(0)
    dev = {
        "uncompensated": rng.normal(0, 0.03, (99, 15)),
        "offline": rng.normal(0, 0.005, (99, 15)),
        "online": rng.normal(0, 0.003, (99, 15)),
    }
    table = {k: {"rmse_mm": float(np.sqrt(np.mean(v**2))), "max_mm": float(np.max(np.abs(v)))} for k, v in dev.items()}
    doc = demo_report.build_report(table=table, diagnosis={"effects": []}, steps=[], extra={"wall_s": 60.0})
    demo = tmp_path / "demo.html"
    demo.write_text(demo_report.to_html(doc, demo_report.surface_figure(dev)))
    with browser() as b:
        view = OfflinePage(b, width=1100, height=900)
        try:
            view.page.goto(iso.as_uri())
            [plot] = _shown_whole(view.page, tmp_path, "iso")
            assert plot["alt"] == "ISO 230-2 plot"
            text = view.page.inner_text("body")
            assert "Test conditions" in text and "B̄ (mean reversal value)" in text and "µm" in text
            view.page.goto(demo.as_uri())
            [maps] = _shown_whole(view.page, tmp_path, "demo")
            assert "one colour scale" in maps["alt"]
            assert "as in the thesis" not in view.page.inner_text("table")
            # one scale, as the reader sees it: the uncompensated map (errors ten times larger) is saturated, the
            # compensated ones stay near the scale's pale middle (each on its own scale, all three would look alike)
            png = np.asarray(Image.open(io.BytesIO(view.page.locator("img").screenshot())).convert("RGB"), float)
            h, w, _ = png.shape
            maps = png[int(0.2 * h) : int(0.8 * h), : int(0.88 * w)]  # the maps' band, left of the colour bar
            third = maps.shape[1] // 3
            colour = [float(np.mean(np.ptp(maps[:, i * third : (i + 1) * third], axis=2))) for i in range(3)]
            assert colour[0] > 2.5 * colour[1] and colour[0] > 2.5 * colour[2], colour
        finally:
            view.close()
        assert not view.errors and not view.external
