"""Where may the robot work beside the person? A check of the cell's task poses under the safety model.

The speed governor (:mod:`app.safety.governor`) lets a robot part move only as fast as it can brake before the
person, as last seen and then doing their worst (speeding up at ``HRC_HUMAN_ACCEL_MAX_MPS2`` for the frame's
age and the reaction time), could close the protective separation ``S_p``. Near a person that speed is zero:
a task pose inside that zone of where the person's hands work is a pose the robot can only creep to, or
wait at, while they are there, however good the plan. :func:`check_layout` measures it for every task pose
of the work cell (pickup, drop stations, their approach poses, home) against recorded frames of a person at
work: per pose, the separation to the person, the speed the governor would allow a part there, and the
share of the frames in which it allows at least a given speed (a slow approach, by default 0.1 m/s).

The robot stands at the pose in the configuration (IK branch) that keeps it farthest from the person; every
part counts, each moving straight at the person (the governor's case for a part without a path to measure
toward). The frames are what the runtime would see: a tracker's recording of the cell, or simulated
participants at work (``hrc cell check``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.safety.governor import GovernorModel, directed_approach

__all__ = ["LayoutReport", "PoseReport", "check_layout"]

#: Speed (m/s) the default check asks of a task pose: a slow, careful approach of the tool.
DEFAULT_SPEED_MPS = 0.1


@dataclass(frozen=True, slots=True)
class PoseReport:
    """One task pose against the recorded person.

    Attributes:
        name: The pose (``pickup``, ``A``, ``A_approach``, ...).
        branch: The IK branch of the robot at the pose (the one farthest from the person).
        separation_m: Smallest surface distance robot-person over the robot's parts, 5th and 50th
            percentile over the frames (m).
        allowed_speed_mps: The governor's speed for the robot there, 5th and 50th percentile (m/s).
        free: Share of the frames in which the governor allows at least the check's speed.
    """

    name: str
    branch: int
    separation_m: tuple[float, float]
    allowed_speed_mps: tuple[float, float]
    free: float

    def to_json(self) -> dict[str, Any]:
        return {
            "branch": self.branch,
            "separation_m": {"p5": round(self.separation_m[0], 3), "p50": round(self.separation_m[1], 3)},
            "allowed_speed_mps": {
                "p5": round(self.allowed_speed_mps[0], 3),
                "p50": round(self.allowed_speed_mps[1], 3),
            },
            "free": round(self.free, 3),
        }


@dataclass(frozen=True, slots=True)
class LayoutReport:
    """The layout check of a work cell.

    Attributes:
        speed_mps: The speed the check asks of each pose (m/s).
        frames: Frames checked (after each first speed window).
        zone_m: Separation (m) below which the governor allows less than ``speed_mps`` even when the person
            stands still (measured directed speed 0): the zone a task pose must keep clear of the person.
        poses: One :class:`PoseReport` per task pose, in the roadmap's order.
    """

    speed_mps: float
    frames: int
    zone_m: float
    poses: tuple[PoseReport, ...]

    def blocked(self, free_below: float = 0.5) -> list[PoseReport]:
        """The poses where the check's speed is allowed in less than ``free_below`` of the frames."""
        return [p for p in self.poses if p.free < free_below]

    def to_json(self) -> dict[str, Any]:
        return {
            "speed_mps": self.speed_mps,
            "frames": self.frames,
            "zone_m": round(self.zone_m, 3),
            "poses": {p.name: p.to_json() for p in self.poses},
        }


def check_layout(
    stack: Any,
    governor: GovernorModel,
    recordings: Sequence[np.ndarray],
    *,
    fps: float,
    speed_mps: float = DEFAULT_SPEED_MPS,
    chunk: int = 4096,
) -> LayoutReport:
    """Check every task pose of ``stack``'s roadmap (:class:`app.control.engine.PlanningStack`) against
    ``recordings``: frames (T, J, 3) of a person at work, in the cell's world frame, at ``fps``.

    ``governor``: the trial's :class:`GovernorModel` (:func:`app.control.engine.governor_model`); the
    person's directed speed is measured over its speed window, as the supervisor measures it.

    Raises:
        ValueError: a recording is not (T, J, 3) or has non-finite positions, none is longer than the
            speed window, or ``speed_mps``/``fps`` is not > 0.
    """
    if not (speed_mps > 0 and fps > 0):
        raise ValueError(f"speed_mps and fps must be > 0, got {speed_mps}, {fps}")
    lag = max(round(governor.speed_window_s * fps), 1)
    poses = [np.asarray(r, dtype=np.float64) for r in recordings]
    for p in poses:
        if p.ndim != 3 or p.shape[-1] != 3:
            raise ValueError(f"a recording must be frames of joint positions (T, J, 3), got {p.shape}")
    used = [p for p in poses if p.shape[0] > lag]
    if not used:
        raise ValueError(f"no recording has more than {lag} frames (the speed window at {fps:g} fps)")
    if not all(np.all(np.isfinite(p)) for p in used):
        raise ValueError("a recording has NaN or infinite joint positions (frames without the person)")
    dt = lag / fps
    roadmap, geometry = stack.roadmap, stack.geometry
    table = _SpeedTable(governor)
    out = []
    for name, node in roadmap.station_nodes.items():
        best: tuple[float, int, np.ndarray, np.ndarray] | None = None
        for branch in np.flatnonzero(np.asarray(roadmap.valid[node], dtype=bool)).tolist():
            q = np.asarray(roadmap.ik[node, branch], dtype=np.float64)
            sep, v_h = _measure(geometry, q, used, lag, dt, governor.near_band_m, chunk)
            score = float(np.median(sep.min(axis=1)))
            if best is None or score > best[0]:
                best = (score, int(branch), sep, v_h)
        if best is None:
            continue
        _, branch, sep, v_h = best
        allowed = table(sep, v_h).min(axis=1)
        nearest = sep.min(axis=1)
        out.append(
            PoseReport(
                name=name,
                branch=branch,
                separation_m=(float(np.percentile(nearest, 5)), float(np.median(nearest))),
                allowed_speed_mps=(float(np.percentile(allowed, 5)), float(np.median(allowed))),
                free=float(np.mean(allowed >= speed_mps - 1e-9)),
            )
        )
    ok = table.values[:, 0] >= speed_mps - 1e-9
    zone = float(table.seps[np.argmax(ok)]) if np.any(ok) else float("inf")
    frames = sum(p.shape[0] - lag for p in used)
    return LayoutReport(speed_mps=float(speed_mps), frames=int(frames), zone_m=zone, poses=tuple(out))


class _SpeedTable:
    """:meth:`GovernorModel.max_speed` tabulated over separation and measured speed, and looked up on the
    safe side: the separation rounded down, the speed up, to the grid (the allowed speed falls as the
    separation shrinks and as the person's speed grows)."""

    SEP_STEP_M = 0.01
    SPEED_STEP_MPS = 0.05

    def __init__(
        self, governor: GovernorModel, *, sep_max_m: float = 2.5, speed_max_mps: float = 4.0
    ) -> None:
        self.seps = np.arange(0.0, sep_max_m + 1e-9, self.SEP_STEP_M)
        self.speeds = np.arange(0.0, speed_max_mps + 1e-9, self.SPEED_STEP_MPS)
        rows = max(1, 8192 // self.speeds.size)  # the envelope's arrays grow with the points asked at once
        self.values = np.concatenate(
            [
                governor.max_speed(self.seps[i : i + rows, None], self.speeds[None, :])
                for i in range(0, self.seps.size, rows)
            ]
        )

    def __call__(self, sep_m: np.ndarray, v_human_mps: np.ndarray) -> np.ndarray:
        i = np.floor(np.asarray(sep_m) / self.SEP_STEP_M + 1e-9).astype(np.int64)
        j = np.ceil(np.maximum(np.asarray(v_human_mps), 0.0) / self.SPEED_STEP_MPS - 1e-9).astype(np.int64)
        out = self.values[np.clip(i, 0, self.seps.size - 1), np.clip(j, 0, self.speeds.size - 1)]
        # beyond the table: no speed closer than its first row or faster than its last column
        return np.where((i < 0) | (j >= self.speeds.size), 0.0, out)


def _measure(
    geometry: Any,
    q: np.ndarray,
    recordings: Sequence[np.ndarray],
    lag: int,
    dt: float,
    band_m: float,
    chunk: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Each part's separation (N, L) from the robot at ``q`` to the person in every frame of ``recordings``
    after its first ``lag`` and the person's directed speed (N, L) toward it since the frame ``lag`` (``dt``
    seconds) earlier (:func:`directed_approach`); each frame's distances are computed once."""
    seps, speeds = [], []
    for rec in recordings:
        d = np.concatenate(
            [geometry.pair_distances(q, rec[s : s + chunk]) for s in range(0, rec.shape[0], chunk)]
        )
        sep, v_h = directed_approach(d[lag:], d[:-lag], dt, band_m=band_m)
        seps.append(sep)
        speeds.append(v_h)
    return np.concatenate(seps), np.concatenate(speeds)
