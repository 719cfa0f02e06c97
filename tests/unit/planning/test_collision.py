"""Collision model: distances against python-fcl and brute force, known static and self-collision cases."""

from __future__ import annotations

import math

import fcl
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from app.config import load_workcell, pose_matrix
from app.planning.collision import (
    HUMAN_CAPSULES,
    ROBOT_LINK_EXTENSIONS,
    ROBOT_LINK_RADII,
    ROBOT_LINKS,
    SELF_COLLISION_PAIRS,
    CollisionModel,
    HumanRadii,
    capsule_distance,
    fcl_box,
    fcl_capsule,
    joint_axis_segments,
    segment_box_distance,
    segment_distance,
)
from app.planning.kinematics import UR5e
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS

PROPERTY = settings(max_examples=200, deadline=None)

coord = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
point = arrays(np.float64, (3,), elements=coord)
radius = st.floats(0.01, 0.2)


@st.composite
def segments(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two segments, sometimes parallel, sometimes degenerate (a point)."""
    p1, q1, p2 = draw(point), draw(point), draw(point)
    kind = draw(st.sampled_from(["general", "parallel", "point", "collinear"]))
    if kind == "general":
        q2 = draw(point)
    elif kind == "parallel":
        q2 = p2 + draw(st.floats(-1.5, 1.5)) * (q1 - p1)
    elif kind == "point":
        q2 = p2.copy()
    else:
        p2 = p1 + draw(st.floats(-2.0, 2.0)) * (q1 - p1)
        q2 = p2 + draw(st.floats(-1.5, 1.5)) * (q1 - p1)
    return p1, q1, p2, q2


def _fcl_distance(o1: fcl.CollisionObject, o2: fcl.CollisionObject) -> float:
    return fcl.distance(o1, o2, fcl.DistanceRequest(), fcl.DistanceResult())


def _fcl_collide(o1: fcl.CollisionObject, o2: fcl.CollisionObject) -> bool:
    return fcl.collide(o1, o2, fcl.CollisionRequest(), fcl.CollisionResult()) > 0


def _brute_segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> float:
    s = np.linspace(0.0, 1.0, 401)
    x1 = p1 + s[:, None] * (q1 - p1)
    x2 = p2 + s[:, None] * (q2 - p2)
    return float(np.min(np.linalg.norm(x1[:, None] - x2[None], axis=-1)))


@pytest.fixture(scope="module")
def cell():
    return load_workcell()


@pytest.fixture(scope="module")
def model(cell) -> CollisionModel:
    return CollisionModel(cell)


def _standing_person(x: float, y: float = 0.0, *, floor_z: float = -0.75, yaw: float = math.pi) -> np.ndarray:
    """A plausible upright canonical skeleton (J, 3) at (x, y), facing ``yaw``, arms hanging."""
    local = {
        "pelvis": (0.0, 0.0, 0.95),
        "spine": (0.0, 0.0, 1.10),
        "chest": (0.0, 0.0, 1.30),
        "neck": (0.0, 0.0, 1.50),
        "head": (0.0, 0.0, 1.62),
        "l_shoulder": (0.0, 0.18, 1.45),
        "l_elbow": (0.0, 0.20, 1.17),
        "l_wrist": (0.0, 0.21, 0.93),
        "l_hand": (0.0, 0.21, 0.85),
        "r_shoulder": (0.0, -0.18, 1.45),
        "r_elbow": (0.0, -0.20, 1.17),
        "r_wrist": (0.0, -0.21, 0.93),
        "r_hand": (0.0, -0.21, 0.85),
        "l_hip": (0.0, 0.10, 0.92),
        "l_knee": (0.0, 0.10, 0.50),
        "l_ankle": (0.0, 0.10, 0.08),
        "r_hip": (0.0, -0.10, 0.92),
        "r_knee": (0.0, -0.10, 0.50),
        "r_ankle": (0.0, -0.10, 0.08),
    }
    c, s = math.cos(yaw), math.sin(yaw)
    joints = np.zeros((NUM_JOINTS, 3))
    for name, (lx, ly, lz) in local.items():
        joints[JOINT_INDEX[name]] = [x + c * lx - s * ly, y + s * lx + c * ly, floor_z + lz]
    return joints


def _random_people(rng: np.random.Generator, n: int) -> np.ndarray:
    """Skeletons (n, J, 3) near the robot: upright people with random arm poses and jitter."""
    out = np.empty((n, NUM_JOINTS, 3))
    for i in range(n):
        joints = _standing_person(
            rng.uniform(0.3, 1.2), rng.uniform(-0.6, 0.6), yaw=rng.uniform(-np.pi, np.pi)
        )
        joints += rng.normal(scale=0.05, size=joints.shape)
        for side in ("l_", "r_"):  # reach towards the table
            sh = joints[JOINT_INDEX[side + "shoulder"]]
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            for k, name in enumerate(("elbow", "wrist", "hand"), start=1):
                joints[JOINT_INDEX[side + name]] = sh + direction * (0.28, 0.52, 0.6)[k - 1]
        out[i] = joints
    return out


# --------------------------------------------------------------------------- kernels vs fcl and brute force


@PROPERTY
@given(seg=segments(), r1=radius, r2=radius)
def test_capsule_distance_matches_fcl(seg, r1: float, r2: float) -> None:
    p1, q1, p2, q2 = seg
    ours = float(capsule_distance(p1, q1, r1, p2, q2, r2))
    o1, o2 = fcl_capsule(p1, q1, r1), fcl_capsule(p2, q2, r2)
    if ours > 1e-6:
        assert ours == pytest.approx(_fcl_distance(o1, o2), abs=1e-6)
    elif ours < -1e-6:
        assert _fcl_collide(o1, o2)
    # the closed form is the minimum; near contact its precision is sqrt(round-off), a few 1e-8 m
    assert float(segment_distance(p1, q1, p2, q2)) <= _brute_segment_distance(p1, q1, p2, q2) + 5e-8


def test_segment_distance_known_cases() -> None:
    o = np.zeros(3)
    ex, ey, ez = np.eye(3)
    assert segment_distance(o, ex, ez, ez + ex) == pytest.approx(1.0)  # parallel, overlapping
    assert segment_distance(o, ex, 2 * ex + ez, 3 * ex + ez) == pytest.approx(
        math.sqrt(2.0)
    )  # parallel, apart
    assert segment_distance(o, ex, 0.5 * ex - ey + ez, 0.5 * ex + ey + ez) == pytest.approx(1.0)  # crossing
    assert segment_distance(o, o, ey, ey) == pytest.approx(1.0)  # two points
    assert segment_distance(o, 2 * ex, ex, ex) == pytest.approx(0.0)  # point on segment
    d = segment_distance(np.zeros((4, 1, 3)), np.ones((1, 5, 3)), ez, ez + ex)
    assert d.shape == (4, 5)


@PROPERTY
@given(p=point, q=point, half=arrays(np.float64, (3,), elements=st.floats(0.02, 0.6)), r=radius)
def test_segment_box_distance_is_exact(p: np.ndarray, q: np.ndarray, half: np.ndarray, r: float) -> None:
    ours = float(segment_box_distance(p[None], q[None], half)[0])
    # brute force: the box signed distance field sampled densely along the segment (ours must be the minimum)
    t = np.linspace(0.0, 1.0, 4001)[:, None]
    x = np.abs(p + t * (q - p)) - half
    sdf = np.sqrt(np.square(np.maximum(x, 0.0)).sum(axis=1)) + np.minimum(x.max(axis=1), 0.0)
    assert ours <= sdf.min() + 1e-12
    # sampling resolution (the field is 1-Lipschitz)
    assert ours >= sdf.min() - np.linalg.norm(q - p) / 4000 - 1e-12
    # python-fcl agrees on the sign, and on the value within its GJK tolerance (its capsule-box distances are
    # always on the high side, usually by about 0.2 % but by several % for some segments, e.g. 5.6 % at
    # 7 cm, and by up to about a centimetre at a few millimetres: 8.8 mm for an exact 5.9 mm and 15.5 mm for
    # an exact 3.9 mm, both found by this test; the brute force above is the exact reference)
    cap = fcl_capsule(p, q, r)
    box = fcl.CollisionObject(fcl.Box(*(2 * half)), fcl.Transform())
    if ours - r > 1e-3:
        d_fcl = _fcl_distance(cap, box)
        assert ours - r - 1e-6 <= d_fcl <= 1.1 * (ours - r) + 1.5e-2
        assert not _fcl_collide(cap, box)
    elif ours - r < -1e-3:
        assert _fcl_collide(cap, box)


def test_segment_box_distance_known_cases() -> None:
    half = np.array([0.5, 0.5, 0.5])
    p = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-2.0, 0.0, 0.1], [1.5, 1.5, 0.0]])
    q = np.array([[3.0, 0.0, 0.0], [0.1, 0.0, 0.0], [2.0, 0.0, 0.1], [1.5, 1.5, 1.0]])
    d = segment_box_distance(p, q, half)
    # outside; deepest at the centre; passing 0.1 off-centre; beside an edge
    np.testing.assert_allclose(d, [1.5, -0.5, -0.4, math.sqrt(2.0)], atol=1e-12)


# --------------------------------------------------------------------------- robot vs person


def test_distance_to_human_matches_brute_force_and_fcl(model: CollisionModel) -> None:
    rng = np.random.default_rng(3)
    kin = model.kin
    q = rng.uniform(kin.q_min, kin.q_max, size=(12, 6))
    joints = _random_people(rng, 7)
    d = model.distance_to_human(q, joints)
    assert d.shape == (12, 7)
    a, b, r = model.robot_capsules(q)
    ha, hb, hr = model.human_capsules(joints)
    brute = capsule_distance(
        a[:, None, :, None], b[:, None, :, None], r[:, None], ha[None, :, None], hb[None, :, None], hr
    ).min(axis=(2, 3))
    np.testing.assert_allclose(d, brute, atol=1e-10)
    # python-fcl, capsule by capsule, for a few (configuration, pose) pairs
    for i, j in [(0, 0), (3, 5), (11, 6), (7, 2)]:
        dmin = min(
            _fcl_distance(fcl_capsule(a[i, li], b[i, li], r[li]), fcl_capsule(ha[j, m], hb[j, m], hr[m]))
            for li in range(len(ROBOT_LINKS))
            for m in range(len(HUMAN_CAPSULES))
        )
        if d[i, j] > 1e-6:
            assert d[i, j] == pytest.approx(dmin, abs=1e-6)


def test_paired_equals_cross_diagonal(model: CollisionModel) -> None:
    rng = np.random.default_rng(4)
    K = 300  # more than one work block
    q = rng.uniform(model.kin.q_min, model.kin.q_max, size=(K, 6))
    joints = _random_people(rng, K)
    paired = model.distance_to_human_paired(q, joints)
    assert paired.shape == (K,)
    sub = np.arange(0, K, 37)
    np.testing.assert_allclose(paired[sub], np.diag(model.distance_to_human(q[sub], joints[sub])), atol=1e-12)
    a, b, r = model.robot_capsules(q)
    ha, hb, hr = model.human_capsules(joints)
    brute = capsule_distance(a[:, :, None], b[:, :, None], r[:, None], ha[:, None], hb[:, None], hr).min(
        axis=(1, 2)
    )
    np.testing.assert_allclose(paired, brute, atol=1e-10)
    # many poses against one configuration also spans several blocks of the cross kernel
    many = model.distance_to_human(q[:1], joints)
    np.testing.assert_allclose(many[0], model.distance_to_human_paired(np.repeat(q[:1], K, axis=0), joints))


def test_paired_distance_over_subsets_and_given_segments(model: CollisionModel) -> None:
    rng = np.random.default_rng(6)
    K = 150
    q = rng.uniform(model.kin.q_min, model.kin.q_max, size=(K, 6))
    joints = _random_people(rng, K)
    a, b, r = model.robot_capsules(q)
    a_c, d_c = model.robot_segments(q)
    assert a_c.shape == d_c.shape == (len(ROBOT_LINKS), 3, K)
    np.testing.assert_allclose(a_c.transpose(2, 0, 1), a, atol=1e-12)
    np.testing.assert_allclose((a_c + d_c).transpose(2, 0, 1), b, atol=1e-12)
    full = model.distance_to_human_paired(q, joints)
    np.testing.assert_allclose(model.distance_to_human_paired(q, joints, segments=(a_c, d_c)), full, atol=0)
    ha, hb, hr = model.human_capsules(joints)
    links, caps = np.array([2, 4, 7, 8]), np.array([0, 3, 9, 12, 17])
    brute = capsule_distance(
        a[:, links, None], b[:, links, None], r[links, None], ha[:, None, caps], hb[:, None, caps], hr[caps]
    ).min(axis=(1, 2))
    sub = model.distance_to_human_paired(q, joints, links=links, capsules=caps)
    np.testing.assert_allclose(sub, brute, atol=1e-10)
    assert np.all(sub >= full - 1e-12)  # a subset's minimum is never below the whole minimum
    assert np.all(np.isinf(model.distance_to_human_paired(q, joints, links=np.array([], dtype=int))))
    with pytest.raises(ValueError, match="segments"):
        model.distance_to_human_paired(q, joints, segments=(a_c[:, :, :5], d_c[:, :, :5]))


def test_distance_to_human_known_answers(model: CollisionModel, cell) -> None:
    home = np.array([cell.robot.home_q])
    tcp = model.kin.fk_tcp(home)[0, :3, 3]
    far = _standing_person(6.0)
    near = far.copy()
    # a hand bone passing straight through the TCP: the surfaces overlap by both radii
    near[JOINT_INDEX["r_wrist"]] = tcp + np.array([0.0, 0.0, 0.1])
    near[JOINT_INDEX["r_hand"]] = tcp - np.array([0.0, 0.0, 0.1])
    d = model.distance_to_human(home, np.stack([far, near]))
    assert d[0, 0] > 4.0
    assert d[0, 1] == pytest.approx(-(cell.tool.radius_m + HumanRadii().hand), abs=1e-6)
    # moving the person away increases the distance by at most the displacement
    p1 = _standing_person(1.0)
    p2 = p1 + np.array([0.5, 0.0, 0.0])
    d12 = model.distance_to_human(home, np.stack([p1, p2]))[0]
    assert d12[0] > 0.0 and d12[0] < d12[1] <= d12[0] + 0.5 + 1e-12
    # a rigid translation of the robot base and the person together changes nothing
    shift = np.array([0.3, -0.2, 0.1])
    moved = CollisionModel(
        cell,
        kin=UR5e(T_world_base=pose_matrix(shift, [0.0, 0.0, 0.0]), T_flange_tcp=cell.tool.T_flange_tcp()),
    )
    np.testing.assert_allclose(
        moved.distance_to_human(home, np.stack([p1 + shift, near + shift])),
        model.distance_to_human(home, np.stack([p1, near])),
        atol=1e-7,  # the hand bone meets the tool axis: sqrt(round-off) precision at contact
    )


def test_human_capsules_and_radii(model: CollisionModel, cell) -> None:
    joints = _standing_person(1.0)
    a, b, r = model.human_capsules(joints[None])
    M = len(HUMAN_CAPSULES)
    assert a.shape == b.shape == (1, M, 3) and r.shape == (M,)
    assert HUMAN_CAPSULES[-1] == "head"
    np.testing.assert_array_equal(a[0, -1], b[0, -1])  # head sphere
    np.testing.assert_array_equal(a[0, -1], joints[JOINT_INDEX["head"]])
    radii = dict(zip(HUMAN_CAPSULES, r, strict=True))
    assert radii["head"] == pytest.approx(0.11)
    assert radii["pelvis-spine"] > radii["l_shoulder-l_elbow"] >= 0.05
    assert 0.05 <= radii["r_elbow-r_wrist"] <= 0.06
    custom = CollisionModel(cell, human_radii={"head": 0.2, "forearm": 0.07})
    r2 = dict(zip(HUMAN_CAPSULES, custom.human_radii, strict=True))
    assert r2["head"] == 0.2 and r2["l_elbow-l_wrist"] == 0.07 and r2["pelvis-spine"] == radii["pelvis-spine"]
    arr = np.full(M, 0.05)
    np.testing.assert_array_equal(CollisionModel(cell, human_radii=arr).human_radii, arr)
    with pytest.raises(ValueError, match="unknown human radius"):
        CollisionModel(cell, human_radii={"tail": 0.1})
    with pytest.raises(ValueError, match="shape"):
        CollisionModel(cell, human_radii=np.ones(3))
    with pytest.raises(ValueError, match="torso"):
        HumanRadii(torso=-0.1)


def test_robot_capsules_follow_the_kinematics(model: CollisionModel, cell) -> None:
    rng = np.random.default_rng(5)
    q = rng.uniform(-np.pi, np.pi, size=(20, 6))
    a, b, r = model.robot_capsules(q)
    L = len(ROBOT_LINKS)
    assert a.shape == b.shape == (20, L, 3) and r.shape == (L,)
    T = model.kin.fk(q)
    # the segments between the joint axes ...
    ra, rd = joint_axis_segments(*model.kin.link_origins_and_axes(q), model.tool_end_fraction)
    ra, rb = ra.transpose(2, 0, 1), (ra + rd).transpose(2, 0, 1)
    np.testing.assert_allclose(ra[:, 0], np.broadcast_to(model.kin.T_world_base[:3, 3], (20, 3)))
    np.testing.assert_allclose(rb[:, 0], T[:, 0, :3, 3])  # base column up to the shoulder axis
    np.testing.assert_allclose(ra[:, -1], T[:, 5, :3, 3])  # tool from the flange ...
    # ... along the TCP direction, its round end capsule_length_m from the flange
    f = model.tool_end_fraction
    np.testing.assert_allclose(rb[:, -1], T[:, 5, :3, 3] + f * (T[:, 6, :3, 3] - T[:, 5, :3, 3]))
    tool = model.cell.tool
    assert f * np.linalg.norm(tool.tcp_xyz) + tool.radius_m == pytest.approx(tool.capsule_length_m)
    assert r[-1] == cell.tool.radius_m
    np.testing.assert_allclose(rb[:, :-1], ra[:, 1:])  # a connected chain
    lengths = np.linalg.norm(rb - ra, axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(lengths[0], lengths.shape), atol=1e-12)  # rigid links
    assert lengths[0, ROBOT_LINKS.index("upper_arm")] == pytest.approx(0.425)
    assert lengths[0, ROBOT_LINKS.index("forearm")] == pytest.approx(0.3922)
    # ... and the capsules, each reaching its extensions beyond them along its axis
    u = (rb - ra) / lengths[..., None]
    ext = np.array([ROBOT_LINK_EXTENSIONS.get(n, (0.0, 0.0)) for n in ROBOT_LINKS])
    np.testing.assert_allclose(a, ra - ext[None, :, :1] * u, atol=1e-12)
    np.testing.assert_allclose(b, rb + ext[None, :, 1:] * u, atol=1e-12)
    assert ext[ROBOT_LINKS.index("tool")].tolist() == [0.0, 0.0]


def test_shape_errors(model: CollisionModel) -> None:
    with pytest.raises(ValueError, match=r"\(B, 6\)"):
        model.distance_to_human(np.zeros(6), np.zeros((1, NUM_JOINTS, 3)))
    with pytest.raises(ValueError, match="canonical joint set"):
        model.distance_to_human(np.zeros((1, 6)), np.zeros((1, 18, 3)))
    with pytest.raises(ValueError, match="same K"):
        model.distance_to_human_paired(np.zeros((2, 6)), np.zeros((3, NUM_JOINTS, 3)))
    assert model.distance_to_human(np.zeros((0, 6)), np.zeros((2, NUM_JOINTS, 3))).shape == (0, 2)
    assert model.distance_to_human_paired(np.zeros((0, 6)), np.zeros((0, NUM_JOINTS, 3))).shape == (0,)


# --------------------------------------------------------------------------- static scene


def test_home_is_free(model: CollisionModel, cell) -> None:
    home = np.array([cell.robot.home_q])
    assert not model.in_static_collision(home)[0]
    assert not model.self_collision(home)[0]
    # the lowest robot part at home is the upper arm's capsule, reaching its extension below the shoulder
    # axis (d1 = 0.1625 m; the base column stands on the table and does not count)
    r = ROBOT_LINK_RADII["upper_arm"]
    below = ROBOT_LINK_EXTENSIONS["upper_arm"][0]
    assert model.static_clearance(home)[0] == pytest.approx(0.1625 - below - r, abs=1e-12)


def test_tool_into_the_table_collides(model: CollisionModel) -> None:
    kin = model.kin
    p = np.array([[0.5, 0.1, 0.10], [0.5, 0.1, -0.02]])
    q_ik, valid = kin.ik_down(p)
    idx = np.argmax(valid, axis=1)
    q = q_ik[np.arange(2), idx]
    tool = model.static_distances(q)[:, ROBOT_LINKS.index("tool"), 0]  # to the table
    t = model.cell.tool
    below = t.capsule_length_m - float(np.linalg.norm(t.tcp_xyz))
    assert below >= t.part_size_m[2] / 2  # at least down to the carried part's bottom
    # tool pointing down: its capsule's round end lies `below` under the TCP; the table top is z = 0
    assert tool[0] == pytest.approx(0.10 - below, abs=1e-9)
    # TCP 2 cm inside the 5 cm table top: depth 2 cm plus the capsule below the TCP
    assert tool[1] == pytest.approx(-0.02 - below, abs=1e-9)
    np.testing.assert_array_equal(model.in_static_collision(q), [False, True])
    np.testing.assert_array_equal(model.in_static_collision(q, margin_m=0.09), [True, True])


def test_obstacle_and_conveyor_are_in_the_scene(model: CollisionModel, cell) -> None:
    names = [box.name for box in model.static_boxes]
    assert names[:2] == ["table", "conveyor"] and "parts_bin" in names
    assert not model.static_pairs[ROBOT_LINKS.index("base"), 0]  # the base stands on the table
    assert model.static_pairs[ROBOT_LINKS.index("base"), 1:].all()
    # TCP put into the parts bin from above
    binbox = next(b for b in model.static_boxes if b.name == "parts_bin")
    top = binbox.center[2] + binbox.size[2] / 2
    q_ik, valid = model.kin.ik_down(np.array([[binbox.center[0], binbox.center[1], top - 0.03]]))
    q = q_ik[0][valid[0]]
    assert len(q) > 0
    d = model.static_distances(q)
    k = names.index("parts_bin")
    t = model.cell.tool
    below = t.capsule_length_m - float(np.linalg.norm(t.tcp_xyz))  # the tool capsule's end under the TCP
    np.testing.assert_allclose(d[:, -1, k], -0.03 - below, atol=1e-9)


def test_static_clearance_matches_fcl_and_exhaustive(model: CollisionModel) -> None:
    rng = np.random.default_rng(6)
    q = rng.uniform(model.kin.q_min, model.kin.q_max, size=(300, 6))
    clearance = model.static_clearance(q)
    exhaustive = model.static_distances(q).reshape(len(q), -1).min(axis=1)
    np.testing.assert_allclose(clearance, exhaustive, atol=0)
    free = np.nonzero(clearance > 1e-3)[0][:40]
    assert len(free) >= 20
    # fcl's GJK capsule-box distance is within about 0.2 % (exactness is shown against brute force above)
    np.testing.assert_allclose(model.static_clearance_fcl(q[free]), clearance[free], rtol=5e-3, atol=1e-3)
    hit = np.nonzero(clearance < -1e-3)[0][:20]
    assert len(hit) >= 5
    a, b, r = model.robot_capsules(q[hit])
    boxes = [fcl_box(box) for box in model.static_boxes]
    for n in range(len(hit)):
        assert any(
            _fcl_collide(fcl_capsule(a[n, li], b[n, li], r[li]), boxes[bi])
            for li, bi in zip(*np.nonzero(model.static_pairs), strict=True)
        )


# --------------------------------------------------------------------------- self-collision


def test_self_collision_known_cases(model: CollisionModel, cell) -> None:
    home = cell.robot.home_q
    folded = [0.0, -math.pi / 2, 2.9, -math.pi / 2, -math.pi / 2, 0.0]  # elbow folded: tool onto the shoulder
    q = np.array([home, folded, [0.0] * 6])
    np.testing.assert_array_equal(model.self_collision(q), [False, True, False])
    d = model.self_distances(q)
    worst = SELF_COLLISION_PAIRS[int(np.argmin(d[1]))]
    # the tool lands on the shoulder housing, which the shoulder's and the upper arm's capsules share
    assert {ROBOT_LINKS[worst[0]], ROBOT_LINKS[worst[1]]} in ({"shoulder", "tool"}, {"upper_arm", "tool"})
    shoulder_tool = SELF_COLLISION_PAIRS.index((ROBOT_LINKS.index("shoulder"), ROBOT_LINKS.index("tool")))
    assert d[1, shoulder_tool] < -0.01
    assert model.self_clearance(q)[1] < -0.01


def test_self_collision_pairs_skip_touching_neighbours() -> None:
    pairs = set(SELF_COLLISION_PAIRS)
    L = len(ROBOT_LINKS)
    assert all(j - i >= 2 for i, j in pairs)
    assert (ROBOT_LINKS.index("base"), ROBOT_LINKS.index("upper_arm")) not in pairs
    assert (ROBOT_LINKS.index("shoulder"), ROBOT_LINKS.index("tool")) in pairs
    assert len(pairs) == (L - 1) * (L - 2) // 2 - 2


def test_structural_minimum_distances_hold_everywhere(model: CollisionModel) -> None:
    """Upper arm and forearm run in parallel planes 0.131 m apart: they never touch (self radii 59, 50 mm)."""
    rng = np.random.default_rng(8)
    q = rng.uniform(model.kin.q_min, model.kin.q_max, size=(2000, 6))
    d = model.self_distances(q)
    k = SELF_COLLISION_PAIRS.index((ROBOT_LINKS.index("upper_arm"), ROBOT_LINKS.index("forearm")))
    assert d[:, k].min() >= 0.131 - 0.11 - 1e-9


def test_model_accepts_custom_kinematics(cell) -> None:
    kin = UR5e(
        T_world_base=pose_matrix([0.0, 0.0, 0.3], [0.0, 0.0, 0.0]), T_flange_tcp=cell.tool.T_flange_tcp()
    )
    model = CollisionModel(cell, kin=kin)
    home = np.array([cell.robot.home_q])
    # the robot lifted by 0.3 m: the shoulder is 0.3 m further from the table
    d = model.static_distances(home)[0]
    assert d[ROBOT_LINKS.index("shoulder"), 0] == pytest.approx(
        0.1625 - ROBOT_LINK_RADII["shoulder"] + 0.3, abs=1e-12
    )
    assert model.static_clearance(home)[0] == pytest.approx(d.min())
