"""ISO 230-4 circular tests: the figures against an independent circle fit, and planted errors recovered."""

from __future__ import annotations

import re

import numpy as np
import pytest

from driftlab.cli import main
from driftlab.metrology import iso230_4

R = 150.0


def circle(alpha=0.0, mismatch=0.0, b1=0.0, b2=0.0, centre=(0.002, -0.001), noise=0.0001, seed=0, n=360):
    """A ccw and a cw run: the machine's actual path for a commanded circle of radius R, as radial deviations."""
    rng = np.random.default_rng(seed)
    th = np.deg2rad(np.arange(n) * 360.0 / n)
    out = []
    for d in (1, -1):
        x, y = R * np.cos(th), R * np.sin(th)
        vx, vy = -np.sin(th) * d, np.cos(th) * d
        # scale mismatch split between the axes, squareness (the second axis leans), backlash (half, lagging)
        xa = x * (1 + mismatch / 2) + alpha * y - np.sign(vx) * b1 / 2 + centre[0]
        ya = y * (1 - mismatch / 2) - np.sign(vy) * b2 / 2 + centre[1]
        dr = np.hypot(xa, ya) - R + rng.normal(0, noise, th.size)
        out.append((np.rad2deg(th), np.full(th.size, d), dr))
    return tuple(np.concatenate(c) for c in zip(*out))


def kasa_width(theta_deg, dr):
    """Band width of a path about its algebraic (Kasa) least-squares circle: an independent fit in x, y."""
    th = np.deg2rad(theta_deg)
    x, y = (R + dr) * np.cos(th), (R + dr) * np.sin(th)
    A = np.column_stack([x, y, np.ones_like(x)])
    (a, b, c), *_ = np.linalg.lstsq(A, x**2 + y**2, rcond=None)
    cx, cy = a / 2, b / 2
    r = np.hypot(x - cx, y - cy)
    return r.max() - r.min()


def test_circular_deviation_and_hysteresis_match_an_independent_fit():
    th, d, dr = circle(alpha=20e-6, b1=0.004, seed=1)
    res = iso230_4.evaluate(th, d, dr, R)
    for name, sel in (("ccw", d > 0), ("cw", d < 0)):
        assert res.G[name] == pytest.approx(kasa_width(th[sel], dr[sel]), abs=2e-5)
    assert res.G["bidirectional"] == pytest.approx(kasa_width(th, dr), abs=2e-5)
    assert res.G["bidirectional"] >= max(res.G["ccw"], res.G["cw"]) - 1e-12
    # hysteresis: the backlash opens the two paths by up to b1 where the first axis reverses
    assert 0.003 < res.H < 0.0055


def test_planted_squareness_scale_and_backlash_are_recovered():
    th, d, dr = circle(alpha=20e-6, mismatch=10e-6, b1=0.004, b2=0.002, seed=2)
    res = iso230_4.evaluate(th, d, dr, R)
    assert res.squareness_rad == pytest.approx(20e-6, rel=0.1)
    assert res.scale_mismatch == pytest.approx(10e-6, rel=0.15)
    assert res.backlash_mm[0] == pytest.approx(0.004, rel=0.1) and res.backlash_mm[1] == pytest.approx(0.002, rel=0.15)
    assert {f["kind"] for f in res.findings} == {"squareness", "scale_mismatch", "backlash_1", "backlash_2"}
    assert "out of square by 20" in next(f["text"] for f in res.findings if f["kind"] == "squareness")
    clean = iso230_4.evaluate(*circle(seed=3), R)
    assert clean.findings == [] and clean.G["ccw"] < 0.001


def test_cli_part4_reads_a_circle_csv(tmp_path, capsys):
    import json

    th, d, dr = circle(alpha=30e-6, seed=4)
    src = tmp_path / "circle.csv"
    rows = ["angle_deg,direction,deviation_um"] + [
        f"{a:.3f},{'ccw' if k > 0 else 'cw'},{v * 1e3:.5f}" for a, k, v in zip(th, d, dr)
    ]
    src.write_text("\n".join(rows) + "\n")
    out = tmp_path / "c.json"
    assert main(["iso230", str(src), "--part", "4", "--radius", str(R), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ISO 230-4" in text and "µm" in text and re.search(r"out of square by (29|30)\.\d µrad", text)
    doc = json.loads(out.read_text())
    assert doc["squareness_rad"] == pytest.approx(30e-6, rel=0.1) and set(doc["G_mm"]) == {"ccw", "cw", "bidirectional"}
    src.write_text("angle_deg,direction,deviation_um\n0,sideways,1\n")
    assert main(["iso230", str(src), "--part", "4", "--radius", "150"]) == 2
    assert "direction 'sideways' is not ccw or cw" in capsys.readouterr().err
