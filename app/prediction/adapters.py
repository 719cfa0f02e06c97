"""Adapters from tracker and dataset joint sets to the canonical skeleton (``skeleton.JOINTS``).

Every adapter is a fixed linear map ``canonical[j] = sum_k W[j, k] * source[k]`` whose rows sum to one
(each canonical joint is one source keypoint or the mean of a few), so it commutes with any rigid motion of
the input: a rigidly moved input gives the same rigidly moved canonical skeleton and the same bone lengths.

Sources:
    * ZED SDK ``BODY_34`` and ``BODY_38`` (Stereolabs). Their keypoints come in the camera or world frame
      chosen in the SDK; pass ``T_world_src`` (4, 4) to express them in the app's world frame (z up, metres).
    * The 38-joint CMU skeleton of the shared ``cmu_mocap`` clips (positions in metres, z up). Each CMU
      position is the start of the bone of that name, so e.g. ``lfemur`` is the hip joint and ``ltibia``
      the knee. Every canonical bone is exactly one CMU bone (zero-length bones skipped), so clips with
      constant CMU bone lengths give constant canonical bone lengths.

Orientation fix of the CMU clips (``fix_cmu_orientation=True``, the default): in the shared clips the body is
mirrored (a right-handed z-up frame puts the limbs labelled left on the body's right) and turned 90 degrees
against its root trajectory (people walk sideways). Swapping the x and y offsets of every joint from the root
fixes both at once: afterwards the labelled-left limbs are on the body's left and the body faces the direction
it walks in (on the walking and running clips the median angle between the heading and the direction of travel
drops from about 95 to 1-21 degrees). The swap is a reflection, so bone lengths are unchanged.
"""

from __future__ import annotations

import numpy as np

from app.prediction.skeleton import JOINT_INDEX, JOINTS, NUM_JOINTS

#: ZED SDK ``BODY_34`` keypoint order (``sl.BODY_34_PARTS``).
ZED34_NAMES: tuple[str, ...] = (
    "PELVIS",
    "NAVAL_SPINE",
    "CHEST_SPINE",
    "NECK",
    "LEFT_CLAVICLE",
    "LEFT_SHOULDER",
    "LEFT_ELBOW",
    "LEFT_WRIST",
    "LEFT_HAND",
    "LEFT_HANDTIP",
    "LEFT_THUMB",
    "RIGHT_CLAVICLE",
    "RIGHT_SHOULDER",
    "RIGHT_ELBOW",
    "RIGHT_WRIST",
    "RIGHT_HAND",
    "RIGHT_HANDTIP",
    "RIGHT_THUMB",
    "LEFT_HIP",
    "LEFT_KNEE",
    "LEFT_ANKLE",
    "LEFT_FOOT",
    "RIGHT_HIP",
    "RIGHT_KNEE",
    "RIGHT_ANKLE",
    "RIGHT_FOOT",
    "HEAD",
    "NOSE",
    "LEFT_EYE",
    "LEFT_EAR",
    "RIGHT_EYE",
    "RIGHT_EAR",
    "LEFT_HEEL",
    "RIGHT_HEEL",
)

#: ZED SDK ``BODY_38`` keypoint order (``sl.BODY_38_PARTS``).
ZED38_NAMES: tuple[str, ...] = (
    "PELVIS",
    "SPINE_1",
    "SPINE_2",
    "SPINE_3",
    "NECK",
    "NOSE",
    "LEFT_EYE",
    "RIGHT_EYE",
    "LEFT_EAR",
    "RIGHT_EAR",
    "LEFT_CLAVICLE",
    "RIGHT_CLAVICLE",
    "LEFT_SHOULDER",
    "RIGHT_SHOULDER",
    "LEFT_ELBOW",
    "RIGHT_ELBOW",
    "LEFT_WRIST",
    "RIGHT_WRIST",
    "LEFT_HIP",
    "RIGHT_HIP",
    "LEFT_KNEE",
    "RIGHT_KNEE",
    "LEFT_ANKLE",
    "RIGHT_ANKLE",
    "LEFT_BIG_TOE",
    "RIGHT_BIG_TOE",
    "LEFT_SMALL_TOE",
    "RIGHT_SMALL_TOE",
    "LEFT_HEEL",
    "RIGHT_HEEL",
    "LEFT_HAND_THUMB_4",
    "RIGHT_HAND_THUMB_4",
    "LEFT_HAND_INDEX_1",
    "RIGHT_HAND_INDEX_1",
    "LEFT_HAND_MIDDLE_4",
    "RIGHT_HAND_MIDDLE_4",
    "LEFT_HAND_PINKY_1",
    "RIGHT_HAND_PINKY_1",
)

#: Joint names of the shared CMU clips (their ``joint_names`` array), in order.
CMU38_NAMES: tuple[str, ...] = (
    "root",
    "lhipjoint",
    "lfemur",
    "ltibia",
    "lfoot",
    "ltoes",
    "ltoes_site",
    "rhipjoint",
    "rfemur",
    "rtibia",
    "rfoot",
    "rtoes",
    "rtoes_site",
    "lowerback",
    "upperback",
    "thorax",
    "lowerneck",
    "upperneck",
    "head",
    "head_site",
    "lclavicle",
    "lhumerus",
    "lradius",
    "lwrist",
    "lhand",
    "lfingers",
    "lfingers_site",
    "lthumb",
    "lthumb_site",
    "rclavicle",
    "rhumerus",
    "rradius",
    "rwrist",
    "rhand",
    "rfingers",
    "rfingers_site",
    "rthumb",
    "rthumb_site",
)

# canonical joint -> source keypoints averaged with equal weights
_ZED34_MAP: dict[str, tuple[str, ...]] = {
    "pelvis": ("PELVIS",),
    "spine": ("NAVAL_SPINE",),
    "chest": ("CHEST_SPINE",),
    "neck": ("NECK",),
    "head": ("HEAD",),
    "l_shoulder": ("LEFT_SHOULDER",),
    "l_elbow": ("LEFT_ELBOW",),
    "l_wrist": ("LEFT_WRIST",),
    "l_hand": ("LEFT_HAND",),
    "r_shoulder": ("RIGHT_SHOULDER",),
    "r_elbow": ("RIGHT_ELBOW",),
    "r_wrist": ("RIGHT_WRIST",),
    "r_hand": ("RIGHT_HAND",),
    "l_hip": ("LEFT_HIP",),
    "l_knee": ("LEFT_KNEE",),
    "l_ankle": ("LEFT_ANKLE",),
    "r_hip": ("RIGHT_HIP",),
    "r_knee": ("RIGHT_KNEE",),
    "r_ankle": ("RIGHT_ANKLE",),
}

_ZED38_MAP: dict[str, tuple[str, ...]] = {
    "pelvis": ("PELVIS",),
    "spine": ("SPINE_2",),
    "chest": ("SPINE_3",),
    "neck": ("NECK",),
    # BODY_38 has no head keypoint: the midpoint of the ears is close to the centre of the head
    "head": ("LEFT_EAR", "RIGHT_EAR"),
    "l_shoulder": ("LEFT_SHOULDER",),
    "l_elbow": ("LEFT_ELBOW",),
    "l_wrist": ("LEFT_WRIST",),
    # the knuckles of index and pinky: the far end of the palm
    "l_hand": ("LEFT_HAND_INDEX_1", "LEFT_HAND_PINKY_1"),
    "r_shoulder": ("RIGHT_SHOULDER",),
    "r_elbow": ("RIGHT_ELBOW",),
    "r_wrist": ("RIGHT_WRIST",),
    "r_hand": ("RIGHT_HAND_INDEX_1", "RIGHT_HAND_PINKY_1"),
    "l_hip": ("LEFT_HIP",),
    "l_knee": ("LEFT_KNEE",),
    "l_ankle": ("LEFT_ANKLE",),
    "r_hip": ("RIGHT_HIP",),
    "r_knee": ("RIGHT_KNEE",),
    "r_ankle": ("RIGHT_ANKLE",),
}

# One CMU point per canonical joint, so that every canonical bone is a single rigid CMU bone:
# root->upperback (lowerback bone), upperback->thorax, thorax(=lowerneck)->upperneck (lowerneck bone),
# upperneck->head (upperneck bone; "head" is the base of the skull), thorax(=lclavicle)->lhumerus,
# lhumerus->lradius->lwrist, lwrist(=lhand)->lfingers (the knuckles), root(=lhipjoint)->lfemur->ltibia->lfoot.
_CMU38_MAP: dict[str, tuple[str, ...]] = {
    "pelvis": ("root",),
    "spine": ("upperback",),
    "chest": ("thorax",),
    "neck": ("upperneck",),
    "head": ("head",),
    "l_shoulder": ("lhumerus",),
    "l_elbow": ("lradius",),
    "l_wrist": ("lwrist",),
    "l_hand": ("lfingers",),
    "r_shoulder": ("rhumerus",),
    "r_elbow": ("rradius",),
    "r_wrist": ("rwrist",),
    "r_hand": ("rfingers",),
    "l_hip": ("lfemur",),
    "l_knee": ("ltibia",),
    "l_ankle": ("lfoot",),
    "r_hip": ("rfemur",),
    "r_knee": ("rtibia",),
    "r_ankle": ("rfoot",),
}


def _weights(names: tuple[str, ...], mapping: dict[str, tuple[str, ...]]) -> np.ndarray:
    index = {n: i for i, n in enumerate(names)}
    W = np.zeros((NUM_JOINTS, len(names)))
    for joint in JOINTS:
        sources = mapping[joint]
        for s in sources:
            W[JOINT_INDEX[joint], index[s]] = 1.0 / len(sources)
    return W


#: Adapter matrices (J, K): ``canonical = W @ source``; every row sums to one.
W_ZED34: np.ndarray = _weights(ZED34_NAMES, _ZED34_MAP)
W_ZED38: np.ndarray = _weights(ZED38_NAMES, _ZED38_MAP)
W_CMU38: np.ndarray = _weights(CMU38_NAMES, _CMU38_MAP)
for _W in (W_ZED34, W_ZED38, W_CMU38):
    _W.setflags(write=False)


def _apply(W: np.ndarray, kp: np.ndarray, name: str) -> np.ndarray:
    kp = np.asarray(kp, dtype=np.float64)
    K = W.shape[1]
    if kp.ndim < 2 or kp.shape[-2:] != (K, 3):
        raise ValueError(f"{name} expects keypoints of shape (..., {K}, 3), got {kp.shape}")
    return np.einsum("jk,...kc->...jc", W, kp)


def _to_world(joints: np.ndarray, T_world_src: np.ndarray | None) -> np.ndarray:
    if T_world_src is None:
        return joints
    T = np.asarray(T_world_src, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_src must be a (4, 4) homogeneous transform, got shape {T.shape}")
    return joints @ T[:3, :3].T + T[:3, 3]


def from_zed34(kp: np.ndarray, *, T_world_src: np.ndarray | None = None) -> np.ndarray:
    """Canonical joints (..., J, 3) from ZED ``BODY_34`` keypoints (..., 34, 3).

    Args:
        kp: Keypoints in metres, in :data:`ZED34_NAMES` order, in the SDK's output frame.
        T_world_src: Optional ``T_world_src`` (4, 4) mapping the SDK frame into the world frame (z up).
    """
    return _to_world(_apply(W_ZED34, kp, "from_zed34"), T_world_src)


def from_zed38(kp: np.ndarray, *, T_world_src: np.ndarray | None = None) -> np.ndarray:
    """Canonical joints (..., J, 3) from ZED ``BODY_38`` keypoints (..., 38, 3).

    Args:
        kp: Keypoints in metres, in :data:`ZED38_NAMES` order, in the SDK's output frame.
        T_world_src: Optional ``T_world_src`` (4, 4) mapping the SDK frame into the world frame (z up).
    """
    return _to_world(_apply(W_ZED38, kp, "from_zed38"), T_world_src)


def from_cmu38(
    pos: np.ndarray, *, fix_cmu_orientation: bool = True, T_world_src: np.ndarray | None = None
) -> np.ndarray:
    """Canonical joints (..., J, 3) from the shared CMU clips' positions (..., 38, 3) (metres, z up).

    Args:
        pos: Positions in :data:`CMU38_NAMES` order.
        fix_cmu_orientation: Swap the x and y offsets from the root (see the module docstring) so that the
            body is not mirrored and faces the way it walks. Per frame; keeps bone lengths.
        T_world_src: Optional transform (4, 4) applied last (to place a clip in the work cell).
    """
    joints = _apply(W_CMU38, pos, "from_cmu38")
    if fix_cmu_orientation:
        root = joints[..., JOINT_INDEX["pelvis"] : JOINT_INDEX["pelvis"] + 1, :]
        offset = joints - root
        joints = root + offset[..., [1, 0, 2]]
    return _to_world(joints, T_world_src)


def _confidence(W: np.ndarray, conf: np.ndarray, name: str) -> np.ndarray:
    conf = np.asarray(conf, dtype=np.float64)
    K = W.shape[1]
    if conf.ndim < 1 or conf.shape[-1] != K:
        raise ValueError(f"{name} expects confidences of shape (..., {K}), got {conf.shape}")
    used = W > 0  # (J, K)
    masked = np.where(used, conf[..., None, :], np.inf)  # (..., J, K)
    return np.min(masked, axis=-1)


def confidence_from_zed34(conf: np.ndarray) -> np.ndarray:
    """Canonical confidences (..., J) from ZED ``BODY_34`` confidences (..., 34): the minimum of the sources.

    The SDK reports confidence in [0, 100]; divide by 100 first for the app's [0, 1] convention.
    """
    return _confidence(W_ZED34, conf, "confidence_from_zed34")


def confidence_from_zed38(conf: np.ndarray) -> np.ndarray:
    """Canonical confidences (..., J) from ZED ``BODY_38`` confidences (..., 38): minimum of the sources."""
    return _confidence(W_ZED38, conf, "confidence_from_zed38")
