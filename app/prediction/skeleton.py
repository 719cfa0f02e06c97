"""The canonical skeleton used everywhere in the app, and the frame type that carries it.

Every human source (simulator, replayed clips, external trackers) is converted to this joint set before
anything else sees it. Positions are in metres in the world frame (z up).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Canonical joints, in index order. Upper body complete, plus the legs.
JOINTS: tuple[str, ...] = (
    "pelvis",
    "spine",
    "chest",
    "neck",
    "head",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "l_hand",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
    "r_hand",
    "l_hip",
    "l_knee",
    "l_ankle",
    "r_hip",
    "r_knee",
    "r_ankle",
)
NUM_JOINTS = len(JOINTS)
#: A joint seen with a lower confidence is not trusted: the predictor repairs it from the joints it trusts,
#: and frame validation rejects a frame with no joint at this confidence or above (``no_valid_joint``).
MIN_JOINT_CONFIDENCE = 0.3
JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINTS)}

_PARENT_NAMES: dict[str, str | None] = {
    "pelvis": None,
    "spine": "pelvis",
    "chest": "spine",
    "neck": "chest",
    "head": "neck",
    "l_shoulder": "chest",
    "l_elbow": "l_shoulder",
    "l_wrist": "l_elbow",
    "l_hand": "l_wrist",
    "r_shoulder": "chest",
    "r_elbow": "r_shoulder",
    "r_wrist": "r_elbow",
    "r_hand": "r_wrist",
    "l_hip": "pelvis",
    "l_knee": "l_hip",
    "l_ankle": "l_knee",
    "r_hip": "pelvis",
    "r_knee": "r_hip",
    "r_ankle": "r_knee",
}
#: Parent index of each joint (-1 for the root), shape (J,).
PARENTS: np.ndarray = np.array(
    [-1 if _PARENT_NAMES[n] is None else JOINT_INDEX[_PARENT_NAMES[n]] for n in JOINTS], dtype=np.int64
)
#: Bones as (parent, child) index pairs, shape (J - 1, 2).
BONES: np.ndarray = np.array([(int(PARENTS[j]), j) for j in range(NUM_JOINTS) if PARENTS[j] >= 0])
#: Left/right joint permutation used for mirroring, shape (J,).
MIRROR_PERMUTATION: np.ndarray = np.array(
    [
        JOINT_INDEX[n.replace("l_", "#").replace("r_", "l_").replace("#", "r_")]
        if n[:2] in ("l_", "r_")
        else JOINT_INDEX[n]
        for n in JOINTS
    ]
)


def bone_lengths(joints: np.ndarray) -> np.ndarray:
    """Bone lengths (..., J - 1) in metres of poses (..., J, 3)."""
    return np.linalg.norm(joints[..., BONES[:, 1], :] - joints[..., BONES[:, 0], :], axis=-1)


@dataclass(frozen=True, slots=True)
class HumanFrame:
    """One tracked skeleton.

    Attributes:
        t: Timestamp in seconds on the runtime's clock.
        joints: Joint positions (J, 3) in metres, world frame, canonical order (:data:`JOINTS`).
        confidence: Per-joint confidence (J,) in [0, 1]; 0 means the joint was not seen.
    """

    t: float
    joints: np.ndarray
    confidence: np.ndarray = field(default_factory=lambda: np.ones(NUM_JOINTS))

    def __post_init__(self) -> None:
        joints = np.asarray(self.joints, dtype=np.float64)
        conf = np.asarray(self.confidence, dtype=np.float64)
        if joints.shape != (NUM_JOINTS, 3):
            raise ValueError(f"HumanFrame.joints must have shape ({NUM_JOINTS}, 3), got {joints.shape}")
        if conf.shape != (NUM_JOINTS,):
            raise ValueError(f"HumanFrame.confidence must have shape ({NUM_JOINTS},), got {conf.shape}")
        joints.setflags(write=False)
        conf.setflags(write=False)
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "confidence", conf)
