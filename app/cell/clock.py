"""Clocks and a fixed-rate loop: the only place in the app that reads time.

Everything that needs "now" takes a :class:`Clock`. Live runs use :class:`WallClock` (``time.monotonic``,
seconds, never jumps); headless runs and tests use :class:`SimClock`, which moves only when told to, so a
simulated study runs faster than real time and tests never sleep.

Example:
    >>> clock = SimClock()
    >>> loop = RateLoop(clock, 100.0)
    >>> for _ in range(3):
    ...     loop.sleep()  # on a SimClock this advances the clock to the next deadline
    True
    True
    True
    >>> round(clock.now(), 6)
    0.03
"""

from __future__ import annotations

import math
import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "RateLoop", "SimClock", "WallClock"]


@runtime_checkable
class Clock(Protocol):
    """A monotonic source of time in seconds."""

    def now(self) -> float:
        """Current time (s). Never decreases."""
        ...

    def sleep_until(self, t: float) -> None:
        """Return once :meth:`now` is at least ``t`` (immediately when ``t`` has passed)."""
        ...


class WallClock:
    """The host's monotonic clock (``time.monotonic``: seconds since an arbitrary point, never jumps).

    ``time.monotonic`` is system-wide on Linux, so timestamps taken in a worker process (e.g. the RTDE
    worker) are comparable with this clock.
    """

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        remaining = t - time.monotonic()
        if remaining > 0.0:
            time.sleep(remaining)

    def sleep(self, dt_s: float) -> None:
        """Sleep ``dt_s`` seconds (no-op for ``dt_s <= 0``)."""
        if dt_s > 0.0:
            time.sleep(dt_s)

    def __repr__(self) -> str:
        return "WallClock()"


class SimClock:
    """A simulated clock that advances only when told to (thread-safe).

    :meth:`advance` and :meth:`set` move it explicitly; :meth:`sleep_until` moves it to the requested time
    (a simulation that "sleeps" is telling its clock to jump there), so code written against :class:`Clock`
    runs unchanged, and instantly, on simulated time.

    Args:
        t0: Initial time (s).
    """

    def __init__(self, t0: float = 0.0) -> None:
        if not math.isfinite(t0):
            raise ValueError(f"SimClock t0 must be finite, got {t0}")
        self._t = float(t0)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def advance(self, dt_s: float) -> float:
        """Move the clock forward by ``dt_s`` >= 0 seconds; returns the new time."""
        if not (dt_s >= 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"SimClock.advance needs a finite dt_s >= 0, got {dt_s}")
        with self._lock:
            self._t += float(dt_s)
            return self._t

    def set(self, t: float) -> None:
        """Move the clock to ``t``; raises ``ValueError`` if that is in the past (time is monotonic)."""
        with self._lock:
            if not (t >= self._t and math.isfinite(t)):
                raise ValueError(f"SimClock.set({t}) would move time backwards from {self._t}")
            self._t = float(t)

    def sleep_until(self, t: float) -> None:
        with self._lock:
            if t > self._t:
                self._t = float(t)

    def __repr__(self) -> str:
        return f"SimClock(t={self.now():.6f})"


class RateLoop:
    """Run a loop body at a fixed rate on a :class:`Clock`, against absolute deadlines.

    Deadlines lie on the grid ``t0 + k / rate_hz``, so timing errors never accumulate (no drift). When the
    body overruns its period, :meth:`sleep` returns at once (``False``), counts one overrun and skips the
    grid points that already passed (no burst of catch-up iterations); the next deadline is the first grid
    point after "now".

    Args:
        clock: The clock to schedule on.
        rate_hz: Loop rate (Hz), > 0.
        t0: Start of the deadline grid (s); default ``clock.now()`` at construction.

    Attributes:
        ticks: Completed periods (grid points reached or skipped).
        overruns: Calls to :meth:`sleep` that found their deadline already passed.
        missed_ticks: Grid points skipped because of overruns.
    """

    def __init__(self, clock: Clock, rate_hz: float, *, t0: float | None = None) -> None:
        if not (rate_hz > 0.0 and math.isfinite(rate_hz)):
            raise ValueError(f"RateLoop needs a finite rate_hz > 0, got {rate_hz}")
        self.clock = clock
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.reset(t0)

    def reset(self, t0: float | None = None) -> None:
        """Restart the grid at ``t0`` (default: now) and zero the counters."""
        self.t0 = self.clock.now() if t0 is None else float(t0)
        self.ticks = 0
        self.overruns = 0
        self.missed_ticks = 0

    @property
    def next_deadline(self) -> float:
        """The deadline the next :meth:`sleep` waits for (s)."""
        return self.t0 + (self.ticks + 1) * self.period_s

    def sleep(self) -> bool:
        """Wait for the next deadline. Returns ``True`` if it was met, ``False`` on an overrun."""
        deadline = self.next_deadline
        now = self.clock.now()
        if now <= deadline:
            self.clock.sleep_until(deadline)
            self.ticks += 1
            return True
        late_periods = math.floor((now - deadline) / self.period_s)
        self.overruns += 1
        self.missed_ticks += late_periods
        self.ticks += 1 + late_periods
        return False

    def stats(self) -> dict[str, float | int]:
        """Counters as a JSON-ready dict."""
        return {
            "rate_hz": self.rate_hz,
            "ticks": self.ticks,
            "overruns": self.overruns,
            "missed_ticks": self.missed_ticks,
        }

    def __repr__(self) -> str:
        return f"RateLoop(rate_hz={self.rate_hz}, ticks={self.ticks}, overruns={self.overruns})"
