"""Benchmark of the cell I/O: simulated robot, simulated operator, frame validation, stream ingest, and the
fixed-rate loop's timing on the wall clock. ``hrc bench cell [--quick] [--json]``."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np


def _stats(samples: list[float], scale: float, unit: str) -> dict[str, Any]:
    a = np.asarray(samples) * scale
    return {
        "median": round(float(np.median(a)), 4),
        "p95": round(float(np.percentile(a, 95)), 4),
        "unit": unit,
        "n": len(a),
    }


def _time(fn: Callable[[], object], n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def run(*, quick: bool = False, progress: bool = False) -> dict[str, Any]:
    """Measure; returns medians and p95 (JSON-ready)."""
    from app.cell.clock import RateLoop, SimClock, WallClock
    from app.cell.human import StreamSource
    from app.cell.operator_sim import SimulatedOperator
    from app.cell.robot import SimRobot
    from app.cell.stream_protocol import make_message
    from app.cell.validation import FrameValidator
    from app.config import load_workcell

    cell = load_workcell()
    reps = 5 if quick else 30
    out: dict[str, Any] = {"benchmark": "cell", "quick": quick}

    # simulated robot: one simulated second of 125 Hz servo + state
    home = np.asarray(cell.robot.home_q, dtype=float)

    def robot_second() -> None:
        clock = SimClock()
        robot = SimRobot(clock, q0=home)
        v = np.full(6, 0.4)
        for _ in range(125):
            t = clock.now()
            robot.servo(home + v * t, v, t)
            clock.advance(0.008)
            robot.state()

    out["sim_robot_ms_per_sim_second_125hz"] = _stats(_time(robot_second, reps), 1e3, "ms")
    if progress:
        print("sim robot done", flush=True)

    # simulated operator: per frame, over 20 s of behaviour with blocks placed every 5 s
    op = SimulatedOperator(cell, seed=1)
    frame_times = []
    for k in range(150 if quick else 600):
        if k % 150 == 0:
            op.notify_block_placed("ABCD"[(k // 150) % 4], k / 30)
        t0 = time.perf_counter()
        op.frame_at(k / 30)
        frame_times.append(time.perf_counter() - t0)
    out["sim_operator_ms_per_frame"] = _stats(frame_times, 1e3, "ms")
    frames = [op.frame_at(k / 30) for k in range(len(frame_times))]
    if progress:
        print("operator done", flush=True)

    # validation
    validator = FrameValidator.for_workcell(cell)
    val_times = []
    for f in frames:
        t0 = time.perf_counter()
        validator.check(f)
        val_times.append(time.perf_counter() - t0)
    out["validate_us_per_frame"] = _stats(val_times, 1e6, "us")

    # stream ingest (JSON text -> validated frame)
    src = StreamSource(validator=FrameValidator.for_workcell(cell))
    texts = [json.dumps(make_message(f.joints, t=f.t)) for f in frames]
    push_times = []
    for k, text in enumerate(texts):
        t0 = time.perf_counter()
        src.push(text, t_received=k / 30 + 0.01)
        push_times.append(time.perf_counter() - t0)
    out["stream_push_us_per_message_canonical"] = _stats(push_times, 1e6, "us")
    zed = StreamSource(validator=FrameValidator.for_workcell(cell))
    rng = np.random.default_rng(0)
    zed_texts = [
        json.dumps(
            make_message(np.array([1.4, 0.0, 0.2]) + rng.normal(0, 0.2, (34, 3)), format="zed34", t=k / 30)
        )
        for k in range(len(frames))
    ]
    zed_times = []
    for k, text in enumerate(zed_texts):
        t0 = time.perf_counter()
        zed.push(text, t_received=k / 30 + 0.01)
        zed_times.append(time.perf_counter() - t0)
    out["stream_push_us_per_message_zed34"] = _stats(zed_times, 1e6, "us")
    if progress:
        print("validation and stream done", flush=True)

    # fixed-rate loop on the wall clock: lateness of each wake-up against its deadline
    clock = WallClock()
    loop = RateLoop(clock, 125.0)
    late = []
    for _ in range(125 if quick else 500):
        deadline = loop.next_deadline
        loop.sleep()
        late.append(clock.now() - deadline)
    out["rate_loop_125hz_wakeup_late_ms"] = _stats(late, 1e3, "ms")
    out["rate_loop_125hz_overruns"] = loop.overruns
    return out
