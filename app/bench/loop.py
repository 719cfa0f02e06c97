"""``hrc bench loop``: the live control loop's latency and the robot command loop's timing.

The live :class:`~app.control.runtime.Runtime` runs on the wall clock with the simulated cell (simulated UR5e,
simulated operator, the default roadmap and the shipped predictor) and runs a proactive trial. Measured:

- ``frame_to_decision_ms``: from reading a new frame to the supervisor's decision on it (validation,
  prediction, the check of the plan in execution against the forecast, the separation and speed scaling,
  the emergency plan when the decision is to stop); the backup plan's own search runs on the planner pool and
  is not included;
- ``servo_jitter_ms``: how late each tick of the robot command loop woke up after its deadline
  (:class:`~app.cell.clock.RateLoop`, ``servo_rate_hz``), with its overruns;
- ``planning``: the compute time of every plan of the trial on the planner pool (a plan that sets the robot
  off also weighs the reactive method's plan: both searches and the check), against the deadline ``D``, and
  the missed deadlines per minute.

Prints one JSON object (percentiles over every frame and tick of the run).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

log = logging.getLogger(__name__)


def _pct(values: list[float], qs: tuple[int, ...]) -> dict[str, float | int]:
    if not values:
        return {f"p{q}": float("nan") for q in qs} | {"n": 0}
    arr = np.asarray(values, dtype=np.float64)
    out: dict[str, float | int] = {f"p{q}": round(float(np.percentile(arr, q)), 3) for q in qs}
    out["max"] = round(float(arr.max()), 3)
    out["n"] = int(arr.size)
    return out


def run(*, quick: bool = False, progress: bool = True, servo_rate_hz: float = 125.0) -> dict[str, Any]:
    """Run the live runtime for a proactive trial (4 s with ``quick``, 120 s otherwise) and measure its
    loops."""
    from app.config import Settings
    from app.control.engine import EngineOptions
    from app.control.runtime import Runtime

    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    duration = 4.0 if quick else 120.0
    settings = Settings(robot="sim", human_source="sim")
    rt = Runtime(settings, servo_rate_hz=servo_rate_hz, options=EngineOptions(record_frames=False))
    t_build = time.perf_counter()
    rt.start()
    build_s = time.perf_counter() - t_build
    try:
        time.sleep(0.5)  # warm up: the threads run, the predictor loads its first frames
        for d in (rt.stats.decide_ms, rt.stats.frame_to_decision_ms, rt.stats.servo_late_ms):
            d.clear()
        overruns0 = rt.stats.servo_overruns
        rt.start_trial(trial_id=1, method="proactive", duration_s=duration + 5.0, seed=1)
        t_end = time.monotonic() + duration
        while time.monotonic() < t_end:
            time.sleep(0.25)
            if progress:
                log.info("bench loop: %d decisions", len(rt.stats.frame_to_decision_ms))
        f2d = list(rt.stats.frame_to_decision_ms)
        decide = list(rt.stats.decide_ms)
        late = list(rt.stats.servo_late_ms)
        overruns = rt.stats.servo_overruns - overruns0
        counters = rt.snapshot().counters
        plans_s, misses = rt.planning_record()
        rt.stop_trial(reason="benchmark done")
    finally:
        rt.stop()
    return {
        "duration_s": duration,
        "servo_rate_hz": servo_rate_hz,
        "frame_rate_hz": round(1.0 / settings.frame_period_s, 3),
        "frame_to_decision_ms": _pct(f2d, (50, 95, 99)),
        "decision_only_ms": _pct(decide, (50, 95)),
        "servo_jitter_ms": _pct(late, (50, 99)),
        "servo_overruns": overruns,
        "servo_ticks": len(late),
        "planning": {
            "deadline_ms": round(1e3 * settings.deadline_s, 3),
            "plan_ms": _pct([1e3 * x for x in plans_s], (50, 95)),
            "deadline_misses": misses,
            "deadline_misses_per_min": round(60.0 * misses / duration, 2),
        },
        "start_s": round(build_s, 3),
        "trial_counters": {k: v for k, v in counters.items() if isinstance(v, int)},
    }
