"""What the daemon's loop needs of a clock, as complete protocols, checked once when the loop is built.

`campaigns.clock.Clock` is what any campaign clock offers (now, wait_until, lag_s, simulated). The loop
needs more: every clock must `set` (a no-op on the wall clock) and report its `max_lag_s`; a simulated
clock is paced against the wall clock, so it must also give its `speed`, the simulated time the wall
clock has reached (`pace_s`) and `anchor` its pacing. `narrow_clock` checks a clock against these
once, as bluesky's ``check_supports(obj, protocol)`` checks a device (``bluesky.protocols``), and
refuses one that lacks a member with one line naming them; the loop then calls the members directly.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from driftlab.campaigns.clock import Clock


@runtime_checkable
class LoopClock(Clock, Protocol):
    """A clock the loop can run on: `campaigns.clock.Clock` with `set` and `max_lag_s`."""

    def set(self, t_s: float) -> None:
        """Set campaign time to `t_s` without pacing (a real clock ignores it)."""
        ...

    def max_lag_s(self) -> float:
        """Return the largest lateness (campaign seconds) of any step so far."""
        ...


@runtime_checkable
class PacedClock(LoopClock, Protocol):
    """A simulated clock paced at `speed` x the wall clock (``math.inf``: as fast as it goes)."""

    speed: float

    def pace_s(self) -> float:
        """Return the simulated time the wall clock has reached at this speed."""
        ...

    def anchor(self) -> None:
        """Start pacing from here (setting up the instruments is not time the campaign fell behind)."""
        ...


#: the members each protocol asks for (runtime_checkable protocols check presence, not types)
_MEMBERS: dict[type, tuple[str, ...]] = {
    LoopClock: ("simulated", "now", "wait_until", "lag_s", "set", "max_lag_s"),
    PacedClock: ("simulated", "now", "wait_until", "lag_s", "set", "max_lag_s", "speed", "pace_s", "anchor"),
}


def check_supports(clock: object, protocol: type) -> None:
    """Raise TypeError naming the members of `protocol` that `clock` lacks (nothing when it has them all)."""
    missing = [m for m in _MEMBERS[protocol] if not hasattr(clock, m)]
    if missing:
        raise TypeError(f"{type(clock).__name__} is not a {protocol.__name__}: it lacks {', '.join(missing)}")


def narrow_clock(clock: object) -> tuple[LoopClock, PacedClock | None]:
    """Return the clock as a LoopClock and, when simulated, as a PacedClock too; TypeError if it lacks a member."""
    check_supports(clock, LoopClock)
    assert isinstance(clock, LoopClock)
    if not clock.simulated:
        return clock, None
    check_supports(clock, PacedClock)
    assert isinstance(clock, PacedClock)
    return clock, clock
