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


def test_a_snapshot_carries_every_tracked_body_with_its_id() -> None:
    base = dict(
        t=1.0, trial_id=None, state="nominal", method=None, separation_m=None, required_separation_m=None,
        planning_ms=(), counters={}, q=np.zeros(6), p_world_tcp=np.zeros(3), speed_scale=0.5,
    )  # fmt: skip
    two = np.concatenate([np.zeros((19, 3)), np.ones((19, 3))])
    snap = Snapshot(
        skeleton=two, body_ids=(3, 7), forecast=np.stack([two] * 4), forecast_body_ids=(3, 7), **base
    )
    out = snap.to_json()
    assert out["body_ids"] == [3, 7] and out["forecast_body_ids"] == [3, 7]
    assert np.asarray(out["skeleton"]).shape == (38, 3) and np.asarray(out["forecast"]).shape == (4, 38, 3)
    # one body without ids (the single-body callers): id 0; nobody in view: no body, no id
    assert Snapshot(skeleton=np.zeros((19, 3)), **base).body_ids == (0,)
    empty = Snapshot(skeleton=np.zeros((0, 3)), **base).to_json()
    assert empty["skeleton"] == [] and empty["body_ids"] == []
    assert Snapshot(**base).to_json()["body_ids"] == []
    with pytest.raises(ValueError, match="body_ids"):
        Snapshot(skeleton=two, body_ids=(3,), **base)
    with pytest.raises(ValueError, match="multiple of 19"):
        Snapshot(skeleton=np.zeros((20, 3)), **base)
