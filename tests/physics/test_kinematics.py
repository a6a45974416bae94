"""HTM chain of ch. 4: closed form, small-angle errors, inverse, allocation, compensation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from driftlab.errors import KinematicsError
from driftlab.physics import kinematics as k

# appendix-A-sized errors: links up to ~0.08 mm and ~25 urad (table A.2), joints similar (A.3, A.4)
ANG, LIN = 30e-6, 0.08


def random_q(rng: np.random.Generator, n: int, a_max: float = np.pi / 4) -> np.ndarray:
    return np.column_stack(
        [
            rng.uniform(-254, 254, n),
            rng.uniform(-254, 254, n),
            rng.uniform(-254, 254, n),
            rng.uniform(-a_max, a_max, n),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )


def random_errors(rng: np.random.Generator, n: int, names=k.ELEMENTS) -> dict[str, np.ndarray]:
    scale = np.array([ANG, ANG, ANG, LIN, LIN, LIN])
    return {e: rng.uniform(-1, 1, (n, 6)) * scale for e in names}


def naive_chain(q: np.ndarray, errors: dict | None = None) -> np.ndarray:
    """The chain as plain 4x4 products of eqs. 4.13-4.18 (independent of the fast kernels)."""
    errors = errors or {}
    out = np.broadcast_to(np.eye(4), (len(q), 4, 4))
    for name in k.ELEMENTS:
        out = out @ k.element_htm(name, q, errors.get(name))
    return out


def rz(c):
    return k.rot_htm("z", c)


# ------------------------------------------------------------------ chain and closed form


def test_table_a1_dimensions():
    assert k.TABLE_A1["T1"] == (0.0, -400.0, -200.0)
    assert k.TABLE_A1["T2"] == (0.0, 400.0, 1200.0)
    assert k.TABLE_A1["T6"] == (0.0, 0.0, -400.0)
    # at home the part origin sits at the tool tip
    np.testing.assert_allclose(k.ideal_chain(np.zeros((1, 5)))[0], np.eye(4), atol=1e-12)


def test_zero_error_chain_equals_closed_form_eq_4_19():
    rng = np.random.default_rng(0)
    q = random_q(rng, 1000)
    closed = k.ideal_chain(q)
    np.testing.assert_allclose(k.machine_chain(q), closed, rtol=0, atol=1e-9)
    np.testing.assert_allclose(naive_chain(q), closed, rtol=0, atol=1e-9)
    # orientation is Rx(theta_x) @ Ry(theta_y) and independent of X, Y, Z (eq. 4.19)
    rot = (k.rot_htm("x", q[:, 3]) @ k.rot_htm("y", q[:, 4]))[:, :3, :3]
    np.testing.assert_allclose(closed[:, :3, :3], rot, atol=1e-12)


def test_closed_form_position_by_hand():
    # A = 90 deg, B = 0: T5 (0,0,-200) and T6 (0,0,-400) turn from -Z into +Y... Rx(90) e_z = -e_y
    q = np.array([[10.0, 20.0, 30.0, np.pi / 2, 0.0]])
    pos = k.ideal_chain(q)[0, :3, 3]
    np.testing.assert_allclose(pos, [10.0, 20.0 + 600.0, 30.0 + 600.0], atol=1e-9)


def test_chain_with_errors_equals_plain_products():
    rng = np.random.default_rng(1)
    q = random_q(rng, 300)
    errs = random_errors(rng, 300)
    np.testing.assert_allclose(k.machine_chain(q, errs), naive_chain(q, errs), atol=1e-9)
    # constant (6,) errors broadcast over the poses
    const = {"T2": errs["T2"][0], "theta_y": errs["theta_y"][0]}
    full = {n: np.broadcast_to(v, (300, 6)) for n, v in const.items()}
    np.testing.assert_allclose(k.machine_chain(q, const), naive_chain(q, full), atol=1e-9)


def test_chunked_kernel_matches_across_chunk_boundaries(monkeypatch):
    rng = np.random.default_rng(2)
    q = random_q(rng, 1000)
    errs = random_errors(rng, 1000)
    whole = k.machine_chain(q, errs)
    monkeypatch.setattr(k, "CHUNK", 97)
    np.testing.assert_allclose(k.machine_chain(q, errs), whole, atol=1e-12)
    # column-major errors (read without copying) give the same chain
    fortran = {n: np.asfortranarray(v) for n, v in errs.items()}
    np.testing.assert_allclose(k.machine_chain(q, fortran), whole, atol=1e-12)
    # a NaN in the last chunk is found
    errs["T4"][-1, 2] = np.nan
    with pytest.raises(KinematicsError, match="T4"):
        k.machine_chain(q, errs)
    with pytest.raises(KinematicsError, match="NaN"):
        k.compensate(q, {"T1": np.array([0, 0, np.inf, 0, 0, 0])})


def test_single_axis_errors_show_up_where_physics_says():
    q = np.array([[100.0, 0.0, 0.0, 0.0, 0.0]])
    # positioning error of X (eq. 4.14): the tool tip moves by dx along X
    w = k.workspace_error(q, {"phi_x": np.array([0, 0, 0, 0.01, 0, 0])})
    np.testing.assert_allclose(w[0], [0, 0, 0, 0.01, 0, 0], atol=1e-12)
    # a tilt of the support acts through the 400 mm of the part table T6 (Abbe): dy = 400 alpha
    w = k.workspace_error(np.zeros((1, 5)), {"T5": np.array([1e-5, 0, 0, 0, 0, 0])})
    np.testing.assert_allclose(w[0], [1e-5, 0, 0, 0, 400 * 1e-5, 0], atol=1e-12)
    # HTMs put a link's angle error at its far end (ch. 4.2): the part table's own tilt has no arm
    w = k.workspace_error(np.zeros((1, 5)), {"T6": np.array([1e-5, 0, 0, 0, 0, 0])})
    np.testing.assert_allclose(w[0], [1e-5, 0, 0, 0, 0, 0], atol=1e-12)


# ------------------------------------------------------------------ small-angle matrix


def test_error_htm_is_eq_4_8():
    e = k.error_htm(np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]))
    np.testing.assert_array_equal(e, [[1, -3, 2, 4], [3, 1, -1, 5], [-2, 1, 1, 6], [0, 0, 0, 1]])
    np.testing.assert_array_equal(k.htm_to_params(e), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0])


def test_small_angle_matrix_differs_from_exact_rotation_at_second_order():
    rng = np.random.default_rng(3)
    direction = rng.uniform(-1, 1, (200, 3))
    diffs = []
    for eps in (1e-2, 1e-3, 1e-4):
        a, b, c = (eps * direction).T
        exact = k.rot_htm("x", a) @ k.rot_htm("y", b) @ k.rot_htm("z", c)
        p = np.column_stack([a, b, c, np.zeros((200, 3))])
        diffs.append(np.abs(k.error_htm(p) - exact).max())
    # first-order terms agree, so the difference shrinks 100x for a 10x smaller angle
    assert diffs[0] < 2e-4
    np.testing.assert_allclose(diffs[0] / diffs[1], 100, rtol=0.05)
    np.testing.assert_allclose(diffs[1] / diffs[2], 100, rtol=0.05)


# ------------------------------------------------------------------ inverses


def test_htm_inverse_times_matrix_is_identity():
    rng = np.random.default_rng(4)
    T = k.ideal_chain(random_q(rng, 500))
    eye = np.broadcast_to(np.eye(4), T.shape)
    np.testing.assert_allclose(k.htm_inverse(T) @ T, eye, atol=1e-12)
    np.testing.assert_allclose(T @ k.htm_inverse(T), eye, atol=1e-12)


def test_affine_inverse_is_exact_for_small_angle_products():
    rng = np.random.default_rng(5)
    q = random_q(rng, 500)
    T = k.machine_chain(q, random_errors(rng, 500))
    eye = np.broadcast_to(np.eye(4), T.shape)
    np.testing.assert_allclose(k.affine_inverse(T) @ T, eye, atol=1e-12)
    # eq. 4.22 (transpose) is only first-order exact on non-orthonormal eq. 4.8 products
    assert np.abs(k.htm_inverse(T) @ T - eye).max() > 1e-11


def test_inverse_rejects_bad_shapes():
    with pytest.raises(KinematicsError):
        k.htm_inverse(np.eye(3))
    with pytest.raises(KinematicsError):
        k.affine_inverse(np.zeros((4, 4)))


# ------------------------------------------------------------------ allocation (eq. 4.20)


@pytest.mark.parametrize("element", k.ELEMENTS)
def test_allocation_round_trip_recovers_planted_error(element):
    rng = np.random.default_rng(abs(hash(element)) % 2**32)
    n = 400
    q = random_q(rng, n)
    errs = random_errors(rng, n)
    W = k.workspace_error_htm(q, errs)
    known = {e: v for e, v in errs.items() if e != element}
    np.testing.assert_allclose(k.allocate(W, q, known, element), errs[element], rtol=0, atol=1e-10)
    # its own entry is the unknown: ignored
    np.testing.assert_allclose(
        k.allocate(W, q, errs | {element: 0 * errs[element]}, element), errs[element], atol=1e-10
    )
    # from the six measured parameters, when that element carries all the error
    w6 = k.workspace_error(q, {element: errs[element]})
    np.testing.assert_allclose(k.allocate(w6, q, None, element), errs[element], rtol=0, atol=1e-10)


def test_allocation_rejects_unknown_element_and_bad_shapes():
    q = np.zeros((3, 5))
    with pytest.raises(KinematicsError, match="unknown element"):
        k.allocate(np.zeros((3, 6)), q, None, "T7")
    with pytest.raises(KinematicsError):
        k.allocate(np.zeros((2, 4, 4)), q, None, "T1")
    with pytest.raises(KinematicsError, match="unknown element"):
        k.machine_chain(q, {"spindle": np.zeros(6)})
    with pytest.raises(KinematicsError, match=r"\(N, 5\)"):
        k.machine_chain(np.zeros((3, 4)))
    with pytest.raises(KinematicsError, match="NaN"):
        k.machine_chain(np.full((1, 5), np.nan))
    with pytest.raises(KinematicsError, match="rows"):
        k.machine_chain(q, {"T1": np.zeros((2, 6))})


# ------------------------------------------------------------------ compensation (eqs. 4.23-4.26)


def test_compensation_cancels_appendix_a_sized_errors():
    rng = np.random.default_rng(6)
    n = 2000
    q = random_q(rng, n)
    errs = random_errors(rng, n)
    before = k.workspace_error(q, errs)
    assert np.abs(before[:, 3:]).max() > 0.05  # the errors are worth compensating
    res = k.compensate(q, errs)
    assert not res.singular.any()
    assert np.abs(res.residual[:, 3:]).max() < 1e-6  # mm
    assert np.abs(res.residual[:, :2]).max() < 1e-9  # rad, alpha and beta
    # the residual is what the real chain does at the commanded joints
    real = k.machine_chain(res.q_cmd, errs) @ k.htm_inverse(k.ideal_chain(q))
    np.testing.assert_allclose(k.htm_to_params(real), res.residual, atol=1e-12)
    np.testing.assert_array_equal(res.uncompensable_roll, res.residual[:, 2])
    np.testing.assert_allclose(res.comp, res.q_cmd - q)
    assert np.abs(res.comp[:, :3]).max() < 1.0 and np.abs(res.comp[:, 3:]).max() < 1e-3


def test_roll_residual_equals_planted_roll():
    rng = np.random.default_rng(7)
    n = 500
    q = random_q(rng, n)
    gamma = rng.uniform(-5e-5, 5e-5, n)
    errs = {"T1": np.column_stack([np.zeros(n), np.zeros(n), gamma, np.zeros((n, 3))])}
    res = k.compensate(q, errs)
    np.testing.assert_allclose(res.uncompensable_roll, gamma, rtol=0, atol=1e-15)
    assert np.abs(res.residual[:, [0, 1, 3, 4, 5]]).max() < 1e-9


def test_roll_is_c_of_the_zxy_decomposition_with_all_errors():
    rng = np.random.default_rng(8)
    n = 300
    q = random_q(rng, n)
    errs = random_errors(rng, n)
    res = k.compensate(q, errs)
    W = k.machine_chain(res.q_cmd, errs) @ k.htm_inverse(k.ideal_chain(q))
    # W = Rz(c) to first order: its rotation is a pure roll about the spindle Z, c = residual gamma
    np.testing.assert_allclose(W[:, :3, :3], rz(res.uncompensable_roll)[:, :3, :3], atol=1e-8)
    assert np.abs(res.uncompensable_roll).max() > 1e-6


def test_theta_x_error_needs_y_z_and_a_motions():
    # thesis ch. 4.5: a theta_X angle error is cancelled by Z, Y and theta_X motions together;
    # here the column T2 tilts about X at its end, 400 mm above the A axis
    q = np.array([[50.0, 80.0, -60.0, 0.3, 0.0]])
    res = k.compensate(q, {"T2": np.array([2e-5, 0, 0, 0, 0, 0])})
    comp = res.comp[0]
    assert abs(comp[3] + 2e-5) < 1e-12  # A turns back by alpha
    assert abs(comp[1]) > 1e-3 and abs(comp[2]) > 1e-3  # Y and Z make up the different pivot
    assert abs(comp[0]) < 1e-12 and abs(comp[4]) < 1e-12
    # an alpha error of the A joint itself is a pure A positioning error: A alone cancels it
    # (Y, Z move only by the second-order alpha^2 x 600 mm by which eq. 4.8 is not a rotation)
    res = k.compensate(q, {"theta_x": np.array([2e-5, 0, 0, 0, 0, 0])})
    np.testing.assert_allclose(res.comp[0], [0, 0, 0, -2e-5, 0], atol=1e-6)
    assert abs(res.comp[0, 3] + 2e-5) < 1e-12


def test_a_90_degree_poses_are_flagged_singular():
    rng = np.random.default_rng(9)
    n = 200
    q = random_q(rng, n)
    q[:100, 3] = np.pi / 2 * np.where(rng.random(100) < 0.5, 1, -1)
    q[100:150, 3] = np.pi / 2 + 0.5 * k.SINGULAR_TOL  # within the tolerance
    errs = random_errors(rng, n)
    res = k.compensate(q, errs)
    assert res.singular[:150].all()
    assert not res.singular[150:].any()
    # position and alpha are still cancelled there; beta is reported, not hidden
    assert np.abs(res.residual[:, 3:]).max() < 1e-6
    assert np.abs(res.residual[:, 0]).max() < 1e-9
    assert np.abs(res.residual[:100, 1]).max() > 1e-6
    assert np.all(np.isfinite(res.q_cmd))
    assert np.abs(res.comp[:, 4]).max() < 1e-3  # B not driven off to infinity


def test_quantised_compensation_leaves_the_resolution():
    rng = np.random.default_rng(10)
    n = 2000
    q = random_q(rng, n)
    errs = random_errors(rng, n)
    step_mm, step_rad = 0.0025, np.deg2rad(0.001)
    res = k.compensate(q, errs, resolution_mm=step_mm, resolution_rad=step_rad)
    np.testing.assert_allclose(res.q_cmd[:, :3] / step_mm, np.round(res.q_cmd[:, :3] / step_mm), atol=1e-6)
    # translations are solved after the angles are quantised: each axis within half a step
    assert np.abs(res.residual[:, 3:]).max() <= 0.5 * step_mm * 1.01
    assert np.abs(res.residual[:, :2]).max() <= step_rad
    assert np.abs(res.residual[:, :2]).max() > 1e-9  # quantisation shows, it is not hidden


def test_no_errors_means_no_compensation():
    q = random_q(np.random.default_rng(11), 50)
    res = k.compensate(q, None)
    np.testing.assert_allclose(res.q_cmd, q, atol=1e-12)
    assert res.iterations == 0


# ------------------------------------------------------------------ property tests

finite_q = st.tuples(
    st.floats(-300, 300), st.floats(-300, 300), st.floats(-300, 300), st.floats(-1.4, 1.4), st.floats(-np.pi, np.pi)
)
small = st.floats(-1.0, 1.0)


@settings(max_examples=60, deadline=None)
@given(q=finite_q, p=st.tuples(*[small] * 6), element=st.sampled_from(k.ELEMENTS))
def test_property_allocation_inverts_the_chain(q, p, element):
    qa = np.array([q])
    pa = np.array([p]) * np.array([ANG, ANG, ANG, LIN, LIN, LIN])
    W = k.workspace_error_htm(qa, {element: pa})
    np.testing.assert_allclose(k.allocate(W, qa, None, element), pa, atol=1e-10)


@settings(max_examples=60, deadline=None)
@given(q=finite_q, seed=st.integers(0, 2**32 - 1))
def test_property_compensation_residual_is_only_roll(q, seed):
    qa = np.array([q])
    errs = random_errors(np.random.default_rng(seed), 1)
    res = k.compensate(qa, errs)
    assert not res.singular[0]  # |A| <= 1.4 rad stays clear of 90 deg
    assert np.abs(res.residual[0, 3:]).max() < 1e-6
    assert np.abs(res.residual[0, :2]).max() < 1e-9


def test_unpredicted_components_are_skipped_exactly():
    """Components a model does not predict (all zero) are skipped; the result equals computing them.

    The same errors with those zeros replaced by 1e-300 go through every product (a nonzero column is
    never skipped) and must give the same commands bit for bit: the shortcut changes no rounding. Mixed
    layouts (C order and column-major, as ``compensator.compensate.fast_predict`` returns) are covered.
    """
    rng = np.random.default_rng(7)
    n = 3000
    q = random_q(rng, n)
    errors = random_errors(rng, n, ("T1", "T3", "phi_x", "theta_x", "theta_y", "T6"))
    errors["T1"][:, [1, 4]] = 0.0  # beta, dy not predicted
    errors["T3"][:, :5] = 0.0  # only dz
    errors["theta_y"][:, 3:] = 0.0  # angles only
    errors["T6"][:] = 0.0  # nothing at all
    errors["phi_x"] = np.ascontiguousarray(errors["phi_x"].T).T  # column-major, as fast_predict gives
    tiny = {e: np.where(v == 0.0, 1e-300, v) for e, v in errors.items()}
    fast = k.compensate(q, errors)
    full = k.compensate(q, tiny)
    assert np.array_equal(fast.q_cmd, full.q_cmd)
    assert np.array_equal(fast.singular, full.singular)
    # and the chain itself: the same with the errors given as one constant row per element
    const = {"T3": np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.05]), "theta_x": errors["theta_x"]}
    assert np.allclose(
        k.compensate(q, const).q_cmd,
        k.compensate(q, {**const, "T3": np.tile(const["T3"], (n, 1))}).q_cmd,
        rtol=0,
        atol=1e-12,
    )
