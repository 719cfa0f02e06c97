"""Faults in headless trials with the real planner, kinematics and simulated operator (a small roadmap):
a stale stream, a planner that raises, a planner slower than the deadline, a lost robot connection.
Compute times are fixed, so the runs are deterministic.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from app.cell.robot import RobotConnectionError, RobotState, SimRobot
from app.cell.source import HumanSource
from app.config import Settings, load_workcell
from app.control.engine import EngineOptions, TrialEngine
from app.control.headless import run_headless_trial
from app.control.stack import PlanningStack
from app.control.world import make_operator
from app.prediction.forecast import HumanForecast, Predictor
from app.prediction.skeleton import NUM_JOINTS

SEED = 4


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> PlanningStack:
    from app.planning.roadmap import RoadmapConfig

    cache = tmp_path_factory.mktemp("roadmaps")
    return PlanningStack.build(
        load_workcell(),
        roadmap_config=RoadmapConfig(num_nodes=250),
        t_reaction_s=Settings().reaction_time_s(1 / 125),
        cache_dir=cache,
    )


def _run(stack: PlanningStack, **kw: Any):
    args = dict(
        settings=Settings(),
        method="reactive",
        duration_s=5.0,
        seed=SEED,
        stack=stack,
        fixed_compute_s=0.02,
        options=EngineOptions(record_frames=False),
    )
    args.update(kw)
    return run_headless_trial(**args)


class _Gap(HumanSource):
    """The operator's frames, with no new frame in [t0, t1) (the tracker lost the person)."""

    def __init__(self, inner: Any, t0: float, t1: float) -> None:
        self.inner, self.t0, self.t1 = inner, t0, t1

    def frame_at(self, t: float) -> Any:
        return self.inner.frame_at(min(t, self.t0 - 1e-6) if self.t0 <= t < self.t1 else t)

    def notify_block_placed(self, station: str, t: float) -> None:
        self.inner.notify_block_placed(station, t)


def _speeds(log: list[tuple[float, np.ndarray]], a: float, b: float) -> list[float]:
    return [float(np.abs(qd).max()) for t, qd in log if a <= t <= b]


def test_stale_stream_stops_the_robot_until_frames_resume(stack: PlanningStack) -> None:
    cell = stack.cell
    human = _Gap(make_operator(cell, source="sim", seed=SEED, participant_seed=SEED), 1.5, 2.8)
    log: list[tuple[float, np.ndarray]] = []
    res = _run(stack, human=human, observer=lambda t, e: log.append((t, e.last_state.qd.copy())))
    kinds = [(ev.t, ev.kind) for ev in res.events]
    stale_t = next(t for t, k in kinds if k == "stale_stream")
    resumed_t = next(t for t, k in kinds if k == "stream_resumed")
    last_frame_t = (np.ceil(1.5 * 30) - 1) / 30  # the last frame before the gap
    timeout = Settings().stale_timeout_s
    assert last_frame_t + timeout < stale_t <= last_frame_t + timeout + 0.01  # the timeout (+ one servo tick)
    assert 2.79 <= resumed_t <= 2.85
    assert res.metrics.stale_stops == 1
    assert max(_speeds(log, 1.4, 1.5)) > 0.05  # it was moving...
    assert max(_speeds(log, stale_t + 0.5, resumed_t)) < 1e-3  # ...and stood still while stale
    assert max(_speeds(log, resumed_t + 0.2, 5.0)) > 0.05  # and went on once frames resumed


def _phantom_predictor(box: dict[str, TrialEngine]) -> Any:
    """A predictor that announces, from t = 1.5 s, a person standing on the robot's path one second
    ahead (a violation predicted after T + D: an online replan is due)."""

    class Phantom(Predictor):
        effective_kind = "phantom"

        def reset(self) -> None: ...

        def update(self, frame: Any) -> HumanForecast:
            eng = box.get("engine")
            st = None if eng is None else eng.supervisor.status()
            if frame.t < 1.5 or st is None or st.plan is None:
                return HumanForecast.hold(frame, margin_m=0.02)
            t_ahead = min(frame.t + 1.0, st.plan.t_end)
            p = eng.stack.kin.fk_tcp(np.asarray(st.plan.q(t_ahead)).reshape(1, 6))[0, :3, 3]
            ghost = np.tile(p, (NUM_JOINTS, 1))
            times = np.array([frame.t, frame.t + 0.5, frame.t + 3.0])
            joints = np.stack([frame.joints, ghost, ghost])
            return HumanForecast(t0=frame.t, times=times, joints=joints, margins=np.full(3, 0.02))

    return Phantom()


def test_planner_exception_takes_the_emergency_path(stack: PlanningStack) -> None:
    box: dict[str, TrialEngine] = {}

    class Flaky:
        """The real planner, except that every plan after the first raises."""

        def __init__(self, inner: Any) -> None:
            self.inner, self.calls = inner, 0

        def plan(self, **kw: Any) -> Any:
            self.calls += 1
            if self.calls > 1:
                raise RuntimeError("planner crashed (test)")
            return self.inner.plan(**kw)

        def __getattr__(self, name: str) -> Any:
            return getattr(self.inner, name)

    import dataclasses

    flaky = dataclasses.replace(stack, planner=Flaky(stack.planner))
    res = _run(
        flaky,
        method="proactive",
        predictor=_phantom_predictor(box),
        observer=lambda t, e: box.setdefault("engine", e),
    )
    fails = [ev for ev in res.events if ev.kind == "plan_failed" and "error" in ev.payload["reason"]]
    stops = [ev for ev in res.events if ev.kind == "stop_replan" and ev.payload["reason"] == "backup_error"]
    assert fails and stops
    assert res.metrics.emergency_plans >= 1
    assert res.status == "completed"  # the loop survived the exceptions


def test_missed_deadlines_leave_the_plan_in_execution(stack: PlanningStack) -> None:
    """No backup is produced in time, so none is switched to: the robot goes on along its plan, whose
    phantom violation (a person forecast on the plan half a second ahead of the robot, wherever it is) never
    comes within D; no miss stops it, and the ground truth sees no violation."""
    box: dict[str, TrialEngine] = {}
    scales: list[tuple[float, float]] = []

    def observer(t: float, e: TrialEngine) -> None:
        box.setdefault("engine", e)
        scales.append((t, e.supervisor.status().scale))

    # 150 ms per plan: starts from rest (deadline 3 D) succeed, backups under D = 100 ms do not
    res = _run(
        stack,
        settings=Settings(deadline_s=0.1),
        method="proactive",
        fixed_compute_s=0.15,
        predictor=_phantom_predictor(box),
        observer=observer,
    )
    misses = [ev for ev in res.events if ev.kind == "deadline_miss"]
    assert len(misses) >= 3 and res.metrics.deadline_misses == len(misses)
    assert res.metrics.online_replans == 0
    assert not [ev for ev in res.events if ev.kind == "stop_replan"]
    assert any(s > 1e-3 for t, s in scales if t > misses[-1].t)  # still under way after the last miss
    assert res.metrics.violations == 0 and res.metrics.contacts == 0


class _LosingRobot(SimRobot):
    """A simulated arm whose connection drops at ``t_lost`` (``mode``: raise, or report disconnected)."""

    def __init__(self, clock: Any, q0: np.ndarray, *, t_lost: float, mode: str) -> None:
        super().__init__(clock, q0=q0)
        self.t_lost, self.mode = t_lost, mode
        self.stopped = False

    def state(self) -> RobotState:
        st = super().state()
        if self.clock.now() >= self.t_lost:
            if self.mode == "raise":
                raise RobotConnectionError("connection reset by peer (test)")
            return RobotState(
                t=st.t,
                q=st.q,
                qd=st.qd,
                protective_stop=st.protective_stop,
                speed_scale=st.speed_scale,
                connected=False,
            )
        return st

    def stop(self) -> None:
        self.stopped = True
        super().stop()


@pytest.mark.parametrize("mode", ["raise", "disconnected"])
def test_lost_robot_connection_aborts_the_trial_cleanly(stack: PlanningStack, mode: str) -> None:
    robots: list[_LosingRobot] = []

    def factory(clock: Any, q0: np.ndarray) -> _LosingRobot:
        robots.append(_LosingRobot(clock, q0, t_lost=2.0, mode=mode))
        return robots[-1]

    res = _run(stack, duration_s=10.0, robot_factory=factory)
    assert (res.status, res.reason) == ("aborted", "robot_fault")
    assert res.metrics.duration_s == pytest.approx(2.0, abs=0.02)
    kinds = [ev.kind for ev in res.events]
    assert "robot_fault" in kinds and kinds[-1] == "trial_ended"
    assert res.events[-1].payload == {"status": "aborted", "reason": "robot_fault"}
    assert robots[0].stopped  # robot.stop() ran on the way out
