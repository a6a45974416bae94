"""HTM kinematic model of the five-axis machine (thesis ch. 4.2-4.4), vectorised over N poses.

Conventions (units and term order: driftlab.vocabulary; layers: docs/architecture.md):

* error vectors ``p`` are ``(alpha, beta, gamma, dx, dy, dz)`` (rad, mm), arrays ``(N, 6)``;
* chain (eq. 4.12) ``T = T1 @ PhiZ @ T2 @ PhiY @ T3 @ PhiX @ T4 @ ThetaX @ T5 @ ThetaY @ T6``;
  the left frame is the spindle (tool) frame, the right frame the part;
* links ``T_i = Trans(a_i, b_i, c_i) @ E(p_i)`` (eqs. 4.9, 4.13), translational joints
  ``Phi = Trans(q) @ E(p)`` (eqs. 4.14-4.16), rotary joints ``Theta = E(p) @ Rot(q)``
  (eqs. 4.17-4.18), ``E(p)`` the small-angle HTM of eq. 4.8 (first order, so not exactly
  orthonormal: every inverse of a real chain here is the exact affine inverse, not eq. 4.22);
* work-space error ``W = T_real @ inv(T_ideal)``: its translation is the displacement of the part
  point that should sit at the tool tip (the spindle origin), in the spindle frame.

Speed: the chain is evaluated on the HTM structure (3x3 rotation + translation, never a generic
4x4 product), the rotation held as three (3, n) column arrays, in chunks of poses that stay in
cache; elements without error skip their rotation product entirely.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from driftlab.errors import KinematicsError
from driftlab.vocabulary import AXES
from driftlab.vocabulary import TERMS as PARAMS

ELEMENTS: tuple[str, ...] = (
    "T1",
    "phi_z",
    "T2",
    "phi_y",
    "T3",
    "phi_x",
    "T4",
    "theta_x",
    "T5",
    "theta_y",
    "T6",
)
LINKS: tuple[str, ...] = ("T1", "T2", "T3", "T4", "T5", "T6")
JOINTS: tuple[str, ...] = ("phi_z", "phi_y", "phi_x", "theta_x", "theta_y")
#: columns of the joint array ``q``: X, Y, Z (mm), A = theta_x, B = theta_y (rad)
#: joint element -> column of q that drives it
JOINT_AXIS: Mapping[str, int] = MappingProxyType({"phi_x": 0, "phi_y": 1, "phi_z": 2, "theta_x": 3, "theta_y": 4})

#: Table A.1: fixed link dimensions (a, b, c) in mm of the simulated machine.
TABLE_A1: Mapping[str, tuple[float, float, float]] = MappingProxyType(
    {
        "T1": (0.0, -400.0, -200.0),  # spindle head
        "T2": (0.0, 400.0, 1200.0),  # vertical column
        "T3": (0.0, 0.0, -200.0),  # Y-X carriage
        "T4": (0.0, 0.0, -200.0),  # main table
        "T5": (0.0, 0.0, -200.0),  # theta_x - theta_z support
        "T6": (0.0, 0.0, -400.0),  # part table
    }
)

#: A pose is flagged singular when the 2x2 Jacobian of (alpha, beta) with respect to (A, B)
#: has |det| below this; to first order |det| = |cos A|, so the tolerance means A within
#: 0.057 deg of +/-90 deg, where B turns within 1 mrad of the spindle axis and a beta error e
#: would need a B correction e / cos A more than 1000 times larger than e.
SINGULAR_TOL: float = 1e-3

#: poses per chunk of the column-wise kernels (arrays of this length stay in cache)
CHUNK: int = 8192

ElementErrors = Mapping[str, np.ndarray]

_Comp = Any  # a float or an (n,) array: one component of a stacked vector


# --------------------------------------------------------------------------- single HTMs


def _as_params(p: np.ndarray | Any) -> np.ndarray:
    arr = np.asarray(p, dtype=float)
    if arr.shape[-1:] != (6,):
        raise KinematicsError(f"error parameters must have a last dimension of 6 {PARAMS}, got shape {arr.shape}")
    return arr


def error_htm(p: np.ndarray) -> np.ndarray:
    """Return the small-angle error HTMs of eq. 4.8, shape ``p.shape[:-1] + (4, 4)``."""
    p = _as_params(p)
    a, b, g, dx, dy, dz = np.moveaxis(p, -1, 0)
    one, zero = np.ones_like(a), np.zeros_like(a)
    rows = [
        [one, -g, b, dx],  # eq. 4.8
        [g, one, -a, dy],
        [-b, a, one, dz],
        [zero, zero, zero, one],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def trans_htm(v: np.ndarray) -> np.ndarray:
    """Return pure translation HTMs (eqs. 4.3, 4.6) for vectors ``v`` of shape ``(..., 3)``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (4, 4))
    out[..., [0, 1, 2, 3], [0, 1, 2, 3]] = 1.0
    out[..., :3, 3] = v
    return out


def rot_htm(axis: str, angle: np.ndarray) -> np.ndarray:
    """Return pure rotation HTMs about ``axis`` ('x', 'y' or 'z') by ``angle`` rad (eq. 4.4)."""
    th = np.asarray(angle, dtype=float)
    c, s = np.cos(th), np.sin(th)
    out = np.zeros(th.shape + (4, 4))
    out[..., 3, 3] = 1.0
    i, j, k = {"x": (0, 1, 2), "y": (1, 2, 0), "z": (2, 0, 1)}[axis.lower()]
    # eq. 4.4: rotation by th in the (j, k) plane, axis i fixed
    out[..., i, i] = 1.0
    out[..., j, j] = c
    out[..., k, k] = c
    out[..., j, k] = -s
    out[..., k, j] = s
    return out


def _dims_array(dims: Mapping[str, Any]) -> dict[str, tuple[float, float, float]]:
    try:
        out = {name: tuple(float(x) for x in dims[name]) for name in LINKS}
    except KeyError as exc:
        raise KinematicsError(f"link dimensions lack {exc.args[0]!r}: need {LINKS}") from None
    except (TypeError, ValueError):
        raise KinematicsError("link dimensions must map T1..T6 to three numbers (a, b, c) in mm") from None
    for name, abc in out.items():
        if len(abc) != 3 or not all(np.isfinite(abc)):
            raise KinematicsError(f"link {name} dimensions must be three finite numbers, got {abc}")
    return out  # type: ignore[return-value]


def _as_q(q: np.ndarray) -> np.ndarray:
    arr = np.asarray(q, dtype=float)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 5:
        raise KinematicsError(f"joint coordinates q must be (N, 5) {AXES}, got shape {np.shape(q)}")
    if not np.isfinite(arr.sum()) and not np.all(np.isfinite(arr)):  # one pass in the common case
        raise KinematicsError("joint coordinates q contain NaN or infinity")
    return arr


def _as_errors(errors: ElementErrors | None, n: int) -> dict[str, np.ndarray]:
    if not errors:
        return {}
    out: dict[str, np.ndarray] = {}
    for name, value in errors.items():
        if name not in ELEMENTS:
            raise KinematicsError(f"unknown element {name!r}: expected one of {ELEMENTS}")
        if value is None:
            continue
        arr = _as_params(value)
        if arr.ndim == 2 and arr.shape[0] == 1:
            arr = arr[0]
        if arr.ndim == 2 and arr.shape[0] != n:
            raise KinematicsError(f"errors of {name} have {arr.shape[0]} rows for {n} poses")
        if arr.ndim > 2:
            raise KinematicsError(f"errors of {name} must be (N, 6) or (6,), got shape {arr.shape}")
        if arr.ndim == 1:
            if not np.all(np.isfinite(arr)):
                raise KinematicsError(f"errors of {name} contain NaN or infinity")
            if not np.any(arr):
                continue
        out[name] = arr  # (N, 6) rows are checked chunk by chunk, while they are in cache
    return out


def element_htm(
    element: str, q: np.ndarray, p: np.ndarray | None = None, dims: Mapping[str, Any] = TABLE_A1
) -> np.ndarray:
    """Return the (N, 4, 4) HTM of one chain element with error ``p`` (eqs. 4.13-4.18)."""
    q = _as_q(q)
    n = q.shape[0]
    e = error_htm(np.zeros(6) if p is None else p)
    e = np.broadcast_to(e, (n, 4, 4))
    if element in LINKS:
        return trans_htm(np.array(_dims_array(dims)[element])) @ e  # eqs. 4.9, 4.13
    if element in ("phi_x", "phi_y", "phi_z"):
        k = JOINT_AXIS[element]
        v = np.zeros((n, 3))
        v[:, k] = q[:, k]
        return trans_htm(v) @ e  # eqs. 4.14-4.16
    if element in ("theta_x", "theta_y"):
        return e @ rot_htm(element[-1], q[:, JOINT_AXIS[element]])  # eqs. 4.17-4.18
    raise KinematicsError(f"unknown element {element!r}: expected one of {ELEMENTS}")


# ------------------------------------------------------------------- column-wise kernels
# A rotation block is held as its three columns, each a (3, n) array (n poses of a chunk) or a
# (3, 1) constant; a vector is (3, n) or (3, 1). Error components are (n,) rows or floats (for
# constant errors), and elements without error skip their rotation product entirely.


def _is_zero(x: _Comp) -> bool:
    return isinstance(x, float) and x == 0.0


def _vec3(x: _Comp, y: _Comp, z: _Comp) -> np.ndarray:
    """Stack three components (floats or (n,) rows) into a (3, n) or (3, 1) array."""
    out = np.empty((3, max(np.size(x), np.size(y), np.size(z))))
    out[0], out[1], out[2] = x, y, z
    return out


_EYE3 = np.eye(3)
_EYE3.setflags(write=False)
_ID_COLS: tuple = (_EYE3[:, 0:1], _EYE3[:, 1:2], _EYE3[:, 2:3])
_ZERO6: tuple = (0.0,) * 6


def _mul_e(m: tuple, a: _Comp, b: _Comp, g: _Comp) -> tuple:
    """M @ E(alpha, beta, gamma), the rotation block of eq. 4.8, on columns."""
    if m is _ID_COLS:
        return (_vec3(1.0, g, -b), _vec3(-g, 1.0, a), _vec3(b, -a, 1.0))  # eq. 4.8 columns
    c0, c1, c2 = m
    if _is_zero(a) and _is_zero(b) and _is_zero(g):
        return m  # E(0, 0, 0) is the identity
    if not (
        c0.shape == c1.shape == c2.shape and all(type(x) is float or x.shape[-1] == c0.shape[-1] for x in (a, b, g))
    ):
        # columns of different shapes (some components constant): the same sums, out of place
        return (c1 * g - c2 * b + c0, c2 * a - c0 * g + c1, c0 * b - c1 * a + c2)
    # the three columns share one shape, so each first product already has the result's
    # shape and is a fresh array: accumulating into it in place is safe and saves temporaries
    n0 = c1 * g
    n0 -= c2 * b
    n0 += c0
    n1 = c2 * a
    n1 -= c0 * g
    n1 += c1
    n2 = c0 * b
    n2 -= c1 * a
    n2 += c2
    return (n0, n1, n2)


def _mul_rx(m: tuple, c: _Comp, s: _Comp) -> tuple:
    """M @ Rx (eq. 4.4) on columns."""
    c0, c1, c2 = m
    n1 = c1 * c
    n1 += c2 * s
    n2 = c2 * c
    n2 -= c1 * s
    return (np.broadcast_to(c0, n1.shape), n1, n2)


def _mul_ry(m: tuple, c: _Comp, s: _Comp) -> tuple:
    """M @ Ry (eq. 4.4) on columns."""
    c0, c1, c2 = m
    n0 = c0 * c
    n0 -= c2 * s
    n2 = c0 * s
    n2 += c2 * c
    return (n0, np.broadcast_to(c1, n0.shape), n2)


def _plus(p: np.ndarray | float, r: np.ndarray | float) -> np.ndarray | float:
    """p + r, in place when p is an array of the result's shape.

    Callers own p: it is always a fresh product or sum (never an input or a shared constant).
    """
    if _is_zero(r):
        return p
    if _is_zero(p):
        return r
    if type(p) is np.ndarray and (type(r) is float or p.shape == r.shape):  # type: ignore[union-attr]
        p += r
        return p
    return p + r


def _matvec(m: Sequence[Any], v: Sequence[Any]) -> np.ndarray | float:
    """M @ v (a fresh array) for column-held M and components v, skipping exact zeros."""
    acc: np.ndarray | float = 0.0
    for col, x in zip(m, v):
        if not _is_zero(x):
            acc = _plus(acc, col * x)
    return acc


_Cols = dict[str, tuple]  # element -> its six error components for one chunk


def _chunk_cols(errs: dict[str, np.ndarray], s: int, t: int) -> _Cols:
    """Six error components per element for poses s:t (floats when constant)."""
    out: _Cols = {}
    for name, e in errs.items():
        if e.ndim == 1:
            out[name] = tuple(float(x) for x in e)
            continue
        rows = e[s:t].T
        if rows.strides[1] != rows.itemsize:  # (N, 6) in C order: one in-cache copy per chunk
            rows = np.ascontiguousarray(rows)  # (column-major errors are read as they are)
        # a component that is exactly zero over the chunk (a parameter the model does not predict)
        # is held as 0.0, so the products below skip it; for finite errors the result is the same
        comps = tuple(r if r.any() else 0.0 for r in rows)
        if any(not _is_zero(c) for c in comps):
            out[name] = comps
    return out


def _check_finite(cols: _Cols, *results: np.ndarray) -> None:
    """Raise KinematicsError naming the element when a chunk's results are not finite.

    NaN and infinity in any error reach the chain's rotation or position (NaN * 0 is NaN), so
    checking the few result arrays replaces a pass over all eleven error arrays.
    """
    if all(np.isfinite(np.sum(r)) for r in results):
        return
    for name, comps in cols.items():
        if not all(np.all(np.isfinite(c)) for c in comps):
            raise KinematicsError(f"errors of {name} contain NaN or infinity")
    raise KinematicsError("the chain overflowed: errors or joints far too large")


@dataclass
class _PreChain:
    """T1 .. ThetaX's error matrix for a chunk: everything before Rx(A)."""

    rot: tuple  # columns of R_pre @ E_theta_x (the 'A' of the compensation solve)
    pos: np.ndarray  # (3, n) position accumulated so far (includes X, Y, Z)
    jac: tuple  # columns d pos / dX, dY, dZ


def _pre_chain(q: np.ndarray, cols: _Cols, dims: dict, s: int, t: int) -> _PreChain:
    """Accumulate T1 PhiZ T2 PhiY T3 PhiX T4 and ThetaX's error (eqs. 4.12-4.17)."""
    m: tuple = _ID_COLS
    p: np.ndarray | float = 0.0
    jac: dict[int, np.ndarray] = {}
    for name in ELEMENTS[:8]:
        a, b, g, dx, dy, dz = cols.get(name, _ZERO6)
        if name in LINKS:
            da, db, dc = dims[name]
            trans = (da + dx, db + dy, dc + dz)  # eq. 4.13: a_i + da_i, ...
        elif name == "theta_x":
            trans = (dx, dy, dz)  # eq. 4.17: E(p) @ Rx, the translation is the error only
        else:
            k = JOINT_AXIS[name]
            jac[k] = m[k]  # d pos / d q_k = M e_k: the position is affine in X, Y, Z
            qk = q[s:t, k]
            trans = tuple(qk + d if i == k else d for i, d in enumerate((dx, dy, dz)))  # eqs. 4.14-4.16
        p = _plus(p, _matvec(m, trans))
        if name in cols:
            m = _mul_e(m, a, b, g)
    return _PreChain(rot=m, pos=p, jac=(jac[0], jac[1], jac[2]))  # type: ignore[arg-type]


def _post_rot(pre_rot: tuple, ca: _Comp, sa: _Comp, cb: _Comp, sb: _Comp, cols: _Cols) -> tuple[tuple, np.ndarray]:
    """Return (rotation of the whole chain, column 1 of A Rx(a) E5 E_theta_y) from the pre-chain."""
    m = _mul_rx(pre_rot, ca, sa)
    for name in ("T5", "theta_y"):
        if name in cols:
            a, b, g, *_ = cols[name]
            m = _mul_e(m, a, b, g)
    ub = m[1]
    m = _mul_ry(m, cb, sb)
    if "T6" in cols:
        a, b, g, *_ = cols["T6"]
        m = _mul_e(m, a, b, g)
    return m, ub


def _post_pos(
    pre: _PreChain, ca: _Comp, sa: _Comp, cb: _Comp, sb: _Comp, cols: _Cols, dims: dict
) -> tuple[tuple, np.ndarray]:
    """Return (rotation, position) of the full chain from the pre-chain (eqs. 4.12, 4.17, 4.18)."""
    m = _mul_rx(pre.rot, ca, sa)
    p: Any = pre.pos.copy()  # accumulated in place below; the pre-chain is reused by the caller
    for name in ("T5", "theta_y", "T6"):
        a, b, g, dx, dy, dz = cols.get(name, _ZERO6)
        if name in LINKS:
            da, db, dc = dims[name]
            trans = (da + dx, db + dy, dc + dz)
        else:
            trans = (dx, dy, dz)
        p = _plus(p, _matvec(m, trans))
        if name in cols:
            m = _mul_e(m, a, b, g)
        if name == "theta_y":
            m = _mul_ry(m, cb, sb)  # eq. 4.18: E(p) @ Ry, the translation applied before the turn
    return m, p


def _ideal_parts(q: np.ndarray, dims: dict, s: int, t: int) -> tuple[tuple, tuple]:
    """Closed-form rotation and position of the error-free chain (eq. 4.19)."""
    x, y, z = q[s:t, 0], q[s:t, 1], q[s:t, 2]
    th_x, th_y = q[s:t, 3], q[s:t, 4]
    cx, sx, cy, sy = np.cos(th_x), np.sin(th_x), np.cos(th_y), np.sin(th_y)
    a = {k: v[0] for k, v in dims.items()}
    b = {k: v[1] for k, v in dims.items()}
    c = {k: v[2] for k, v in dims.items()}
    a14 = a["T1"] + a["T2"] + a["T3"] + a["T4"]
    b14 = b["T1"] + b["T2"] + b["T3"] + b["T4"]
    c14 = c["T1"] + c["T2"] + c["T3"] + c["T4"]
    sxsy, sxcy, cxsy, cxcy = sx * sy, sx * cy, cx * sy, cx * cy
    # eq. 4.19: orientation Rx(theta_x) @ Ry(theta_y)
    rot = (cy, 0.0 * cy, sy, sxsy, cx, -sxcy, -cxsy, sx, cxcy)
    # eq. 4.19: position column as printed there
    px = a["T6"] * cy + c["T6"] * sy + a["T5"] + a14 + x
    py = a["T6"] * sxsy + b["T6"] * cx - c["T6"] * sxcy + b["T5"] * cx - c["T5"] * sx + b14 + y
    pz = -a["T6"] * cxsy + b["T6"] * sx + c["T6"] * cxcy + b["T5"] * sx + c["T5"] * cx + c14 + z
    return rot, (px, py, pz)


def _write(out: np.ndarray, s: int, t: int, rot: tuple, pos: tuple) -> None:
    """Write a rotation held as 9 components and a position as 3 into out[s:t]."""
    for i in range(3):
        for j in range(3):
            out[s:t, i, j] = rot[3 * i + j]
        out[s:t, i, 3] = pos[i]


def _write_cols(out: np.ndarray, s: int, t: int, rot: tuple, pos: np.ndarray) -> None:
    """Write a rotation held as columns and a (3, n) position into out[s:t]."""
    for j in range(3):
        out[s:t, :3, j] = rot[j].T
    out[s:t, :3, 3] = pos.T


def _new_htm_stack(n: int) -> np.ndarray:
    out = np.empty((n, 4, 4))
    out[:, 3, :3] = 0.0
    out[:, 3, 3] = 1.0
    return out


# --------------------------------------------------------------------------- public API


def machine_chain(q: np.ndarray, errors: ElementErrors | None = None, dims: Mapping[str, Any] = TABLE_A1) -> np.ndarray:
    """Return the (N, 4, 4) real machine HTMs of eq. 4.12 at joints q with element errors."""
    q = _as_q(q)
    n = q.shape[0]
    errs = _as_errors(errors, n)
    d = _dims_array(dims)
    out = _new_htm_stack(n)
    for s in range(0, n, CHUNK):
        t = min(n, s + CHUNK)
        cols = _chunk_cols(errs, s, t)
        pre = _pre_chain(q, cols, d, s, t)
        ca, sa = np.cos(q[s:t, 3]), np.sin(q[s:t, 3])
        cb, sb = np.cos(q[s:t, 4]), np.sin(q[s:t, 4])
        rot, pos = _post_pos(pre, ca, sa, cb, sb, cols, d)
        _check_finite(cols, pos, *rot)
        _write_cols(out, s, t, rot, pos)
    return out


def ideal_chain(q: np.ndarray, dims: Mapping[str, Any] = TABLE_A1) -> np.ndarray:
    """Return the (N, 4, 4) error-free machine HTMs in the closed form of eq. 4.19."""
    q = _as_q(q)
    n = q.shape[0]
    d = _dims_array(dims)
    out = _new_htm_stack(n)
    for s in range(0, n, CHUNK):
        t = min(n, s + CHUNK)
        rot, pos = _ideal_parts(q, d, s, t)
        _write(out, s, t, rot, pos)
    return out


def _htm_stack(T: np.ndarray) -> np.ndarray:
    """Return ``T`` as a float array of (..., 4, 4) HTMs; KinematicsError for any other shape."""
    T = np.asarray(T, dtype=float)
    if T.shape[-2:] != (4, 4):
        raise KinematicsError(f"HTMs must be (..., 4, 4), got shape {T.shape}")
    return T


def _with_inverse_block(T: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """Return [inv, -inv P; 0, 1] for the positions P of ``T`` and a 3x3 block ``inv`` (eq. 4.22)."""
    out = np.zeros_like(T)
    out[..., :3, :3] = inv
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", inv, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def htm_inverse(T: np.ndarray) -> np.ndarray:
    """Return the inverse of rigid HTMs by eqs. 4.21-4.22: [O^T, -O^T P; 0, 1]."""
    T = _htm_stack(T)
    return _with_inverse_block(T, np.swapaxes(T[..., :3, :3], -1, -2))  # eq. 4.22: O^T


def affine_inverse(T: np.ndarray) -> np.ndarray:
    """Return the exact inverse of affine HTMs whose 3x3 block need not be orthonormal."""
    T = _htm_stack(T)
    m = T[..., :3, :3]
    # adjugate / determinant: exact for the eq. 4.8 products, which are only orthonormal to first order
    adj = np.empty_like(m)
    for i in range(3):
        for j in range(3):
            r0, r1 = [k for k in range(3) if k != j]
            c0, c1 = [k for k in range(3) if k != i]
            adj[..., i, j] = (-1) ** (i + j) * (m[..., r0, c0] * m[..., r1, c1] - m[..., r0, c1] * m[..., r1, c0])
    det = np.einsum("...j,...j->...", m[..., 0, :], adj[..., :, 0])
    if np.any(np.abs(det) < 1e-12):
        raise KinematicsError("HTM rotation block is singular and cannot be inverted")
    return _with_inverse_block(T, adj / det[..., None, None])


def htm_to_params(T: np.ndarray) -> np.ndarray:
    """Return the (..., 6) small-angle parameters of HTMs (exact for eq. 4.8 matrices)."""
    T = _htm_stack(T)
    out = np.empty(T.shape[:-2] + (6,))
    # eq. 4.8: the antisymmetric part of the rotation block holds alpha, beta, gamma
    out[..., 0] = 0.5 * (T[..., 2, 1] - T[..., 1, 2])
    out[..., 1] = 0.5 * (T[..., 0, 2] - T[..., 2, 0])
    out[..., 2] = 0.5 * (T[..., 1, 0] - T[..., 0, 1])
    out[..., 3:] = T[..., :3, 3]
    return out


def workspace_error_htm(q: np.ndarray, errors: ElementErrors | None, dims: Mapping[str, Any] = TABLE_A1) -> np.ndarray:
    """Return the (N, 4, 4) work-space error W = T_real @ inv(T_ideal) (eq. 4.12's E)."""
    return machine_chain(q, errors, dims) @ htm_inverse(ideal_chain(q, dims))


def workspace_error(q: np.ndarray, errors: ElementErrors | None, dims: Mapping[str, Any] = TABLE_A1) -> np.ndarray:
    """Return the (N, 6) work-space error parameters that a laser or probe would measure."""
    return htm_to_params(workspace_error_htm(q, errors, dims))


def parameter_jacobian(q: np.ndarray, element: str, k: int, dims: Mapping[str, Any] = TABLE_A1) -> np.ndarray:
    """Return (N, 6) dW/dp at poses ``q``: the work-space error per unit of parameter ``k`` of ``element``.

    Eq. 4.12 to first order around zero error, by a step of 1e-6 (rad or mm) in that one parameter.
    """
    eps = 1e-6
    unit = np.zeros((np.atleast_2d(q).shape[0], 6))
    unit[:, k] = eps
    return workspace_error(q, {element: unit}, dims) / eps


def _chain_product(
    q: np.ndarray, errs: dict[str, np.ndarray], dims: Mapping[str, Any], names: tuple[str, ...]
) -> np.ndarray:
    n = q.shape[0]
    out = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    for name in names:
        out = out @ element_htm(name, q, errs.get(name), dims)
    return out


def allocate(
    W: np.ndarray, q: np.ndarray, known_errors: ElementErrors | None, element: str, dims: Mapping[str, Any] = TABLE_A1
) -> np.ndarray:
    """Return the (N, 6) error of ``element`` that explains the work-space error W (eq. 4.20).

    ``W`` is either the (N, 4, 4) matrix ``T_real @ inv(T_ideal)`` or its (N, 6) parameters
    (then rebuilt with eq. 4.8, exact when one element carries all the error). Errors of the other
    elements are taken as known; an entry for ``element`` itself is ignored (it is the unknown).
    """
    if element not in ELEMENTS:
        raise KinematicsError(f"unknown element {element!r}: expected one of {ELEMENTS}")
    q = _as_q(q)
    n = q.shape[0]
    W = np.asarray(W, dtype=float)
    if W.shape[-1:] == (6,) and W.ndim <= 2:
        W = error_htm(W)
    if W.ndim == 2:
        W = W[None]
    if W.shape[-2:] != (4, 4) or W.shape[0] not in (1, n):
        raise KinematicsError(f"W must be (N, 4, 4) or (N, 6) for {n} poses, got shape {W.shape}")
    errs = {k: v for k, v in _as_errors(known_errors, n).items() if k != element}
    k = ELEMENTS.index(element)
    left = _chain_product(q, errs, dims, ELEMENTS[:k])
    right = _chain_product(q, errs, dims, ELEMENTS[k + 1 :])
    t_real = W @ ideal_chain(q, dims)
    # eq. 4.20 with exact inverses: X = inv(left) @ T_real @ inv(right)
    x = affine_inverse(left) @ t_real @ affine_inverse(right)
    nominal = element_htm(element, q, None, dims)
    if element in ("theta_x", "theta_y"):
        e = x @ htm_inverse(nominal)  # eqs. 4.17-4.18: Theta = E @ Rot
    else:
        e = htm_inverse(nominal) @ x  # eqs. 4.13-4.16: T = Trans @ E
    return htm_to_params(e)


@dataclass(frozen=True)
class CompensationResult:
    """Axis commands that cancel the modelled work-space error, and what they cannot cancel."""

    #: (N, 5) commanded joints X, Y, Z (mm), A, B (rad): nominal + compX..comp theta_Y (eqs. 4.23-4.24)
    q_cmd: np.ndarray
    #: (N, 6) parameters of W = T_real(q_cmd) @ inv(T_ideal(q)) left after compensation
    residual: np.ndarray
    #: (N,) True where |det d(alpha, beta)/d(A, B)| < SINGULAR_TOL (A near +/-90 deg): beta is not compensated
    singular: np.ndarray
    #: (N,) rad: roll gamma about the spindle Z that five axes cannot cancel (residual[:, 2])
    uncompensable_roll: np.ndarray
    #: (N, 5) nominal joints the compensation was solved for
    q_nominal: np.ndarray | None = None
    #: Newton iterations used for the angles (the most any chunk needed)
    iterations: int = 0

    @property
    def comp(self) -> np.ndarray:
        """Return the (N, 5) compensation values compX, compY, compZ, comp theta_X, comp theta_Y."""
        if self.q_nominal is None:
            raise KinematicsError("this result does not carry its nominal joints")
        return self.q_cmd - self.q_nominal


def _quantise(x: _Comp, step: float | None) -> _Comp:
    return x if not step else np.round(x / step) * step


def compensate(
    q: np.ndarray,
    errors: ElementErrors | None,
    dims: Mapping[str, Any] = TABLE_A1,
    *,
    resolution_mm: float | None = None,
    resolution_rad: float | None = None,
    max_iter: int = 8,
    tol_rad: float = 1e-14,
) -> CompensationResult:
    """Return the axis commands making the real chain reproduce the ideal one (eqs. 4.23-4.26).

    Angles first (Newton on alpha, beta of W over A, B: the chain's orientation does not depend
    on X, Y, Z), then translations (the position is exactly affine in X, Y, Z for fixed errors,
    so one linear solve is exact). The target is ``W = Rz(c)``: the real orientation is
    ``Rz(c) @ Rx(A) @ Ry(B)``, c the roll about the spindle that five axes cannot reach, and the
    translation of W (tool tip versus part) is zero. With ``resolution_*`` the angles are
    quantised before the translations are solved, then the translations are quantised: the
    residual then shows what the machine's resolution leaves.
    """
    q = _as_q(q)
    n = q.shape[0]
    errs = _as_errors(errors, n)
    d = _dims_array(dims)
    q_cmd = q.copy()
    residual = np.empty((n, 6))
    singular = np.zeros(n, dtype=bool)
    iters_used = 0
    for s in range(0, n, CHUNK):
        t = min(n, s + CHUNK)
        cols = _chunk_cols(errs, s, t)
        pre = _pre_chain(q, cols, d, s, t)
        rid, pid = _ideal_parts(q, d, s, t)
        a0, b0 = q[s:t, 3], q[s:t, 4]
        a, b = a0.copy(), b0.copy()
        ua = pre.rot[0]  # d omega / dA = A e_x (Rx keeps e_x)
        for it in range(max_iter + 1):
            ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
            rot, ub = _post_rot(pre.rot, ca, sa, cb, sb, cols)
            wx, wy, _ = _omega(rot, rid)  # alpha, beta of W = T_real @ inv(T_ideal)
            # Newton on (alpha, beta) of W: d omega = u_a dA + u_b dB (2x2, closed form)
            j00, j10 = ua[0] + 0.0 * a, ua[1] + 0.0 * a
            j01, j11 = ub[0], ub[1]
            det = j00 * j11 - j01 * j10
            sing = np.abs(det) < SINGULAR_TOL
            if it == max_iter or (np.max(np.abs(wx)) <= tol_rad and np.max(np.abs(np.where(sing, 0.0, wy))) <= tol_rad):
                break
            safe = np.where(sing, 1.0, det)
            # singular poses: B no longer turns beta, so only alpha is driven (by A)
            a = a + np.where(sing, -wx / j00, -(j11 * wx - j01 * wy) / safe)
            b = b + np.where(sing, 0.0, -(j00 * wy - j10 * wx) / safe)
            iters_used = max(iters_used, it + 1)
        a = _quantise(a, resolution_rad)
        b = _quantise(b, resolution_rad)
        ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
        rot, pos = _post_pos(pre, ca, sa, cb, sb, cols, d)
        # W's translation vanishes when p_real = R_W @ p_ideal = R_real @ (R_ideal^T @ p_ideal)
        u = [rid[k] * pid[0] + rid[3 + k] * pid[1] + rid[6 + k] * pid[2] for k in range(3)]
        target = _matvec(rot, u)
        dxyz = _solve3(pre.jac, target - pos)
        xyz = [_quantise(q[s:t, k] + dxyz[k], resolution_mm) for k in range(3)]
        pos = pos + _matvec(pre.jac, [xyz[k] - q[s:t, k] for k in range(3)])  # affine in X, Y, Z: exact
        q_cmd[s:t, 0], q_cmd[s:t, 1], q_cmd[s:t, 2] = xyz
        q_cmd[s:t, 3], q_cmd[s:t, 4] = a, b
        residual[s:t, :3] = np.array(_omega(rot, rid)).T
        residual[s:t, 3:] = (pos - target).T
        _check_finite(cols, residual[s:t], *rot)
        singular[s:t] = sing
    return CompensationResult(
        q_cmd=q_cmd,
        residual=residual,
        singular=singular,
        uncompensable_roll=residual[:, 2].copy(),
        q_nominal=q,
        iterations=iters_used,
    )


def _omega(rot: tuple, rid: tuple) -> tuple:
    """alpha, beta, gamma (eq. 4.8 extraction) of R_real @ R_ideal^T, R_real held as columns."""

    def w(i: int, j: int) -> np.ndarray:
        return rot[0][i] * rid[3 * j] + rot[1][i] * rid[3 * j + 1] + rot[2][i] * rid[3 * j + 2]

    return 0.5 * (w(2, 1) - w(1, 2)), 0.5 * (w(0, 2) - w(2, 0)), 0.5 * (w(1, 0) - w(0, 1))


def _solve3(cols: tuple, v: np.ndarray) -> np.ndarray:
    """Solve the stacked 3x3 systems M x = v by Cramer's rule, M given by its columns."""
    (m00, m10, m20), (m01, m11, m21), (m02, m12, m22) = cols
    c00 = m11 * m22 - m12 * m21
    c01 = m12 * m20 - m10 * m22
    c02 = m10 * m21 - m11 * m20
    det = m00 * c00 + m01 * c01 + m02 * c02
    inv_cols = (
        _vec3(c00, c01, c02),
        _vec3(m02 * m21 - m01 * m22, m00 * m22 - m02 * m20, m01 * m20 - m00 * m21),
        _vec3(m01 * m12 - m02 * m11, m02 * m10 - m00 * m12, m00 * m11 - m01 * m10),
    )
    return _matvec(inv_cols, tuple(v)) / det
