"""Where may the robot work beside the person? A check of the cell's task poses under the safety model.

The speed governor (:mod:`app.safety.governor`) lets a robot part move only as fast as it can brake before the
person, as last seen and then approaching at the speed the safety model assumes (``HRC_HUMAN_MODEL``) for
the frame's age and the reaction time, could close the protective separation ``S_p``. Near a body region
that admits no contact (skull, face, neck) that speed is zero: a task pose inside that zone of where the
person's head is while they work is a pose the robot can only creep to, or wait at, while they are there,
however good the plan. :func:`check_layout` measures it for every task pose
of the work cell (pickup, drop stations, their approach poses, home) against recorded frames of a person at
work: per pose, the separation to the person, the speed the governor would allow a part there, and the
share of the frames in which it allows at least a given speed (a slow approach, by default 0.1 m/s).
:func:`suggest_stations` then looks, for every drop station, for the nearest place away from the person's work
spot where the robot could work: what a cell designer would move, since no plan gets the robot faster into a
zone the person works in.

The robot stands at the pose in the configuration (IK branch) that keeps it farthest from the person; every
part counts, each moving straight at the person (the governor's case for a part without a path to measure
toward). With power and force limiting (the governor model's ``pfl_caps_mps``), a part may move toward a
body region that admits contact at that region's permissible speed however close it is, as the governor
lets it (:mod:`app.safety.pfl`); skull, face and neck admit none, so near a head the part keeps ``S_p``.
The frames are what the runtime would see: a tracker's recording of the cell, or simulated participants at
work (``hrc cell check``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.safety.governor import GovernorModel, nearest_approach

__all__ = ["LayoutReport", "PoseReport", "StationMove", "check_layout", "suggest_stations"]

#: Speed (m/s) the default check asks of a task pose: a slow, careful approach of the tool.
DEFAULT_SPEED_MPS = 0.1
#: Share of the frames in which a suggested station must let the robot move at the check's speed (three
#: quarters of the time: a design default, not tuned on any figure).
DEFAULT_TARGET_FREE = 0.75
#: The ways :func:`suggest_stations` tries to move a station: straight away from the person's work spot
#: first, then turned by 30 degrees either side (round a conveyor or an obstacle in the way).
DIRECTIONS_RAD = (0.0, math.radians(-30.0), math.radians(30.0))
#: How far :func:`suggest_stations` moves a station at most (m).
DEFAULT_MAX_SHIFT_M = 0.5


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
    """Check every task pose of ``stack``'s roadmap (:class:`app.control.stack.PlanningStack`) against
    ``recordings``: frames (T, J, 3) of a person at work, in the cell's world frame, at ``fps``.

    ``governor``: the trial's :class:`GovernorModel` (:func:`app.control.engine.governor_model`); the
    person's directed speed is measured over its speed window, as the supervisor measures it.

    Raises:
        ValueError: a recording is not (T, J, 3) or has non-finite positions, none is longer than the
            speed window, or ``speed_mps``/``fps`` is not > 0.
    """
    used, lag = _recordings(governor, recordings, fps=fps, speed_mps=speed_mps)
    dt = lag / fps
    roadmap, geometry = stack.roadmap, stack.geometry
    table = _speed_table(governor)
    out = []
    for name, node in roadmap.station_nodes.items():
        branches = np.flatnonzero(np.asarray(roadmap.valid[node], dtype=bool))
        if branches.size == 0:
            continue
        qs = np.asarray(roadmap.ik[node], dtype=np.float64)[branches]
        i, sep, v_h = _farthest_branch(geometry, qs, used, lag, dt, governor.near_band_m, chunk)
        branch = int(branches[i])
        allowed = _allowed(table, sep, v_h, governor).min(axis=1)
        nearest = sep.min(axis=(1, 2))
        out.append(
            PoseReport(
                name=name,
                branch=branch,
                separation_m=(float(np.percentile(nearest, 5)), float(np.median(nearest))),
                allowed_speed_mps=(float(np.percentile(allowed, 5)), float(np.median(allowed))),
                free=_free_share(allowed, speed_mps),
            )
        )
    ok = _allows(table.values[:, 0], speed_mps)
    zone = float(table.seps[np.argmax(ok)]) if np.any(ok) else float("inf")
    frames = sum(p.shape[0] - lag for p in used)
    return LayoutReport(speed_mps=float(speed_mps), frames=int(frames), zone_m=zone, poses=tuple(out))


@dataclass(frozen=True, slots=True)
class StationMove:
    """Where a drop station could go so that the robot can work at it beside the person.

    Attributes:
        name: The drop station.
        xyz: Where it is (m).
        free: The smaller share, of the station's and its approach pose's, of the frames in which the
            governor allows the check's speed there (0 where the robot cannot reach both tool-down).
        suggested_xyz: The nearest place found away from the person's work spot (same height) where that
            share reaches the target; None if none within the search.
        shift_m: How far ``suggested_xyz`` is from ``xyz`` (m); 0 when the station is free enough already.
        suggested_free: The share at ``suggested_xyz``.
        reach_change_m: How much farther (m; negative: nearer) ``suggested_xyz`` is from the pickup than
            ``xyz``, straight: what the move costs the robot's way from the conveyor.
    """

    name: str
    xyz: tuple[float, float, float]
    free: float
    suggested_xyz: tuple[float, float, float] | None
    shift_m: float | None
    suggested_free: float | None
    reach_change_m: float | None

    def to_json(self) -> dict[str, Any]:
        def r(v: Any) -> Any:
            return None if v is None else [round(float(x), 3) for x in v]

        return {
            "xyz": r(self.xyz),
            "free": round(self.free, 3),
            "suggested_xyz": r(self.suggested_xyz),
            "shift_m": None if self.shift_m is None else round(self.shift_m, 3),
            "suggested_free": None if self.suggested_free is None else round(self.suggested_free, 3),
            "reach_change_m": None if self.reach_change_m is None else round(self.reach_change_m, 3),
        }


def suggest_stations(
    stack: Any,
    governor: GovernorModel,
    recordings: Sequence[np.ndarray],
    *,
    fps: float,
    speed_mps: float = DEFAULT_SPEED_MPS,
    target_free: float = DEFAULT_TARGET_FREE,
    max_shift_m: float = DEFAULT_MAX_SHIFT_M,
    step_m: float = 0.025,
    chunk: int = 4096,
) -> tuple[StationMove, ...]:
    """For every drop station of ``stack``'s cell, the nearest place, moving it away from the person's work
    spot (``cell.operator.work_spot``; in the table's plane, straight away or turned by
    :data:`DIRECTIONS_RAD`, up to ``max_shift_m`` in steps of ``step_m``), where the governor lets the
    robot move at ``speed_mps`` in at least ``target_free`` of the frames of ``recordings`` both at the
    station and at its approach pose (the check of :func:`check_layout`, each pose in its IK branch
    farthest from the person).

    A place counts only where a block can be put and the robot can work: on the table, clear of the
    conveyor and the other obstacles' footprints and of the other drop stations by the block's size plus
    5 cm (the stations are taken in the cell's order, each clear of where the ones before it are to go),
    and with an IK branch (tool down) at both poses that is clear of the static scene and of itself.
    The person is the recorded one, reaches to the station's old place included: a person who fetches
    blocks from the new place reaches there instead, for the few seconds of each fetch.

    Raises:
        ValueError: as :func:`check_layout`; ``target_free`` not in (0, 1], ``step_m`` or ``max_shift_m``
            not > 0.
    """
    if not (0.0 < target_free <= 1.0):
        raise ValueError(f"target_free must be in (0, 1], got {target_free}")
    if not (step_m > 0 and max_shift_m > 0):
        raise ValueError(f"step_m and max_shift_m must be > 0, got {step_m}, {max_shift_m}")
    from app.planning.roadmap import RoadmapConfig, StaticChecker

    used, lag = _recordings(governor, recordings, fps=fps, speed_mps=speed_mps)
    dt = lag / fps
    cell, geometry = stack.cell, stack.geometry
    table = _speed_table(governor)
    checker = StaticChecker(stack.collision, margin_m=RoadmapConfig().static_margin_m)
    yaw = float(getattr(stack.roadmap, "yaw", 0.0))
    half_part = 0.5 * float(np.max(np.asarray(cell.tool.part_size_m, dtype=np.float64)))
    spot = np.asarray(cell.operator.work_spot, dtype=np.float64)
    pickup = np.asarray(cell.conveyor.pickup.xyz, dtype=np.float64)
    stations = {st.name: np.asarray(st.xyz, dtype=np.float64) for st in cell.drop_stations}

    def placeable(p: np.ndarray, name: str) -> bool:
        if not _within_footprint(p, cell.table, -half_part):
            return False
        if any(_within_footprint(p, box, half_part + 0.05) for box in (cell.conveyor.body, *cell.obstacles)):
            return False
        return all(
            np.linalg.norm(p[:2] - o[:2]) >= 2 * half_part + 0.05 for n, o in stations.items() if n != name
        )

    def free_at(p: np.ndarray) -> float | None:
        """The smaller share of free frames of the pose at ``p`` and its approach; None: not workable."""
        q, valid = stack.kin.ik_down(np.stack([p, p + cell.drop_approach_offset(p)]), yaw=yaw)
        q = np.nan_to_num(np.asarray(q, dtype=np.float64))
        valid = np.asarray(valid, dtype=bool)
        shares = []
        for k in range(2):
            ok = np.flatnonzero(valid[k])
            if ok.size:
                ok = ok[~checker.bad(q[k, ok])]
            if ok.size == 0:
                return None
            _, sep, v_h = _farthest_branch(geometry, q[k, ok], used, lag, dt, governor.near_band_m, chunk)
            shares.append(_free_share(_allowed(table, sep, v_h, governor).min(axis=1), speed_mps))
        return min(shares)

    out = []
    for name, xyz in list(stations.items()):
        free = free_at(xyz)
        away = xyz[:2] - spot[:2]
        norm = float(np.linalg.norm(away))
        found: tuple[np.ndarray, float, float] | None = None
        if free is not None and free >= target_free:
            found = (xyz, 0.0, free)
        elif norm > 1e-9:
            for shift, p in _away(xyz, math.atan2(away[1], away[0]), step_m, max_shift_m):
                share = free_at(p) if placeable(p, name) else None
                if share is not None and share >= target_free:
                    found = (p, shift, share)
                    break
        if found is not None:
            stations[name] = found[0]  # the stations after this one keep clear of where it is to go
        out.append(
            StationMove(
                name=name,
                xyz=tuple(float(v) for v in xyz),
                free=0.0 if free is None else free,
                suggested_xyz=None if found is None else tuple(float(v) for v in found[0]),
                shift_m=None if found is None else found[1],
                suggested_free=None if found is None else found[2],
                reach_change_m=None
                if found is None
                else float(np.linalg.norm(found[0] - pickup) - np.linalg.norm(xyz - pickup)),
            )
        )
    return tuple(out)


def _allows(allowed_mps: np.ndarray, speed_mps: float) -> np.ndarray:
    """Where the governor's allowed speed (m/s) reaches ``speed_mps`` (to rounding)."""
    return np.asarray(allowed_mps) >= speed_mps - 1e-9


def _free_share(allowed_mps: np.ndarray, speed_mps: float) -> float:
    """The share of the frames in which the slowest part may move at ``speed_mps`` (``allowed_mps``: the
    allowed speed per frame, the smallest over the parts)."""
    return float(np.mean(_allows(allowed_mps, speed_mps)))


def _within_footprint(p: np.ndarray, box: Any, grow_m: float) -> bool:
    """Whether the point ``p`` lies over ``box``'s footprint in the table's plane (its rectangle, turned by
    its yaw), grown by ``grow_m`` on every side (shrunk where negative)."""
    local = np.linalg.inv(box.transform()) @ np.append(np.asarray(p, dtype=np.float64)[:3], 1.0)
    return bool(np.all(np.abs(local[:2]) <= np.asarray(box.size[:2], dtype=np.float64) / 2.0 + grow_m))


def _away(
    xyz: np.ndarray, heading: float, step_m: float, max_shift_m: float
) -> Iterator[tuple[float, np.ndarray]]:
    """The places :func:`suggest_stations` tries for a station at ``xyz``, nearest first: ``(shift, place)``
    every ``step_m`` up to ``max_shift_m`` along ``heading`` (rad, in the table's plane), each shift turned by
    :data:`DIRECTIONS_RAD` in turn."""
    for shift in np.arange(step_m, max_shift_m + 1e-9, step_m):
        for turn in DIRECTIONS_RAD:
            way = np.array([math.cos(heading + turn), math.sin(heading + turn), 0.0])
            yield float(shift), xyz + shift * way


def _recordings(
    governor: GovernorModel, recordings: Sequence[np.ndarray], *, fps: float, speed_mps: float
) -> tuple[list[np.ndarray], int]:
    """The recordings a check can use (longer than the governor's speed window) and that window in frames;
    ValueError for bad input (see :func:`check_layout`)."""
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
    return used, lag


def _farthest_branch(
    geometry: Any,
    qs: np.ndarray,
    used: Sequence[np.ndarray],
    lag: int,
    dt: float,
    band_m: float,
    chunk: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """Of the configurations ``qs`` (B, 6) of one pose, the one whose median separation from the person is
    the largest: its index, and the separations of its parts from the person's capsules and the person's
    directed speeds toward them (:func:`_measure`)."""
    best: tuple[float, int, np.ndarray, np.ndarray] | None = None
    for i, q in enumerate(np.asarray(qs, dtype=np.float64)):
        sep, v_h = _measure(geometry, q, used, lag, dt, band_m, chunk)
        score = float(np.median(sep.min(axis=(1, 2))))
        if best is None or score > best[0]:
            best = (score, i, sep, v_h)
    assert best is not None
    return best[1], best[2], best[3]


@functools.lru_cache(maxsize=4)
def _speed_table(governor: GovernorModel) -> _SpeedTable:
    """The governor's :class:`_SpeedTable`, built once per governor model (a second or more to tabulate):
    ``hrc cell check --suggest`` asks for it twice."""
    return _SpeedTable(governor)


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
        for a in (self.seps, self.speeds, self.values):
            a.setflags(write=False)  # shared by every check of the same governor (:func:`_speed_table`)

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
    """The separation (N, L, M) of each part of the robot at ``q`` from each capsule of the person in every
    frame of ``recordings`` after its first ``lag``, and the person's directed speed toward the part: per
    capsule, how fast that distance shrank since the frame ``lag`` (``dt`` seconds) earlier, for a
    capsule within ``band_m`` of the part's nearest the fastest of those (the supervisor's
    :func:`~app.safety.governor.nearest_approach`: a limb beside the nearest one counts as it does for the
    governor). Each frame's distances are computed once."""
    seps, speeds = [], []
    for rec in recordings:
        d = np.concatenate(
            [geometry.pair_distances(q, rec[s : s + chunk]) for s in range(0, rec.shape[0], chunk)]
        )
        d_now, d_before = d[lag:], d[:-lag]
        v_pairs = np.maximum(d_before - d_now, 0.0) / dt
        sep, v_near = nearest_approach(d_now, v_pairs, band_m=band_m)  # the fastest of the near capsules
        seps.append(d_now)
        speeds.append(np.where(d_now <= sep[..., None] + band_m, v_near[..., None], v_pairs))
    return np.concatenate(seps), np.concatenate(speeds)


def _allowed(table: _SpeedTable, sep: np.ndarray, v_h: np.ndarray, governor: GovernorModel) -> np.ndarray:
    """The governor's speed (N, L) for each part, from its separations (N, L, M) from the person's
    capsules and the person's directed speeds toward it: toward each capsule the braking envelope's speed
    (:meth:`GovernorModel.max_speed`), or that capsule's permissible contact speed where power and force
    limiting allows more (the governor model's ``pfl_caps_mps``; -1: none, skull, face and neck), the
    slowest over the capsules."""
    per_capsule = table(sep, v_h)
    caps = governor.caps_for(sep.shape[-1])
    return np.maximum(per_capsule, np.maximum(caps, 0.0)).min(axis=-1)
