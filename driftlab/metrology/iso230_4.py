"""ISO 230-4:2022 circular tests of two linear axes (ballbar or probe circle) and what their shape says.

Input: the radial deviation ``dr`` (measured radius - nominal, mm) at angles ``theta`` (deg, from
the first axis towards the second) of a contouring run clockwise (``direction`` -1) and counter-
clockwise (+1), nominal radius ``R``. The figures of the standard:

* circular deviation G (per direction): the radial width of the band enclosing the path about the
  least-squares circle's centre;
* bidirectional circular deviation G(b): the same for both paths about one least-squares centre;
* circular hysteresis H: the largest radial difference between the two paths at one angle.

The errors the thesis reviews with the ballbar (ch. 2) leave shapes in the path, fitted by least
squares to both directions together (small errors, first order in R):

* out-of-squareness alpha (rad, the second axis leaning towards the first): ``R alpha / 2 sin 2theta``;
* scale mismatch (the first axis' scale minus the second's, dimensionless): ``R (e1 - e2) / 2 cos 2theta``;
* backlash b1, b2 (mm, each axis lags by half of it in the direction it moves): ``-(b1/2) sign(v1) cos
  theta - (b2/2) sign(v2) sin theta`` with the axes' velocity signs of the run's direction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, TypedDict

import numpy as np

from driftlab.errors import ValidationError
from driftlab.labels import UM


class CircleFinding(TypedDict):
    """An error diagnosed from the circular path's shape: which, how large (mm), in words."""

    kind: str  # "squareness", "scale_mismatch", "backlash_1" or "backlash_2"
    amplitude_mm: float
    text: str


class Iso230_4Record(TypedDict):
    """The JSON form of an :class:`Iso230_4Result` (lengths in mm, angles in rad)."""

    radius_mm: float
    G_mm: dict[str, float]
    H_mm: float
    centre_mm: list[float]
    squareness_rad: float
    scale_mismatch: float
    backlash_mm: list[float]
    residual_mm: float
    findings: list[CircleFinding]


@dataclass(frozen=True)
class Iso230_4Result:
    """The circular test's figures (mm) and the errors diagnosed from the path's shape."""

    radius_mm: float
    G: dict[str, float]  # "ccw", "cw", "bidirectional"
    H: float
    centre_mm: tuple[float, float]
    squareness_rad: float
    scale_mismatch: float
    backlash_mm: tuple[float, float]
    residual_mm: float  # what the shapes leave unexplained (RMS)
    findings: list[CircleFinding] = field(default_factory=list)

    def to_json_dict(self) -> Iso230_4Record:
        """Return the figures and findings as a JSON-ready dict (lengths in mm, angles in rad)."""
        return {
            "radius_mm": self.radius_mm,
            "G_mm": self.G,
            "H_mm": self.H,
            "centre_mm": list(self.centre_mm),
            "squareness_rad": self.squareness_rad,
            "scale_mismatch": self.scale_mismatch,
            "backlash_mm": list(self.backlash_mm),
            "residual_mm": self.residual_mm,
            "findings": self.findings,
        }


def _centre(theta: np.ndarray, dr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the least-squares circle's centre offset (a, b) and the deviations about it (small offsets)."""
    basis = np.column_stack([np.cos(theta), np.sin(theta), np.ones_like(theta)])
    coef, *_ = np.linalg.lstsq(basis, dr, rcond=None)
    return coef[:2], dr - basis[:, :2] @ coef[:2]


def evaluate(
    theta_deg: np.ndarray, direction: np.ndarray, dr_mm: np.ndarray, radius_mm: float, *, noise_mm: float = 0.0
) -> Iso230_4Result:
    """Return the ISO 230-4 figures of a bidirectional circular test and the errors its shape shows."""
    th = np.deg2rad(np.asarray(theta_deg, float))
    d = np.asarray(direction, int)
    dr = np.asarray(dr_mm, float)
    if not (np.isfinite(radius_mm) and radius_mm > 0):
        raise ValidationError(f"the nominal radius must be positive, got {radius_mm!r}")
    if not np.all(np.isfinite(dr)) or not np.all(np.isfinite(th)):
        raise ValidationError("the circle's angles and deviations must be finite numbers")
    runs = {"ccw": d > 0, "cw": d < 0}
    for name, sel in runs.items():
        if sel.sum() < 8:
            raise ValidationError(f"the {name} run has {int(sel.sum())} points: ISO 230-4 needs a full circle each way")
    G: dict[str, float] = {}
    for name, sel in runs.items():
        _, res = _centre(th[sel], dr[sel])
        G[name] = float(res.max() - res.min())
    centre, res_all = _centre(th, dr)
    G["bidirectional"] = float(res_all.max() - res_all.min())
    # hysteresis: the two paths compared at the same angles (the cw path interpolated onto the ccw angles)
    a_ccw, r_ccw = th[runs["ccw"]] % (2 * np.pi), res_all[runs["ccw"]]
    a_cw, r_cw = th[runs["cw"]] % (2 * np.pi), res_all[runs["cw"]]
    order = np.argsort(a_cw)
    cw_at = np.interp(a_ccw, a_cw[order], r_cw[order], period=2 * np.pi)
    H = float(np.abs(r_ccw - cw_at).max())
    # the shapes, by least squares over both runs: squareness, scale mismatch, backlash of each axis
    v1 = np.sign(-np.sin(th)) * d  # the first axis' velocity sign: x = R cos theta, theta grows with ccw
    v2 = np.sign(np.cos(th)) * d
    shapes = np.column_stack(
        [
            np.cos(th),
            np.sin(th),
            np.ones_like(th),
            radius_mm / 2.0 * np.sin(2 * th),
            radius_mm / 2.0 * np.cos(2 * th),
            -0.5 * v1 * np.cos(th),
            -0.5 * v2 * np.sin(th),
        ]
    )
    coef, *_ = np.linalg.lstsq(shapes, dr, rcond=None)
    residual = float(np.sqrt(np.mean((dr - shapes @ coef) ** 2)))
    alpha, mismatch, b1, b2 = (float(c) for c in coef[3:])
    result = Iso230_4Result(
        float(radius_mm), G, H, (float(centre[0]), float(centre[1])), alpha, mismatch, (b1, b2), residual
    )
    return _with_findings(result, max(noise_mm, residual))


def _with_findings(r: Iso230_4Result, noise_mm: float) -> Iso230_4Result:
    """Return the result with a finding for each shape larger than three times the unexplained RMS."""
    out: list[CircleFinding] = []
    floor = 3.0 * noise_mm
    size = {
        "squareness": abs(r.squareness_rad) * r.radius_mm / 2.0,
        "scale_mismatch": abs(r.scale_mismatch) * r.radius_mm / 2.0,
        "backlash_1": abs(r.backlash_mm[0]) / 2.0,
        "backlash_2": abs(r.backlash_mm[1]) / 2.0,
    }
    words = {
        "squareness": f"the axes are out of square by {r.squareness_rad * 1e6:.1f} µrad",
        "scale_mismatch": f"the axes' scales differ by {r.scale_mismatch * 1e6:.1f} µm/m",
        "backlash_1": f"the first axis has {r.backlash_mm[0] * 1e3:.2f} {UM} of backlash",
        "backlash_2": f"the second axis has {r.backlash_mm[1] * 1e3:.2f} {UM} of backlash",
    }
    for kind, amplitude in size.items():
        if amplitude > floor:
            out.append({"kind": kind, "amplitude_mm": amplitude, "text": words[kind]})
    return Iso230_4Result(
        r.radius_mm, r.G, r.H, r.centre_mm, r.squareness_rad, r.scale_mismatch, r.backlash_mm, r.residual_mm, out
    )


def read_circle_csv(path: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (angle deg, direction +1 ccw / -1 cw, radial deviation mm) of a circle CSV: columns ``angle_deg``,
    ``direction`` (ccw/cw or +1/-1) and ``deviation_um`` (or ``deviation_mm``)."""
    # lazy: pandas adds 0.55 s to `import driftlab.metrology.iso230_4` (measured); only the CSV reader needs it
    import pandas as pd

    try:
        frame = pd.read_csv(path, dtype=str, keep_default_na=False)
    except (OSError, pd.errors.ParserError, ValueError) as exc:
        raise ValidationError(f"{path}: cannot read the circle ({' '.join(str(exc).split())})") from None
    cols = {c.strip().lower(): c for c in frame.columns}
    if "angle_deg" not in cols or "direction" not in cols or not ({"deviation_um", "deviation_mm"} & set(cols)):
        raise ValidationError(f"{path}: needs columns angle_deg, direction and deviation_um (or deviation_mm)")
    words = {"ccw": 1, "+1": 1, "1": 1, "+": 1, "cw": -1, "-1": -1, "-": -1}
    dirs = [words.get(str(v).strip().lower()) for v in frame[cols["direction"]]]
    bad = next((i for i, v in enumerate(dirs) if v is None), None)
    if bad is not None:
        raise ValidationError(f"{path}:{bad + 2}: direction {frame[cols['direction']].iloc[bad]!r} is not ccw or cw")
    unit = "deviation_um" if "deviation_um" in cols else "deviation_mm"
    try:
        angle = frame[cols["angle_deg"]].astype(float).to_numpy()
        dev = frame[cols[unit]].astype(float).to_numpy() * (1e-3 if unit == "deviation_um" else 1.0)
    except ValueError as exc:
        raise ValidationError(f"{path}: {' '.join(str(exc).split())}") from None
    return angle, np.array(dirs, dtype=int), dev
