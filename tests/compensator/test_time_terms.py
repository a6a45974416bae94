"""Time-dependent model terms (drift, ch. 6.4.3) are evaluated at each block's time, not at 'now'."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import pytest

from driftlab.compensator.compensate import ErrorModel, correct_points
from driftlab.compensator.gcode import parse_program
from driftlab.compensator.stream import FixedTemperatures, StaticModel, Streamer, subdivide
from driftlab.daq.sim.instruments import ManualClock
from driftlab.models.features import Feature

ORIGIN = datetime(2026, 3, 2, 8, 0, tzinfo=UTC)
RATE_MM_PER_DAY = 0.004  # wear of the Z slideways (ch. 6.4.3)
PROGRAM = "G90 G1 X10 Y10 Z-10 F2000\nG1 X20 Y10 Z-10\nG1 X30 Y20 Z-12\n"


def _doc() -> dict:
    return {
        "machine": "m1",
        "version": 1,
        "time_origin": ORIGIN.isoformat(),
        "inputs": {"T1": {"reference": 20.0, "min": 10.0, "max": 40.0}},
        "terms": [
            {
                "element": "phi_z",
                "param": "dz",
                "features": [Feature("time", label="Z").to_dict()],
                "coefficients": [RATE_MM_PER_DAY],
                "statistics": {"rmse_train": 0.0},
            }
        ],
    }


def _z_correction(at: float) -> np.ndarray:
    prog = parse_program(PROGRAM, name="p")
    pts = subdivide(prog, 5.0, 5.0)
    corr = correct_points(prog, pts, ErrorModel.from_document(_doc()), {"T1": 20.0}, at=at)
    return corr.desired[:, 2]


def test_correct_points_evaluates_drift_at_the_given_time():
    day0, day3 = _z_correction(ORIGIN.timestamp()), _z_correction(ORIGIN.timestamp() + 3 * 86400)
    # the Z error grows by 3 days x rate; the correction moves the other way by the same amount
    assert day3 - day0 == pytest.approx(np.full(day0.shape, -3 * RATE_MM_PER_DAY), abs=1e-9)


def _streamed(epoch_s: float, start_s: float) -> list[str]:
    clock = ManualClock(start_s)
    prog = parse_program(PROGRAM, name="p")
    s = Streamer(
        prog,
        StaticModel(ErrorModel.from_document(_doc())),
        FixedTemperatures({"T1": 20.0}),
        clock=clock.now,
        sleep=clock.sleep,
        epoch_s=epoch_s,
    )
    s.prime()
    return list(s.lines())


def test_the_streamer_corrects_each_block_for_the_clock_time_it_is_prepared():
    # a session on the simulated clock: t = 0 is two days after the model's time origin
    late = _streamed(ORIGIN.timestamp() + 2 * 86400, 0.0)
    early = _streamed(ORIGIN.timestamp(), 0.0)
    assert late != early
    z = lambda lines: [float(w[1:]) for ln in lines for w in ln.split() if w.startswith("Z")]  # noqa: E731
    assert np.allclose(np.array(z(late)) - np.array(z(early)), -2 * RATE_MM_PER_DAY, atol=0.0025 + 1e-9)
    # the same instant reached through the clock instead of the epoch gives the same blocks
    assert _streamed(ORIGIN.timestamp(), 2 * 86400.0) == late
