"""The canonical skeleton used everywhere in the app, and the frame type that carries it.

Every human source (simulator, replayed clips, external trackers) is converted to this joint set before
anything else sees it. Positions are in metres in the world frame (z up).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

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


def body_count(n_joints: int) -> int:
    """How many canonical skeletons a stacked joint array of ``n_joints`` rows holds; ValueError where the
    rows are no whole number of skeletons."""
    bodies, rest = divmod(int(n_joints), NUM_JOINTS)
    if rest:
        raise ValueError(
            f"a stacked skeleton array must have a multiple of {NUM_JOINTS} joints (one block per body), "
            f"got {n_joints}"
        )
    return bodies


@dataclass(frozen=True, slots=True)
class HumanFrame:
    """The tracked people of one capture: every body the tracker reports, each with its tracker id.

    The bodies are stacked: body ``k`` (id ``body_ids[k]``) holds rows ``k*J .. (k+1)*J - 1`` of ``joints``
    and ``confidence`` (J = :data:`NUM_JOINTS`). One body is the common case (the default id 0); no body is
    a person-free capture, a frame all the same. What decides about the robot takes every body at once;
    what works on one skeleton (the predictor, frame validation) takes :meth:`body`.

    Attributes:
        t: Timestamp in seconds on the runtime's clock.
        joints: Joint positions (B*J, 3) in metres, world frame, canonical order (:data:`JOINTS`) per body.
        confidence: Per-joint confidence (B*J,) in [0, 1]; 0 means the joint was not seen (default: every
            joint seen).
        body_ids: The tracker's id of each body (B,), distinct and >= 0.
    """

    t: float
    joints: np.ndarray
    confidence: np.ndarray | None = None
    body_ids: tuple[int, ...] = (0,)

    def __post_init__(self) -> None:
        joints = np.asarray(self.joints, dtype=np.float64)
        conf = (
            np.ones(joints.shape[0])
            if self.confidence is None
            else np.asarray(self.confidence, dtype=np.float64)
        )
        ids = tuple(int(i) for i in self.body_ids)
        B = len(ids)
        if len(set(ids)) != B or any(i < 0 for i in ids):
            raise ValueError(f"HumanFrame.body_ids must be distinct and >= 0, got {self.body_ids}")
        if joints.shape != (B * NUM_JOINTS, 3):
            raise ValueError(
                f"HumanFrame.joints must have shape ({B * NUM_JOINTS}, 3) for {B} bodies, got {joints.shape}"
            )
        if conf.shape != (B * NUM_JOINTS,):
            raise ValueError(
                f"HumanFrame.confidence must have shape ({B * NUM_JOINTS},) for {B} bodies, got {conf.shape}"
            )
        joints.setflags(write=False)
        conf.setflags(write=False)
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "body_ids", ids)

    @property
    def bodies(self) -> int:
        """The number of bodies (B)."""
        return len(self.body_ids)

    def body(self, k: int) -> HumanFrame:
        """Body ``k`` (its index in :attr:`body_ids`, not its id) alone, with its id."""
        if not 0 <= k < self.bodies:
            raise IndexError(f"body {k} of a frame with {self.bodies} body(ies)")
        rows = slice(k * NUM_JOINTS, (k + 1) * NUM_JOINTS)
        # a part of a checked frame needs no check of its own (read-only views of its arrays)
        part = object.__new__(HumanFrame)
        object.__setattr__(part, "t", self.t)
        object.__setattr__(part, "joints", self.joints[rows])
        object.__setattr__(part, "confidence", self.confidence[rows])
        object.__setattr__(part, "body_ids", (self.body_ids[k],))
        return part

    def matched(self, before: HumanFrame) -> np.ndarray:
        """(B*J, 3) ``before``'s joints of this frame's bodies, matched by id, in this frame's order; a body
        that ``before`` lacks (it has just appeared) at its own pose here (no motion measured)."""
        if before.body_ids == self.body_ids:
            return before.joints
        rows = {i: k for k, i in enumerate(before.body_ids)}
        out = np.array(self.joints)
        for k, i in enumerate(self.body_ids):
            j = rows.get(i)
            if j is not None:
                out[k * NUM_JOINTS : (k + 1) * NUM_JOINTS] = before.joints[
                    j * NUM_JOINTS : (j + 1) * NUM_JOINTS
                ]
        return out

    def split(self) -> list[HumanFrame]:
        """Every body alone, in order."""
        return [self.body(k) for k in range(self.bodies)]

    @classmethod
    def stack(cls, t: float, bodies: Sequence[HumanFrame]) -> HumanFrame:
        """One frame at ``t`` of ``bodies`` (each of one or more bodies; ids must stay distinct)."""
        if not bodies:
            return cls(t, np.zeros((0, 3)), np.zeros(0), ())
        return cls(
            t,
            np.concatenate([b.joints for b in bodies]),
            np.concatenate([b.confidence for b in bodies]),
            tuple(i for b in bodies for i in b.body_ids),
        )
