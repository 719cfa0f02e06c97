"""``hrc bench loop``: the live control loop's latency and the robot command loop's timing.

The live :class:`~app.control.runtime.Runtime` runs on the wall clock with the simulated cell (simulated UR5e,
simulated operator, the default roadmap and the shipped predictor) and runs a proactive trial. Measured:

- ``frame_to_decision_ms``: from the source handing over a new frame to the supervisor's decision on it
  (validation, the people's tracks, prediction, the check of the plan in execution against the forecast, the
  separation and speed scaling, the emergency plan when the decision is to stop); the time the source takes to
  make the frame (here the simulated people and the tracker model; in a cell the tracker's own) is not
  included, nor is the backup plan's own search, which runs on the planner pool;
- ``servo_jitter_ms``: how late each tick of the robot command loop woke up after its deadline
  (:class:`~app.cell.clock.RateLoop`, ``servo_rate_hz``), with its overruns;
- ``planning``: the compute time of every plan of the trial on the planner pool (a plan that sets the robot
  off also weighs the reactive method's plan: both searches and the check), against the deadline ``D``, the
  missed deadlines per minute, and how long the plans waited for the frames' decisions in all
  (``waited_for_frames_ms``, ``waits_for_frames``: :class:`~app.control.backup.ForegroundGate`).

With ``bodies`` N > 1 the cell holds N people: the simulated operator, seen through the tracker model, and
N - 1 copies of what the tracker reports of them, standing elsewhere around the table (:class:`_Copies`):
every decision then takes N bodies. ``bodies=1`` runs the same path with the operator alone, so the figures
compare like for like (the default, ``bodies=None``, runs the runtime's own simulated cell).

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


#: Where the copies of the operator stand (their pelvis moved by this in the floor plane, m): colleagues
#: at the operator's left and right along the table's far edge, and one behind the operator, each doing
#: what the operator does (their hands stay on their side of the table).
COPY_OFFSETS_M: tuple[tuple[float, float], ...] = ((0.0, 1.2), (0.0, -1.2), (0.7, 0.4))


class _Copies:
    """A human source's people and copies of the first of them moved by :data:`COPY_OFFSETS_M`, with ids
    1, 2, ...; the truth likewise (the benchmark's load of several bodies)."""

    validates_frames = False

    def __init__(self, source: Any, bodies: int) -> None:
        if not 1 <= bodies <= len(COPY_OFFSETS_M) + 1:
            raise ValueError(f"bodies must be 1 to {len(COPY_OFFSETS_M) + 1}, got {bodies}")
        self.source = source
        self.offsets = np.array([(0.0, 0.0), *COPY_OFFSETS_M[: bodies - 1]], dtype=np.float64)
        self._truth = source.ground_truth()

    def _people(self, t: float, joints: np.ndarray) -> Any:
        from app.prediction.skeleton import HumanFrame

        copies = [np.concatenate([joints[:, :2] + off, joints[:, 2:]], axis=1) for off in self.offsets]
        return HumanFrame(t, np.concatenate(copies), body_ids=tuple(range(len(copies))))

    def frame_at(self, t: float) -> Any:
        frame = self.source.frame_at(t)
        return None if frame is None else self._people(frame.t, frame.body(0).joints)

    def notify_block_placed(self, station: str, t: float) -> None:
        self.source.notify_block_placed(station, t)

    def reset_counters(self) -> None:
        pass

    def ground_truth(self) -> Any:
        truth = self._truth
        if truth is None:
            return None
        return lambda t: self._people(t, np.asarray(truth(t), dtype=np.float64))


def _people_source(settings: Any, clock: Any, bodies: int) -> Any:
    """The simulated operator (participant 1) through the tracker model, and copies: :class:`_Copies`."""
    from app.cell.tracker import TrackedSource, TrackerModel
    from app.control.world import make_operator

    t0 = clock.now()
    person = make_operator(
        settings.load_workcell(), source="sim", seed=1, participant_seed=1, population=settings.population,
        noise=False, t0=t0,
    )  # fmt: skip
    return _Copies(TrackedSource(person, TrackerModel.from_settings(settings), seed=1, t0=t0), bodies)


def run(
    *, quick: bool = False, progress: bool = True, servo_rate_hz: float = 125.0, bodies: int | None = None
) -> dict[str, Any]:
    """Run the live runtime for a proactive trial (4 s with ``quick``, 120 s otherwise) and measure its
    loops; ``bodies``: that many people in the cell (see the module's docstring)."""
    from app.cell.clock import WallClock
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
    clock = WallClock()
    source = None if bodies is None else _people_source(settings, clock, bodies)
    rt = Runtime(
        settings, servo_rate_hz=servo_rate_hz, options=EngineOptions(record_frames=False), clock=clock,
        source=source,
    )  # fmt: skip
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
        record = rt.planning_record()
        rt.stop_trial(reason="benchmark done")
    finally:
        rt.stop()
    return {
        "bodies": 1 if bodies is None else bodies,
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
            "plan_ms": _pct([1e3 * x for x in record.times_s], (50, 95)),
            "deadline_misses": record.deadline_misses,
            "deadline_misses_per_min": round(60.0 * record.deadline_misses / duration, 2),
            "waited_for_frames_ms": round(1e3 * record.waited_s, 1),
            "waits_for_frames": record.waits,
        },
        "start_s": round(build_s, 3),
        "trial_counters": {k: v for k, v in counters.items() if isinstance(v, int)},
    }
