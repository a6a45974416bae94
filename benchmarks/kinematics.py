"""Kinematics speed on one core: forward chain (eq. 4.12) and compensation solve (eqs. 4.23-4.26).

Prints one JSON line; each figure sits beside an in-run baseline, a Python loop over poses with
plain numpy 4x4 products (measured on a subset and scaled to poses per second).
Targets: chain >= 2,000,000 poses/s at N = 1e6, compensation >= 100,000 poses/s.
Figures are best-of wall time; the ``*_cpu`` twins use this process's CPU time, which is what one
core does when other work shares the machine (``load_avg_1min`` says how busy it was).
"""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import time  # noqa: E402

from _common import emit, load_average, timeit_best  # noqa: E402  (sets one thread before numpy loads)

# isort: split

import numpy as np  # noqa: E402

from driftlab.models.simulation import appendix_a_errors, sinusoidal_program  # noqa: E402
from driftlab.physics import kinematics as kin  # noqa: E402

N_CHAIN = 1_000_000
N_COMP = 1_000_000
N_LOOP = 2_000
N_LOOP_COMP = 100


def _element_4x4(name: str, q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """One element as a plain 4x4 for one pose (eqs. 4.8, 4.13-4.18)."""
    a, b, g, dx, dy, dz = p
    e = np.array([[1.0, -g, b, dx], [g, 1.0, -a, dy], [-b, a, 1.0, dz], [0.0, 0.0, 0.0, 1.0]])
    if name in kin.LINKS:
        t = np.eye(4)
        t[:3, 3] = kin.TABLE_A1[name]
        return t @ e
    k = kin.JOINT_AXIS[name]
    if k < 3:
        t = np.eye(4)
        t[k, 3] = q[k]
        return t @ e
    c, s = np.cos(q[k]), np.sin(q[k])
    r = np.eye(4)
    if name == "theta_x":
        r[1:3, 1:3] = [[c, -s], [s, c]]
    else:
        r[0, 0], r[0, 2], r[2, 0], r[2, 2] = c, s, -s, c
    return e @ r


def loop_chain(q: np.ndarray, errs: dict[str, np.ndarray]) -> np.ndarray:
    """Baseline: the chain pose by pose with numpy 4x4 products."""
    out = np.empty((len(q), 4, 4))
    for i in range(len(q)):
        t = np.eye(4)
        for name in kin.ELEMENTS:
            t = t @ _element_4x4(name, q[i], errs[name][i])
        out[i] = t
    return out


def _loop_w(qc: np.ndarray, ideal_inv: np.ndarray, errs_i: dict[str, np.ndarray]) -> np.ndarray:
    t = np.eye(4)
    for name in kin.ELEMENTS:
        t = t @ _element_4x4(name, qc, errs_i[name])
    w = t @ ideal_inv
    # reachable parameters: alpha, beta and the translation (the roll gamma is not)
    return np.array([0.5 * (w[2, 1] - w[1, 2]), 0.5 * (w[0, 2] - w[2, 0]), w[0, 3], w[1, 3], w[2, 3]])


def loop_compensate(q: np.ndarray, errs: dict[str, np.ndarray], iters: int = 3) -> np.ndarray:
    """Baseline: Gauss-Newton per pose on the looped chain with a finite-difference Jacobian."""
    out = q.copy()
    ideal_inv = kin.htm_inverse(kin.ideal_chain(q))
    steps = np.array([1e-4, 1e-4, 1e-4, 1e-7, 1e-7])
    for i in range(len(q)):
        errs_i = {n: v[i] for n, v in errs.items()}
        qc = q[i].copy()
        for _ in range(iters):
            r0 = _loop_w(qc, ideal_inv[i], errs_i)
            jac = np.empty((5, 5))
            for j in range(5):
                dq = qc.copy()
                dq[j] += steps[j]
                jac[:, j] = (_loop_w(dq, ideal_inv[i], errs_i) - r0) / steps[j]
            qc = qc - np.linalg.solve(jac, r0)
        out[i] = qc
    return out


def main() -> None:
    """Measure and print the figures."""
    t = np.linspace(0.0, 8 * 3600.0, N_CHAIN)
    q, direction = sinusoidal_program(t, seed=0)
    q[:, 4] = np.random.default_rng(0).uniform(-np.pi, np.pi, N_CHAIN)  # all B angles
    errs = appendix_a_errors(t, q, direction)  # every element carries a per-pose error

    load = load_average()
    cpu = time.process_time
    chain_s = timeit_best(lambda: kin.machine_chain(q, errs), repeat=3)
    chain_cpu = timeit_best(lambda: kin.machine_chain(q, errs), repeat=3, clock=cpu)
    ideal_s = timeit_best(lambda: kin.ideal_chain(q), repeat=3)
    sub = slice(0, N_LOOP)
    sub_errs = {n: v[sub] for n, v in errs.items()}
    loop_s = timeit_best(lambda: loop_chain(q[sub], sub_errs), repeat=1)
    loop_cpu = timeit_best(lambda: loop_chain(q[sub], sub_errs), repeat=1, clock=cpu)
    few = {n: v[:200] for n, v in errs.items()}
    chain_check = float(np.abs(loop_chain(q[:200], few) - kin.machine_chain(q[:200], few)).max())

    qc, ec = q[:N_COMP], {n: v[:N_COMP] for n, v in errs.items()}
    comp_s = timeit_best(lambda: kin.compensate(qc, ec), repeat=2)
    comp_cpu = timeit_best(lambda: kin.compensate(qc, ec), repeat=2, clock=cpu)
    res = kin.compensate(qc, ec)
    lsub = slice(0, N_LOOP_COMP)
    lerrs = {n: v[lsub] for n, v in errs.items()}
    loop_comp_s = timeit_best(lambda: loop_compensate(q[lsub], lerrs), repeat=1)
    loop_comp_cpu = timeit_best(lambda: loop_compensate(q[lsub], lerrs), repeat=1, clock=cpu)
    comp_check = float(np.abs(loop_compensate(q[lsub], lerrs) - res.q_cmd[lsub]).max())

    figures = {
        "n_chain": N_CHAIN,
        "chain_poses_per_s": round(N_CHAIN / chain_s),
        "ideal_chain_poses_per_s": round(N_CHAIN / ideal_s),
        "baseline_loop_poses_per_s": round(N_LOOP / loop_s),
        "chain_speedup": round(loop_s / N_LOOP / (chain_s / N_CHAIN), 1),
        "chain_poses_per_s_cpu": round(N_CHAIN / chain_cpu),
        "baseline_loop_poses_per_s_cpu": round(N_LOOP / loop_cpu),
        "chain_vs_loop_max_abs_diff": chain_check,
        "n_compensate": N_COMP,
        "compensate_poses_per_s": round(N_COMP / comp_s),
        "baseline_loop_compensate_poses_per_s": round(N_LOOP_COMP / loop_comp_s, 1),
        "compensate_speedup": round(loop_comp_s / N_LOOP_COMP / (comp_s / N_COMP), 1),
        "compensate_poses_per_s_cpu": round(N_COMP / comp_cpu),
        "baseline_loop_compensate_poses_per_s_cpu": round(N_LOOP_COMP / loop_comp_cpu, 1),
        "compensate_vs_loop_max_abs_diff": comp_check,
        "compensate_max_residual_mm": float(np.abs(res.residual[:, 3:]).max()),
        "compensate_max_residual_rad": float(np.abs(res.residual[:, :2]).max()),
        "target_chain_poses_per_s": 2_000_000,
        "target_compensate_poses_per_s": 100_000,
        "load_avg_1min": load,
    }
    figures["meets_targets"] = bool(
        figures["chain_poses_per_s"] >= figures["target_chain_poses_per_s"]
        and figures["compensate_poses_per_s"] >= figures["target_compensate_poses_per_s"]
    )
    figures["meets_targets_cpu"] = bool(
        figures["chain_poses_per_s_cpu"] >= figures["target_chain_poses_per_s"]
        and figures["compensate_poses_per_s_cpu"] >= figures["target_compensate_poses_per_s"]
    )
    emit(figures)


if __name__ == "__main__":
    main()
