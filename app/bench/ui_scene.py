"""Benchmark of the 3D view: the time to apply one runtime snapshot to the viser scene (in place).

The scene thread applies at most 30 snapshots per second; this measures what one costs on the scene thread
(robot capsules from the collision model, person, forecast ghosts, plans, separation sphere, labels), so that
its share of a CPU core next to the control loop is known. Prints median and p95 over many snapshots.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class _Snap:
    t: float
    q: np.ndarray
    p_world_tcp: np.ndarray
    skeleton: np.ndarray
    forecast: np.ndarray
    plan_tcp: np.ndarray
    backup_tcp: np.ndarray
    state: str = "nominal"
    required_separation_m: float = 0.4
    separation_m: float = 0.8
    speed_scale: float = 0.7
    stale: bool = False
    estopped: bool = False
    method: str = "proactive"
    trial_id: int = 1
    trial_elapsed_s: float = 10.0
    trial_duration_s: float = 60.0
    body_ids: tuple[int, ...] = ()


def _snapshots(n: int, seed: int = 0, bodies: int = 1) -> list[_Snap]:
    from app.config import load_workcell
    from app.planning.kinematics import UR5e
    from app.prediction.skeleton import NUM_JOINTS

    cell = load_workcell()
    kin = UR5e.from_workcell(cell)
    rng = np.random.default_rng(seed)
    home = np.asarray(cell.robot.home_q)
    out = []
    for k in range(n):
        q = home + rng.uniform(-0.5, 0.5, 6)
        tcp = kin.fk_tcp(q[None])[0, :3, 3]
        sk = np.concatenate(
            [np.array([1.3, 0.8 * b, 0.2]) + rng.uniform(-0.3, 0.3, (NUM_JOINTS, 3)) for b in range(bodies)]
        )  # every body stacked, as a frame holds them
        forecast = sk[None] + np.linspace(0, 0.3, 30)[:, None, None]
        plan = tcp + np.linspace(0, 0.4, 40)[:, None] * np.array([1.0, -0.5, -0.3])
        out.append(
            _Snap(
                t=k / 30,
                q=q,
                p_world_tcp=tcp,
                skeleton=sk,
                forecast=forecast,
                plan_tcp=plan,
                backup_tcp=plan[::2],
                body_ids=tuple(range(3, 3 + bodies)),
            )
        )
    return out


def run(*, quick: bool, progress: bool, bodies: int = 1) -> dict[str, Any]:
    """Apply ``n`` distinct snapshots of ``bodies`` tracked people each to a live
    :class:`~app.ui.scene.CellView`; return timing statistics."""
    import contextlib
    import sys

    import viser

    from app.config import load_workcell
    from app.planning.collision import CollisionModel
    from app.ui.scene import CellView

    n = 150 if quick else 1500
    cell = load_workcell()
    snaps = _snapshots(n, bodies=bodies)
    with contextlib.redirect_stdout(sys.stderr):  # viser prints its banner to stdout; keep stdout JSON
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        view = CellView(server, cell, robot_capsules=CollisionModel(cell).robot_capsules)
        for s in snaps[:10]:  # warm-up
            view.apply(s)
        times_ms = np.empty(n)
        for i, s in enumerate(snaps):
            t0 = time.perf_counter()
            view.apply(s)
            times_ms[i] = (time.perf_counter() - t0) * 1e3
            if progress and i % 500 == 0:
                print(f"  {i}/{n}", flush=True)
    finally:
        with contextlib.redirect_stdout(sys.stderr):
            server.stop()
    median, p95 = float(np.median(times_ms)), float(np.percentile(times_ms, 95))
    return {
        "benchmark": "ui_scene",
        "snapshots": n,
        "bodies": bodies,
        "apply_ms": {
            "median": round(median, 3),
            "p95": round(p95, 3),
            "max": round(float(times_ms.max()), 3),
        },
        "cpu_share_at_30hz": round(30.0 * median / 1e3, 4),
    }
