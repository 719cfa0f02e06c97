from __future__ import annotations

import numpy as np
import pytest

from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import BONES, JOINTS, MIRROR_PERMUTATION, NUM_JOINTS, PARENTS, HumanFrame


def _pose(offset: float) -> np.ndarray:
    return np.tile(np.array([offset, 0.0, 1.0]), (NUM_JOINTS, 1))


def test_skeleton_tables_consistent() -> None:
    assert PARENTS[0] == -1 and (PARENTS[1:] >= 0).all()
    assert BONES.shape == (NUM_JOINTS - 1, 2)
    mirrored = [JOINTS[i] for i in MIRROR_PERMUTATION]
    assert mirrored[JOINTS.index("l_hand")] == "r_hand"
    assert sorted(MIRROR_PERMUTATION.tolist()) == list(range(NUM_JOINTS))


def test_frame_validates_shapes() -> None:
    with pytest.raises(ValueError, match="shape"):
        HumanFrame(t=0.0, joints=np.zeros((5, 3)))


def test_forecast_interpolates_and_grows_beyond_horizon() -> None:
    f = HumanForecast(
        t0=1.0,
        times=np.array([1.0, 2.0]),
        joints=np.stack([_pose(0.0), _pose(1.0)]),
        margins=np.array([0.0, 0.2]),
        growth_mps=0.5,
        max_margin_m=0.6,
    )
    joints, margins = f.poses_at(np.array([0.5, 1.5, 2.0, 2.5, 10.0]))
    np.testing.assert_allclose(joints[:, 0, 0], [0.0, 0.5, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(margins, [0.0, 0.1, 0.2, 0.45, 0.6])


def test_hold_forecast_is_static() -> None:
    frame = HumanFrame(t=3.0, joints=_pose(0.3))
    f = HumanForecast.hold(frame, margin_m=0.05)
    pose, margin = f.pose_at(7.0)
    np.testing.assert_allclose(pose, frame.joints)
    assert margin == pytest.approx(0.05)
