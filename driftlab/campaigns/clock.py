"""Campaign clocks: simulated time paced (or not) against the wall clock, and the wall clock itself.

The scheduler asks a clock to `wait_until(t_s)` (seconds since the campaign
started) before each step and stores the time the clock returns. The simulated
clock is a discrete-event clock: it jumps to exactly `t_s`, so what a simulated
instrument reads there is a function of the step alone, which is what makes an
interrupted and resumed simulated campaign store exactly the rows of one that
ran through. `speed` paces it against the wall clock (3600 = an hour a second;
`math.inf` = as fast as the instruments and the store allow).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """What the scheduler needs from a clock."""

    simulated: bool

    def now(self) -> float:
        """Return the current campaign time in seconds."""
        ...

    def wait_until(self, t_s: float) -> float:
        """Block until campaign time `t_s` and return the time to record for a step scheduled then."""
        ...

    def lag_s(self) -> float:
        """Return how far (campaign seconds) the steps run behind the pace the clock sets."""
        ...


class SimClock:
    """Simulated campaign time: jumps to each step's time, paced at `speed` x the wall clock."""

    simulated = True

    def __init__(self, speed: float = 3600.0, start_s: float = 0.0) -> None:
        if not speed > 0:
            raise ValueError("speed must be positive")
        self.speed = float(speed)
        self._t0 = float(start_s)
        self._now = float(start_s)
        self._wall0 = time.monotonic()
        self._lock = threading.Lock()
        self._max_lag = 0.0

    def anchor(self) -> None:
        """Start pacing from here: the current simulated time corresponds to this wall-clock moment."""
        with self._lock:
            self._t0 = self._now
            self._wall0 = time.monotonic()
            self._max_lag = 0.0

    def now(self) -> float:
        """Return the simulated time of the current step."""
        with self._lock:
            return self._now

    def pace_s(self) -> float:
        """Return the simulated time the wall clock has reached at this speed."""
        if math.isinf(self.speed):
            return math.inf
        return self._t0 + (time.monotonic() - self._wall0) * self.speed

    def wait_until(self, t_s: float) -> float:
        """Sleep until the wall clock reaches `t_s` at this speed, then set simulated time to exactly `t_s`."""
        if not math.isinf(self.speed):
            delay = (t_s - self._t0) / self.speed - (time.monotonic() - self._wall0)
            if delay > 0:
                time.sleep(delay)
            else:
                self._max_lag = max(self._max_lag, -delay * self.speed)
        with self._lock:
            self._now = max(self._now, float(t_s))
            return self._now

    def sleep(self, dt_s: float) -> None:
        """Let `dt_s` simulated seconds pass at once (the simulated servers' Clock protocol)."""
        with self._lock:
            self._now += max(float(dt_s), 0.0)

    def set(self, t_s: float) -> None:
        """Set simulated time to `t_s` without pacing (for reads inside one step, e.g. laser averaging)."""
        with self._lock:
            self._now = float(t_s)

    def lag_s(self) -> float:
        """Return how far behind the pace the last step was (0 when keeping up)."""
        if math.isinf(self.speed):
            return 0.0
        return max(0.0, self.pace_s() - self._now)

    def max_lag_s(self) -> float:
        """Return the largest lag seen at any step so far."""
        return self._max_lag


class WallClock:
    """Real campaign time: seconds since `started_epoch_s` on the system clock."""

    simulated = False

    def __init__(self, started_epoch_s: float | None = None) -> None:
        self.started_epoch_s = time.time() if started_epoch_s is None else float(started_epoch_s)
        self._max_lag = 0.0

    def now(self) -> float:
        """Return seconds since the campaign started."""
        return time.time() - self.started_epoch_s

    def wait_until(self, t_s: float) -> float:
        """Sleep until campaign time `t_s` and return the actual time (late steps record when they ran)."""
        delay = t_s - self.now()
        if delay > 0:
            time.sleep(delay)
        else:
            self._max_lag = max(self._max_lag, -delay)
        return self.now()

    def set(self, t_s: float) -> None:
        """Do nothing: real time cannot be set."""

    def lag_s(self) -> float:
        """Return 0: a real clock is never ahead of itself (lateness is reported by `max_lag_s`)."""
        return 0.0

    def max_lag_s(self) -> float:
        """Return the largest lateness of any step so far."""
        return self._max_lag
