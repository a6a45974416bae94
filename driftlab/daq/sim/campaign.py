"""Simulated test campaigns on the virtual machine, as bundle v1 frames (docs/bundle.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from driftlab.daq.sim import truth
from driftlab.daq.sim.machine import VirtualMachine
from driftlab.daq.sim.scenario import Scenario
from driftlab.daq.sim.sites import CHANNELS, ROOM_CHANNELS, SITE_INDEX, channel_map
from driftlab.metrics import rmse
from driftlab.vocabulary import AXES, TERMS


@dataclass(frozen=True)
class SimulatedCampaign:
    """One simulated campaign: campaign.json dict, the three bundle frames, and the planted truth."""

    meta: dict[str, Any]
    temperatures: pd.DataFrame
    conditions: pd.DataFrame
    errors: pd.DataFrame
    truth: dict[str, Any] = field(default_factory=dict)


def machine_travel() -> dict[str, list[float]]:
    """Return the virtual machine's travel as campaign.json states it (mm for X Y Z, degrees for A B)."""
    return {axis: [float(lo), float(hi)] for axis, (lo, hi) in truth.AXIS_RANGE.items()}


def campaign_meta(scenario: Scenario, machine: VirtualMachine | None = None) -> dict[str, Any]:
    """Return the campaign.json document (bundle v1) of a scenario."""
    vm = machine or VirtualMachine(scenario)
    return {
        "format": "driftlab-bundle/1",
        # the virtual machine's travel (Tables A.3, A.4) goes with the campaign, so a model fitted on it
        # carries its machine's limits into the compensator's envelope (docs/compensate.md)
        "machine": {**scenario.machine.model_dump(mode="json", exclude_none=True), "travel": machine_travel()},
        "started_at": scenario.started_at,
        "channels": channel_map(),
        "room_channels": list(ROOM_CHANNELS),
        "model_channels": {ax: list(chs) for ax, chs in truth.MODEL_CHANNELS.items()},
        "stages": [st.model_dump() for st in vm.stages],
        "noise": {"length_mm": scenario.noise.length_mm, "angle_rad": scenario.noise.angle_rad},
    }


def sweep_points(scenario: Scenario) -> pd.DataFrame:
    """Return one laser sweep's points: axis, position (bundle units), direction, in measuring order."""
    rows: list[tuple[str, float, int]] = []
    for axis in AXES:
        lo, hi = truth.AXIS_RANGE[axis]
        pos = np.linspace(lo, hi, scenario.points_per_axis)
        for direction, order in ((1, pos), (-1, pos[::-1])):  # both approach directions (ch. 5.5)
            rows.extend((axis, float(p), direction) for p in order)
    return pd.DataFrame(rows, columns=["axis", "position", "direction"])


def simulate_campaign(scenario: Scenario) -> SimulatedCampaign:
    """Run the staged plan on the virtual machine: scans every scan_interval_s, full laser sweeps every
    sweep_interval_s."""
    vm = VirtualMachine(scenario)
    end = scenario.duration_s
    vm.advance_to(end)
    scan_t = np.arange(0.0, end + 1e-9, scenario.scan_interval_s)
    temps = pd.DataFrame(vm.readings_array(scan_t), columns=list(CHANNELS))
    temps.insert(0, "time_s", scan_t)
    state = vm.state_array(scan_t)
    conditions = pd.DataFrame({"time_s": scan_t, **state})

    sweep_t = np.arange(0.0, end + 1e-9, scenario.sweep_interval_s)
    pts = sweep_points(scenario)
    n_pts, n_sw = len(pts), len(sweep_t)
    frames = []
    for axis in AXES:
        sel = (pts["axis"] == axis).to_numpy()
        pos = np.tile(pts["position"].to_numpy()[sel], n_sw)
        d = np.tile(pts["direction"].to_numpy()[sel], n_sw)
        t = np.repeat(sweep_t, sel.sum())
        values = vm.measure_errors_array(t, axis, pos, d)  # (n, 6)
        order = np.tile(np.flatnonzero(sel), n_sw) + np.repeat(np.arange(n_sw) * n_pts, sel.sum())
        frames.append((order, t, pos, d, values, axis))
    # interleave back into measuring order: sweep, axis, direction, position; six terms per point
    n = n_pts * n_sw
    t_all = np.empty(n)
    pos_all = np.empty(n)
    d_all = np.empty(n, dtype=np.int64)
    ax_all = np.empty(n, dtype=object)
    val_all = np.empty((n, 6))
    for order, t, pos, d, values, axis in frames:
        t_all[order], pos_all[order], d_all[order], ax_all[order], val_all[order] = t, pos, d, axis, values
    errors = pd.DataFrame(
        {
            "time_s": np.repeat(t_all, 6),
            "axis": np.repeat(ax_all, 6),
            "term": np.tile(np.array(TERMS, dtype=object), n),
            "position": np.repeat(pos_all, 6),
            "direction": np.repeat(d_all, 6),
            "value": val_all.ravel(),
        }
    )
    errors["axis"] = errors["axis"].astype(str)
    errors["term"] = errors["term"].astype(str)
    return SimulatedCampaign(
        campaign_meta(scenario, vm), temps, conditions, errors, _truth_record(scenario, vm, sweep_t)
    )


def _truth_record(scenario: Scenario, vm: VirtualMachine, sweep_t: np.ndarray) -> dict[str, Any]:
    """Return what was planted: base coefficients of every (axis, term), hidden effects with their sizes."""
    base = truth.base_coefficients()
    hidden = []
    for eff in scenario.hidden:
        rec: dict[str, Any] = eff.model_dump()
        if eff.kind == "thermal_lag":
            rec["coef_per_degC"] = truth.lag_coefficient(eff)
        if eff.kind == "sensor_fault":  # how far the readings leave the structure after start_s
            scan_t = np.arange(float(eff.params["start_s"]), scenario.duration_s + 1e-9, scenario.scan_interval_s)
            if scan_t.size:
                idx = [SITE_INDEX[c] for c in eff.channels]
                off = vm.readings_array(scan_t)[:, idx] - vm.true_temperatures_array(scan_t)[:, idx]
                fin = np.isfinite(off)
                rec["reading_offset_rms_degC"] = rmse(off[fin]) if fin.any() else None
        else:
            assert eff.axis is not None  # HiddenEffect: every kind but sensor_fault has an axis
            pts = sweep_points(scenario)
            pts = pts[pts["axis"] == eff.axis]
            t = np.repeat(sweep_t, len(pts))
            pos = np.tile(pts["position"].to_numpy(), len(sweep_t))
            d = np.tile(pts["direction"].to_numpy(), len(sweep_t))
            dT = vm.true_dT_array(t)[:, SITE_INDEX[eff.channels[0]]] if eff.channels else None
            lag = vm.lagged_dT(eff.channels[0], float(eff.params["tau_s"]), t) if eff.kind == "thermal_lag" else None
            delta = truth.hidden_delta(eff, t, pos, d, dT, lag)
            rec["rms"] = rmse(delta)
            rec["peak"] = float(np.max(np.abs(delta)))
            # the part no standard model (spec section 2) can absorb: what diagnosis can find at best
            model = [SITE_INDEX[c] for c in truth.MODEL_CHANNELS[eff.axis]]
            X = np.column_stack([np.vander(pos, 4, increasing=True), vm.true_dT_array(t)[:, model]])
            X = X / np.where(X.std(axis=0) > 0, X.std(axis=0), 1.0)
            coef, *_ = np.linalg.lstsq(X, delta, rcond=None)
            rec["rms_beyond_standard_model"] = rmse(delta - X @ coef)
        hidden.append(rec)
    return {
        "alpha_c_per_degC": truth.ALPHA_C,
        "dT_reference": "true structure temperature at t = 0 s",
        "base": base,
        "model_channels": {ax: list(chs) for ax, chs in truth.MODEL_CHANNELS.items()},
        "drivers": list(truth.DRIVERS),
        "thermal_terms": [
            {"element": e, "param": p, "coef": c, "weights": dict(w), "relationship": why}
            for e, p, c, w, why in truth.THERMAL_TERMS
        ],
        "noise": scenario.noise.model_dump(),
        "hidden": hidden,
    }
