"""Correction engine: planted errors cancelled, sub-resolution carry, temperatures per block, files."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from driftlab.compensator.compensate import (
    ErrorModel,
    TemperatureTable,
    compensate_file,
    compensate_program,
    correct_points,
    quantise_carry,
)
from driftlab.compensator.gcode import Points, parse_program, subdivide
from driftlab.errors import ValidationError
from driftlab.physics import kinematics as k

RES_MM, RES_DEG = 0.0025, 0.001

#: a constant error field on the links and joints ahead of the rotary table (mm, rad)
PLANTED = {
    "T1": np.array([2e-5, -3e-5, 0.0, 0.021, -0.016, 0.034]),
    "phi_y": np.array([0.0, 1e-5, 0.0, 0.0, 0.011, 0.0]),
    "phi_x": np.array([-1e-5, 0.0, 0.0, 0.013, 0.0, -0.007]),
    "T3": np.array([0.0, 0.0, 0.0, 0.0, 0.0, -0.019]),
}


def constant_model(errors=PLANTED) -> ErrorModel:
    """Return a model that predicts the same element errors everywhere."""

    def predict(q, temps, direction):
        return {e: np.tile(v, (q.shape[0], 1)) for e, v in errors.items()}

    return ErrorModel(predict)


PROGRAM = (
    "%\n(five-axis test path)\nG90 G21 G1 F2000\n"
    "X-120.0 Y80.0 Z-150.0 A0.0 B0.0\n"
    "X-60.5 Y40.25 Z-120.0 A12.5 B-30.0\n"
    "X0 Y0 Z-100 A25.0 B15.0\n"
    "X75.125 Y-50 Z-130 A-20.0 B45.0\n"
    "G91 X10 Y10 A5 B-5\n"
    "G90 G0 Z0\nM30\n%\n"
)


def _workspace_translation(q_cmd: np.ndarray, q_nom: np.ndarray, errors) -> np.ndarray:
    """Return the (N, 3) tool-versus-part offset: real chain at q_cmd against ideal chain at q_nom."""
    T_real = k.machine_chain(q_cmd, errors)
    T_ideal = k.ideal_chain(q_nom)
    W = T_real @ k.affine_inverse(T_ideal)
    return W[:, :3, 3]


def test_planted_error_field_is_cancelled_within_resolution():
    p = parse_program(PROGRAM, "t.nc")
    result = compensate_program(p, constant_model(), {}, max_segment_mm=20.0, max_segment_deg=10.0)
    back = parse_program(result.text, "out.nc")
    pts = subdivide(p, 20.0, 10.0)
    assert back.n_blocks == pts.n > p.n_blocks  # long segments were cut
    n = pts.n
    errors = {e: np.tile(v, (n, 1)) for e, v in PLANTED.items()}
    q_nom = p.to_q(pts.nominal_int)
    before = _workspace_translation(q_nom, q_nom, errors)
    after = _workspace_translation(back.to_q(back.target_int), q_nom, errors)
    assert np.abs(before).max() > 5 * RES_MM  # the planted field matters
    assert np.abs(after).max() <= RES_MM * 1.001
    # orientation: alpha, beta of the work-space error within one angular step (carried remainder)
    T_real = k.machine_chain(back.to_q(back.target_int), errors)
    W = T_real @ k.affine_inverse(k.ideal_chain(q_nom))
    ab = k.htm_to_params(W)[:, :2]
    assert np.abs(ab).max() < np.deg2rad(RES_DEG) * 1.001
    assert result.max_correction["X"] > 0.01


def test_sub_resolution_corrections_accumulate_and_then_step():
    # a scale error of 1e-4 mm per mm on X: the correction creeps by 0.0001 mm per 1 mm block
    def predict(q, temps, direction):
        e = np.zeros((q.shape[0], 6))
        e[:, 3] = 1e-4 * q[:, 0]
        return {"phi_x": e}

    lines = ["G1 X0.0"] + [f"X{i}.0" for i in range(1, 61)]
    text = "\n".join(lines) + "\n"
    p = parse_program(text)
    out = compensate_program(p, ErrorModel(predict), {}).text.decode().splitlines()
    # nothing sent while the accumulated correction is under half of the 0.0025 mm step (the default:
    # the nearest step) ...
    assert out[:13] == lines[:13]
    # ... then whole steps, the remainder carried over
    assert out[13] == "X12.9975"
    assert out[37] == "X36.9975"
    assert out[38] == "X37.995"
    back = parse_program("\n".join(out) + "\n")
    sent = back.target_int[:, 0] * back.scale[0]
    desired = -1e-4 * np.arange(61)
    assert np.all(np.abs(sent - np.arange(61) - desired) <= 0.5 * RES_MM + 1e-12)


def test_hysteresis_is_an_option_of_the_grid():
    # a creeping X correction, -0.036 steps per 1 mm block: the default (rounding) sends the first
    # step once it passes half a step (X14), a hysteresis of 0.1 once it passes 0.6 (X17)
    def predict(q, temps, direction):
        e = np.zeros((q.shape[0], 6))
        e[:, 3] = 0.9e-4 * q[:, 0]
        return {"phi_x": e}

    p = parse_program("G1 X0.0\n" + "".join(f"X{i}.0\n" for i in range(1, 31)))
    pts = subdivide(p, 5.0, 5.0)
    first = [
        int(np.argmax(correct_points(p, pts, ErrorModel(predict), {}, **kw).steps[:, 0] != 0))
        for kw in ({}, {"hysteresis_steps": 0.1})
    ]
    assert first == [14, 17]


def _reference_carry(u: np.ndarray, s0: np.ndarray, hysteresis: float) -> np.ndarray:
    """Return the sequential definition: move only when more than 0.5 + hysteresis steps away, and
    then only as far as it takes to be back within that band (written as a loop, not as the window)."""
    out = np.empty(u.shape, dtype=np.int64)
    prev = s0.copy()
    band = 0.5 + hysteresis
    for i in range(u.shape[0]):
        for a in range(u.shape[1]):
            while u[i, a] - prev[a] > band:
                prev[a] += 1
            while prev[a] - u[i, a] > band:
                prev[a] -= 1
        out[i] = prev
    return out


@settings(max_examples=80, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 300),
    st.floats(0.01, 3.0),
    st.integers(1, 300),
    st.sampled_from([0.0, 0.1, 0.25, 0.45]),
)
def test_carry_quantiser_matches_sequential_definition_in_pieces(seed, n, sigma, cut, hysteresis):
    rng = np.random.default_rng(seed)
    u = np.cumsum(rng.normal(0, sigma, (n, 5)), axis=0)
    exact = rng.random(n) < 0.1
    u[exact] = np.round(u[exact])  # on the grid exactly
    s0 = rng.integers(-3, 4, 5)
    ref = _reference_carry(u, s0, hysteresis)
    np.testing.assert_array_equal(quantise_carry(u, s0, hysteresis), ref)
    assert np.all(np.abs(u - ref) <= 0.5 + hysteresis + 1e-12)
    cut = min(cut, n)
    first = quantise_carry(u[:cut], s0, hysteresis)
    second = quantise_carry(u[cut:], first[-1], hysteresis)
    np.testing.assert_array_equal(np.vstack([first, second]), ref)


def test_quantiser_follows_a_drift_within_its_band_not_a_step_behind():
    """A correction drifting over 40 steps (a warming machine) is followed within 0.5 + hysteresis of a
    step, and on average lags by the hysteresis only. The full-step rule (send once a whole step has
    accumulated) lagged by half a step on average: 1.25 um at 0.0025 mm, the cutting test's floor."""
    u = np.linspace(0.0, 40.0, 4001)[:, None] * np.ones((1, 5))
    lag = u - quantise_carry(u)  # the default: the nearest step
    assert np.all(np.abs(lag) <= 0.5 + 1e-12)
    assert abs(float(lag.mean())) < 0.02
    lag = u - quantise_carry(u, None, 0.1)
    assert np.all(np.abs(lag) <= 0.6 + 1e-12)
    assert abs(float(lag.mean()) - 0.1) < 0.02
    full_step = _reference_carry(u, np.zeros(5, dtype=np.int64), 0.4999)  # about the old rule
    assert float((u - full_step).mean()) > 0.45
    with pytest.raises(ValueError, match="hysteresis"):
        quantise_carry(u, None, 0.5)


def test_quantiser_hysteresis_keeps_noise_from_toggling_a_step():
    """A correction sitting on a step's half-way point with noise of 0.03 steps: rounding (the default)
    toggles on every other point, a hysteresis of 0.1 step (``--hysteresis-steps 0.1``) sends one step
    change at most."""
    rng = np.random.default_rng(3)
    u = (0.5 + 0.03 * rng.standard_normal(500))[:, None]
    assert int(np.count_nonzero(np.diff(quantise_carry(u, None, 0.1)[:, 0]))) <= 1
    assert int(np.count_nonzero(np.diff(quantise_carry(u)[:, 0]))) > 100


def test_streaming_in_pieces_equals_one_go():
    p = parse_program(PROGRAM)
    pts = subdivide(p, 7.0, 3.0)
    model = constant_model()
    whole = correct_points(p, pts, model, {})
    cut = pts.n // 2
    a = correct_points(p, Points(pts.block[:cut], pts.nominal_int[:cut]), model, {})
    b = correct_points(
        p,
        Points(pts.block[cut:], pts.nominal_int[cut:]),
        model,
        {},
        state=a.steps[-1],
        prev_nominal=pts.nominal_int[cut - 1],
        prev_direction=a.direction[-1],
    )
    np.testing.assert_array_equal(np.vstack([a.sent_int, b.sent_int]), whole.sent_int)
    np.testing.assert_array_equal(np.vstack([a.direction, b.direction]), whole.direction)


def _temperature_model() -> ErrorModel:
    """Return a model whose spindle-head growth follows channel T9: dz = 0.01 mm/degC above 20 degC."""

    def predict(q, temps, direction):
        t9 = np.asarray(temps["T9"], dtype=float)
        e = np.zeros((q.shape[0], 6))
        e[:, 5] = 0.01 * (np.broadcast_to(t9, (q.shape[0],)) - 20.0)
        return {"T1": e}

    return ErrorModel(predict, channels=("T9",))


def test_latest_scan_or_nearest_scan_per_block_time(tmp_path):
    csv = tmp_path / "temperatures.csv"
    pd.DataFrame({"time_s": [0.0, 100.0, 200.0], "T9": [20.0, 22.0, np.nan], "T49": [19.0, 19.5, 19.7]}).to_csv(
        csv, index=False
    )
    table = TemperatureTable.read_csv(csv)
    assert table.latest() == {"T9": 22.0, "T49": 19.7}  # missing reading carried forward
    timed = "(T=0)\nG1 X0 Z0\n(T=90)\nZ-10\n(T=190)\nZ-20\n"
    p = parse_program(timed)
    out = compensate_program(p, _temperature_model(), table, max_segment_mm=50).text.decode().splitlines()
    # T1 dz grows the head by +dz: the compensation lowers Z by the same amount
    assert out[1] == "G1 X0 Z0"  # 20 degC at t = 0: no error
    assert out[3] == "Z-10.02"  # nearest scan to t = 90 s: 22 degC
    assert out[5] == "Z-20.02"
    plain = parse_program("G1 X0 Z0\nZ-10\n")
    out = compensate_program(plain, _temperature_model(), table, max_segment_mm=50)
    assert out.text.decode().splitlines() == ["G1 X0 Z-0.02", "Z-10.02"]
    assert out.temperatures == "latest scan"


def _lag_document() -> dict:
    """Return a document whose head grows 0.01 mm per degC of the one-hour lag of T9 (ch. 5.3)."""
    return {
        "machine": "m1",
        "inputs": {"T9": {"reference": 20.0, "min": 10.0, "max": 40.0}},
        "terms": [
            {
                "element": "T1",
                "param": "dz",
                "features": [{"kind": "lag", "name": "lag3600[T9]", "channels": ["T9"], "tau_s": 3600.0}],
                "coefficients": [0.01],
                "statistics": {"rmse_train": 0.0},
            }
        ],
    }


def test_a_lagged_term_takes_the_lag_of_the_whole_temperature_log_however_the_program_is_batched():
    """The scans before the program (the machine warming since 0 s) set the lag at its first block."""
    from driftlab.physics.lag import first_order_lag

    t = np.arange(0.0, 7201.0, 60.0)
    temps = 20.0 + t / 720.0  # 5 degC per hour since the log began
    table = TemperatureTable.from_frame(pd.DataFrame({"time_s": t, "T9": temps}))
    timed = "".join(f"(T={3600 + 60 * k})\nG1 X{k} Z0\n" for k in range(40))
    model = ErrorModel.from_document(_lag_document())
    one = compensate_program(parse_program(timed), model, table, max_segment_mm=500).text
    small = compensate_program(parse_program(timed), model, table, max_segment_mm=500, chunk_points=3).text
    assert one == small
    lag = first_order_lag(temps, t, 3600.0)
    first = one.decode().splitlines()[1]
    # at 3600 s the lagged T9 is about 21.9 degC, not the 25 degC it reads: Z-0.0187 at the 0.0025 mm step
    want = -0.01 * (lag[60] - 20.0)
    assert first == f"G1 X0 Z{round(want / RES_MM) * RES_MM:.4f}"
    assert abs(want) < 0.02  # the settled lag would be -0.05
    latest = table.latest(model.channels, model.lag_taus)
    assert latest.lagged[("T9", 3600.0)] == pytest.approx(lag[-1])  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    "content,needle",
    [
        ("time_s,T9\n0,20\n-5,21\n", ":3: time_s goes backwards"),
        ("time_s,T9\n0,abc\n", ":2: T9 is not a number"),
        ("T9\n20\n", ":1: no time_s column"),
    ],
)
def test_bad_temperature_file(tmp_path, content, needle):
    path = tmp_path / "t.csv"
    path.write_text(content)
    with pytest.raises(ValidationError, match=needle):
        TemperatureTable.read_csv(path)


def test_model_channel_without_reading_is_refused(tmp_path):
    table = TemperatureTable.from_frame(pd.DataFrame({"time_s": [0.0], "T49": [20.0]}))
    with pytest.raises(ValidationError, match="T9"):
        compensate_program(parse_program("G1 X1\n"), _temperature_model(), table)


def test_bad_program_writes_nothing(tmp_path):
    src = tmp_path / "bad.nc"
    src.write_text("G1 X1\nG1 X2\nG3 X1 Y1 R5\n")
    out = tmp_path / "out.nc"
    with pytest.raises(ValidationError) as exc:
        compensate_file(src, constant_model(), {}, out)
    assert f"{src}:3:" in str(exc.value)
    assert not out.exists() and not list(tmp_path.glob("out.nc*"))


def test_registry_document_drives_the_correction(tmp_path):
    doc = {
        "machine": "vmc-5ax-01",
        "version": 3,
        "inputs": {"T9": {"reference": 20.0, "min": 15.0, "max": 40.0}},
        "terms": [
            {
                "element": "T1",
                "param": "dz",
                "features": [{"kind": "dT", "name": "dT[T9]", "channels": ["T9"]}],
                "coefficients": [0.01],
                "statistics": {"rmse_train": 0.001},
            },
        ],
    }
    model = ErrorModel.from_document(doc)
    assert model.label == "vmc-5ax-01 v3" and model.channels == ("T9",)
    src = tmp_path / "p.nc"
    src.write_text("G1 X0 Z0\nZ-4\n")
    result = compensate_file(src, model, {"T9": 25.0}, tmp_path / "o.nc")
    assert (tmp_path / "o.nc").read_text().splitlines() == ["G1 X0 Z-0.05", "Z-4.05"]
    assert result.max_correction["Z"] == pytest.approx(0.05)


def _all_kinds_doc() -> dict:
    """Return a document using every feature kind of models.features."""
    f = lambda kind, name, **kw: {"kind": kind, "name": name, **kw}  # noqa: E731
    feats = [
        f("intercept", "const"),
        f("position", "pos", label="X", power=1),
        f("position", "pos^2", label="X", power=2),
        f("position", "pos^3", label="Y", power=3),
        f("direction", "dir", label="X"),
        f("dT", "dT[T9]", channels=["T9"]),
        f("lag", "lag900[T10]", channels=["T10"], tau_s=900.0),
        f("mean", "mean[col]", channels=["T9", "T10", "T11"], label="col"),
        f("gradient", "grad[T9-T11]", channels=["T9", "T11"]),
        f("pos_dT", "pos*dT[T10]", channels=["T10"], label="A"),
        # a structure's two sides of several sites each (eqs. 3.4-3.5): split after the first two
        f("gradient", "grad[upper-lower]", channels=["T9", "T10", "T11"], power=2, label="upper-lower"),
    ]
    coefs = [0.003, 1e-5, -2e-8, 3e-11, 0.0012, 0.004, -0.002, 0.001, 0.0007, 1.5e-3, 0.0021]
    inputs = {c: {"reference": 20.0 + i, "min": 10.0, "max": 40.0} for i, c in enumerate(["T9", "T10", "T11"])}
    terms = [
        {
            "element": "phi_x",
            "param": "dx",
            "features": feats,
            "coefficients": coefs,
            "statistics": {"rmse_train": 0.0},
        },
        {
            "element": "T2",
            "param": "beta",
            "features": feats[5:9],
            "coefficients": [1e-6, 2e-6, -1e-6, 5e-7],
            "statistics": {"rmse_train": 0.0},
        },
    ]
    return {"machine": "m", "version": 1, "inputs": inputs, "terms": terms}


def test_fast_prediction_equals_the_registry_for_every_feature_kind():
    from driftlab.compensator.compensate import fast_predict
    from driftlab.models import document as documents

    doc = documents.validate_document(_all_kinds_doc())
    rng = np.random.default_rng(3)
    n = 50
    q = np.column_stack([rng.uniform(-300, 300, (n, 3)), rng.uniform(-1, 1, (n, 2))])
    direction = rng.choice([-1.0, 1.0], size=(n, 5))
    snapshot = {"T9": 24.0, "T10": 19.5, "T11": 23.25, "T49": 18.0}
    frame = pd.DataFrame({"T9": rng.uniform(18, 30, n), "T10": rng.uniform(18, 30, n), "T11": rng.uniform(18, 30, n)})
    fast = fast_predict(doc)
    for temps in (snapshot, frame, frame.iloc[:1]):
        want = documents.predict_element_errors(doc, temps, q, direction)
        got = fast(q, temps, direction)
        assert set(got) == set(want)
        for e in want:
            np.testing.assert_allclose(got[e], want[e], rtol=1e-12, atol=1e-15)
    assert ErrorModel.from_document(doc).predict.__name__ == "predict"  # the fast path was accepted


def test_model_falls_back_to_the_registry_when_the_fast_path_disagrees(monkeypatch, caplog):
    from driftlab.models import document as documents

    real = documents.predict_element_errors

    def changed(doc, temps, q, direction=None):
        out = real(doc, temps, q, direction)
        return {e: v * 1.5 for e, v in out.items()}

    monkeypatch.setattr(documents, "predict_element_errors", changed)
    model = ErrorModel.from_document(_all_kinds_doc())
    assert model.predict.__name__ == "slow"
    assert "registry" in caplog.text


def test_sub_resolution_angle_corrections_accumulate_and_the_tool_point_holds():
    # an A-axis angular error growing 2e-4 rad per rad of A: 0.0001 deg per 0.5 deg block
    def predict(q, temps, direction):
        e = np.zeros((q.shape[0], 6))
        e[:, 0] = 2e-4 * q[:, 3]
        return {"theta_x": e}

    text = "G1 X0 Y0 Z-100 A0.0\n" + "".join(f"A{0.5 * i:.1f}\n" for i in range(1, 31))
    p = parse_program(text)
    out = compensate_program(p, ErrorModel(predict), {}, max_segment_mm=1000).text
    back = parse_program(out)
    assert back.n_blocks == p.n_blocks
    a_sent = back.target_int[:, 3] * back.scale[3]
    a_nom = p.target_int[:, 3] * p.scale[3]
    desired = np.rad2deg(correct_points(p, subdivide(p, 1000, 5), ErrorModel(predict), {}).desired[:, 3])
    assert np.all(np.abs(desired[a_nom < 4.9]) < RES_DEG) and desired[-1] < -2 * RES_DEG
    steps = np.round((a_sent - a_nom) / RES_DEG).astype(int)
    small = np.abs(desired) < 0.5 * RES_DEG - 1e-9
    assert small.sum() >= 5 and np.all(steps[small] == 0)  # under half a step: nothing sent on A yet
    assert steps[-1] <= -2 and np.all(np.abs(a_sent - a_nom - desired) <= 0.5 * RES_DEG + 1e-9)
    # the unsent remainder of A is taken up by Y, Z: the tool point stays within the linear resolution
    q_cmd = back.to_q(back.target_int)
    q_nom = p.to_q(p.target_int)
    n = q_nom.shape[0]
    errors = {"theta_x": np.column_stack([2e-4 * q_nom[:, 3], np.zeros((n, 5))])}
    assert np.abs(_workspace_translation(q_cmd, q_nom, errors)).max() <= RES_MM * 1.001
