"""Compiled inner loops of the simulated cell (numba): the servo tracker and the simulated operator's body.

:func:`track_substeps` is the loop form of :meth:`app.cell.reference.ReferenceJointTracker.step` and
:func:`body_pose` of :func:`app.cell.reference.body_pose_reference`, NumPy references that only the tests
import; the tests compare each kernel with its reference. They run per servo tick or camera frame on arrays
of six joints or nineteen body joints, where NumPy's per-call cost (about a microsecond per operation,
dozens to hundreds per call) is most of the time.

The arithmetic is written in the references' order of operations and compiled without ``fastmath``, so the
results agree to rounding. ``cache=True`` keeps the machine code next to this file (numba compiles in
memory with a warning where that folder is read-only).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from app.jit import jit

__all__ = ["JointTrackerParams", "TrackerCommand", "body_pose", "track_substeps"]


class JointTrackerParams(NamedTuple):
    """A joint tracker's constants as :func:`track_substeps` reads them (built once per tracker).

    Attributes:
        hold_after_s: How long (s) a command is extrapolated with its velocity.
        kp: Feedback gain (1/s).
        ref_lo: Lower bounds (6,) of the reference (rad), a hair inside the position limits.
        ref_hi: Upper bounds (6,) of the reference (rad).
        q_min: Lower position limits (6,) (rad).
        q_max: Upper position limits (6,) (rad).
        qdd_max: Acceleration limits (6,) (rad/s^2).
        inv_qd_max: Reciprocals (6,) of the speed limits (s/rad).
        brake_decel: How fast each joint can slow down (6,) (rad/s^2).
    """

    hold_after_s: float
    kp: float
    ref_lo: np.ndarray
    ref_hi: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    qdd_max: np.ndarray
    inv_qd_max: np.ndarray
    brake_decel: np.ndarray


class TrackerCommand(NamedTuple):
    """The servo set-point a joint tracker follows, as :func:`track_substeps` reads it (built once per
    command).

    Attributes:
        t: Time of the set-point (s).
        q: Joint positions (6,) (rad).
        qd: Joint velocities (6,) (rad/s).
        active: False: there is no command and the tracker holds its position (``t``, ``q``, ``qd`` unused).
    """

    t: float
    q: np.ndarray
    qd: np.ndarray
    active: bool


@jit
def track_substeps(
    q: np.ndarray,
    qd: np.ndarray,
    t: float,
    h: float,
    n: int,
    s: float,
    stopping: bool,
    command: TrackerCommand,
    params: JointTrackerParams,
) -> None:
    """``n`` substeps of ``h`` (s) of the joint tracker from time ``t``, updating ``q`` and ``qd`` (6,) in
    place: tracking the ``command`` at speed scale ``s``, or braking to rest along the path when
    ``stopping``."""
    cmd_t, cmd_q, cmd_qd, has_cmd = command.t, command.q, command.qd, command.active
    hold_after_s, kp = params.hold_after_s, params.kp
    ref_lo, ref_hi, q_min, q_max = params.ref_lo, params.ref_hi, params.q_min, params.q_max
    qdd_max, inv_qd_max, brake_decel = params.qdd_max, params.inv_qd_max, params.brake_decel
    q_ref = np.empty(6)
    qd_ff = np.empty(6)
    qd_new = np.empty(6)
    for step in range(n):
        if stopping:
            t_stop = 0.0
            for j in range(6):
                t_stop = max(t_stop, abs(qd[j]) / brake_decel[j])
            if t_stop == 0.0:
                continue  # at rest
            for j in range(6):
                qd_new[j] = 0.0 if t_stop <= h else qd[j] * (1.0 - h / t_stop)
        else:
            tau = t + step * h + h
            if not has_cmd:
                for j in range(6):
                    q_ref[j] = q[j]
                    qd_ff[j] = 0.0
            else:
                lead = tau - cmd_t
                for j in range(6):
                    if lead > hold_after_s:
                        r = cmd_q[j] + cmd_qd[j] * hold_after_s
                        qd_ff[j] = 0.0
                    else:
                        r = cmd_q[j] + cmd_qd[j] * lead
                        qd_ff[j] = cmd_qd[j]
                    q_ref[j] = min(max(r, ref_lo[j]), ref_hi[j])
            worst = 0.0
            for j in range(6):
                err = q_ref[j] - q[j]
                mag = abs(err)
                ah = qdd_max[j] * h
                v_brake = ah * (math.sqrt(0.25 + 2.0 * mag / (ah * h)) - 0.5)
                v_des = qd_ff[j] + math.copysign(min(kp * mag, v_brake), err)
                qd_new[j] = v_des
                worst = max(worst, abs(v_des) * inv_qd_max[j])
            if s <= 0.0:
                for j in range(6):
                    qd_new[j] = 0.0
            else:
                worst = worst / s
                if worst > 1.0:
                    for j in range(6):
                        qd_new[j] = qd_new[j] / worst
            for j in range(6):
                qd_new[j] = _limited_change(qd[j], qd_new[j], qdd_max[j] * h, brake_decel[j] * h)
        for j in range(6):
            q_new = q[j] + qd_new[j] * h
            v = qd_new[j]
            if q_new < q_min[j]:
                q_new, v = q_min[j], 0.0
            elif q_new > q_max[j]:
                q_new, v = q_max[j], 0.0
            q[j] = q_new
            qd[j] = v


@jit
def _limited_change(v: float, v_des: float, up: float, down: float) -> float:
    """The speed a joint moving at ``v`` reaches toward ``v_des`` in one substep: it may lose up to ``down``
    of its speed and gain up to ``up`` (rad/s per substep); through zero it first stops, then speeds up."""
    if v > 0.0:
        out = min(max(v_des, v - down), v + up)
        return out if out >= 0.0 else max(out, -up)
    if v < 0.0:
        out = max(min(v_des, v + down), v - up)
        return out if out <= 0.0 else min(out, up)
    return min(max(v_des, -up), up)


# ----------------------------------------------------------------------------------------------------
# The simulated operator's body
# ----------------------------------------------------------------------------------------------------


@jit(inline="always")
def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    out = np.zeros((3, 3))
    out[0, 0], out[0, 1], out[1, 0], out[1, 1], out[2, 2] = c, -s, s, c, 1.0
    return out


@jit(inline="always")
def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    out = np.zeros((3, 3))
    out[0, 0], out[0, 2], out[1, 1], out[2, 0], out[2, 2] = c, s, 1.0, -s, c
    return out


@jit(inline="always")
def _mv(R: np.ndarray, x: float, y: float, z: float) -> np.ndarray:
    out = np.empty(3)
    for i in range(3):
        out[i] = R[i, 0] * x + R[i, 1] * y + R[i, 2] * z
    return out


@jit(inline="always")
def _unit3(v: np.ndarray) -> np.ndarray:
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return v / n if n > 1e-12 else v


@jit
def _two_link(
    a: np.ndarray, target: np.ndarray, l1: float, l2: float, pole: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    d_vec = target - a
    d = math.sqrt(d_vec[0] * d_vec[0] + d_vec[1] * d_vec[1] + d_vec[2] * d_vec[2])
    reach = 0.999 * (l1 + l2)
    n = _unit3(d_vec) if d > 1e-9 else np.array([0.0, 0.0, -1.0])
    d = min(max(d, abs(l1 - l2) + 1e-6), reach)
    end = a + n * d
    x = (l1 * l1 - l2 * l2 + d * d) / (2.0 * d)
    r = math.sqrt(max(l1 * l1 - x * x, 0.0))
    perp = pole - n * (pole[0] * n[0] + pole[1] * n[1] + pole[2] * n[2])
    if math.sqrt(perp[0] * perp[0] + perp[1] * perp[1] + perp[2] * perp[2]) < 1e-9:
        perp = np.array([-n[2], 0.0, n[0]])  # n x (0, 1, 0)
    return a + n * x + _unit3(perp) * r, end


@jit
def body_pose(
    posture: np.ndarray, lh: np.ndarray, rh: np.ndarray, sway: np.ndarray, dims: np.ndarray, out: np.ndarray
) -> None:
    """Joints (19, 3) of the simulated operator's body frame into ``out`` for a posture (lean, twist, dx,
    dy) (rad, rad, m, m), hand targets ``lh``, ``rh`` (3,) and a sway (3,) (m): the loop form of
    :meth:`app.cell.operator_sim._Body.pose` (the joint order of :data:`app.prediction.skeleton.JOINTS`).
    ``dims``: :meth:`app.cell.operator_sim._Body.kernel_dims`."""
    k, pelvis_z, l_spine, l_chest, l_neck, l_head = dims[0], dims[1], dims[2], dims[3], dims[4], dims[5]
    sh_y, sh_z, l_upper, l_fore, l_hand = dims[6], dims[7], dims[8], dims[9], dims[10]
    hip_y, hip_z, l_thigh, l_shank = dims[11], dims[12], dims[13], dims[14]
    ankle_z, foot_y = dims[15], dims[16]
    arm, protraction = dims[17], dims[18]
    lean, twist, dx, dy = posture[0], posture[1], posture[2], posture[3]
    p = np.array([dx, dy, pelvis_z - 0.08 * k * (1.0 - math.cos(lean))]) + sway
    R_half = _rz(0.6 * twist) @ _ry(0.45 * lean)
    R = _rz(twist) @ _ry(lean)
    spine = p + _mv(R_half, 0.0, 0.0, l_spine)
    chest = spine + _mv(R, 0.0, 0.0, l_chest)
    neck = chest + _mv(R, 0.0, 0.0, l_neck)
    head = neck + _mv(R @ _ry(-0.35 * lean + 0.2), 0.0, 0.0, l_head)
    out[0], out[1], out[2], out[3], out[4] = p, spine, chest, neck, head
    for i in range(2):
        side = 1.0 if i == 0 else -1.0
        hand = lh if i == 0 else rh
        base = 5 if i == 0 else 9
        sh = chest + _mv(R, 0.0, side * sh_y, sh_z)
        u = _unit3(_unit3(hand - sh) + np.array([0.0, 0.0, -0.7]))
        w = hand - l_hand * u
        ws = w - sh
        excess = math.sqrt(ws[0] * ws[0] + ws[1] * ws[1] + ws[2] * ws[2]) - 0.85 * arm
        if excess > 0:  # the shoulder comes forward on a long reach
            sh = sh + _unit3(ws) * min(protraction, excess)
        pu = _unit3(np.array([-0.3, side * 0.6, -1.0]))
        pole = _mv(R, pu[0], pu[1], pu[2])
        elbow, wrist = _two_link(sh, w, l_upper, l_fore, pole)
        out[base], out[base + 1], out[base + 2] = sh, elbow, wrist
        out[base + 3] = wrist + l_hand * u
    R_p = _rz(0.35 * twist)
    for i in range(2):
        side = 1.0 if i == 0 else -1.0
        base = 13 if i == 0 else 16
        hip = p + _mv(R_p, 0.0, side * hip_y, hip_z)
        ankle = np.array([0.0, side * foot_y, ankle_z])
        knee, ankle = _two_link(hip, ankle, l_thigh, l_shank, np.array([1.0, 0.0, 0.0]))
        out[base], out[base + 1], out[base + 2] = hip, knee, ankle
