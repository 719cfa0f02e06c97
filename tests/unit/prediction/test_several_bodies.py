"""Frames and forecasts of several bodies: stacked, with their tracker ids."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.prediction.forecast import HumanForecast, stack_forecasts
from app.prediction.skeleton import NUM_JOINTS, HumanFrame


def _pose(x: float) -> np.ndarray:
    return np.full((NUM_JOINTS, 3), x)


def test_a_frame_stacks_bodies_and_gives_each_back_with_its_id() -> None:
    f = HumanFrame.stack(
        1.0, [HumanFrame(1.0, _pose(0.0), body_ids=(4,)), HumanFrame(1.0, _pose(2.0), body_ids=(9,))]
    )
    assert f.bodies == 2 and f.body_ids == (4, 9) and f.joints.shape == (2 * NUM_JOINTS, 3)
    b = f.body(1)
    assert b.body_ids == (9,) and np.all(b.joints == 2.0) and b.t == 1.0
    assert [x.body_ids for x in f.split()] == [(4,), (9,)]
    empty = HumanFrame.stack(1.0, [])
    assert empty.bodies == 0 and empty.joints.shape == (0, 3)
    with pytest.raises(IndexError):
        f.body(2)


@pytest.mark.parametrize(
    ("joints", "ids", "match"),
    [
        (np.zeros((NUM_JOINTS, 3)), (1, 1), "distinct"),
        (np.zeros((NUM_JOINTS, 3)), (-1,), "distinct and >= 0"),
        (np.zeros((NUM_JOINTS + 1, 3)), (0,), "must have shape"),
        (np.zeros((2 * NUM_JOINTS, 3)), (0,), "for 1 bodies"),
    ],
)
def test_a_malformed_frame_is_rejected_with_what_was_wrong(
    joints: np.ndarray, ids: tuple[int, ...], match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        HumanFrame(0.0, joints, np.ones(joints.shape[0]), ids)


def test_matched_gives_the_earlier_pose_of_each_body_by_id() -> None:
    now = HumanFrame.stack(
        1.0, [HumanFrame(1.0, _pose(1.0), body_ids=(2,)), HumanFrame(1.0, _pose(5.0), body_ids=(3,))]
    )
    before = HumanFrame.stack(
        0.9, [HumanFrame(0.9, _pose(0.5), body_ids=(3,)), HumanFrame(0.9, _pose(7.0), body_ids=(8,))]
    )
    m = now.matched(before)
    assert np.all(m[:NUM_JOINTS] == 1.0)  # 2 has just appeared: its own pose (no motion)
    assert np.all(m[NUM_JOINTS:] == 0.5)  # 3 was there


def test_forecasts_of_several_bodies_stack_on_the_longest_grid() -> None:
    times = 0.0 + np.array([0.0, 0.5, 1.0])
    walking = HumanForecast(
        0.0, times, np.stack([_pose(x) for x in (0.0, 0.5, 1.0)]), np.array([0.02, 0.1, 0.2])
    )
    held = HumanForecast.hold(HumanFrame(0.0, _pose(3.0), body_ids=(6,)), margin_m=0.3, growth_mps=0.4)
    both = stack_forecasts([walking, held], t0=0.0)
    assert both.body_ids == (0, 6) and both.joints.shape == (3, 2 * NUM_JOINTS, 3)
    np.testing.assert_allclose(both.joints[:, 0, 0], [0.0, 0.5, 1.0])
    np.testing.assert_allclose(both.joints[:, NUM_JOINTS, 0], 3.0)
    # each time's margin is the larger of the bodies': the held one grows at 0.4 m/s from 0.3
    np.testing.assert_allclose(both.margins, [0.3, 0.5, 0.7])
    assert both.growth_mps == 0.4
    nobody = stack_forecasts([], t0=2.0)
    assert nobody.bodies == 0 and nobody.t0 == 2.0
    with pytest.raises(ValueError, match="after t0"):
        stack_forecasts([walking, HumanForecast.hold(HumanFrame(0.5, _pose(1.0), body_ids=(2,)))], t0=0.0)
    # a forecast kept from the frame before: evaluated at the newest one's times
    older = HumanForecast(-0.1, times - 0.1, np.stack([_pose(x) for x in (2.0, 2.5, 3.0)]), np.full(3, 0.02))
    both = stack_forecasts([walking, dataclasses.replace(older, body_ids=(5,))], t0=0.0)
    assert both.t0 == 0.0 and both.body_ids == (0, 5)
    np.testing.assert_allclose(both.joints[:2, NUM_JOINTS, 0], [2.1, 2.6])
