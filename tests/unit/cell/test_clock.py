"""Clocks and the fixed-rate loop, on a simulated clock (no real sleeps)."""

from __future__ import annotations

import math

import pytest

from app.cell.clock import Clock, RateLoop, SimClock, WallClock


def test_sim_clock_moves_only_when_told() -> None:
    clock = SimClock(5.0)
    assert clock.now() == 5.0
    assert clock.now() == 5.0
    assert clock.advance(0.25) == 5.25
    clock.set(6.0)
    assert clock.now() == 6.0
    clock.sleep_until(5.0)  # in the past: no change
    assert clock.now() == 6.0
    clock.sleep_until(7.5)
    assert clock.now() == 7.5


def test_sim_clock_refuses_to_go_backwards() -> None:
    clock = SimClock(1.0)
    with pytest.raises(ValueError, match="backwards"):
        clock.set(0.5)
    with pytest.raises(ValueError):
        clock.advance(-0.1)
    with pytest.raises(ValueError):
        clock.advance(math.nan)
    with pytest.raises(ValueError):
        SimClock(math.inf)


def test_wall_clock_is_monotonic_and_a_clock() -> None:
    clock = WallClock()
    a = clock.now()
    clock.sleep_until(a - 1.0)  # past deadline: returns at once
    b = clock.now()
    assert b >= a
    assert isinstance(clock, Clock)
    assert isinstance(SimClock(), Clock)


def test_rate_loop_has_no_drift() -> None:
    clock = SimClock(10.0)
    loop = RateLoop(clock, 500.0)
    for i in range(1000):
        clock.advance(0.0007 if i % 2 else 0.0013)  # the body takes varying time, always < period
        assert loop.sleep()
    # deadlines are absolute: exactly 1000 periods later, however long the bodies took
    assert clock.now() == pytest.approx(10.0 + 1000 * 0.002, abs=1e-9)
    assert loop.overruns == 0
    assert loop.ticks == 1000


def test_rate_loop_counts_overruns_and_stays_on_its_grid() -> None:
    clock = SimClock(0.0)
    loop = RateLoop(clock, 100.0)  # 10 ms
    assert loop.sleep()  # -> 0.010
    clock.advance(0.025)  # body overruns: now 0.035, deadline was 0.020
    assert not loop.sleep()  # returns at once
    assert clock.now() == pytest.approx(0.035)
    assert loop.overruns == 1
    assert loop.missed_ticks == 1  # the 0.030 grid point was skipped
    assert loop.next_deadline == pytest.approx(0.040)  # back on the grid, no catch-up burst
    assert loop.sleep()
    assert clock.now() == pytest.approx(0.040)
    assert loop.stats()["overruns"] == 1


def test_rate_loop_rejects_bad_rates() -> None:
    with pytest.raises(ValueError):
        RateLoop(SimClock(), 0.0)
    with pytest.raises(ValueError):
        RateLoop(SimClock(), math.inf)
