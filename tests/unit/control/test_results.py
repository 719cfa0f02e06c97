"""What a trial shows: the one speed that the operator page and the 3D view print (:class:`ShownSpeed`)."""

from __future__ import annotations

import numpy as np
import pytest

from app.control.results import ShownSpeed, Snapshot


def test_the_shown_speed_holds_between_refreshes_and_follows_a_change_of_state_at_once() -> None:
    shown = ShownSpeed(rate_hz=4.0)
    key = ("nominal", "ssm")
    assert shown(10.00, key, 0.40) == 0.40
    # within the same quarter second: held, whatever the snapshots say
    assert shown(10.10, key, 0.55) == 0.40
    assert shown(10.24, key, 0.61) == 0.40
    # the next quarter second: refreshed from the snapshot that opens it
    assert shown(10.25, key, 0.62) == 0.62
    assert shown(10.40, key, 0.70) == 0.62
    # a new state or mode: its own speed at once
    assert shown(10.41, ("collision_avoidance", "stopped"), 0.0) == 0.0
    assert shown(10.45, ("collision_avoidance", "stopped"), 0.2) == 0.0
    with pytest.raises(ValueError, match="rate_hz"):
        ShownSpeed(rate_hz=0.0)


def test_a_snapshot_prints_its_shown_speed_or_else_its_own() -> None:
    base = dict(
        t=1.0, trial_id=None, state="nominal", method=None, separation_m=None, required_separation_m=None,
        planning_ms=(), counters={}, q=np.zeros(6), p_world_tcp=np.zeros(3),
    )  # fmt: skip
    assert Snapshot(speed_scale=0.3, **base).to_json()["speed_shown"] == 0.3
    assert Snapshot(speed_scale=0.3, speed_shown=0.25, **base).to_json()["speed_shown"] == 0.25
