from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from app.prediction.adapters import (
    CMU38_NAMES,
    W_CMU38,
    W_ZED34,
    W_ZED38,
    ZED34_NAMES,
    ZED38_NAMES,
    confidence_from_zed34,
    confidence_from_zed38,
    from_cmu38,
    from_zed34,
    from_zed38,
)
from app.prediction.skeleton import BONES, JOINT_INDEX, NUM_JOINTS, bone_lengths

ADAPTERS = [(from_zed34, 34), (from_zed38, 38), (from_cmu38, 38)]


def _rigid(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return Rotation.random(random_state=seed).as_matrix(), rng.uniform(-3, 3, size=3)


def test_name_lists_are_complete_and_unique() -> None:
    assert len(ZED34_NAMES) == len(set(ZED34_NAMES)) == 34
    assert len(ZED38_NAMES) == len(set(ZED38_NAMES)) == 38
    assert len(CMU38_NAMES) == len(set(CMU38_NAMES)) == 38
    assert ZED34_NAMES[26] == "HEAD" and ZED34_NAMES[33] == "RIGHT_HEEL"
    assert ZED38_NAMES[4] == "NECK" and ZED38_NAMES[37] == "RIGHT_HAND_PINKY_1"
    for W in (W_ZED34, W_ZED38, W_CMU38):
        np.testing.assert_allclose(W.sum(axis=1), 1.0)
        assert W.shape[0] == NUM_JOINTS


def test_zed34_picks_named_keypoints() -> None:
    kp = np.arange(34 * 3, dtype=float).reshape(34, 3)
    out = from_zed34(kp)
    np.testing.assert_allclose(out[JOINT_INDEX["l_elbow"]], kp[ZED34_NAMES.index("LEFT_ELBOW")])
    np.testing.assert_allclose(out[JOINT_INDEX["r_knee"]], kp[ZED34_NAMES.index("RIGHT_KNEE")])


def test_zed38_averages_ears_for_head() -> None:
    kp = np.zeros((38, 3))
    kp[ZED38_NAMES.index("LEFT_EAR")] = [0.1, 0.0, 1.6]
    kp[ZED38_NAMES.index("RIGHT_EAR")] = [-0.1, 0.0, 1.6]
    np.testing.assert_allclose(from_zed38(kp)[JOINT_INDEX["head"]], [0.0, 0.0, 1.6])


def test_world_transform_and_shape_errors() -> None:
    kp = np.random.default_rng(0).normal(size=(2, 34, 3))
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    np.testing.assert_allclose(from_zed34(kp, T_world_src=T), from_zed34(kp) + np.array([1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match=r"\(\.\.\., 34, 3\)"):
        from_zed34(np.zeros((38, 3)))
    with pytest.raises(ValueError, match="4, 4"):
        from_zed38(np.zeros((38, 3)), T_world_src=np.eye(3))


def test_confidence_is_minimum_of_sources() -> None:
    conf = np.ones(38)
    conf[ZED38_NAMES.index("RIGHT_EAR")] = 0.2
    assert confidence_from_zed38(conf)[JOINT_INDEX["head"]] == pytest.approx(0.2)
    assert confidence_from_zed34(np.full(34, 0.7)).shape == (NUM_JOINTS,)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), which=st.sampled_from(range(len(ADAPTERS))))
def test_rigid_motion_keeps_bone_lengths(seed: int, which: int) -> None:
    adapter, K = ADAPTERS[which]
    rng = np.random.default_rng(seed)
    kp = rng.normal(scale=0.5, size=(K, 3))
    R, t = _rigid(seed)
    moved = kp @ R.T + t
    kwargs = {"fix_cmu_orientation": False} if adapter is from_cmu38 else {}
    a, b = adapter(kp, **kwargs), adapter(moved, **kwargs)
    np.testing.assert_allclose(bone_lengths(b), bone_lengths(a), atol=1e-9)
    np.testing.assert_allclose(b, a @ R.T + t, atol=1e-9)


def _cmu_chain(rng: np.random.Generator, T: int) -> np.ndarray:
    """A CMU-like 38-joint motion with constant bone lengths: random rotations of fixed offsets per bone."""
    parents = [-1, 0, 1, 2, 3, 4, 5, 0, 7, 8, 9, 10, 11, 0, 13, 14, 15, 16, 17, 18]
    parents += [15, 20, 21, 22, 23, 24, 25, 23, 27, 15, 29, 30, 31, 32, 33, 34, 32, 36]
    offsets = rng.normal(scale=0.1, size=(38, 3))
    offsets[[1, 7, 13, 16, 20, 29, 24, 33]] = 0.0  # zero-length bones as in the clips
    pos = np.zeros((T, 38, 3))
    for t in range(T):
        rots = Rotation.random(38, random_state=int(rng.integers(1 << 30))).as_matrix()
        glob = [np.eye(3)] * 38
        pos[t, 0] = rng.uniform(-2, 2, size=3)
        for j in range(1, 38):
            p = parents[j]
            glob[j] = glob[p] @ rots[j]
            pos[t, j] = pos[t, p] + glob[p] @ offsets[j]
    return pos


@pytest.mark.parametrize("fix", [True, False])
def test_constant_cmu_bones_give_constant_canonical_bones(fix: bool) -> None:
    pos = _cmu_chain(np.random.default_rng(3), T=6)
    lengths = bone_lengths(from_cmu38(pos, fix_cmu_orientation=fix))
    np.testing.assert_allclose(lengths, np.broadcast_to(lengths[0], lengths.shape), atol=1e-9)
    assert lengths.shape == (6, BONES.shape[0])


def test_shared_cmu_clips_keep_bone_lengths(cmu_dir) -> None:
    data = np.load(cmu_dir / "train" / "walking_1.npz")
    assert tuple(str(n) for n in data["joint_names"]) == CMU38_NAMES
    joints = from_cmu38(data["positions"].astype(np.float64))
    lengths = bone_lengths(joints)
    assert np.ptp(lengths, axis=0).max() < 1e-4
    # after the orientation fix the body faces the way it walks (+x in this clip) and left is on the left
    pelvis_velocity = joints[-1, 0] - joints[0, 0]
    left = joints[:, JOINT_INDEX["l_hip"]] - joints[:, JOINT_INDEX["r_hip"]]
    forward = np.cross(left, [0.0, 0.0, 1.0])
    assert np.mean(forward[:, :2] @ pelvis_velocity[:2]) > 0.0
