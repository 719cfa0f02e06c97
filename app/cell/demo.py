"""``hrc cell demo``: the simulated robot and a human source running together on the wall clock.

The robot shuttles between the conveyor pickup and the drop stations with plain joint-space moves (quintic,
within the joint limits; no planner, no supervision) and tells the human source when it places a block;
the human source (simulated operator or a replayed clip) runs behind frame validation and the stale
watchdog. At the end it reports the frame rate, the validation counters and the control loop's timing.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from app.cell.clock import Clock, RateLoop, WallClock

if TYPE_CHECKING:
    from app.config import Settings, WorkCell

__all__ = ["JointMove", "run_demo", "task_configurations"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class JointMove:
    """A rest-to-rest quintic move in joint space, timed so that no joint exceeds its limits.

    Attributes:
        q0: Start (6,), rad. q1: End (6,), rad.
        t0: Start time (s). duration_s: Length (s).
    """

    q0: np.ndarray
    q1: np.ndarray
    t0: float
    duration_s: float

    @classmethod
    def timed(
        cls, q0: np.ndarray, q1: np.ndarray, t0: float, *, qd_max: np.ndarray, qdd_max: np.ndarray
    ) -> JointMove:
        """The shortest quintic move: peak speed 1.875 |dq| / T, peak acceleration 5.774 |dq| / T^2."""
        dq = np.abs(np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float))
        T = max(float(np.max(1.875 * dq / qd_max)), float(np.max(np.sqrt(5.7735 * dq / qdd_max))), 0.05)
        return cls(np.asarray(q0, dtype=float), np.asarray(q1, dtype=float), float(t0), T)

    @property
    def t_end(self) -> float:
        return self.t0 + self.duration_s

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Position (6,) rad and velocity (6,) rad/s at time ``t`` (held outside the move)."""
        s = min(max((t - self.t0) / self.duration_s, 0.0), 1.0)
        p = s**3 * (10 - 15 * s + 6 * s * s)
        dp = 30 * s * s * (1 - s) ** 2 / self.duration_s
        dq = self.q1 - self.q0
        return self.q0 + dq * p, dq * dp


def task_configurations(cell: WorkCell) -> dict[str, np.ndarray]:
    """Joint configurations (6,) of home, the pickup and every drop station (tool down), each on the IK
    branch nearest the home configuration."""
    from app.planning.kinematics import UR5e, nearest_branch

    kin = UR5e.from_workcell(cell)
    home_q = np.asarray(cell.robot.home_q, dtype=float)
    stations = [cell.home, cell.conveyor.pickup, *cell.drop_stations]
    q, valid = kin.ik_down(np.array([s.xyz for s in stations], dtype=float))
    idx, _ = nearest_branch(q, valid, np.broadcast_to(home_q, (len(stations), 6)))
    out = {}
    for k, s in enumerate(stations):
        if idx[k] < 0:
            raise ValueError(f"station {s.name!r} at {s.xyz} has no IK solution within the joint limits")
        out[s.name] = q[k, idx[k]]
    return out


def run_demo(
    *,
    seconds: float = 10.0,
    source: Literal["sim", "replay"] = "sim",
    clip: Path | None = None,
    seed: int = 0,
    rate_hz: float = 125.0,
    settings: Settings | None = None,
    clock: Clock | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the demo for ``seconds`` and return its report (JSON-ready).

    Args:
        seconds: Duration (s).
        source: ``"sim"`` (a simulated operator drawn from ``seed``) or ``"replay"`` (``clip``, looped).
        clip: The clip to replay (npz: the shared CMU format or a canonical recording).
        seed: Participant seed of the simulated operator.
        rate_hz: Servo rate of the control loop (Hz).
        settings: Settings (work cell); default from the environment.
        clock: The clock (default the wall clock; a :class:`~app.cell.clock.SimClock` runs it instantly).
        progress: Called with a one-line status about once a second.
    """
    from app.cell.human import ReplaySource, SimulatedOperator
    from app.cell.operator_sim import OperatorParams
    from app.cell.robot import SimRobot
    from app.cell.validation import FrameValidator, StaleWatchdog, ValidatedSource
    from app.config import Settings

    settings = settings if settings is not None else Settings()
    cell = settings.load_workcell()
    clock = clock if clock is not None else WallClock()
    configs = task_configurations(cell)
    drops = [s.name for s in cell.drop_stations]
    t_start = clock.now()
    if source == "sim":
        human: Any = SimulatedOperator(cell, OperatorParams.draw(seed), seed=seed, t0=t_start)
    elif source == "replay":
        if clip is None:
            raise ValueError("--source replay needs --clip PATH (an .npz clip)")
        human = ReplaySource(clip, cell, t0=t_start)
    else:
        raise ValueError(f"unknown source {source!r}; expected 'sim' or 'replay'")
    validated = ValidatedSource(
        human, validator=FrameValidator.for_workcell(cell), watchdog=StaleWatchdog(0.1)
    )
    robot = SimRobot(clock, q0=configs[cell.home.name])
    lim = robot.limits
    plan = [cell.conveyor.pickup.name if i % 2 == 0 else drops[(i // 2) % len(drops)] for i in range(10_000)]
    move = JointMove.timed(
        configs[cell.home.name], configs[plan[0]], t_start, qd_max=0.6 * lim.qd_max, qdd_max=lim.qdd_max
    )
    step, dwell_until = 0, -math.inf
    frames = stale_events = blocks = 0
    max_err = 0.0
    loop = RateLoop(clock, rate_hz, t0=t_start)
    t_end = t_start + seconds
    next_progress = t_start + 1.0
    try:
        while True:
            now = clock.now()
            if now >= t_end:
                break
            if now >= move.t_end and now >= dwell_until:
                if dwell_until == -math.inf:  # just arrived: dwell 0.3 s (grasp or release)
                    dwell_until = now + 0.3
                    if plan[step] in drops:
                        validated.notify_block_placed(plan[step], now)
                        blocks += 1
                else:
                    step += 1
                    move = JointMove.timed(
                        move.q1, configs[plan[step]], now, qd_max=0.6 * lim.qd_max, qdd_max=lim.qdd_max
                    )
                    dwell_until = -math.inf
            q_cmd, qd_cmd = move.sample(now)
            robot.servo(q_cmd, qd_cmd, now)
            max_err = max(max_err, float(np.max(np.abs(robot.state().q - q_cmd))))
            if validated.poll(now) is not None:
                frames += 1
            if validated.watchdog.poll(now) == "stale":
                stale_events += 1
            if progress is not None and now >= next_progress:
                next_progress += 1.0
                c = validated.counters
                progress(
                    f"t={now - t_start:5.1f} s  frames={frames}  accepted={c['accepted']}  "
                    f"rejected={c['rejected']}  blocks={blocks}  overruns={loop.overruns}"
                )
            loop.sleep()
    finally:
        robot.close()
    elapsed = max(clock.now() - t_start, 1e-9)
    counters = validated.counters
    report: dict[str, Any] = {
        "seconds": round(elapsed, 3),
        "source": source if source == "sim" else f"replay:{clip}",
        "frames": frames,
        "frame_rate_hz": round(frames / elapsed, 2),
        "validation": counters,
        "stale_events": stale_events,
        "control_loop": loop.stats(),
        "robot": {"moves": step + 1, "blocks_placed": blocks, "max_tracking_error_rad": round(max_err, 5)},
    }
    if source == "sim":
        kinds = [a.kind for a in human.actions]
        report["operator"] = {
            "params": {
                k: (round(v, 3) if isinstance(v, float) else v) for k, v in human.params.to_dict().items()
            },
            "fetches": kinds.count("fetch"),
            "reaches_across": kinds.count("reach_across"),
        }
    return report
