"""NumPy references of the cell's compiled loops, for the tests and benchmarks only (nothing at run time
imports this module; ``tests/unit/test_layout.py`` checks that).

- :class:`ReferenceJointTracker` is a :class:`~app.cell.joint_tracking.JointTracker` whose :meth:`step`
  integrates in NumPy, one substep at a time: the reference of :func:`app.cell._kernels.track_substeps`.
- :func:`body_pose_reference` is the simulated operator's body pose in NumPy: the reference of
  :func:`app.cell._kernels.body_pose` (:meth:`app.cell.operator_sim._Body.pose`).

The tests compare each with its kernel; the kernels are written in these references' order of operations.
"""

from __future__ import annotations

import math

import numpy as np

from app.cell.joint_tracking import JointTracker
from app.cell.operator_sim import _J, _Body, _norm, _ry, _rz, _unit
from app.prediction.skeleton import NUM_JOINTS

__all__ = ["ReferenceJointTracker", "body_pose_reference"]


class ReferenceJointTracker(JointTracker):
    """A :class:`~app.cell.joint_tracking.JointTracker` that integrates in NumPy (the same arguments)."""

    def step(self, t: float, dt_s: float, *, speed_scale: float = 1.0, stopping: bool = False) -> None:
        """:meth:`JointTracker.step` in NumPy, one substep at a time."""
        n, h, s = self._substeps(dt_s, speed_scale)
        for i in range(n):
            if stopping:
                self._substep_stop(h)
            else:
                self._substep_track(t + i * h, h, s)

    def _substep_stop(self, h: float) -> None:
        lim = self.limits
        speed = np.abs(self.qd)
        if not np.any(speed > 0):
            return
        t_stop = float(np.max(speed / lim.brake_decel))
        if t_stop <= h:
            qd_new = np.zeros(6)
        else:
            qd_new = self.qd * (1.0 - h / t_stop)
        self._integrate(qd_new, h)

    def _substep_track(self, tau: float, h: float, s: float) -> None:
        q_ref, qd_ff = self.reference(tau + h)
        err = q_ref - self.q
        mag = np.abs(err)
        # Fastest speed from which the joint still stops on the reference, for this discrete step: the
        # continuous sqrt(2 a |e|) overshoots by about a h^2 per step.
        ah = self._qdd_max * h
        v_brake = ah * (np.sqrt(0.25 + 2.0 * mag / (ah * h)) - 0.5)
        v_des = qd_ff + np.copysign(np.minimum(self.kp * mag, v_brake), err)
        if s <= 0.0:
            v_des = np.zeros(6)
        else:
            worst = float(np.max(np.abs(v_des) * self._inv_qd_max)) / s
            if worst > 1.0:  # scale the whole vector: the direction of motion is kept
                v_des = v_des / worst
        down = self.limits.brake_decel * h
        out = np.empty(6)
        for j in range(6):  # a braking joint may lose speed at brake_decel, one speeding up gains at qdd_max
            v, vd = float(self.qd[j]), float(v_des[j])
            if v > 0.0:
                o = min(max(vd, v - down[j]), v + ah[j])
                out[j] = o if o >= 0.0 else max(o, -ah[j])
            elif v < 0.0:
                o = max(min(vd, v + down[j]), v - ah[j])
                out[j] = o if o <= 0.0 else min(o, ah[j])
            else:
                out[j] = min(max(vd, -ah[j]), ah[j])
        self._integrate(out, h)

    def _integrate(self, qd_new: np.ndarray, h: float) -> None:
        lim = self.limits
        q_new = self.q + qd_new * h  # semi-implicit Euler, consistent with the braking speed above
        if (q_new < lim.q_min).any() or (q_new > lim.q_max).any():
            clipped = (q_new < lim.q_min) | (q_new > lim.q_max)
            q_new = np.clip(q_new, lim.q_min, lim.q_max)
            qd_new = np.where(clipped, 0.0, qd_new)
        self.q = q_new
        self.qd = qd_new


def _two_link(
    a: np.ndarray, target: np.ndarray, l1: float, l2: float, pole: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Middle joint and end point of a two-link chain from ``a`` towards ``target`` (clamped to reach),
    bending towards ``pole``."""
    d_vec = target - a
    d = _norm(d_vec)
    reach = 0.999 * (l1 + l2)
    n = _unit(d_vec) if d > 1e-9 else np.array([0.0, 0.0, -1.0])
    d = min(max(d, abs(l1 - l2) + 1e-6), reach)
    end = a + n * d
    x = (l1 * l1 - l2 * l2 + d * d) / (2.0 * d)
    r = math.sqrt(max(l1 * l1 - x * x, 0.0))
    perp = pole - n * float(pole @ n)
    if _norm(perp) < 1e-9:
        perp = np.cross(n, [0.0, 1.0, 0.0])
    return a + n * x + _unit(perp) * r, end


def body_pose_reference(
    body: _Body, posture: np.ndarray, lh: np.ndarray, rh: np.ndarray, sway: np.ndarray
) -> np.ndarray:
    """:meth:`app.cell.operator_sim._Body.pose` of ``body`` in NumPy: joints (J, 3) in the body frame for a
    posture (lean, twist, dx, dy) (rad, rad, m, m), hand targets ``lh``, ``rh`` (3,) and a sway (3,) (m)."""
    lean, twist = posture[0], posture[1]
    out = np.empty((NUM_JOINTS, 3))
    p = body.pelvis(posture) + sway
    R_half = _rz(0.6 * twist) @ _ry(0.45 * lean)
    R = body.torso_rotation(posture)
    spine = p + R_half @ np.array([0.0, 0.0, body.l_spine])
    chest = spine + R @ np.array([0.0, 0.0, body.l_chest])
    neck = chest + R @ np.array([0.0, 0.0, body.l_neck])
    head = neck + R @ _ry(-0.35 * lean + 0.2) @ np.array([0.0, 0.0, body.l_head])
    out[_J["pelvis"]], out[_J["spine"]], out[_J["chest"]] = p, spine, chest
    out[_J["neck"]], out[_J["head"]] = neck, head
    for side, hand, names in (
        (1.0, lh, ("l_shoulder", "l_elbow", "l_wrist", "l_hand")),
        (-1.0, rh, ("r_shoulder", "r_elbow", "r_wrist", "r_hand")),
    ):
        sh = chest + R @ np.array([0.0, side * body.sh_y, body.sh_z])
        w, u = body.wrist_target(sh, hand)
        excess = _norm(w - sh) - 0.85 * body.arm
        if excess > 0:  # the shoulder comes forward on a long reach
            sh = sh + _unit(w - sh) * min(body.protraction, excess)
        pole = R @ _unit(np.array([-0.3, side * 0.6, -1.0]))
        elbow, wrist = _two_link(sh, w, body.l_upper, body.l_fore, pole)
        out[_J[names[0]]], out[_J[names[1]]], out[_J[names[2]]] = sh, elbow, wrist
        out[_J[names[3]]] = wrist + body.l_hand * u
    R_p = _rz(0.35 * twist)
    for side, names in ((1.0, ("l_hip", "l_knee", "l_ankle")), (-1.0, ("r_hip", "r_knee", "r_ankle"))):
        hip = p + R_p @ np.array([0.0, side * body.hip_y, body.hip_z])
        ankle = np.array([0.0, side * body.foot_y, body.ankle_z])
        knee, ankle = _two_link(hip, ankle, body.l_thigh, body.l_shank, np.array([1.0, 0.0, 0.0]))
        out[_J[names[0]]], out[_J[names[1]]], out[_J[names[2]]] = hip, knee, ankle
    return out
