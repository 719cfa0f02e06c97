"""``hrc bench kinematics``: batched UR5e IK/FK and robot-person distances against published implementations.

Measured in one run, on the default work cell (its tool included):

* ``ik_us_per_pose``: :meth:`UR5e.ik` on a batch of 1000 TCP poses (all 8 branches and the validity mask).
* ``ik_reference_us_per_pose``: the published ``ur_analytic_ik`` (C++), one pose per call
  (``ur5e.inverse_kinematics_with_tcp``, the same poses and tool).
* ``fk_us_per_config``: :meth:`UR5e.fk` (every link frame and the TCP) on a batch of 1000 configurations.
* ``distance_ns_per_pair``: :meth:`CollisionModel.distance_to_human_paired` on 1024 (configuration, person
  pose) pairs, the planner's hot path; ``distance_cross_ns_per_pair``:
  :meth:`CollisionModel.distance_to_human` on 32 configurations x 32 poses.
* ``fcl_distance_ns_per_pair``: python-fcl on the same 1024 pairs: persistent collision objects for the robot
  links (their transforms updated per pair), person capsules built per pose (bone lengths vary between
  poses), and the minimum distance from two dynamic AABB-tree managers (fcl's broad phase, faster than
  querying the 171 capsule pairs one by one). Rotations and centres are precomputed outside the timing.
* ``static_us_per_config``: :meth:`CollisionModel.static_clearance` (robot vs table, conveyor, boxes).

Times are medians of wall-clock time over repeats (``*_p95`` the 95th percentile); ``*_cpu`` are medians of
the thread's CPU time, which a busy shared machine disturbs much less (the ``*_speedup_*_cpu`` ratios use
them). Correctness is checked on the way: the largest round-trip error of the IK and the largest difference
to fcl's distances are reported too.
"""

from __future__ import annotations

import math
import platform
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

IK_BATCH = 1000
FK_BATCH = 1000
PAIRS = 1024


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(msg, file=sys.stderr, flush=True)


def _time(fn: Callable[[], object], repeats: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and this thread's CPU seconds per call, one sample per repeat (after one warm-up call)."""
    fn()
    wall = np.empty(repeats)
    cpu = np.empty(repeats)
    for i in range(repeats):
        c0 = time.thread_time()
        t0 = time.perf_counter()
        fn()
        wall[i] = time.perf_counter() - t0
        cpu[i] = time.thread_time() - c0
    return wall, cpu


def _people(rng: np.random.Generator, n: int) -> np.ndarray:
    """Person poses (n, J, 3) around the table: upright bodies, arms reaching in random directions."""
    from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS

    local = {
        "pelvis": (0.0, 0.0, 0.95),
        "spine": (0.0, 0.0, 1.10),
        "chest": (0.0, 0.0, 1.30),
        "neck": (0.0, 0.0, 1.50),
        "head": (0.0, 0.0, 1.62),
        "l_shoulder": (0.0, 0.18, 1.45),
        "r_shoulder": (0.0, -0.18, 1.45),
        "l_hip": (0.0, 0.10, 0.92),
        "l_knee": (0.0, 0.10, 0.50),
        "l_ankle": (0.0, 0.10, 0.08),
        "r_hip": (0.0, -0.10, 0.92),
        "r_knee": (0.0, -0.10, 0.50),
        "r_ankle": (0.0, -0.10, 0.08),
    }
    out = np.zeros((n, NUM_JOINTS, 3))
    for i in range(n):
        x, y, yaw = rng.uniform(0.4, 1.4), rng.uniform(-0.7, 0.7), rng.uniform(-math.pi, math.pi)
        c, s = math.cos(yaw), math.sin(yaw)
        for name, (lx, ly, lz) in local.items():
            out[i, JOINT_INDEX[name]] = [x + c * lx - s * ly, y + s * lx + c * ly, -0.75 + lz]
        for side in ("l_", "r_"):
            sh = out[i, JOINT_INDEX[side + "shoulder"]]
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            for name, reach in (("elbow", 0.28), ("wrist", 0.52), ("hand", 0.60)):
                out[i, JOINT_INDEX[side + name]] = sh + reach * u
        out[i] += rng.normal(scale=0.02, size=(NUM_JOINTS, 3))
    return out


def _record(
    out: dict[str, Any], key: str, samples: tuple[np.ndarray, np.ndarray], per: int, scale: float
) -> None:
    """``key`` (median wall time per item), ``key_p95`` and ``key_cpu`` (median CPU time per item)."""
    wall, cpu = (x / per * scale for x in samples)
    out[key] = float(np.median(wall))
    out[f"{key}_p95"] = float(np.percentile(wall, 95))
    out[f"{key}_cpu"] = float(np.median(cpu))


def _fcl_pairs(model: Any, q: np.ndarray, joints: np.ndarray) -> Callable[[], np.ndarray]:
    """python-fcl minimum distance for each (q[k], joints[k]); returns a closure that computes all of them."""
    import fcl

    from app.planning.collision import rotation_z_to

    a, b, r = model.robot_capsules(q)
    ha, hb, hr = model.human_capsules(joints)
    K, L, _ = a.shape
    M = ha.shape[1]
    # Robot links are rigid: one object per link, moved per configuration.
    lengths = np.linalg.norm(b[0] - a[0], axis=-1)
    robot_objs = [
        fcl.CollisionObject(
            fcl.Capsule(float(r[i]), float(lengths[i])) if lengths[i] > 1e-12 else fcl.Sphere(r[i])
        )
        for i in range(L)
    ]
    robot_tf = [
        [
            fcl.Transform(rotation_z_to((b[k, i] - a[k, i]) / lengths[i]), 0.5 * (a[k, i] + b[k, i]))
            if lengths[i] > 1e-12
            else fcl.Transform(a[k, i])
            for i in range(L)
        ]
        for k in range(K)
    ]
    # Person geometry is precomputed too (rotations, centres, lengths): only fcl's own work is timed.
    h_len = np.linalg.norm(hb - ha, axis=-1)
    h_geo = [
        [
            (
                float(hr[m]),
                float(h_len[k, m]),
                rotation_z_to((hb[k, m] - ha[k, m]) / h_len[k, m]),
                0.5 * (ha[k, m] + hb[k, m]),
            )
            if h_len[k, m] > 1e-12
            else (float(hr[m]), 0.0, None, ha[k, m])
            for m in range(M)
        ]
        for k in range(K)
    ]
    robot_mgr = fcl.DynamicAABBTreeCollisionManager()
    robot_mgr.registerObjects(robot_objs)
    robot_mgr.setup()

    def run() -> np.ndarray:
        out = np.empty(K)
        for k in range(K):
            for obj, tf in zip(robot_objs, robot_tf[k], strict=True):
                obj.setTransform(tf)
            robot_mgr.update()
            human = [
                fcl.CollisionObject(fcl.Capsule(rad, ln), fcl.Transform(R, c))
                if R is not None
                else fcl.CollisionObject(fcl.Sphere(rad), fcl.Transform(c))
                for rad, ln, R, c in h_geo[k]
            ]
            human_mgr = fcl.DynamicAABBTreeCollisionManager()
            human_mgr.registerObjects(human)
            human_mgr.setup()
            data = fcl.DistanceData(request=fcl.DistanceRequest())
            robot_mgr.distance(human_mgr, data, fcl.defaultDistanceCallback)
            out[k] = data.result.min_distance
        return out

    return run


def run(*, quick: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run the benchmark and return its JSON object (see the module docstring)."""
    import ur_analytic_ik

    from app.config import load_workcell
    from app.planning.collision import CollisionModel
    from app.planning.kinematics import UR5e

    repeats = 5 if quick else 25
    fcl_repeats = 1 if quick else 3
    rng = np.random.default_rng(0)
    cell = load_workcell()
    kin = UR5e.from_workcell(cell)
    model = CollisionModel(cell, kin=kin)
    out: dict[str, Any] = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "quick": quick,
        "repeats": repeats,
    }

    # ---- IK: batched (ours) vs one call per pose (ur_analytic_ik), same poses and tool
    q = rng.uniform(kin.q_min, kin.q_max, size=(IK_BATCH, 6))
    T = kin.fk_tcp(q)
    q_ik, valid = kin.ik(T)
    reached = kin.fk_tcp(q_ik[valid])
    target = np.repeat(T, valid.sum(axis=1), axis=0)
    out["ik_max_position_error_m"] = float(
        np.max(np.linalg.norm(reached[:, :3, 3] - target[:, :3, 3], axis=-1))
    )
    out["ik_valid_branches_per_pose"] = float(valid.sum(axis=1).mean())
    _record(out, "ik_us_per_pose", _time(lambda: kin.ik(T), repeats), IK_BATCH, 1e6)
    tcp = np.ascontiguousarray(kin.T_flange_tcp)
    poses = [np.ascontiguousarray(t) for t in T]
    ref_ik = ur_analytic_ik.ur5e.inverse_kinematics_with_tcp

    def reference() -> None:
        for pose in poses:
            ref_ik(pose, tcp)

    ref_repeats = max(3, repeats // 5)
    _record(out, "ik_reference_us_per_pose", _time(reference, ref_repeats), IK_BATCH, 1e6)
    out["ik_speedup_vs_reference"] = out["ik_reference_us_per_pose"] / out["ik_us_per_pose"]
    out["ik_speedup_vs_reference_cpu"] = out["ik_reference_us_per_pose_cpu"] / out["ik_us_per_pose_cpu"]
    _log(
        progress, f"ik: {out['ik_us_per_pose']:.3f} us/pose, reference {out['ik_reference_us_per_pose']:.3f}"
    )

    # ---- FK
    qf = rng.uniform(kin.q_min, kin.q_max, size=(FK_BATCH, 6))
    _record(out, "fk_us_per_config", _time(lambda: kin.fk(qf), repeats), FK_BATCH, 1e6)
    _log(progress, f"fk: {out['fk_us_per_config']:.3f} us/config")

    # ---- robot vs person distances
    qd = rng.uniform(-math.pi, math.pi, size=(PAIRS, 6))
    joints = _people(rng, PAIRS)
    ours = model.distance_to_human_paired(qd, joints)
    out["distance_pairs"] = PAIRS
    _record(
        out,
        "distance_ns_per_pair",
        _time(lambda: model.distance_to_human_paired(qd, joints), repeats),
        PAIRS,
        1e9,
    )
    qc, jc = qd[:32], joints[:32]
    _record(
        out,
        "distance_cross_ns_per_pair",
        _time(lambda: model.distance_to_human(qc, jc), repeats),
        32 * 32,
        1e9,
    )
    _log(
        progress, f"distance: {out['distance_ns_per_pair']:.0f} ns/pair; running python-fcl on the same pairs"
    )

    fcl_run = _fcl_pairs(model, qd, joints)
    theirs = fcl_run()
    separated = ours > 1e-6
    out["distance_max_abs_diff_vs_fcl_m"] = float(np.max(np.abs(ours[separated] - theirs[separated])))
    out["distance_collisions_agree_with_fcl"] = bool(np.all((ours < -1e-6) <= (theirs <= 0.0)))
    _record(out, "fcl_distance_ns_per_pair", _time(fcl_run, fcl_repeats), PAIRS, 1e9)
    out["distance_speedup_vs_fcl"] = out["fcl_distance_ns_per_pair"] / out["distance_ns_per_pair"]
    out["distance_speedup_vs_fcl_cpu"] = out["fcl_distance_ns_per_pair_cpu"] / out["distance_ns_per_pair_cpu"]
    _log(progress, f"fcl: {out['fcl_distance_ns_per_pair']:.0f} ns/pair")

    # ---- static scene (roadmap construction)
    qs = rng.uniform(-math.pi, math.pi, size=(1000, 6))
    _record(
        out,
        "static_us_per_config",
        _time(lambda: model.static_clearance(qs), max(3, repeats // 3)),
        1000,
        1e6,
    )
    return out
