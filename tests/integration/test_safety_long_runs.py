"""Safety over long seeded headless trials, checked by a monitor that shares nothing with the supervisor.

At every servo tick the monitor takes the robot's *reported* state (joint positions and velocities) and the
person's *true* pose (a noise-free twin of the simulated operator: same participant, same seed, same
notifications; the runtime sees the noisy frames), and, for every robot part (capsule) that moves faster
than 1 cm/s, requires ISO/TS 15066's protective separation distance for that part's speed and the person's
directed speed toward it: ``S_p = v_h (T_r + T_s) + v_r (T_r + T_s / 2) + C + Z_d + Z_r``
(:func:`app.safety.ssm.protective_separation`), with ``T_s`` the robot's stopping time from its current
speed (its fastest part's, at 2 m/s^2). Every tick that breaks it is a violation; there must be none, for
either method.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from app.cell.operator_sim import OperatorParams, SimulatedOperator
from app.config import Settings, load_workcell
from app.control.engine import EngineOptions, PlanningStack
from app.control.headless import run_headless_trial
from app.planning.collision import capsule_distance
from app.safety.ssm import protective_separation

pytestmark = pytest.mark.slow

MOVING_MPS = 0.01
STOP_DECEL_MPS2 = 2.0  # the robot's stopping deceleration: T_s = v / STOP_DECEL_MPS2


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> PlanningStack:
    from app.planning.roadmap import RoadmapConfig

    cache = tmp_path_factory.mktemp("roadmaps")
    return PlanningStack.build(load_workcell(), roadmap_config=RoadmapConfig(num_nodes=250), cache_dir=cache)


class _Twin:
    """The noisy operator the runtime sees, and its noise-free twin for the monitor."""

    def __init__(self, cell: Any, seed: int) -> None:
        params = OperatorParams.draw(seed)
        self.seen = SimulatedOperator(cell, params, seed=seed)
        self.true = SimulatedOperator(cell, params, seed=seed, noise=False)

    def frame_at(self, t: float) -> Any:
        return self.seen.frame_at(t)

    def notify_block_placed(self, station: str, t: float) -> None:
        self.seen.notify_block_placed(station, t)
        self.true.notify_block_placed(station, t)

    def pose(self, t: float) -> np.ndarray:
        """The true pose (J, 3) at any ``t`` (not only on the 30 Hz frame grid): the operator's own
        motion tracks, evaluated where the frames sample them."""
        self.true.frame_at(t)  # plans the behaviour up to t, on the frame grid, as the seen operator does
        return self.true.to_world(self.true._pose_body(t))


class _Monitor:
    def __init__(self, stack: PlanningStack, twin: _Twin, dt: float) -> None:
        self.col = stack.collision
        self.ssm = stack.ssm
        self.twin = twin
        self.dt = dt
        self.ticks = 0
        self.moving_ticks = 0
        self.violations: list[tuple[float, float, float, float, float]] = []
        self.min_sep_moving = np.inf

    def _parts(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, b, r = self.col.robot_capsules(q.reshape(1, 6))
        return a[0], b[0], r

    def __call__(self, t: float, engine: Any) -> None:
        st = engine.robot.state()
        q, qd = np.asarray(st.q), np.asarray(st.qd)
        self.ticks += 1
        if not np.any(np.abs(qd) > 1e-6):
            return
        h = 1e-3
        a0, b0, rr = self._parts(q)
        a1, b1, _ = self._parts(q + h * qd)
        v_part = np.maximum(np.linalg.norm(a1 - a0, axis=1), np.linalg.norm(b1 - b0, axis=1)) / h
        moving = v_part > MOVING_MPS
        if not moving.any():
            return
        self.moving_ticks += 1
        poses = np.stack([self.twin.pose(t), self.twin.pose(t - self.dt)])
        ha, hb, hr = self.col.human_capsules(poses)
        d = capsule_distance(
            a0[None, :, None], b0[None, :, None], rr[None, :, None], ha[:, None], hb[:, None], hr[None, None]
        ).min(axis=2)  # (2, L): separation of each robot part now and one tick earlier
        sep = d[0]
        v_h = np.maximum((d[1] - d[0]) / self.dt, 0.0)  # the person's directed speed toward each part
        self.min_sep_moving = min(self.min_sep_moving, float(sep[moving].min()))
        params = dataclasses.replace(self.ssm, t_stop_s=float(v_part.max()) / STOP_DECEL_MPS2)
        for i in np.flatnonzero(moving):
            need = float(protective_separation(float(v_part[i]), params, v_human_mps=float(v_h[i])))
            if sep[i] < need:
                self.violations.append((t, float(sep[i]), need, float(v_part[i]), float(v_h[i])))


@pytest.mark.parametrize(("method", "seed"), [("proactive", 1), ("reactive", 2)])
def test_the_moving_robot_never_comes_closer_than_the_protective_distance(
    stack: PlanningStack, method: str, seed: int
) -> None:
    rate = 125.0
    twin = _Twin(stack.cell, seed)
    monitor = _Monitor(stack, twin, 1.0 / rate)
    res = run_headless_trial(
        settings=Settings(),
        method=method,  # type: ignore[arg-type]
        duration_s=45.0,
        seed=seed,
        stack=stack,
        human=twin,
        fixed_compute_s=0.03,
        servo_rate_hz=rate,
        options=EngineOptions(record_frames=False),
        observer=monitor,
    )
    assert res.status == "completed"
    # the run is meaningful: the robot worked, and worked near the person
    assert monitor.moving_ticks > 0.3 * monitor.ticks
    assert monitor.min_sep_moving < 0.5
    assert res.metrics.stop_replans + res.metrics.online_replans + res.metrics.completed_tasks > 0
    assert monitor.violations == [], f"{len(monitor.violations)} violations, first: {monitor.violations[:3]}"
    assert res.metrics.violations == 0  # the runtime's own monitor agrees
