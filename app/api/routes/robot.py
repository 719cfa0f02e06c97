"""``/api/robot``: the robot and supervisor state, the E-stop and the reset after a stop; ``/api/state``: the
full runtime snapshot (the same JSON as one ``/api/live`` message)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from fastapi import APIRouter, HTTPException, status

from app.api.deps import RuntimeDep
from app.api.live_hub import finite_json, snapshot_json
from app.api.schemas import AUTH_RESPONSES, CONFLICT, RobotStatus, robot_status
from app.control.runtime import Runtime, Snapshot

logger = logging.getLogger(__name__)

router = APIRouter(tags=["robot"], responses=AUTH_RESPONSES)

#: Longest wait for the first snapshot that shows the effect of an E-stop or reset (a few frames).
FRESH_SNAPSHOT_TIMEOUT_S = 0.5


def _snapshot_after(runtime: Runtime, action: Callable[[], None]) -> Snapshot:
    """Run ``action``, then return the first snapshot built after it (bounded wait; the runtime publishes
    one per camera frame), or the newest one when none comes in time."""
    clock = getattr(runtime, "clock", None)
    if clock is None:
        action()
        return runtime.snapshot()
    sub = runtime.subscribe(maxsize=2)
    try:
        action()
        t_after = clock.now()
        deadline = time.monotonic() + FRESH_SNAPSHOT_TIMEOUT_S
        while (left := deadline - time.monotonic()) > 0:
            snap = sub.get(timeout=left)
            if snap is not None and snap.t >= t_after:
                return snap
        return runtime.snapshot()
    finally:
        sub.close()


@router.get("/robot", response_model=RobotStatus)
def get_robot(runtime: RuntimeDep) -> RobotStatus:
    """Robot configuration, tool position, supervisor state, speed scale, separation and E-stop flag."""
    return robot_status(runtime.snapshot())


@router.get("/state")
def get_state(runtime: RuntimeDep) -> dict[str, Any]:
    """The runtime's latest snapshot: state, counters, planning times, skeleton, forecast, plans (JSON); and
    the human source's frames, ``frames_received`` and ``frames_rejected`` (``total`` and ``by_reason``),
    since the current trial started (before the first: since the start), and the servo loop's
    ``servo_overruns`` since the start."""
    return finite_json({**snapshot_json(runtime.snapshot()), **runtime.frame_counts()})


@router.post("/robot/estop", response_model=RobotStatus)
def estop(runtime: RuntimeDep) -> RobotStatus:
    """Emergency stop: the robot stops now and a running trial ends. Always accepted."""
    snap = _snapshot_after(runtime, lambda: runtime.estop(source="api"))
    logger.warning("E-stop from the API")
    return robot_status(snap)


@router.post("/robot/reset", response_model=RobotStatus, responses={**CONFLICT})
def reset(runtime: RuntimeDep) -> RobotStatus:
    """Clear an E-stop or protective stop so that trials can run again; 409 when the runtime refuses."""
    try:
        snap = _snapshot_after(runtime, runtime.reset)
    except (RuntimeError, ValueError) as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, f"cannot reset: {exc}") from exc
    logger.info("reset from the API")
    return robot_status(snap)
