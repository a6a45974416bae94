"""The cutting test of thesis ch. 7.3 on the virtual machine: a freeform surface cut three times.

The design surface (fig. 7.2 stands for "a surface which would require the motion of all of the
axes and be realistic compared to the surfaces created in the mold and die industry") is the
analytic height field of :class:`MouldSurface`: over ``u`` (across the part, 15 CMM points) and
``v`` (along the part, 99 CMM points, the direction of time)

    z(u, v) = h1 sin(pi v / L) cos(0.8 pi (u - W/2) / W) + h2 sin(2 pi v / L + pi u / W)

a doubly curved bump with an oblique ripple, whose normal tilts by up to about 20 degrees in
both directions. A ball-nose tool (radius 3 mm) is held along the surface normal, so the A and B
axes move with X, Y and Z; the tool centre follows the offset surface ``S + r n``. The program is
a raster of short 5-axis G1 blocks across the part (passes along ``u``, zig-zag, stepping along
``v``), at 2000 mm/min translation and at most 300 deg/min rotation, the spindle at 10,000 rpm.

While it runs, the virtual machine heats up: :class:`MachiningMachine` turns the spindle and the
mean feed of every axis into the heat sources of its thermal network for the time of the cut. The
program streams through the machine link (``daq.machine_link.SerialMachineLink``) to the
simulated controller, which executes it at the programmed feeds on the simulated clock; every
executed block is logged with its time. The compensator reads the 50 thermocouples through the
thermocouple-card driver (``daq.thermocouple.ThermocoupleCard``) from the simulated card. The machined
surface is the tool centre as the real,
error-laden chain (eq. 4.12 with the true link and joint errors of the virtual machine at the
moment the block ends) places it on the part; measured like the CMM of ch. 7.3 it is the normal
deviation from the design surface at 15 x 99 points.

Three runs (ch. 7.3): uncompensated; compensated with the off-line model (streamed through
``compensator.stream.Streamer``); and off-line plus the on-line model of ch. 6.4.3: every
15 minutes the program pauses, the touch probe measures reference spheres at the extremes of the
work space (``daq.probe.TouchProbe`` through the controller), and a recursive least-squares
model (eqs. 6.10-6.13) of what the off-line model leaves (measured minus predicted work-space
translation) is updated; its prediction is applied on top of the off-line model as a translation
of the spindle-side link T1, i.e. directly as axis offsets (ch. 7.2).

Conventions: the chain maps part coordinates to the spindle frame, the tool centre sits at the
spindle origin, so the machined point is ``inv(T_real) @ origin`` (part frame). A probed sphere
appears displaced by the work-space translation error at its pose (the convention of
``daq.sim.instruments.world_sphere_offset``), so the probe measures ``W`` directly. Hidden effects of
the scenario are defined as work-space errors of one axis moving with the others at home (spec
section 3); at a general pose each is the error of that axis' own joint which, with the other
axes at home, produces exactly that work-space error (allocated by eq. 4.20).
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NotRequired, Protocol, TypedDict

import httpx
import numpy as np
import pandas as pd

from driftlab.compensator.compensate import ErrorModel
from driftlab.compensator.gcode import parse_program
from driftlab.compensator.guard import Guard
from driftlab.compensator.stream import Streamer

if TYPE_CHECKING:
    from driftlab.compensator.stream import ModelSource
    from driftlab.models.document import ModelDocument
from driftlab.daemon import machining
from driftlab.daemon.machining import ExecutedBlock, MachiningMachine, Scenario, SimSphere, true_errors
from driftlab.daq.machine_link import SerialMachineLink
from driftlab.daq.probe import TouchProbe
from driftlab.daq.thermocouple import ThermocoupleCard
from driftlab.daq.transport import LineChannel, open_port
from driftlab.errors import InstrumentError, ValidationError
from driftlab.metrics import rmse
from driftlab.models import document as documents
from driftlab.models.document import predict_workspace_sd
from driftlab.models.envelope import Envelope
from driftlab.models.online import ONLINE_P0, rls_init, rls_update
from driftlab.physics import kinematics as kin
from driftlab.physics.lag import LaggedReadings, LagState
from driftlab.vocabulary import AXES

log = logging.getLogger(__name__)

#: ch. 7.3 cutting conditions
SPINDLE_RPM = 10000.0
FEED_MM_MIN = 2000.0
ROTARY_FEED_DEG_MIN = 300.0
#: ch. 7.3 CMM grid: 15 points across the part, 99 along it (the direction of time)
CMM_ACROSS = 15
CMM_ALONG = 99
#: ch. 7.3: "a single pass of the endmill up the centre of the part was done to provide a reference
#: surface for aligning the part on the machine and later on the CMM"; it is cut first, this much below
#: the design surface (the line "still noticeable in the surface" after the raster)
REFERENCE_DEPTH_MM = 0.1
#: the longest move of the hop from the reference pass to the raster (short enough to run as one block)
HOP_STEP_MM = 40.0
#: ch. 7.3: the on-line model was updated every 15 minutes
ONLINE_INTERVAL_S = 900.0
JOINT_OF_AXIS = {"X": "phi_x", "Y": "phi_y", "Z": "phi_z", "A": "theta_x", "B": "theta_y"}


# ----------------------------------------------------------------------------- the design surface


@dataclass(frozen=True)
class MouldSurface:
    """The analytic design surface of the cutting test (see the module docstring), part frame in mm."""

    width_mm: float = 112.0  # across (u): part y
    length_mm: float = 120.0  # along (v): part x, the direction of time
    h1_mm: float = 8.0
    h2_mm: float = 3.0
    tool_radius_mm: float = 3.0

    def height(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return the surface height z(u, v) (mm)."""
        W, L = self.width_mm, self.length_mm
        return self.h1_mm * np.sin(np.pi * v / L) * np.cos(0.8 * np.pi * (u - W / 2) / W) + self.h2_mm * np.sin(
            2 * np.pi * v / L + np.pi * u / W
        )

    def gradient(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (dz/du, dz/dv)."""
        W, L = self.width_mm, self.length_mm
        k = 0.8 * np.pi / W
        ph = 2 * np.pi * v / L + np.pi * u / W
        dzu = -self.h1_mm * np.sin(np.pi * v / L) * k * np.sin(k * (u - W / 2)) + self.h2_mm * np.pi / W * np.cos(ph)
        dzv = self.h1_mm * np.pi / L * np.cos(np.pi * v / L) * np.cos(
            k * (u - W / 2)
        ) + self.h2_mm * 2 * np.pi / L * np.cos(ph)
        return dzu, dzv

    def point(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return (N, 3) surface points in the part frame: x = v, y = u, z = height."""
        u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float))
        return np.stack([v, u, self.height(u, v)], axis=-1)

    def normal(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return (N, 3) outward unit normals (part frame; +z side)."""
        u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float))
        dzu, dzv = self.gradient(u, v)
        n = np.stack([-dzv, -dzu, np.ones_like(dzu)], axis=-1)  # x = v, y = u
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


def inverse_kinematics(
    centre: np.ndarray, axis: np.ndarray, dims: Mapping[str, Any] = kin.TABLE_A1, angle_step_deg: float = 0.001
) -> np.ndarray:
    """Return (N, 5) joints putting the tool centre on ``centre`` with the tool along ``axis`` (part frame).

    The ideal chain (eq. 4.19) turns the part by ``Rx(A) Ry(B)``; the tool axis is the spindle z,
    so ``Rx(A) Ry(B) n = e_z``: ``B = atan2(-n_x, n_z)``, ``A = atan2(n_y, -n_x sin B + n_z cos B)``.
    The angles are put on the program's grid first and X, Y, Z solved for them (the position of the
    chain is affine in X, Y, Z with unit slope), so rounding the angles does not move the tool centre.
    """
    c = np.atleast_2d(np.asarray(centre, float))
    n = np.atleast_2d(np.asarray(axis, float))
    b = np.arctan2(-n[:, 0], n[:, 2])
    a = np.arctan2(n[:, 1], -n[:, 0] * np.sin(b) + n[:, 2] * np.cos(b))
    step = np.deg2rad(angle_step_deg)
    a, b = np.round(a / step) * step, np.round(b / step) * step
    q = np.column_stack([np.zeros((len(c), 3)), a, b])
    T0 = kin.ideal_chain(q, dims)
    # spindle-frame position of the part point: R c + t; zero at the tool centre
    q[:, :3] = -(np.einsum("nij,nj->ni", T0[:, :3, :3], c) + T0[:, :3, 3])
    return q


def tool_centre(
    q: np.ndarray, errors: kin.ElementErrors | None = None, dims: Mapping[str, Any] = kin.TABLE_A1
) -> np.ndarray:
    """Return (N, 3) the tool centre (spindle origin) in the part frame for the chain at q (eq. 4.12)."""
    T = kin.machine_chain(q, errors, dims) if errors else kin.ideal_chain(q, dims)
    return kin.affine_inverse(T)[:, :3, 3]


# ----------------------------------------------------------------------------- the program


@dataclass(frozen=True)
class CuttingProgram:
    """The raster program of the cutting test and where each CMM point lies in it."""

    text: str
    #: (B, 5) block targets as written (mm, deg); block 0 is the rapid to above the first point
    pose_written: np.ndarray
    #: (B, 3) design tool centres and (B, 3) surface normals, part frame
    centre: np.ndarray
    normal: np.ndarray
    #: (B, 2) surface parameters (u across, v along) of each block's target
    uv: np.ndarray
    #: (3,) where the part frame's origin of the surface sits
    part_origin: np.ndarray
    #: (CMM_ALONG, CMM_ACROSS) block index whose end is each CMM point
    cmm_block: np.ndarray
    #: (CMM_ALONG,) block index whose end is each CMM point of the reference pass (ch. 7.3), along v
    reference_block: np.ndarray
    #: (B,) estimated duration of each block (s) at the programmed feeds
    block_s: np.ndarray
    #: mean |speed| of each axis over the cut, mm/min (deg/min for A, B)
    mean_feed: dict[str, float]
    surface: MouldSurface
    passes: int

    @property
    def duration_s(self) -> float:
        """Return the estimated cutting time (s)."""
        return float(self.block_s.sum())

    @property
    def start_pose(self) -> tuple[float, ...]:
        """Return the pose of the rapid move's target (mm, deg)."""
        return tuple(float(v) for v in self.pose_written[0])

    def lines(self) -> list[str]:
        """Return the program's lines."""
        return self.text.splitlines()


def make_program(
    surface: MouldSurface | None = None,
    passes: int = 700,
    *,
    part_origin: Sequence[float] | None = None,
    dims: Mapping[str, Any] = kin.TABLE_A1,
) -> CuttingProgram:
    """Return the cutting program: the reference pass, then ``passes`` zig-zag passes across the part.

    Ch. 7.3: first a single pass up the centre of the part (``u = W/2``, 99 points along ``v``,
    ``REFERENCE_DEPTH_MM`` deep), the reference the CMM aligns the part on; the tool then retracts to
    a clearance height above the part and comes down 10 mm above the raster's first point; then the
    raster, 15 points per pass (5-axis G1). The part sits on the table so that the middle of the cut is
    in the middle of the X, Y, Z travel (Tables A.3/A.4). Each G1 block's F makes the block last as long
    as the slower of 2000 mm/min translation and 300 deg/min rotation (ch. 7.3).
    """
    s = surface or MouldSurface()
    if passes < CMM_ALONG:
        raise ValidationError(f"the cutting test needs at least {CMM_ALONG} passes (one per CMM row), got {passes}")
    u = np.linspace(0.0, s.width_mm, CMM_ACROSS)
    v = np.linspace(0.0, s.length_mm, passes)
    uu = np.tile(u, (passes, 1))
    uu[1::2] = uu[1::2, ::-1]  # zig-zag
    vv = np.repeat(v[:, None], CMM_ACROSS, axis=1)
    uf, vf = uu.ravel(), vv.ravel()
    n = s.normal(uf, vf)
    c = s.point(uf, vf) + s.tool_radius_mm * n
    if part_origin is None:
        q0 = inverse_kinematics(c, n, dims)
        target = np.array([127.0, 127.0, -127.0])
        part_origin = (q0[:, :3].min(axis=0) + q0[:, :3].max(axis=0)) / 2 - target
    # block 0: the rapid to 10 mm above the reference pass' first point; then the reference pass, the hop
    # and the raster, point by point
    head = _reference_and_hop(s, c[0], n[0], (uf[0], vf[0]))
    c = np.vstack([head.centre, c]) + np.asarray(part_origin, float)
    n = np.vstack([head.normal, n])
    uf, vf = np.r_[head.uv[:, 0], uf], np.r_[head.uv[:, 1], vf]
    first = len(head.centre)  # block index of the raster's first point
    pose = _written_poses(inverse_kinematics(c, n, dims))
    feed, block_s = _feeds(pose)
    lines = [
        "%",
        "(driftlab cutting test, thesis ch. 7.3: freeform surface, ball nose r3)",
        "G90",
        f"S{SPINDLE_RPM:.0f} M3",
        "G0 " + _words(pose[0]),
    ]
    lines += [f"G1 {_words(p)} F{f:.1f}" for p, f in zip(pose[1:], feed[1:])]
    lines += ["M5", "%"]
    rows = np.round(np.linspace(0, passes - 1, CMM_ALONG)).astype(int)
    cols = np.arange(CMM_ACROSS)
    cmm = (
        first
        + rows[:, None] * CMM_ACROSS
        + np.where(rows[:, None] % 2 == 0, cols[None, :], CMM_ACROSS - 1 - cols[None, :])
    )
    dur = block_s.sum() / 60.0
    mean_feed = (
        {a: float(np.abs(np.diff(pose[:, k])).sum() / dur) for k, a in enumerate(AXES)}
        if dur > 0
        else {a: 0.0 for a in AXES}
    )
    return CuttingProgram(
        "\n".join(lines) + "\n",
        pose,
        c,
        n,
        np.column_stack([uf, vf]),
        np.asarray(part_origin, float),
        cmm,
        np.arange(1, 1 + CMM_ALONG),
        block_s,
        mean_feed,
        s,
        passes,
    )


@dataclass(frozen=True)
class _Head:
    """The program's blocks before the raster: the rapid, the reference pass and the hop (part frame)."""

    centre: np.ndarray  # (B, 3) tool centres, before the part's origin is added
    normal: np.ndarray  # (B, 3) tool axes
    uv: np.ndarray  # (B, 2) surface parameters


def _reference_and_hop(s: MouldSurface, c0: np.ndarray, n0: np.ndarray, uv0: tuple[float, float]) -> _Head:
    """Return the rapid, the reference pass up the centre (ch. 7.3) and the hop to above the raster's start.

    The reference pass has its CMM points at the 99 stations along ``v``, ``REFERENCE_DEPTH_MM`` below
    the surface. The hop: up 10 mm along the normal, up to a clearance plane 10 mm above the part's
    highest point, across (in steps of at most HOP_STEP_MM, the tool turning on the way) to above the
    raster's first point ``c0`` (normal ``n0``), down to 10 mm above it along its normal.
    """
    ru, rv = np.full(CMM_ALONG, s.width_mm / 2), np.linspace(0.0, s.length_mm, CMM_ALONG)
    rn = s.normal(ru, rv)
    rc = s.point(ru, rv) + (s.tool_radius_mm - REFERENCE_DEPTH_MM) * rn
    clear = float(s.h1_mm + s.h2_mm + s.tool_radius_mm + 10.0)
    up = rc[-1] + 10.0 * rn[-1]
    a, b = np.array([up[0], up[1], clear]), np.array([c0[0], c0[1], clear])
    k = max(1, int(np.ceil(np.linalg.norm(b - a) / HOP_STEP_MM)))
    w = np.linspace(0.0, 1.0, k + 1)[:, None]
    across_n = (1 - w) * rn[-1] + w * n0
    end = [ru[-1], rv[-1]]
    return _Head(
        np.vstack([rc[:1] + 10.0 * rn[:1], rc, up, a + w * (b - a), c0 + 10.0 * n0]),
        np.vstack([rn[:1], rn, rn[-1], across_n / np.linalg.norm(across_n, axis=1, keepdims=True), n0]),
        np.vstack([[ru[0], rv[0]], np.column_stack([ru, rv]), end, (1 - w) * end + w * list(uv0), list(uv0)]),
    )


def _written_poses(q: np.ndarray) -> np.ndarray:
    """Return the (B, 5) block targets as written: mm to 4 decimals, degrees to 3."""
    pose = q.copy()
    pose[:, 3:] = np.rad2deg(pose[:, 3:])
    pose[:, :3] = np.round(pose[:, :3], 4)
    pose[:, 3:] = np.round(pose[:, 3:], 3)
    return pose


def _feeds(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return each block's F (mm/min) and duration (s): the slower of 2000 mm/min and 300 deg/min (ch. 7.3)."""
    lin = np.r_[0.0, np.linalg.norm(np.diff(pose[:, :3], axis=0), axis=1)]
    rot = np.r_[0.0, np.linalg.norm(np.diff(pose[:, 3:], axis=0), axis=1)]
    t_min = np.maximum(lin / FEED_MM_MIN, rot / ROTARY_FEED_DEG_MIN)  # minutes per block
    feed = np.where(lin > 0, lin / np.where(t_min > 0, t_min, 1.0), FEED_MM_MIN)
    feed = np.clip(np.floor(feed * 10) / 10, 1.0, FEED_MM_MIN)
    block_s = np.where(lin > 0, 60.0 * lin / feed, 60.0 * rot / ROTARY_FEED_DEG_MIN)
    block_s[0] = 0.0
    return feed, block_s


def _words(p: np.ndarray) -> str:
    """Return the axis words of one pose (4 decimals in mm, 3 in deg)."""
    return f"X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f} A{p[3]:.3f} B{p[4]:.3f}"


# ----------------------------------------------------------------------------- the machine while it cuts


# ----------------------------------------------------------------------------- the controller's log


# ----------------------------------------------------------------------------- on-line model


class OnlineUpdater(Protocol):
    """The on-line model: updated from probe measurements, predicting the off-line model's residual."""

    version: int

    def update(self, xyz: Sequence[float], measured: np.ndarray, temperatures: Mapping[str, float], t_s: float) -> None:
        """Feed one probe measurement (work-space translation at pose X, Y, Z; A = B = 0)."""

    def predict(self, temperatures: Mapping[str, float]) -> np.ndarray:
        """Return the (3,) predicted residual translation (dx, dy, dz) for these temperatures."""


class LocalRLS:
    """The on-line RLS of eqs. 6.10-6.13 in process: one fit per translation on phi = [1, dT_k ...]."""

    def __init__(
        self, document: Any, channels: Sequence[str] = (), forgetting: float = 0.9, p0: float = ONLINE_P0
    ) -> None:
        self.doc = documents.validate_document(document)
        self.channels = list(channels)
        self.refs: dict[str, float] | None = None
        self.states = [rls_init(1 + len(self.channels), lam=forgetting, p0=p0) for _ in range(3)]
        self.version = 0

    def _phi(self, temps: Mapping[str, float]) -> np.ndarray:
        """Return the regressor vector of eq. 6.10."""
        if self.refs is None:
            self.refs = {
                c: (self.doc.inputs[c].reference if c in self.doc.inputs else float(temps[c])) for c in self.channels
            }
        return np.array([1.0, *[float(temps[c]) - self.refs[c] for c in self.channels]])

    def update(self, xyz: Sequence[float], measured: np.ndarray, temperatures: Mapping[str, float], t_s: float) -> None:
        """Update the three fits with measured minus off-line predicted translation (eqs. 6.11-6.13)."""
        q = np.array([[xyz[0], xyz[1], xyz[2], 0.0, 0.0]])
        offline = documents.predict_workspace_errors(self.doc, temperatures, q)[0, 3:]
        phi = self._phi(temperatures)
        self.states = [rls_update(st, phi, float(measured[k] - offline[k]))[0] for k, st in enumerate(self.states)]
        self.version += 1

    def predict(self, temperatures: Mapping[str, float]) -> np.ndarray:
        """Return the predicted residual translation (eq. 6.10)."""
        if self.version == 0:
            return np.zeros(3)
        phi = self._phi(temperatures)
        return np.array([float(phi @ st.theta) for st in self.states])


class OnlineModelSource:
    """A model source giving the off-line model plus the on-line prediction as a translation of T1 (ch. 7.2)."""

    def __init__(self, base: Any, online: OnlineUpdater) -> None:
        self.base = base
        self.online = online
        self._seen = -1
        self.model: ErrorModel | None = None

    def refresh(self) -> bool:
        """Refresh the off-line model; rebuild the combination when either part changed."""
        changed = bool(self.base.refresh())
        if changed or self.model is None or self.online.version != self._seen:
            self._seen = self.online.version
            self.model = self._combine(self.base.model)
            return True
        return False

    def _combine(self, off: ErrorModel) -> ErrorModel:
        """Return the off-line model with the on-line translation added to T1 (leftmost: W moves by it directly)."""
        online = self.online

        def predict(q: np.ndarray, temps: Any, direction: np.ndarray | None, at: Any = None) -> kin.ElementErrors:
            """Return the off-line element errors plus the on-line residual on T1."""
            errs = dict(off.predict(q, temps, direction) if at is None else off.predict(q, temps, direction, at=at))
            t = temps if isinstance(temps, Mapping) else {c: float(temps[c].iloc[-1]) for c in temps.columns}
            r = online.predict(t)
            t1 = np.array(errs["T1"], float, copy=True) if "T1" in errs else np.zeros((q.shape[0], 6))
            if t1.ndim == 1:
                t1 = np.broadcast_to(t1, (q.shape[0], 6)).copy()
            t1[:, 3:] += r
            errs["T1"] = t1
            return errs

        return ErrorModel(
            predict=predict,
            dims=off.dims,
            label=f"{off.label} + on-line ({online.version} updates)",
            channels=off.channels,
            machine=off.machine,
            ranges=off.ranges,
            envelope=off.envelope,
            lag_taus=off.lag_taus,
        )


# ----------------------------------------------------------------------------- a run


class ProbeCycleRecord(TypedDict):
    """One probing cycle of the on-line run: when, and each sphere's measured drift (dx, dy, dz mm)."""

    t_s: float
    spheres: dict[str, list[float]]


class RunSummary(TypedDict):
    """The JSON-ready figures of one cutting run (a row of the ch. 7.3 table)."""

    rmse_mm: float
    max_mm: float
    duration_min: float
    blocks: int
    probe_cycles: int
    unaligned_rmse_mm: NotRequired[float]  # before the alignment on the reference pass, when known
    stream: NotRequired[dict[str, int]]  # a streamed run: blocks_sent, recomputed, model_reloads


class OfflineInterval(TypedDict):
    """The off-line model's predicted interval of the cut beside what the CMM measured (mm)."""

    z: float
    predicted_rmse_mm: float
    mean_half_width_mm: float
    measured_rmse_mm: float
    inside: float  # the share of CMM points inside their interval


@dataclass
class RunResult:
    """One cutting run: the CMM deviations and what the streaming did."""

    name: str
    deviation_mm: np.ndarray  # (CMM_ALONG, CMM_ACROSS) normal deviation from the design surface
    duration_s: float
    blocks: int
    probes: list[ProbeCycleRecord] = field(default_factory=list)
    stream: dict[str, int] = field(default_factory=dict)  # blocks_sent, recomputed, model_reloads
    #: where and when the CMM points were cut, and the card's readings then (channel -> (N,) degC)
    cmm: CmmPoints | None = None
    readings: dict[str, np.ndarray] = field(default_factory=dict)
    #: (CMM_ALONG, CMM_ACROSS) normal deviation before the alignment on the reference pass (machine frame)
    absolute_mm: np.ndarray | None = None

    @property
    def rmse_mm(self) -> float:
        """Return the RMS normal deviation over the CMM grid."""
        return rmse(self.deviation_mm)

    @property
    def max_mm(self) -> float:
        """Return the largest absolute normal deviation."""
        return float(np.max(np.abs(self.deviation_mm)))

    def summary(self) -> RunSummary:
        """Return the JSON-ready figures of the run."""
        out: RunSummary = {
            "rmse_mm": round(self.rmse_mm, 6),
            "max_mm": round(self.max_mm, 6),
            "duration_min": round(self.duration_s / 60.0, 2),
            "blocks": self.blocks,
            "probe_cycles": len(self.probes),
        }
        if self.absolute_mm is not None:
            out["unaligned_rmse_mm"] = round(rmse(self.absolute_mm), 6)
        if self.stream:
            out["stream"] = self.stream
        return out


class CardTemperatures:
    """The latest scan of a thermocouple card (``daq.thermocouple.ThermocoupleCard``): a TemperatureSource."""

    def __init__(self, scanner: Any) -> None:
        self.scanner = scanner

    def read(self) -> dict[str, float]:
        """Return one fresh scan, degC per channel (NaN where a junction is open)."""
        return {c: float(v) for c, v in self.scanner.scan().values.items()}


@dataclass(frozen=True)
class CmmPoints:
    """Where and when the CMM points were machined: the end of one block each, in CMM grid order."""

    q: np.ndarray  # (N, 5) joint coordinates reached (mm, rad)
    t_s: np.ndarray  # (N,) time each block ended (s, bench clock)
    direction: np.ndarray  # (N, 5) approach direction of each axis (+1/-1)
    normal: np.ndarray  # (N, 3) design surface normal (part frame)


def cmm_points(program: CuttingProgram, log_: Sequence[ExecutedBlock]) -> CmmPoints:
    """Return the CMM points of a run from the controller's log (one executed block per program block)."""
    return _block_points(program, log_, program.cmm_block.ravel())


def _block_points(program: CuttingProgram, log_: Sequence[ExecutedBlock], idx: np.ndarray) -> CmmPoints:
    """Return where and when the blocks ``idx`` ended, from the controller's log, with their design normals."""
    n_prog = program.pose_written.shape[0]
    if len(log_) != n_prog:
        raise ValidationError(f"the controller executed {len(log_)} blocks, the program has {n_prog}")
    all_target = np.array([b.target for b in log_])
    all_start = np.array([b.start for b in log_])
    q = all_target[idx].copy()
    q[:, 3:] = np.deg2rad(q[:, 3:])
    t_end = np.array([log_[i].t_end_s for i in idx])
    return CmmPoints(q, t_end, approach_directions(all_start, all_target)[idx], program.normal[idx])


def _normal_deviations(
    vm: MachiningMachine, program: CuttingProgram, pts: CmmPoints, idx: np.ndarray, dims: Mapping[str, Any]
) -> np.ndarray:
    """Return the normal deviations (mm) of the cut at the ends of blocks ``idx`` (``pts``: where and when)."""
    real = tool_centre(pts.q, true_errors(vm, pts.t_s, pts.q, pts.direction), dims)
    return np.einsum("ij,ij->i", real - program.centre[idx], pts.normal)


def align_on_reference(deviation: np.ndarray, reference: np.ndarray, surface: MouldSurface) -> np.ndarray:
    """Return the (99, 15) deviations as the CMM reports them, aligned on the reference pass (ch. 7.3).

    The part is aligned on the CMM by the line cut up its centre: the height and the pitch of that
    line (a straight line ``a + b v`` fitted by least squares to the reference pass' 99 normal
    deviations along ``v``) define the part's datum, and are taken from every point. What the machine
    did the same to the reference and to the surface (a constant offset, a tilt along the part) is the
    part's set-up, not its form.
    """
    v = np.linspace(0.0, surface.length_mm, len(reference))
    b, a = np.polyfit(v, reference, 1)
    rows = np.linspace(0.0, surface.length_mm, deviation.shape[0])
    return deviation - (a + b * rows)[:, None]


def measure_surface(
    vm: MachiningMachine,
    program: CuttingProgram,
    log_: Sequence[ExecutedBlock],
    dims: Mapping[str, Any] = kin.TABLE_A1,
    *,
    aligned: bool = True,
) -> np.ndarray:
    """Return the (99, 15) normal deviations (mm) of the machined surface at the CMM points.

    Each CMM point is the end of one block: the tool centre there is placed by the real chain at
    the pose the controller reached, with the true errors of the moment it got there. With
    ``aligned`` (the CMM of ch. 7.3), the deviations are relative to the reference pass
    (``align_on_reference``); else they are from the design surface in the machine's own frame.
    """
    absolute, aligned_dev, _ = _surface(vm, program, log_, dims)
    return aligned_dev if aligned else absolute


def _surface(
    vm: MachiningMachine, program: CuttingProgram, log_: Sequence[ExecutedBlock], dims: Mapping[str, Any]
) -> tuple[np.ndarray, np.ndarray, CmmPoints]:
    """Return the (99, 15) deviations before and after the alignment on the reference pass, and the CMM points."""
    pts = cmm_points(program, log_)
    idx = program.cmm_block.ravel()
    absolute = _normal_deviations(vm, program, pts, idx, dims).reshape(program.cmm_block.shape)
    ref_idx = program.reference_block
    ref = _normal_deviations(vm, program, _block_points(program, log_, ref_idx), ref_idx, dims)
    return absolute, align_on_reference(absolute, ref, program.surface), pts


def approach_directions(start: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Return (B, 5) +1/-1 per axis: the sign of the last move of each axis up to each block (+1 before any)."""
    sgn = np.sign(target - start)
    idx = np.arange(len(sgn))[:, None]
    last = np.maximum.accumulate(np.where(sgn != 0, idx, -1), axis=0)
    picked = np.take_along_axis(sgn, np.maximum(last, 0), axis=0)
    return np.where(last >= 0, picked, 1.0)


class CuttingBench:
    """The virtual machine, its simulated controller and the machine link for one cutting run."""

    def __init__(
        self,
        scenario: Scenario,
        program: CuttingProgram,
        *,
        lead_s: float = 300.0,
        spheres: Mapping[str, SimSphere] | None = None,
        capacity: int = 16,
        age_s: float = 0.0,
    ) -> None:
        self.program = program
        # the machine is switched on at t = 0 (soaked at room temperature) and cuts after lead_s
        self.clock, self.vm, self.ctrl, self.card = machining.open_bench(
            scenario,
            lead_s,
            lead_s + program.duration_s,
            program.mean_feed,
            spheres=spheres or machining.default_spheres(),
            capacity=capacity,
            age_s=age_s,
        )
        self.lead_s = lead_s
        self.first_block = 0
        # the 50 thermocouples of Table 5.1 on the simulated card, read through the real driver
        card_map = dict(enumerate(machining.CHANNELS))
        self.temperatures = CardTemperatures(
            ThermocoupleCard(
                LineChannel(open_port(machining.serial_url(self.card)), "thermocouple card"),
                card_map,
                clock=self.clock.now,
            )
        )
        self.link = SerialMachineLink.open(machining.serial_url(self.ctrl), sleep=self.clock.sleep, poll_s=0.5)

    def close(self) -> None:
        """Close the link and the card, stop the simulated instruments."""
        self.link.close()
        self.temperatures.scanner.close()
        self.ctrl.close()
        self.card.close()

    def __enter__(self) -> CuttingBench:
        """Return the bench (closed on exit)."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Close the link and stop the controller."""
        self.close()

    def rapid_to_start(self) -> None:
        """Send the head of the program (up to the rapid to the first point) and wait until the cut may start."""
        lines = self.program.lines()
        self.link.send_program([ln for ln in lines if ln.startswith(("S", "G90"))], wait=True)
        self.first_block = len(self.ctrl.log)  # the log from the rapid on is the program's motion
        self.link.send_program([ln for ln in lines if ln.startswith("G0")], wait=True)
        self.clock.advance_to(self.lead_s)

    def probe_cycle(self, online: OnlineUpdater, temps: Mapping[str, float]) -> ProbeCycleRecord:
        """Probe every sphere, feed the on-line model, return what was measured (ch. 6.4.3)."""
        probe = TouchProbe.on_link(self.link, stylus_radius_mm=self.ctrl.stylus_radius_mm, lobing=self.ctrl.lobing)
        out: ProbeCycleRecord = {"t_s": self.clock.now(), "spheres": {}}
        for name, sph in self.ctrl.spheres.items():
            m = probe.probe_sphere(name, sph.centre, sph.radius_mm)
            measured = np.asarray(m.centre) - np.asarray(sph.centre)
            online.update(sph.centre, measured, temps, self.clock.now())
            out["spheres"][name] = [round(float(x), 6) for x in measured]
            self.clock.sleep(15.0)  # moving to and touching one sphere takes about 15 s of machine time
        return out


def _chunks(program: CuttingProgram, interval_s: float) -> list[tuple[int, int]]:
    """Return [start, end) block ranges of about ``interval_s`` machining time each (block 0 excluded)."""
    t = np.cumsum(program.block_s)
    out, s = [], 1
    n = program.pose_written.shape[0]
    while s < n:
        e = int(np.searchsorted(t, t[s - 1] + interval_s, side="right"))
        e = min(n, max(e, s + 1))
        out.append((s, e))
        s = e
    return out


def run_uncompensated(bench: CuttingBench) -> RunResult:
    """Stream the program as written and measure the part."""
    bench.rapid_to_start()
    body = [ln for ln in bench.program.lines() if ln.startswith("G1")]
    t0 = bench.clock.now()
    bench.link.send_program(body, wait=True)
    return _result("uncompensated", bench, t0)


def run_compensated(
    bench: CuttingBench,
    models: Any,
    *,
    online: OnlineUpdater | None = None,
    interval_s: float = ONLINE_INTERVAL_S,
    name: str | None = None,
    max_segment_mm: float = 100.0,
    max_segment_deg: float = 30.0,
    epoch_s: float | None = None,
) -> RunResult:
    """Stream the program through the compensator (with the on-line model every ``interval_s`` when given).

    The blocks are short on the part already (8 mm); their machine-axis travel is longer through the
    rotary axes' levers, so the subdivision limits are set above it: one executed block per program
    block, which is how the CMM points are found in the controller's log.
    """
    bench.rapid_to_start()
    temps = bench.temperatures
    lines = bench.program.lines()
    g1 = [i for i, ln in enumerate(lines) if ln.startswith("G1")]
    ranges = _chunks(bench.program, interval_s) if online is not None else [(1, bench.program.pose_written.shape[0])]
    source = OnlineModelSource(models, online) if online is not None else models
    guard = bench_guard(source)  # the envelope checks of `driftlab compensate`: nothing leaves unchecked
    t0 = bench.clock.now()
    probes: list[ProbeCycleRecord] = []
    stream: dict[str, Any] = {"blocks_sent": 0, "recomputed": 0, "model_reloads": 0}
    pose = bench.program.start_pose
    # the lags of the readings (ch. 5.3) for the model's lagged terms, kept over the whole run
    lags = LagState(models.model.lag_taus if models.model is not None else ())
    for s, e in ranges:
        if online is not None:
            scan = temps.read()
            lags.update(bench.clock.now(), scan)
            probes.append(bench.probe_cycle(online, LaggedReadings(scan, lags.values())))
        text = "\n".join(lines[g1[s - 1] : g1[e - 2] + 1]) + "\n"
        prog = parse_program(text, name="cutting-test", start=pose, min_decimals=(4, 3))
        streamer = Streamer(
            prog,
            source,
            temps,
            max_segment_mm=max_segment_mm,
            max_segment_deg=max_segment_deg,
            clock=bench.clock.now,
            sleep=bench.clock.sleep,
            timer=time.perf_counter,
            epoch_s=epoch_s,
            lags=lags,
            guard=guard,
        )
        res = streamer.run(bench.link, low_water=4)
        done: Mapping[str, object] = res.summary()
        for k in stream:
            stream[k] += done[k]
        pose = tuple(float(v) for v in bench.program.pose_written[e - 1])
    out = _result(name or ("off-line + on-line" if online is not None else "off-line"), bench, t0)
    out.probes = probes
    out.stream = stream
    return out


def bench_guard(source: ModelSource) -> Guard:
    """Return the envelope guard of a model source on the bench: the model's envelope and fitted ranges,
    the virtual machine's travel (Tables A.3, A.4) taking precedence."""
    source.refresh()
    if source.model is None:
        raise ValidationError("no model to compensate with")
    return Guard.for_model(source.model, Envelope(travel=machining.travel(), source="the virtual machine"))


def _result(name: str, bench: CuttingBench, t0: float) -> RunResult:
    """Return the run's CMM figures from the controller's log."""
    log_ = bench.ctrl.log[bench.first_block :]
    absolute, dev, pts = _surface(bench.vm, bench.program, log_, kin.TABLE_A1)
    # the thermocouple card's readings at each CMM point (what the compensator read then)
    scans = bench.vm.readings_array(pts.t_s)
    readings = {c: scans[:, k] for k, c in enumerate(machining.CHANNELS)}
    duration = (log_[-1].t_end_s - t0) if log_ else 0.0
    return RunResult(name, dev, duration, len(log_), cmm=pts, readings=readings, absolute_mm=absolute)


def offline_interval(
    document: ModelDocument | Mapping[str, object], run: RunResult, *, epoch_s: float | None = None, z: float = 1.96
) -> OfflineInterval | None:
    """Return the off-line model's predicted interval of the cut beside what the CMM measured, or None.

    The document's term covariances and residual variances (``models.document.predict_workspace_sd``,
    issue 21.4) give the standard deviation of the work-space translation at each CMM point, at the
    readings of that moment; projected on the surface normal (components taken independent) it is the
    predicted spread of the normal deviation there. Returned: the predicted RMSE (the root mean square
    of those), the mean half-width of the ``z`` interval, and the share of CMM points whose measured
    deviation lies inside their interval (0.95 for an honest model at z = 1.96).
    """
    if run.cmm is None or not run.readings:
        return None
    pts = run.cmm
    order = np.argsort(pts.t_s, kind="stable")  # lagged terms read the readings in time order
    frame = pd.DataFrame({"time_s": pts.t_s[order], **{c: v[order] for c, v in run.readings.items()}})
    at = None if epoch_s is None else epoch_s + pts.t_s[order]
    sd = predict_workspace_sd(document, frame, pts.q[order], pts.direction[order], at=at)
    if sd is None:
        return None
    sd_n = np.empty(len(order))
    sd_n[order] = np.sqrt(np.sum((pts.normal[order] * sd[:, 3:]) ** 2, axis=1))
    # the interval is of the error itself, before the CMM's alignment on the reference pass
    absolute = run.deviation_mm if run.absolute_mm is None else run.absolute_mm
    dev = absolute.ravel()
    return {
        "z": z,
        "predicted_rmse_mm": round(float(np.sqrt(np.mean(sd_n**2))), 6),
        "mean_half_width_mm": round(float(np.mean(z * sd_n)), 6),
        "measured_rmse_mm": round(rmse(absolute), 6),
        "inside": round(float(np.mean(np.abs(dev) <= z * sd_n)), 3),
    }


# ----------------------------------------------------------------------------- the test


@dataclass
class CuttingTest:
    """The three runs of ch. 7.3 and their table."""

    runs: dict[str, RunResult]
    program: CuttingProgram
    #: the off-line model's predicted interval beside the measured cut (``offline_interval``), when known
    offline_predicted: OfflineInterval | None = None

    def table(self) -> dict[str, RunSummary]:
        """Return {run: {rmse_mm, max_mm, ...}} for uncompensated, offline and online."""
        return {k: r.summary() for k, r in self.runs.items()}

    def ordered(self) -> bool:
        """Return True when uncompensated > off-line > off-line + on-line in RMSE (the thesis' ordering)."""
        r = [self.runs[k].rmse_mm for k in ("uncompensated", "offline", "online")]
        return r[0] > r[1] > r[2]


#: the thesis' figures (ch. 7.3), mm
THESIS_TABLE = {
    "uncompensated": {"rmse_mm": 0.060, "max_mm": 0.082},
    "offline": {"rmse_mm": 0.005, "max_mm": 0.015},
    "online": {"rmse_mm": 0.003, "max_mm": 0.012},
}


@dataclass(frozen=True)
class CuttingSession:
    """How each run of the cutting test goes: ``lead_s`` of warm-up before the cut, the on-line model's interval."""

    lead_s: float = 300.0
    interval_s: float = ONLINE_INTERVAL_S


def run_cutting_test(
    scenario: Scenario,
    models: Callable[[], Any],
    online: Callable[[], OnlineUpdater],
    *,
    passes: int = 700,
    age_s: float = 0.0,
    on_run: Callable[[str], None] | None = None,
    epoch_s: float | None = None,
    session: CuttingSession = CuttingSession(),
) -> CuttingTest:
    """Return the three runs of the cutting test, each on a fresh, cold virtual machine.

    Each run switches the machine on, waits ``session.lead_s`` and cuts; ``age_s`` is how long after the
    campaign's start the runs take place (see ``MachiningMachine``).

    ``models()`` returns a fresh model source (``compensator.stream`` ModelSource: a StaticModel or
    an ApiModel), ``online()`` a fresh on-line model (LocalRLS, or one kept by the API).
    ``epoch_s`` is the POSIX time of the bench's t = 0 (the campaign's start plus ``age_s``): each block
    is then corrected for the time it runs, so a model's drift terms follow the session (ch. 6.4.3).
    """
    program = make_program(passes=passes)
    runs: dict[str, RunResult] = {}
    for key in ("uncompensated", "offline", "online"):
        with CuttingBench(scenario, program, lead_s=session.lead_s, age_s=age_s) as bench:
            if key == "uncompensated":
                runs[key] = run_uncompensated(bench)
            elif key == "offline":
                runs[key] = run_compensated(bench, models(), name="off-line", epoch_s=epoch_s)
            else:
                runs[key] = run_compensated(
                    bench, models(), online=online(), interval_s=session.interval_s, epoch_s=epoch_s
                )
        if on_run is not None:
            on_run(key)
    return CuttingTest(runs, program)


def format_table(test: CuttingTest) -> list[tuple[str, str, str, str, str]]:
    """Return rows (run, RMSE, max, thesis RMSE, thesis max) in mm, for printing."""
    names = {"uncompensated": "without compensation", "offline": "off-line model", "online": "off-line + on-line"}
    return [
        (
            names[k],
            f"{r.rmse_mm:.4f}",
            f"{r.max_mm:.4f}",
            f"{THESIS_TABLE[k]['rmse_mm']:.3f}",
            f"{THESIS_TABLE[k]['max_mm']:.3f}",
        )
        for k, r in test.runs.items()
    ]


class ApiRLS:
    """The on-line model kept by the driftlab API (``POST /machines/{id}/online/probe``, eqs. 6.10-6.13).

    Each probe measurement is posted with the temperatures; the API updates the machine's RLS state
    of the current model version (phi = [1], eq. 6.10) and answers with its coefficients, from
    which the residual is predicted here for every block.
    """

    def __init__(
        self,
        api: str,
        machine: str,
        *,
        token: str | None = None,
        forgetting: float = 0.9,
        client: Any | None = None,
        started_at: float | None = None,
    ) -> None:
        self.url = f"{api.rstrip('/')}/machines/{machine}/online/probe"
        self.forgetting = forgetting
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.client = client or httpx.Client(timeout=10.0, headers=headers)
        self.theta = np.zeros((3, 1))
        self.version = 0
        self.replies: list[dict[str, Any]] = []
        self.epoch_s = time.time() if started_at is None else started_at

    def update(self, xyz: Sequence[float], measured: np.ndarray, temperatures: Mapping[str, float], t_s: float) -> None:
        """Post one probe measurement; keep the coefficients the API answers with."""
        temps = {c: round(float(v), 4) for c, v in temperatures.items() if np.isfinite(v)}
        body: dict[str, Any] = {
            "x": float(xyz[0]),
            "y": float(xyz[1]),
            "z": float(xyz[2]),
            "a_deg": 0.0,
            "b_deg": 0.0,
            "dx": float(measured[0]),
            "dy": float(measured[1]),
            "dz": float(measured[2]),
            "temperatures": temps,
            "measured_at": _dt.datetime.fromtimestamp(self.epoch_s + t_s, _dt.UTC).isoformat(),
        }
        if self.version == 0:
            body["forgetting"] = self.forgetting
        reply = self.client.post(self.url, json=body)
        if reply.status_code != 200:
            raise InstrumentError(f"on-line update refused by {self.url}: HTTP {reply.status_code} {reply.text[:200]}")
        out = reply.json()
        self.theta = np.array([out["theta"][c] for c in ("dx", "dy", "dz")], float)
        self.replies.append(out)
        self.version += 1

    def predict(self, temperatures: Mapping[str, float]) -> np.ndarray:
        """Return the predicted residual translation (eq. 6.10 with phi = [1])."""
        if self.version == 0:
            return np.zeros(3)
        return self.theta @ np.ones(self.theta.shape[1])
