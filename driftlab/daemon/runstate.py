"""The run states of the daemon's loop and the transitions allowed between them.

Modelled on bluesky's RunEngine (``bluesky.run_engine``: a ``RunEngineStateMachine`` whose states
are an enum and whose allowed transitions are a table; asking for any other transition raises):
the scheduler's run is in exactly one state, and every change of state goes through `RunStateMachine.to`,
which refuses a transition the table does not list. Two threads change it - the acquiring thread
(the loop) and the writer thread (a failed commit) - so a lock guards every change.

    idle --> running --> paced            (the card's pacer started: blocks come from its memory)
    running | paced --> stopping          (asked to stop: what was read is committed, nothing more read)
    running | paced --> finished          (the plan is complete and every batch committed)
    stopping --> stopped
    running | paced | stopping --> aborting --> aborted
                                          (the loop raised, or a second interrupt: commit nothing more)
    any state not final --> failed        (a commit failed: nothing more is committed, its error raised)
"""

from __future__ import annotations

import enum
import threading


class RunState(enum.Enum):
    """Where the scheduler's run is."""

    IDLE = "idle"
    RUNNING = "running"
    PACED = "paced"
    STOPPING = "stopping"
    FINISHED = "finished"
    STOPPED = "stopped"
    ABORTING = "aborting"
    ABORTED = "aborted"
    FAILED = "failed"


_S = RunState
#: state -> the states it may go to; a final state goes nowhere
TRANSITIONS: dict[RunState, frozenset[RunState]] = {
    _S.IDLE: frozenset({_S.RUNNING}),
    _S.RUNNING: frozenset({_S.PACED, _S.STOPPING, _S.FINISHED, _S.ABORTING, _S.FAILED}),
    _S.PACED: frozenset({_S.STOPPING, _S.FINISHED, _S.ABORTING, _S.FAILED}),
    _S.STOPPING: frozenset({_S.STOPPED, _S.ABORTING, _S.FAILED}),
    _S.ABORTING: frozenset({_S.ABORTED, _S.FAILED}),
    _S.FINISHED: frozenset(),
    _S.STOPPED: frozenset(),
    _S.ABORTED: frozenset(),
    _S.FAILED: frozenset(),
}
#: the states in which batches are still committed
COMMITTING = frozenset({_S.RUNNING, _S.PACED, _S.STOPPING})


class IllegalTransition(RuntimeError):
    """A change of run state that the transition table does not allow (a bug in the loop, never bad input)."""


class RunStateMachine:
    """The state of one run, changed only along `TRANSITIONS`; a failure keeps the error that caused it."""

    def __init__(self) -> None:
        self._state = RunState.IDLE
        self._error: BaseException | None = None
        self._lock = threading.Lock()

    @property
    def state(self) -> RunState:
        """Return the current state."""
        return self._state

    @property
    def error(self) -> BaseException | None:
        """Return the error that failed the run (None unless the state is ``failed``)."""
        return self._error

    @property
    def committing(self) -> bool:
        """Return True while batches are still to be committed (not after a failure or an abort)."""
        return self._state in COMMITTING

    @property
    def paced(self) -> bool:
        """Return True in the ``paced`` state (the card's pacer started, blocks come from its memory)."""
        return self._state is RunState.PACED

    def to(self, new: RunState) -> None:
        """Go to state `new`; IllegalTransition if the table does not allow it from the current state.

        A run the writer thread has failed meanwhile raises that failure's error instead: the acquiring
        thread learns of it at its next change of state.
        """
        with self._lock:
            if self._error is not None:
                raise self._error
            self._go(new)

    def fail(self, error: BaseException) -> None:
        """Go to ``failed``, keeping the first error (a second failure of a failed run changes nothing)."""
        with self._lock:
            if self._state is RunState.FAILED:
                return
            self._go(RunState.FAILED)
            self._error = error

    def raise_failure(self) -> None:
        """Re-raise, in the calling thread, the error that failed the run (nothing when it has not failed)."""
        if self._error is not None:
            raise self._error

    def settle(self) -> None:
        """End the run: ``stopping`` -> stopped, ``aborting`` -> aborted, still stepping -> finished, failed stays."""
        with self._lock:
            state = self._state
            if state is RunState.FAILED:
                return
            ended = {RunState.STOPPING: RunState.STOPPED, RunState.ABORTING: RunState.ABORTED}
            self._go(ended.get(state, RunState.FINISHED))

    def abort(self) -> None:
        """Go to ``aborting`` because the loop raised (a failed run stays failed: its error is the one raised)."""
        with self._lock:
            if self._state is not RunState.FAILED:
                self._go(RunState.ABORTING)

    def _go(self, new: RunState) -> None:
        """Change state under the lock, or raise IllegalTransition."""
        if new not in TRANSITIONS[self._state]:
            raise IllegalTransition(f"run state {self._state.value} -> {new.value} is not allowed")
        self._state = new
