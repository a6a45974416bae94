"""The daemon loop's run states (a transition table; an illegal transition refused) and its narrowed clock."""

from __future__ import annotations

import math
import sys
import threading
from pathlib import Path

import pytest

from driftlab.campaigns.acquisition import Batch, open_campaign
from driftlab.campaigns.clock import SimClock, WallClock
from driftlab.campaigns.plan import Cursor, Plan, parse_plan
from driftlab.daemon.clocks import LoopClock, PacedClock, check_supports, narrow_clock
from driftlab.daemon.loop import RunStats, Scheduler, SchedulerOptions
from driftlab.daemon.runstate import TRANSITIONS, IllegalTransition, RunState, RunStateMachine
from driftlab.daemon.simrig import scenario_meta
from driftlab.errors import ConflictError
from tests.daemon.sim_helpers import SimRun, plant_reading, sim_run

ROOT = Path(__file__).resolve().parents[2]
S = RunState


def test_the_table_names_every_state_and_final_states_go_nowhere() -> None:
    """Every state has a row; finished, stopped, aborted and failed are final; any live state may fail."""
    assert set(TRANSITIONS) == set(RunState)
    assert [s for s, to in TRANSITIONS.items() if not to] == [S.FINISHED, S.STOPPED, S.ABORTED, S.FAILED]
    for state, allowed in TRANSITIONS.items():
        if allowed and state is not S.IDLE:
            assert S.FAILED in allowed, state


@pytest.mark.parametrize(
    ("path", "illegal"),
    [
        ([], S.FINISHED),  # idle cannot finish without running
        ([S.RUNNING, S.FINISHED], S.RUNNING),  # a finished run does not run again
        ([S.RUNNING, S.STOPPING], S.PACED),  # a stopping run reads no more blocks
        ([S.RUNNING, S.PACED], S.RUNNING),  # the pacer is not stopped again
        ([S.RUNNING, S.ABORTING], S.FINISHED),  # an aborting run cannot finish
    ],
)
def test_an_illegal_transition_is_refused_and_changes_nothing(path: list[RunState], illegal: RunState) -> None:
    """Asking for a transition the table does not list raises IllegalTransition; the state stays where it was."""
    m = RunStateMachine()
    for state in path:
        m.to(state)
    before = m.state
    with pytest.raises(IllegalTransition, match=f"{before.value} -> {illegal.value}"):
        m.to(illegal)
    assert m.state is before


def test_a_failure_keeps_its_error_and_surfaces_at_the_next_transition() -> None:
    """The writer's failure stops committing; the acquiring thread gets that error (the first one) when it moves on."""
    m = RunStateMachine()
    m.to(S.RUNNING)
    assert m.committing and not m.paced
    first, second = ConflictError("already holds a reading"), OSError("disk gone")
    m.fail(first)
    m.fail(second)
    assert m.state is S.FAILED and m.error is first and not m.committing
    with pytest.raises(ConflictError, match="already holds"):
        m.to(S.PACED)
    m.abort()
    m.settle()
    assert m.state is S.FAILED


@pytest.mark.parametrize(
    ("path", "ended"),
    [
        ([S.RUNNING], S.FINISHED),
        ([S.RUNNING, S.PACED], S.FINISHED),
        ([S.RUNNING, S.PACED, S.STOPPING], S.STOPPED),
        ([S.RUNNING, S.ABORTING], S.ABORTED),
    ],
)
def test_settle_ends_each_passing_state(path: list[RunState], ended: RunState) -> None:
    """The end of a run: still stepping -> finished, stopping -> stopped, aborting -> aborted."""
    m = RunStateMachine()
    for state in path:
        m.to(state)
    m.settle()
    assert m.state is ended


class _NoPace:
    """A simulated clock that cannot say where the wall clock's pace is (no pace_s, no anchor)."""

    simulated = True
    speed = math.inf

    def now(self) -> float:
        return 0.0

    def wait_until(self, t_s: float) -> float:
        return t_s

    def lag_s(self) -> float:
        return 0.0

    def set(self, t_s: float) -> None:
        """Nothing."""

    def max_lag_s(self) -> float:
        return 0.0


def test_the_clock_is_narrowed_once_and_an_incomplete_one_refused() -> None:
    """SimClock is a PacedClock, WallClock a LoopClock only; a simulated clock without pace_s/anchor is refused."""
    sim = SimClock(speed=10.0)
    assert narrow_clock(sim) == (sim, sim)
    wall = WallClock()
    assert narrow_clock(wall) == (wall, None)
    check_supports(wall, LoopClock)
    with pytest.raises(TypeError, match="WallClock is not a PacedClock: it lacks speed, pace_s, anchor"):
        check_supports(wall, PacedClock)
    with pytest.raises(TypeError, match="_NoPace is not a PacedClock: it lacks pace_s, anchor"):
        narrow_clock(_NoPace())


def _small_run(tmp_path: Path, name: str) -> tuple[Plan, SimRun]:
    """Return a plan of 60 scans (10 s apart, one idle stage) and its new campaign on the virtual machine, flat out."""
    plan = parse_plan(
        {
            "name": name,
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 10,
            "stages": [{"name": "idle", "axis": "Z", "duration_s": 600}],
        }
    )
    return plan, sim_run(plan, f"sqlite:///{tmp_path / (name + '.sqlite')}")


def test_runs_end_finished_or_stopped_and_do_not_run_twice(tmp_path: Path) -> None:
    """A run to the end is finished (block mode went through paced); one stopped mid-way is stopped, cursor kept."""
    plan, run = _small_run(tmp_path, "whole")
    switch = sys.getswitchinterval()
    try:
        sched = Scheduler(plan, run.rig, run.sink, run.clock, options=SchedulerOptions(max_batch=20))
        stats = sched.run()
        assert stats.finished and sched.state.state is S.FINISHED and stats.scans == plan.n_scans
        assert sys.getswitchinterval() == switch != sched.switch_interval_s  # the writer's interval is undone
        with pytest.raises(IllegalTransition, match="finished -> running"):
            sched.run()
    finally:
        run.rig.close()
    plan, run = _small_run(tmp_path, "part")
    stop = threading.Event()

    def stop_after_two(batch: Batch, stats: RunStats) -> None:
        if stats.commits == 2:
            stop.set()

    try:
        options = SchedulerOptions(max_batch=5, flush_s=0.0, on_commit=stop_after_two, stop=stop)
        sched = Scheduler(plan, run.rig, run.sink, run.clock, options=options)
        stats = sched.run()
    finally:
        run.rig.close()
    assert not stats.finished and sched.state.state is S.STOPPED
    assert 0 < stats.scans < plan.n_scans and sched.cursor == Cursor(stats.scans, 0)
    resumed = open_campaign(run.engine, plan, scenario_meta(None)["channels"], [], resume=True, origin={})
    assert resumed.cursor == sched.cursor  # the stored cursor is where the stopped run left off


def test_a_failed_commit_fails_the_run_and_nothing_after_it_is_committed(tmp_path: Path) -> None:
    """A reading already stored makes the third batch conflict: the run fails with that error, commits stop there."""
    plan, run = _small_run(tmp_path, "fails")
    plant_reading(run, 100.0)  # scan 10 (t = 100 s) is already in the store: batches of 5 scans hit it third
    try:
        sched = Scheduler(plan, run.rig, run.sink, run.clock, options=SchedulerOptions(max_batch=5, flush_s=0.0))
        with pytest.raises(ConflictError, match="already holds a reading"):
            sched.run()
    finally:
        run.rig.close()
    assert sched.state.state is S.FAILED and not sched.stats.finished
    assert sched.stats.commits == 2 and sched.stats.scans == 10
    resumed = open_campaign(run.engine, plan, scenario_meta(None)["channels"], [], resume=True, origin={})
    assert resumed.cursor == Cursor(10, 0)


def test_an_error_in_on_commit_in_the_writer_thread_fails_the_run(tmp_path: Path) -> None:
    """The writer thread's on_commit raising is not lost: the run fails with that error, nothing more committed."""
    plan, run = _small_run(tmp_path, "hook")

    def refuse_second(batch: Batch, stats: RunStats) -> None:
        if stats.commits == 2:
            raise RuntimeError("progress display gone")

    try:
        options = SchedulerOptions(max_batch=5, flush_s=0.0, on_commit=refuse_second)
        sched = Scheduler(plan, run.rig, run.sink, run.clock, options=options)
        assert sched.block_scans() > 1  # block mode: commits in the writer thread
        with pytest.raises(RuntimeError, match="progress display gone"):
            sched.run()
    finally:
        run.rig.close()
    assert sched.state.state is S.FAILED and sched.stats.commits == 2
