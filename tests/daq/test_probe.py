"""Touch probe: sphere fit, lobing compensation, exact bytes of the probing cycle, spindle angles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from driftlab.daq.probe import (
    LobingMap,
    TouchProbe,
    fit_sphere,
    sphere_pattern,
    spindle_angles,
    table_tilt,
)
from driftlab.daq.protocols import Prober
from driftlab.errors import InstrumentError, ValidationError
from tests.daq.protocol_helpers import expected_protocol

CENTRE = np.array([250.0, -120.0, 35.0])


def test_sphere_fit_recovers_known_centre_from_five_points():
    normals = sphere_pattern(CENTRE, 10.0)
    pts = CENTRE + 11.0 * normals
    centre, radius, rms = fit_sphere(pts)
    assert centre == pytest.approx(CENTRE, abs=1e-9) and radius == pytest.approx(11.0) and rms < 1e-9


def test_sphere_fit_with_noise():
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(40, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    pts = CENTRE + 12.7 * normals + rng.normal(scale=1e-4, size=(40, 3))
    centre, radius, rms = fit_sphere(pts)
    assert centre == pytest.approx(CENTRE, abs=1e-4) and radius == pytest.approx(12.7, abs=1e-4)
    assert 3e-5 < rms < 3e-4


def test_sphere_fit_rejects_degenerate_points():
    ring = np.column_stack([np.cos(np.arange(6)), np.sin(np.arange(6)), np.zeros(6)])
    with pytest.raises(ValidationError):
        fit_sphere(ring)
    with pytest.raises(ValidationError):
        fit_sphere(ring[:3])


def test_lobing_fit_and_compensation():
    truth = LobingMap(0.002, (3,), (0.0015,), (-0.0005,))
    az = np.linspace(0, 2 * np.pi, 18, endpoint=False)
    dirs = np.column_stack([np.cos(az), np.sin(az), np.zeros_like(az)])
    fitted = LobingMap.fit(dirs, truth.pretravel(dirs), harmonics=(3, 6))
    assert fitted.a0 == pytest.approx(0.002) and fitted.cos[0] == pytest.approx(0.0015)
    assert fitted.sin[0] == pytest.approx(-0.0005) and abs(fitted.cos[1]) < 1e-12
    # a vertical approach sees only the constant part
    assert float(fitted.pretravel(np.array([[0.0, 0.0, -1.0]]))[0]) == pytest.approx(0.002)
    # compensation steps back along the approach
    p = np.array([[10.0, 0.0, 0.0]])
    u = np.array([[-1.0, 0.0, 0.0]])
    assert fitted.compensate(p, u)[0] == pytest.approx([10.0 + float(truth.pretravel(u)[0]), 0.0, 0.0])


def _hit(x):
    return ("HIT " + ",".join(f"{v:.6f}" for v in x)).encode() + b"\n"


def test_probe_sphere_exact_bytes():
    true_centre = CENTRE + [0.004, -0.002, 0.003]
    reach = 10.0 + 1.0
    normals = sphere_pattern(CENTRE, 10.0)
    pairs = []
    for n in normals:
        start = CENTRE + (reach + 3.0) * n
        cmd = "PRB " + ",".join(f"{v + 0.0:.6f}" for v in (*start, *(-n), 6.0))
        # where the stylus centre meets the displaced sphere along -n
        w = start - true_centre
        b = w @ -n
        lam = -b - math.sqrt(b * b - (w @ w - reach**2))
        pairs.append((cmd.encode() + b"\n", _hit(start - lam * n)))
    assert pairs[0][0] == b"PRB 250.000000,-120.000000,49.000000,0.000000,0.000000,-1.000000,6.000000\n"
    with expected_protocol(TouchProbe, pairs) as probe:
        assert isinstance(probe, Prober)
        m = probe.probe_sphere("S1", CENTRE, 10.0)
    assert m.centre == pytest.approx(true_centre, abs=2e-6)
    assert m.radius_mm == pytest.approx(10.0, abs=2e-6) and m.name == "S1"


def test_probe_miss_is_an_instrument_error():
    pairs = [(b"PRB 0.000000,0.000000,10.000000,0.000000,0.000000,-1.000000,5.000000\n", b"MISS\n")]
    with expected_protocol(TouchProbe, pairs) as probe:
        with pytest.raises(InstrumentError, match="no trigger"):
            probe.probe_point([0, 0, 10], [0, 0, -1], 5.0)


def test_garbled_hit_is_retried():
    cmd = b"PRB 0.000000,0.000000,10.000000,0.000000,0.000000,-1.000000,5.000000\n"
    pairs = [(cmd, b"HIT 1.0,2.0\n"), (cmd, b"HIT 0.000000,0.000000,7.500000\n")]
    with expected_protocol(TouchProbe, pairs) as probe:
        assert list(probe.probe_point([0, 0, 10], [0, 0, -2], 5.0)) == [0.0, 0.0, 7.5]


def test_spindle_angles_from_four_sensors():
    spacing = 100.0
    alpha, beta, dx, dy = 2e-5, -3e-5, 0.004, -0.002
    # X sensors at the lower/upper level see dx and dx + beta L; Y sensors dy and dy - alpha L
    gaps = np.array([dx, dx + spacing * math.tan(beta), dy, dy - spacing * math.tan(alpha)])
    out = spindle_angles(gaps, spacing)
    assert float(out["alpha"]) == pytest.approx(alpha) and float(out["beta"]) == pytest.approx(beta)
    assert float(out["dx"]) == dx and float(out["dy"]) == dy
    stacked = spindle_angles(np.vstack([gaps, gaps]), spacing)
    assert stacked["beta"].shape == (2,)


def test_table_tilt_from_two_spheres():
    a0, b0 = np.array([0.0, 0.0, 50.0]), np.array([400.0, 0.0, 50.0])
    tilt = table_tilt(a0 + [0, 0, 0.001], b0 + [0, 0, 0.005], a0, b0)
    assert tilt == pytest.approx(math.atan(0.004 / 400.0))
