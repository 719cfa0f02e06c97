"""UR5e kinematics: FK against the published ``ur_analytic_ik``, IK round trips, branches, limits."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import ur_analytic_ik
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from app.config import R_WORLD_TOOL_DOWN, load_workcell, pose_matrix
from app.planning.kinematics import (
    Q_MAX,
    Q_MIN,
    QD_MAX,
    QDD_MAX,
    UR5e,
    align_branches,
    nearest_branch,
    within_limits,
    wrap_angle,
)

PROPERTY = settings(max_examples=150, deadline=None)
TOL = 1e-8


def _q_in_limits() -> st.SearchStrategy[np.ndarray]:
    # strictly inside: at exactly +-2 pi a round-off can put the only 2 pi-copy outside the limits
    lo, hi = Q_MIN + 1e-6, Q_MAX - 1e-6

    def scale(u: np.ndarray) -> np.ndarray:
        return lo + (hi - lo) * u

    unit = st.floats(0.0, 1.0, allow_nan=False, allow_infinity=False)
    return arrays(np.float64, (6,), elements=unit).map(scale)


def _pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation angle (rad) between poses (..., 4, 4)."""
    dp = np.linalg.norm(T_a[..., :3, 3] - T_b[..., :3, 3], axis=-1)
    # angle = 2 asin(|R_a - R_b|_F / (2 sqrt 2)): accurate for small angles, unlike acos of the trace.
    fro = np.linalg.norm(T_a[..., :3, :3] - T_b[..., :3, :3], axis=(-2, -1))
    dr = 2.0 * np.arcsin(np.minimum(fro / (2.0 * math.sqrt(2.0)), 1.0))
    return dp, dr


def _away_from_singular(kin: UR5e, q: np.ndarray, *, margin: float = 0.05) -> bool:
    """Wrist (sin q5), elbow (sin q3) and shoulder (wrist centre near the base axis) singularities."""
    if abs(math.sin(q[4])) < margin or abs(math.sin(q[2])) < margin:
        return False
    T = kin.fk(q[None])[0]
    p5 = T[4, :3, 3] - kin.T_world_base[:3, 3]  # DH frame 5 origin, on the wrist-3 axis
    rho2 = p5[0] ** 2 + p5[1] ** 2
    return rho2 - 0.1333**2 > margin * 0.1


def _contains(q_branches: np.ndarray, valid: np.ndarray, q: np.ndarray, tol: float) -> bool:
    aligned = align_branches(q_branches, q)
    err = np.max(np.abs(aligned - q), axis=-1)
    return bool(np.any(valid & (err < tol)))


# --------------------------------------------------------------------------- constants and limits


def test_limits_and_speeds_match_the_contract() -> None:
    assert Q_MIN.shape == Q_MAX.shape == QD_MAX.shape == QDD_MAX.shape == (6,)
    np.testing.assert_allclose(Q_MAX, [2 * np.pi, 2 * np.pi, np.pi, 2 * np.pi, 2 * np.pi, 2 * np.pi])
    np.testing.assert_allclose(Q_MIN, -Q_MAX)
    np.testing.assert_allclose(QD_MAX, np.pi)
    assert np.all(QDD_MAX > 0)


def test_within_limits() -> None:
    q = np.array([[0.0] * 6, [0, 0, 3.2, 0, 0, 0], [6.3, 0, 0, 0, 0, 0], [np.nan, 0, 0, 0, 0, 0]])
    np.testing.assert_array_equal(within_limits(q), [True, False, False, False])
    assert within_limits(np.zeros((2, 3, 6))).shape == (2, 3)
    with pytest.raises(ValueError, match="shape"):
        within_limits(np.zeros((4, 5)))


def test_wrap_angle() -> None:
    np.testing.assert_allclose(
        wrap_angle(np.array([0.0, 3 * np.pi / 2, -3 * np.pi / 2])), [0, -np.pi / 2, np.pi / 2]
    )


# --------------------------------------------------------------------------- forward kinematics


def test_fk_home_configuration_by_hand() -> None:
    kin = UR5e()
    # q = 0: the arm stretches along -x of the base (a2, a3 negative), the wrist offsets follow the DH table.
    T = kin.fk(np.zeros((1, 6)))[0]
    np.testing.assert_allclose(T[0, :3, 3], [0.0, 0.0, 0.1625], atol=1e-12)
    np.testing.assert_allclose(T[1, :3, 3], [-0.425, 0.0, 0.1625], atol=1e-12)
    np.testing.assert_allclose(T[2, :3, 3], [-0.8172, 0.0, 0.1625], atol=1e-12)
    np.testing.assert_allclose(T[5, :3, 3], [-0.8172, -0.1333 - 0.0996, 0.1625 - 0.0997], atol=1e-12)
    np.testing.assert_allclose(T[6], T[5], atol=0)


@PROPERTY
@given(q=_q_in_limits())
def test_fk_matches_ur_analytic_ik(q: np.ndarray) -> None:
    """Independent check: the published implementation uses the same DH frames 0 (base) and 6 (flange)."""
    cell = load_workcell()
    T_flange_tcp = cell.tool.T_flange_tcp()
    kin = UR5e(T_flange_tcp=T_flange_tcp)
    T = kin.fk(q[None])[0]
    np.testing.assert_allclose(T[5], ur_analytic_ik.ur5e.forward_kinematics(*q), atol=1e-12)
    ref_tcp = ur_analytic_ik.ur5e.forward_kinematics_with_tcp(*q, np.ascontiguousarray(T_flange_tcp))
    np.testing.assert_allclose(T[6], ref_tcp, atol=1e-12)
    np.testing.assert_allclose(kin.fk_tcp(q[None])[0], ref_tcp, atol=1e-12)


def test_fk_world_placement_and_tool() -> None:
    rng = np.random.default_rng(1)
    q = rng.uniform(Q_MIN, Q_MAX, size=(64, 6))
    T_world_base = pose_matrix([0.3, -0.2, 0.75], [0.1, -0.2, 0.8])
    T_flange_tcp = pose_matrix([0.01, 0.02, 0.15], [0.0, 0.0, 0.5])
    plain = UR5e().fk(q)
    placed = UR5e(T_world_base=T_world_base, T_flange_tcp=T_flange_tcp).fk(q)
    np.testing.assert_allclose(placed[:, :6], T_world_base @ plain[:, :6], atol=1e-12)
    np.testing.assert_allclose(placed[:, 6], T_world_base @ plain[:, 5] @ T_flange_tcp, atol=1e-12)
    kin = UR5e(T_world_base=T_world_base, T_flange_tcp=T_flange_tcp)
    p, z, p_tcp = kin.link_origins_and_axes(q)
    np.testing.assert_allclose(p[1:].transpose(2, 0, 1), placed[:, :6, :3, 3], atol=1e-12)
    np.testing.assert_allclose(z[1:].transpose(2, 0, 1), placed[:, :6, :3, 2], atol=1e-12)
    np.testing.assert_allclose(p_tcp.T, placed[:, 6, :3, 3], atol=1e-12)


def test_from_workcell_uses_mount_and_tool() -> None:
    cell = load_workcell()
    kin = UR5e.from_workcell(cell)
    np.testing.assert_allclose(kin.T_world_base, cell.robot.T_world_base())
    np.testing.assert_allclose(kin.T_flange_tcp, cell.tool.T_flange_tcp())


def test_bad_shapes_and_transforms_are_rejected() -> None:
    kin = UR5e()
    with pytest.raises(ValueError, match=r"\(B, 6\)"):
        kin.fk(np.zeros(6))
    with pytest.raises(ValueError, match=r"\(B, 4, 4\)"):
        kin.ik(np.eye(4))
    with pytest.raises(ValueError, match=r"\(B, 3\)"):
        kin.ik_down(np.zeros(3))
    with pytest.raises(ValueError, match="rotation"):
        UR5e(T_world_base=np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="q_min < q_max"):
        UR5e(q_min=np.zeros(6), q_max=np.zeros(6))


# --------------------------------------------------------------------------- inverse kinematics


def _arm(cell: Any) -> UR5e:
    """The cell's arm (mount and tool) within the UR5e's own joint limits, not the cell's narrower ones."""
    return UR5e(T_world_base=cell.robot.T_world_base(), T_flange_tcp=cell.tool.T_flange_tcp())


@PROPERTY
@given(q=_q_in_limits())
def test_ik_of_fk_contains_q(q: np.ndarray) -> None:
    kin = _arm(load_workcell())
    assume(_away_from_singular(kin, q))
    T = kin.fk_tcp(q[None])
    q_ik, valid = kin.ik(T)
    assert q_ik.shape == (1, 8, 6) and valid.shape == (1, 8)
    assert _contains(q_ik[0], valid[0], q, 1e-9)


@PROPERTY
@given(q=_q_in_limits(), x=st.floats(-0.3, 0.3), y=st.floats(-0.3, 0.3), yaw=st.floats(-3.0, 3.0))
def test_every_valid_branch_reaches_the_pose(q: np.ndarray, x: float, y: float, yaw: float) -> None:
    """Also near singularities: whatever is marked valid must reach the asked pose. Not at the wrist
    singularity (sin q5 = 0) of an arm stretched straight (sin q3 = 0) at once: there the free split of the
    wrist's rotation between q4 and q6 (q6 = 0) moves the wrist by round-off, past the arm's full reach, and
    the pose counts as unreachable (a found case: q3 = q5 = 0, q6 = 1e-6)."""
    assume(not (abs(math.sin(q[2])) < 1e-6 and abs(math.sin(q[4])) < 1e-6))
    T_world_base = pose_matrix([x, y, 0.0], [0.0, 0.0, yaw])
    kin = UR5e(T_world_base=T_world_base, T_flange_tcp=pose_matrix([0.0, 0.03, 0.15], [0.0, 0.2, 0.0]))
    T = kin.fk_tcp(q[None])
    q_ik, valid = kin.ik(T)
    assert valid.any()
    reached = kin.fk_tcp(q_ik[0][valid[0]])
    dp, dr = _pose_error(reached, T)
    assert dp.max() < TOL and dr.max() < TOL
    assert within_limits(q_ik[0][valid[0]]).all()


@PROPERTY
@given(q=_q_in_limits())
def test_ur_analytic_ik_solutions_are_among_ours(q: np.ndarray) -> None:
    """Independent check: each solution of the published IK (flange poses in DH frame 0) is one of ours."""
    kin = UR5e()
    assume(_away_from_singular(kin, q))
    T = kin.fk_tcp(q[None])
    ref = ur_analytic_ik.ur5e.inverse_kinematics(np.ascontiguousarray(T[0]))
    assert len(ref) >= 1
    q_ik, valid = kin.ik(T)
    for q_ref in ref:
        if not (-np.pi <= q_ref[2] <= np.pi):  # elbow outside our limits: not a solution we may return
            continue
        diff = np.abs(wrap_angle(q_ik[0] - q_ref))
        assert np.any(valid[0] & (diff.max(axis=-1) < 1e-7)), f"reference solution {q_ref} missing"


def test_ik_batch_round_trip_and_branch_structure() -> None:
    rng = np.random.default_rng(7)
    kin = _arm(load_workcell())
    q = rng.uniform(Q_MIN, Q_MAX, size=(2000, 6))
    T = kin.fk_tcp(q)
    q_ik, valid = kin.ik(T)
    assert q_ik.shape == (2000, 8, 6) and valid.shape == (2000, 8)
    # every valid branch reaches the pose
    reached = kin.fk_tcp(q_ik[valid])
    dp, dr = _pose_error(reached, np.repeat(T, valid.sum(axis=1), axis=0))
    assert dp.max() < TOL and dr.max() < TOL
    # IK angles are the representatives closest to 0
    assert np.all(np.abs(q_ik[valid]) <= np.pi + 1e-12)
    # branch layout: index = 4 * shoulder + 2 * wrist + elbow
    qv = np.where(valid[..., None], q_ik, np.nan)
    assert np.all(np.nan_to_num(np.sin(qv[:, [0, 1, 4, 5], 4]), nan=1.0) >= -1e-12)  # wrist 0: sin q5 >= 0
    assert np.all(np.nan_to_num(qv[:, 0::2, 2], nan=1.0) >= 0)  # elbow 0: q3 >= 0
    # all reachable poses (generated by FK) have at least one valid branch, most have 8
    assert valid.any(axis=1).all()
    aligned = align_branches(q_ik, q[:, None, :])
    hit = np.any(valid & (np.max(np.abs(aligned - q[:, None, :]), axis=-1) < 1e-6), axis=1)
    assert hit.mean() > 0.99  # the rest sit at singularities where q is one of infinitely many solutions


def test_ik_unreachable_pose_has_no_valid_branch() -> None:
    kin = UR5e()
    T = np.eye(4)[None].copy()
    T[0, :3, 3] = [2.0, 0.0, 0.5]
    _, valid = kin.ik(T)
    assert not valid.any()


def test_ik_at_wrist_singularity() -> None:
    kin = UR5e()
    q = np.array([[0.3, -1.2, 1.4, -0.7, 0.0, 0.8]])  # sin q5 = 0: q4 and q6 share one rotation
    T = kin.fk_tcp(q)
    q_ik, valid = kin.ik(T)
    assert valid.sum() >= 2
    dp, dr = _pose_error(kin.fk_tcp(q_ik[0][valid[0]]), T)
    assert dp.max() < TOL and dr.max() < TOL
    sols = q_ik[0][valid[0]]
    singular = np.abs(np.sin(sols[:, 4])) < 1e-9
    assert singular.sum() >= 2  # the branches of the original shoulder: q6 is free, set to 0
    np.testing.assert_array_equal(sols[singular, 5], 0.0)


def test_ik_down_points_the_tool_down() -> None:
    cell = load_workcell()
    kin = UR5e.from_workcell(cell)
    p = np.array([s.xyz for s in cell.task_stations()])
    yaw = np.linspace(-1.0, 1.0, len(p))
    q_ik, valid = kin.ik_down(p, yaw=yaw)
    assert valid.any(axis=1).all(), "every station of the default cell is reachable with the tool down"
    for i in range(len(p)):
        T = kin.fk_tcp(q_ik[i][valid[i]])
        np.testing.assert_allclose(T[:, :3, 3], np.broadcast_to(p[i], (len(T), 3)), atol=1e-9)
        c, s = math.cos(yaw[i]), math.sin(yaw[i])
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R_WORLD_TOOL_DOWN
        np.testing.assert_allclose(T[:, :3, :3], np.broadcast_to(R, (len(T), 3, 3)), atol=1e-9)
    q0, v0 = kin.ik_down(p)  # scalar yaw
    q_same, v_same = kin.ik_down(p, yaw=np.zeros(len(p)))
    np.testing.assert_array_equal(v0, v_same)
    np.testing.assert_allclose(q0[v0], q_same[v_same])


def test_narrow_limits_pick_representative_within_limits() -> None:
    q_min = np.array([0.0, -2 * np.pi, -np.pi, -2 * np.pi, -2 * np.pi, -2 * np.pi])
    q_max = np.array([2 * np.pi, 2 * np.pi, np.pi, 2 * np.pi, 2 * np.pi, 2 * np.pi])
    wide = UR5e()
    narrow = UR5e(q_min=q_min, q_max=q_max)
    q = np.array([[-1.0, -1.2, 1.4, -0.7, 0.9, 0.8]])
    T = wide.fk_tcp(q)
    q_w, v_w = wide.ik(T)
    q_n, v_n = narrow.ik(T)
    np.testing.assert_array_equal(v_w, v_n)
    assert np.all(q_n[0][v_n[0]][:, 0] >= 0.0)
    np.testing.assert_allclose(wrap_angle(q_n - q_w)[v_n], 0.0, atol=1e-12)
    assert _contains(q_n[0], v_n[0], np.array([2 * np.pi - 1.0, -1.2, 1.4, -0.7, 0.9, 0.8]), 1e-9)
    # a limit that excludes a branch's elbow angle invalidates it
    no_pos_elbow = UR5e(
        q_min=Q_MIN, q_max=np.array([2 * np.pi, 2 * np.pi, 0.0, 2 * np.pi, 2 * np.pi, 2 * np.pi])
    )
    _, v_e = no_pos_elbow.ik(T)
    np.testing.assert_array_equal(v_e[0, 0::2], False)
    np.testing.assert_array_equal(v_e[0, 1::2], v_w[0, 1::2])


# --------------------------------------------------------------------------- branch helpers


def test_nearest_branch() -> None:
    q_b = np.zeros((2, 8, 6))
    q_b[:, :, 0] = np.arange(8)[None, :] * 0.1
    valid = np.ones((2, 8), dtype=bool)
    valid[1] = False
    q_ref = np.zeros((2, 6))
    q_ref[:, 0] = 0.32
    idx, dist = nearest_branch(q_b, valid, q_ref)
    assert idx.tolist() == [3, -1]
    np.testing.assert_allclose(dist[0], 0.02, atol=1e-12)
    assert dist[1] == np.inf
    valid[0, 3] = False
    idx, dist = nearest_branch(q_b, valid, q_ref, metric="max")
    assert idx[0] == 4 and dist[0] == pytest.approx(0.08)
    with pytest.raises(ValueError, match="metric"):
        nearest_branch(q_b, valid, q_ref, metric="l1")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="q_ref"):
        nearest_branch(q_b, valid, np.zeros(6))


def test_align_branches_moves_2pi_copies_next_to_the_reference() -> None:
    q = np.array([[-2.8, 0.5, 3.0, 0.0, 0.0, 0.0]])
    q_ref = np.array([3.5, 0.5, -3.0, 0.0, 6.0, -6.0])
    out = align_branches(q, q_ref)
    np.testing.assert_allclose(out[0], [-2.8 + 2 * np.pi, 0.5, 3.0, 0.0, 2 * np.pi, -2 * np.pi])
    assert within_limits(out).all()
    # the nearest copy would leave the limits: take the nearest one within them
    out = align_branches(np.array([-1.0, 0, 0, 0, 0, 0]), np.array([7.5, 0, 0, 0, 0, 0]))
    assert out[0] == pytest.approx(2 * np.pi - 1.0)
    out = align_branches(np.array([[1.0, 0, 0, 0, 0, 0]]), np.array([[9.0, 0, 0, 0, 0, 0]]))
    assert out[0, 0] == pytest.approx(1.0)
