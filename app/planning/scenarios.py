"""The reference scenario set: seeded planning queries between task poses with a person reaching in.

Two sources of the person:

- **synthetic** (:func:`synthetic_forecast`): a standing operator at a random spot of the cell's operator
  area, facing the table, hands at their work spot; one hand reaches toward a random point of the shared
  area (a drop station or between it and the work spot) with a minimum-jerk profile whose start, duration
  and hold are drawn from the seed. Needs no data: tests use it.
- **recorded** (:func:`recorded_forecasts`): windows of the CMU motion-capture clips (``cmu_dir``; only the
  benchmark uses them, and skips them when the folder is absent), converted to the canonical skeleton,
  turned to face the table and placed in the operator area with the feet on the floor.

Either way the forecast is the person's true future over the horizon (a perfect predictor) with margins
that grow with the horizon like a predictor's error; it tests the planner, not the predictor.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS

if TYPE_CHECKING:
    from app.config import WorkCell
    from app.planning.roadmap import Roadmap

#: A standing person working at a table, in a body frame: x forward, y left, z up from the floor (m).
_TEMPLATE: dict[str, tuple[float, float, float]] = {
    "pelvis": (0.0, 0.0, 0.95),
    "spine": (0.0, 0.0, 1.12),
    "chest": (0.02, 0.0, 1.32),
    "neck": (0.03, 0.0, 1.50),
    "head": (0.05, 0.0, 1.63),
    "l_shoulder": (0.02, 0.19, 1.45),
    "l_elbow": (0.12, 0.24, 1.18),
    "l_wrist": (0.36, 0.16, 0.86),
    "l_hand": (0.44, 0.12, 0.80),
    "r_shoulder": (0.02, -0.19, 1.45),
    "r_elbow": (0.12, -0.24, 1.18),
    "r_wrist": (0.36, -0.16, 0.86),
    "r_hand": (0.44, -0.12, 0.80),
    "l_hip": (0.0, 0.10, 0.93),
    "l_knee": (0.02, 0.10, 0.50),
    "l_ankle": (0.0, 0.10, 0.08),
    "r_hip": (0.0, -0.10, 0.93),
    "r_knee": (0.02, -0.10, 0.50),
    "r_ankle": (0.0, -0.10, 0.08),
}
_TEMPLATE_ARRAY = np.array([_TEMPLATE[n] for n in sorted(JOINT_INDEX, key=JOINT_INDEX.__getitem__)])

#: Forecast sampling: 30 Hz over 1 s (the paper's predictor horizon).
FORECAST_FPS = 30.0
FORECAST_HORIZON_S = 1.0


@dataclass(frozen=True)
class ReferenceQuery:
    """One planning query of the reference set.

    Attributes:
        name: ``"<start>-><goal>#<seed>"``.
        q_start: Start configuration (6,) (rad): a roadmap branch of the start station.
        t_start: Start time (s) = the forecast's ``t0``.
        goal: Goal station name.
        forecast: The person's forecast (world frame).
        source: ``"synthetic"`` or ``"recorded:<clip>"``.
    """

    name: str
    q_start: np.ndarray
    t_start: float
    goal: str
    forecast: HumanForecast
    source: str


def _min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s * s)


def _body_to_world(cell: WorkCell, p_body: np.ndarray, xy: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return p_body @ R.T + np.array([xy[0], xy[1], cell.operator.floor_z])


#: Forecast margin (m) at t0 and its growth (m/s) over the horizon, growth (m/s) beyond it and its cap (m):
#: about the error of a good 1 s predictor (a few cm at 0.1 s, ~10 cm at 1 s).
MARGIN_T0_M = 0.02
MARGIN_RATE_MPS = 0.08
GROWTH_BEYOND_MPS = 0.1
MAX_MARGIN_M = 0.15


def _margins(times: np.ndarray, t0: float) -> np.ndarray:
    return MARGIN_T0_M + MARGIN_RATE_MPS * np.maximum(times - t0, 0.0)


def synthetic_forecast(
    cell: WorkCell,
    *,
    seed: int,
    t0: float = 0.0,
    horizon_s: float = FORECAST_HORIZON_S,
    fps: float = FORECAST_FPS,
    reach: bool = True,
) -> HumanForecast:
    """A seeded operator at the table whose hand reaches into the shared area (see the module docstring).

    Args:
        cell: The work cell (operator area, floor height, drop stations, work spot).
        seed: Seed of every random choice.
        t0: Forecast start time (s).
        horizon_s: Forecast horizon (s); samples at ``fps``.
        reach: False keeps both hands at the work spot.
    """
    rng = np.random.default_rng(seed)
    op = cell.operator
    xy = np.asarray(op.center_xy) + (rng.uniform(-0.5, 0.5, 2) * np.asarray(op.size_xy)) * np.array(
        [0.4, 0.8]
    )
    yaw = op.facing_yaw + rng.uniform(-0.2, 0.2)
    c, s = math.cos(yaw), math.sin(yaw)
    R_wb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    base_world = _body_to_world(cell, _TEMPLATE_ARRAY, xy, yaw)
    n = max(round(horizon_s * fps), 1)
    times = t0 + np.arange(n + 1) / fps
    joints = np.repeat(base_world[None], n + 1, axis=0)
    if reach:
        side = "l" if rng.random() < 0.5 else "r"
        station = cell.drop_stations[int(rng.integers(len(cell.drop_stations)))]
        work = np.asarray(op.work_spot, dtype=float)
        lam = rng.uniform(0.2, 0.8)
        target = work + lam * (np.asarray(station.xyz, dtype=float) - work)
        target[2] = max(target[2], work[2]) + rng.uniform(0.05, 0.15)
        shoulder = joints[0, JOINT_INDEX[f"{side}_shoulder"]]
        # an arm reaches about 0.7 m from the shoulder: stop short of targets beyond it
        to = target - shoulder
        dist = float(np.linalg.norm(to))
        if dist > 0.68:
            target = shoulder + to * (0.68 / dist)
        t_reach = t0 + rng.uniform(-0.6, 0.3)
        dur = rng.uniform(0.4, 0.7)
        hold = rng.uniform(0.1, 0.4)
        out = np.clip((times - t_reach) / dur, 0.0, 1.0)
        back = np.clip((times - (t_reach + dur + hold)) / dur, 0.0, 1.0)
        w = _min_jerk(out) - _min_jerk(back)  # 0 -> 1 -> 0
        hand0 = joints[0, JOINT_INDEX[f"{side}_hand"]]
        hand = hand0[None] + w[:, None] * (target - hand0)[None]
        direction = (target - shoulder) / max(float(np.linalg.norm(target - shoulder)), 1e-9)
        wrist0 = joints[0, JOINT_INDEX[f"{side}_wrist"]]
        wrist = wrist0[None] + w[:, None] * ((target - 0.08 * direction) - wrist0)[None]
        elbow0 = joints[0, JOINT_INDEX[f"{side}_elbow"]]
        elbow1 = 0.5 * (shoulder + target - 0.08 * direction) + np.array([0.0, 0.0, -0.08])
        elbow = elbow0[None] + w[:, None] * (elbow1 - elbow0)[None]
        joints[:, JOINT_INDEX[f"{side}_hand"]] = hand
        joints[:, JOINT_INDEX[f"{side}_wrist"]] = wrist
        joints[:, JOINT_INDEX[f"{side}_elbow"]] = elbow
        # the upper body leans toward the reach a little
        lean = (R_wb @ np.array([0.08, 0.0, -0.03]))[None] * w[:, None]
        for name in ("chest", "neck", "head", "l_shoulder", "r_shoulder"):
            joints[:, JOINT_INDEX[name]] += lean
    return HumanForecast(
        t0=t0,
        times=times,
        joints=joints,
        margins=_margins(times, t0),
        growth_mps=GROWTH_BEYOND_MPS,
        max_margin_m=MAX_MARGIN_M,
    )


def _start_configuration(roadmap: Roadmap, station: str, q_ref: np.ndarray) -> np.ndarray:
    """The station node's valid branch nearest ``q_ref`` (2 pi-aligned to it)."""
    node = roadmap.resolve(station)
    branches = roadmap.ik[node][roadmap.valid[node]]
    d = branches - q_ref
    d = d - 2 * np.pi * np.rint(d / (2 * np.pi))
    return q_ref + d[int(np.argmin(np.abs(d).max(axis=1)))]


def _station_pairs(roadmap: Roadmap, rng: np.random.Generator, n: int) -> list[tuple[str, str]]:
    names = sorted(roadmap.station_nodes)
    pairs = []
    for _ in range(n):
        a, b = rng.choice(len(names), size=2, replace=False)
        pairs.append((names[int(a)], names[int(b)]))
    return pairs


def reference_queries(
    cell: WorkCell,
    roadmap: Roadmap,
    *,
    n: int,
    seed: int = 0,
    source: Literal["synthetic", "recorded"] = "synthetic",
    cmu_dir: str | Path | None = None,
) -> list[ReferenceQuery]:
    """``n`` seeded queries between task poses with a forecast person.

    Args:
        cell: The work cell. roadmap: Its roadmap (the start configurations are its station branches).
        n: Number of queries.
        seed: Seed of the station pairs and of the person.
        source: ``"synthetic"`` or ``"recorded"`` (CMU clips from ``cmu_dir``; an empty list when absent).
        cmu_dir: Folder of the CMU clips (``index.json``, ``train/``, ``test/``).
    """
    rng = np.random.default_rng(seed)
    q_home = np.asarray(cell.robot.home_q, dtype=float)
    pairs = _station_pairs(roadmap, rng, n)
    if source == "synthetic":
        forecasts = [
            (synthetic_forecast(cell, seed=seed * 100003 + i, t0=10.0 * i), "synthetic") for i in range(n)
        ]
    else:
        if cmu_dir is None:
            return []
        forecasts = recorded_forecasts(cell, cmu_dir, n=n, seed=seed)
        if not forecasts:
            return []
    out = []
    for i, ((a, b), (fc, src)) in enumerate(zip(pairs, forecasts, strict=False)):
        q0 = _start_configuration(roadmap, a, q_home)
        out.append(ReferenceQuery(f"{a}->{b}#{i}", q0, float(fc.t0), b, fc, src))
    return out


def _face_and_place(joints: np.ndarray, cell: WorkCell, xy: np.ndarray, yaw: float) -> np.ndarray:
    """Turn a canonical clip window (T, J, 3) to face ``yaw`` at its first frame and put its first pelvis
    position at ``xy`` with its lowest ankle on the floor."""
    hips = joints[0, JOINT_INDEX["l_hip"]] - joints[0, JOINT_INDEX["r_hip"]]
    left = np.array([hips[0], hips[1], 0.0])
    left /= max(np.linalg.norm(left), 1e-9)
    forward = np.cross(left, np.array([0.0, 0.0, 1.0]))
    heading = math.atan2(forward[1], forward[0])
    a = yaw - heading
    c, s = math.cos(a), math.sin(a)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    p0 = joints[0, JOINT_INDEX["pelvis"]]
    out = (joints - np.array([p0[0], p0[1], 0.0])) @ R.T
    feet = out[:, [JOINT_INDEX["l_ankle"], JOINT_INDEX["r_ankle"]], 2].min()
    out += np.array([xy[0], xy[1], cell.operator.floor_z - feet + 0.06])
    return out


def _through_table(joints: np.ndarray, cell: WorkCell, *, clearance_m: float = 0.02) -> bool:
    """Whether an arm joint (elbow, wrist, hand) of the poses (T, J, 3) dips into the table top."""
    table = cell.table
    T = table.transform()
    arm = [JOINT_INDEX[f"{s}_{n}"] for s in "lr" for n in ("elbow", "wrist", "hand")]
    local = (joints[:, arm].reshape(-1, 3) - T[:3, 3]) @ T[:3, :3]
    half = np.asarray(table.size, dtype=float) / 2.0
    over = (np.abs(local[:, 0]) <= half[0]) & (np.abs(local[:, 1]) <= half[1])
    return bool(np.any(over & (local[:, 2] < half[2] + clearance_m)))


def _reaches_in(joints: np.ndarray, cell: WorkCell) -> bool:
    """Whether a hand of the poses (T, J, 3) comes at least as close to the robot's base as the work spot
    (in the horizontal plane): the person reaches into the shared area."""
    base = np.asarray(cell.robot.base_xyz, dtype=float)[:2]
    hands = joints[:, [JOINT_INDEX["l_hand"], JOINT_INDEX["r_hand"]], :2].reshape(-1, 2)
    spot = float(np.linalg.norm(np.asarray(cell.operator.work_spot, dtype=float)[:2] - base))
    return bool(np.min(np.linalg.norm(hands - base, axis=1)) <= spot)


def recorded_forecasts(
    cell: WorkCell, cmu_dir: str | Path, *, n: int, seed: int = 0, split: str | None = None
) -> list[tuple[HumanForecast, str]]:
    """``n`` forecasts from CMU clip windows placed in the operator area (empty when the clips are absent).

    Prefers the clips whose subject mostly stays in place (directing traffic, washing windows, basketball
    signals); uses the others when those are missing. ``split`` picks ``"train"`` or ``"test"`` clips, None
    both (the planner's benchmark does not evaluate the predictor, so it may use either). Windows and
    placements are drawn (up to 30 times per forecast) until a hand reaches into the shared area (as close
    to the robot as the work spot) without an arm passing through the table top: a person working at a
    table keeps their hands on or above it.
    """
    from app.prediction.adapters import from_cmu38

    root = Path(cmu_dir)
    index_path = root / "index.json"
    if not index_path.is_file():
        return []
    index = json.loads(index_path.read_text())
    clips = index if isinstance(index, list) else index.get("clips", [])
    files = []
    for entry in clips:
        path = entry.get("path") or entry.get("file") if isinstance(entry, dict) else str(entry)
        if not path:
            continue
        p = root / path
        if split is not None and not p.is_file() and (root / split / Path(path).name).is_file():
            p = root / split / Path(path).name
        in_split = split is None or split in p.parts or not any(x in p.parts for x in ("train", "test"))
        if p.is_file() and in_split:
            action = entry.get("action", "") if isinstance(entry, dict) else ""
            files.append((action, p))
    if not files:
        folders = ("train", "test") if split is None else (split,)
        files = [("", p) for folder in folders for p in sorted((root / folder).glob("*.npz"))]
    if not files:
        return []
    calm = [f for f in files if f[0] in ("directing_traffic", "washwindow", "basketball_signal")]
    files = calm or files
    rng = np.random.default_rng(seed)
    op = cell.operator
    out = []
    n_frames = round(FORECAST_HORIZON_S * FORECAST_FPS) + 1
    cache: dict[Path, np.ndarray] = {}
    for i in range(n):
        joints = None
        for _ in range(30):
            action, path = files[int(rng.integers(len(files)))]
            if path not in cache:
                with np.load(path) as data:
                    cache[path] = from_cmu38(np.asarray(data["positions"], dtype=np.float64))
            seq = cache[path]
            if seq.shape[0] < n_frames:
                continue
            start = int(rng.integers(0, seq.shape[0] - n_frames + 1))
            window = seq[start : start + n_frames]
            xy = np.asarray(op.center_xy) + rng.uniform(-0.5, 0.5, 2) * np.asarray(op.size_xy) * 0.5
            joints = _face_and_place(window, cell, xy, op.facing_yaw)
            if _reaches_in(joints, cell) and not _through_table(joints, cell):
                break
        if joints is None:
            continue
        t0 = 10.0 * i
        times = t0 + np.arange(n_frames) / FORECAST_FPS
        assert joints.shape == (n_frames, NUM_JOINTS, 3)
        fc = HumanForecast(
            t0=t0,
            times=times,
            joints=joints,
            margins=_margins(times, t0),
            growth_mps=GROWTH_BEYOND_MPS,
            max_margin_m=MAX_MARGIN_M,
        )
        out.append((fc, f"recorded:{action or path.stem}"))
    return out
