"""A simulated operator: a standing person across the table who assembles the blocks the robot brings.

The person stands in the cell's operator area facing the robot. They assemble at their own work spot
(small, quick hand movements), fetch each block the robot placed at a drop station (a reach into the shared
area, a short grasp, a return), and now and then reach across into the shared area for no task reason.
Reaches are minimum-jerk movements of the hand in the world, with a lift over the table, at the
participant's hand speed (peaks of 1-1.5 m/s on long reaches); the torso leans and twists with the reach,
the pelvis sways slightly, and every joint gets tracking noise.

The body has the proportions of the canonical skeleton of the recorded CMU clips (the data the motion
predictor learns from), scaled to the participant's height.

Determinism: everything is drawn from ``seed``; decisions are made on the 30 Hz frame grid, in time order,
when a frame at or after the decision time is first asked for, and they see the notifications
(:meth:`SimulatedOperator.notify_block_placed`) whose time is at or before the decision. The same seed,
parameters and notifications give the same frames, however the frames are queried.

Frames: body frame ``B`` = x forward (``facing_yaw``), y left, z up, origin on the floor under the pelvis;
world = ``R_z(yaw) @ p_B + origin``. Metres, seconds.
"""

from __future__ import annotations

import bisect
import copy
import functools
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from app.cell._kernels import body_pose
from app.cell.population import Population, load_population
from app.cell.source import HumanSource
from app.prediction.forecast import HumanForecast, Predictor
from app.prediction.profiles import min_jerk
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS, HumanFrame

if TYPE_CHECKING:
    from app.config import WorkCell

__all__ = ["OperatorParams", "OracleForecaster", "SimulatedOperator"]

log = logging.getLogger(__name__)

# Canonical-skeleton proportions measured on the shared CMU clips (metres for a person 1.65 m tall).
_REF_HEIGHT_M = 1.65
_PELVIS_Z = 1.01
_L_SPINE, _L_CHEST, _L_NECK, _L_HEAD = 0.116, 0.117, 0.089, 0.088
_SHOULDER_Y, _SHOULDER_Z = 0.199, 0.05
_L_UPPER_ARM, _L_FOREARM, _L_HAND = 0.28, 0.19, 0.04
_HIP_Y, _HIP_Z = 0.092, -0.108
_L_THIGH, _L_SHANK, _ANKLE_Z, _FOOT_Y = 0.428, 0.41, 0.075, 0.10

_J = JOINT_INDEX
#: Postures searched for a reach: forward lean (rad) and a step of the pelvis towards the table (m).
_LEAN_GRID = np.arange(0.0, 1.3501, 0.05)
_DX_GRID = np.array([0.0, 0.04, 0.08, 0.12])
_NOISE_BLOCK = 256  # frames of tracking noise drawn at once


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a: float) -> np.ndarray:
    # Positive ``a`` tips +z towards +x (a forward lean in the body frame).
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _norm(v: np.ndarray) -> float:
    return math.sqrt(float(v @ v))


def _unit(v: np.ndarray) -> np.ndarray:
    n = _norm(v)
    return v / n if n > 1e-12 else v


@dataclass(frozen=True)
class OperatorParams:
    """One participant's body and behaviour.

    Attributes:
        height_m: Body height (m); all segment lengths scale with it.
        handedness: The preferred hand for reaches straight ahead.
        hand_speed_mps: Peak hand speed of a long reach (m/s).
        reaction_s: Delay from a block being placed to the start of fetching it (s).
        assemble_s: Mean time spent assembling one block at the work spot (s).
        reach_rate_hz: Spontaneous reaches into the shared area per second (while busy or idle).
        reach_depth: 0..1, how far those reaches go into the shared area (0: just past the work spot,
            1: beyond the drop stations).
        stand_forward_m: Where they stand relative to the operator area's centre, towards the table (m).
        stand_left_m: ... and to their left (m).
        sway_m: Amplitude of the slow body sway (m).
        noise_m: Standard deviation of the per-joint tracking noise (m).
    """

    height_m: float = 1.72
    handedness: Literal["right", "left"] = "right"
    hand_speed_mps: float = 1.2
    reaction_s: float = 0.6
    assemble_s: float = 3.0
    reach_rate_hz: float = 0.08
    reach_depth: float = 0.5
    stand_forward_m: float = 0.05
    stand_left_m: float = 0.0
    sway_m: float = 0.01
    noise_m: float = 0.005

    def __post_init__(self) -> None:
        checks = {
            "height_m": (1.3, 2.2),
            "hand_speed_mps": (0.2, 3.0),
            "reaction_s": (0.0, 10.0),
            "assemble_s": (0.2, 60.0),
            "reach_rate_hz": (0.0, 2.0),
            "reach_depth": (0.0, 1.0),
            "stand_forward_m": (-0.5, 0.5),
            "stand_left_m": (-0.5, 0.5),
            "sway_m": (0.0, 0.1),
            "noise_m": (0.0, 0.1),
        }
        for name, (lo, hi) in checks.items():
            v = getattr(self, name)
            if not (lo <= v <= hi):
                raise ValueError(f"OperatorParams.{name} must be within [{lo}, {hi}], got {v}")
        if self.handedness not in ("right", "left"):
            raise ValueError(f"handedness must be 'right' or 'left', got {self.handedness!r}")

    @classmethod
    def draw(cls, seed: int, population: Population | None = None) -> OperatorParams:
        """A random participant of ``population`` (default: the shipped one), reproducible from ``seed``."""
        return cls(**(population if population is not None else cls.population()).draw(seed))

    @classmethod
    def population(cls, path: str | Path | None = None) -> Population:
        """The population of participants in ``path`` (None: the shipped ``app/assets/population.toml``).

        Raises:
            PopulationError: The file cannot be used (the message names it and says why).
        """
        if path is None:
            return _default_population()
        return load_population(path, [f.name for f in fields(cls)], lambda d: cls(**d))

    def to_dict(self) -> dict[str, float | str]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@functools.cache
def _default_population() -> Population:
    return load_population(None, [f.name for f in fields(OperatorParams)], lambda d: OperatorParams(**d))


class _Track:
    """A piecewise minimum-jerk signal: segments (t0, t1, v0, v1, arc) in time order; holds between them."""

    def __init__(self, v0: np.ndarray) -> None:
        self.t0: list[float] = []
        self.segs: list[tuple[float, float, np.ndarray, np.ndarray, float]] = []
        self.initial = np.asarray(v0, dtype=float)

    def end_value(self) -> np.ndarray:
        return self.segs[-1][3] if self.segs else self.initial

    def move(self, t0: float, t1: float, v1: np.ndarray, arc: float = 0.0) -> None:
        if self.segs and t0 < self.segs[-1][1] - 1e-9:
            raise RuntimeError("operator track segments must not overlap")
        self.t0.append(t0)
        self.segs.append((t0, t1, self.end_value(), np.asarray(v1, dtype=float), arc))

    def value(self, t: float) -> np.ndarray:
        i = bisect.bisect_right(self.t0, t) - 1
        if i < 0:
            return self.segs[0][2] if self.segs else self.initial
        t0, t1, v0, v1, arc = self.segs[i]
        if t >= t1:
            return v1
        s = float(min_jerk((t - t0) / (t1 - t0)))
        v = v0 + (v1 - v0) * s
        if arc:
            v = v.copy()
            v[2] += arc * math.sin(math.pi * s)
        return v

    def prune(self, t: float) -> None:
        """Drop segments that ended before ``t`` (keeps the last one for its end value)."""
        n = bisect.bisect_left([s[1] for s in self.segs], t)
        n = min(n, len(self.segs) - 1)
        if n > 0:
            self.initial = self.segs[n - 1][3]
            del self.segs[:n]
            del self.t0[:n]


class _Body:
    """Segment lengths for a height, and the pose function (body frame)."""

    def __init__(self, height_m: float) -> None:
        k = height_m / _REF_HEIGHT_M
        self.k = k
        self.pelvis_z = _PELVIS_Z * k
        self.l_spine, self.l_chest, self.l_neck, self.l_head = (
            _L_SPINE * k,
            _L_CHEST * k,
            _L_NECK * k,
            _L_HEAD * k,
        )
        self.sh_y, self.sh_z = _SHOULDER_Y * k, _SHOULDER_Z * k
        self.l_upper, self.l_fore, self.l_hand = _L_UPPER_ARM * k, _L_FOREARM * k, _L_HAND * k
        self.hip_y, self.hip_z = _HIP_Y * k, _HIP_Z * k
        self.l_thigh, self.l_shank, self.ankle_z, self.foot_y = (
            _L_THIGH * k,
            _L_SHANK * k,
            _ANKLE_Z * k,
            _FOOT_Y * k,
        )
        self.arm = self.l_upper + self.l_fore
        self.protraction = 0.05 * k
        self._dims = self.kernel_dims()

    def pelvis(self, posture: np.ndarray) -> np.ndarray:
        lean, _, dx, dy = posture
        drop = 0.08 * self.k * (1.0 - math.cos(lean))  # knees give a little on a deep lean
        return np.array([dx, dy, self.pelvis_z - drop])

    def torso_rotation(self, posture: np.ndarray) -> np.ndarray:
        lean, twist = posture[0], posture[1]
        return _rz(twist) @ _ry(lean)

    def wrist_target(self, shoulder: np.ndarray, hand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Wrist target and the hand's pointing direction (forward and down, like a grasp from above)."""
        u = _unit(_unit(hand - shoulder) + np.array([0.0, 0.0, -0.7]))
        return hand - self.l_hand * u, u

    def kernel_dims(self) -> np.ndarray:
        """The segment lengths (m) in the order :func:`app.cell._kernels.body_pose` reads them."""
        return np.array(
            [
                self.k,
                self.pelvis_z,
                self.l_spine,
                self.l_chest,
                self.l_neck,
                self.l_head,
                self.sh_y,
                self.sh_z,
                self.l_upper,
                self.l_fore,
                self.l_hand,
                self.hip_y,
                self.hip_z,
                self.l_thigh,
                self.l_shank,
                self.ankle_z,
                self.foot_y,
                self.arm,
                self.protraction,
            ],
            dtype=np.float64,
        )

    def pose(self, posture: np.ndarray, lh: np.ndarray, rh: np.ndarray, sway: np.ndarray) -> np.ndarray:
        """Joints (J, 3) in the body frame for a posture (lean, twist, dx, dy) and hand targets (compiled:
        :func:`app.cell._kernels.body_pose`; the tests compare it with the NumPy reference
        :func:`app.cell.reference.body_pose_reference`)."""
        out = np.empty((NUM_JOINTS, 3))
        body_pose(
            np.asarray(posture, dtype=np.float64),
            np.asarray(lh, dtype=np.float64),
            np.asarray(rh, dtype=np.float64),
            np.asarray(sway, dtype=np.float64),
            self._dims,
            out,
        )
        return out

    def solve_posture(self, lh: np.ndarray, rh: np.ndarray, *, reaching: str | None) -> np.ndarray:
        """The least-effort posture (lean, twist, dx, dy) from which both hands reach their targets."""
        if reaching == "left":
            focus = lh
        elif reaching == "right":
            focus = rh
        else:
            focus = 0.5 * (lh + rh)
        side_y = self.sh_y if reaching == "left" else -self.sh_y if reaching == "right" else 0.0
        twist = float(np.clip(0.5 * math.atan2(focus[1] - side_y, max(focus[0], 0.05)), -0.5, 0.5))
        lean, dx = (g.reshape(-1) for g in np.meshgrid(_LEAN_GRID, _DX_GRID))
        n = lean.size
        pelvis = np.stack([dx, np.zeros(n), self.pelvis_z - 0.08 * self.k * (1.0 - np.cos(lean))], axis=-1)
        Rz_half, Rz = _rz(0.6 * twist), _rz(twist)
        spine_local = np.stack(
            [self.l_spine * np.sin(0.45 * lean), np.zeros(n), self.l_spine * np.cos(0.45 * lean)], -1
        )
        chest_local = np.stack([self.l_chest * np.sin(lean), np.zeros(n), self.l_chest * np.cos(lean)], -1)
        chest = pelvis + spine_local @ Rz_half.T + chest_local @ Rz.T
        excess = np.full(n, -np.inf)
        for side, hand in ((1.0, lh), (-1.0, rh)):
            sh_local = np.stack(
                [self.sh_z * np.sin(lean), np.full(n, side * self.sh_y), self.sh_z * np.cos(lean)], -1
            )
            sh = chest + sh_local @ Rz.T
            d = hand - sh
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            u = d + np.array([0.0, 0.0, -0.7])
            u /= np.linalg.norm(u, axis=-1, keepdims=True)
            w = hand - self.l_hand * u
            excess = np.maximum(
                excess, np.linalg.norm(w - sh, axis=-1) - (0.97 * self.arm + self.protraction)
            )
        feasible = excess <= 0
        i = (
            int(np.argmin(np.where(feasible, lean + 3.0 * dx, np.inf)))
            if feasible.any()
            else int(np.argmin(excess))
        )
        return np.array([lean[i], twist, dx[i], 0.0])


@dataclass(frozen=True)
class OperatorAction:
    """One scheduled action (for inspection and tests).

    Attributes:
        t_start: Start (s). t_end: End (s).
        kind: ``assemble``, ``idle``, ``fetch`` or ``reach_across``.
        station: The drop station of a fetch.
        hand: ``left``/``right`` for reaches.
        target_world: Hand target (3,) of a reach (world frame, m).
    """

    t_start: float
    t_end: float
    kind: str
    station: str | None = None
    hand: str | None = None
    target_world: tuple[float, float, float] | None = None


class SimulatedOperator(HumanSource):
    """A simulated person working across the table (a :class:`~app.cell.source.HumanSource`).

    Args:
        cell: The work cell (operator area, work spot, drop stations, table).
        params: The participant (default ``OperatorParams.draw(seed)``).
        seed: Seeds the behaviour, the sway and the tracking noise.
        t0: Time of the first frame (s); frames lie on ``t0 + k / fps``.
        fps: Frame rate (Hz).
        noise: Add tracking noise.
    """

    def __init__(
        self,
        cell: WorkCell,
        params: OperatorParams | None = None,
        *,
        seed: int = 0,
        t0: float = 0.0,
        fps: float = 30.0,
        noise: bool = True,
    ) -> None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.cell = cell
        self.seed = int(seed)
        self.params = params if params is not None else OperatorParams.draw(seed)
        self.t0 = float(t0)
        self.fps = float(fps)
        self.noise = bool(noise)
        p = self.params
        op = cell.operator
        self.yaw = float(op.facing_yaw)
        self.R_world_body = _rz(self.yaw)
        fwd, left = self.R_world_body[:, 0], self.R_world_body[:, 1]
        half = np.asarray(op.size_xy) / 2
        origin_xy = np.asarray(op.center_xy) + p.stand_forward_m * fwd[:2] + p.stand_left_m * left[:2]
        origin_xy = np.clip(origin_xy, np.asarray(op.center_xy) - half, np.asarray(op.center_xy) + half)
        self.origin_world = np.array([origin_xy[0], origin_xy[1], op.floor_z])
        self.body = _Body(p.height_m)
        self.table_top_z = cell.table.center[2] + cell.table.size[2] / 2
        self._block_z = self.table_top_z + 0.04
        self.stations_body = {
            s.name: self.to_body(np.array([s.xyz[0], s.xyz[1], self._block_z])) for s in cell.drop_stations
        }
        spot = self.to_body(np.asarray(op.work_spot, dtype=float))
        spot[2] = max(spot[2], self.to_body(np.array([0.0, 0.0, self.table_top_z]))[2]) + 0.05
        self.home = {"left": spot + np.array([0.0, 0.1, 0.0]), "right": spot + np.array([0.0, -0.1, 0.0])}
        self._rng = np.random.default_rng([self.seed, 0x5EED])
        phase_rng = np.random.default_rng([self.seed, 0x5A7])
        self._sway_f = phase_rng.uniform(0.12, 0.35, size=3)
        self._sway_phi = phase_rng.uniform(0, 2 * math.pi, size=3)
        self._tracks = {
            "left": _Track(self.home["left"]),
            "right": _Track(self.home["right"]),
            "torso": _Track(self.body.solve_posture(self.home["left"], self.home["right"], reaching=None)),
        }
        self._plan_end = self.t0
        self._pending: deque[tuple[float, str]] = deque(maxlen=64)
        self._future: list[tuple[float, int, str]] = []
        self._notify_count = 0
        self._work_left_s = 0.0
        self._cache: tuple[int, HumanFrame] | None = None
        self._noise_block: tuple[int, np.ndarray] | None = None
        self._oldest_t = self.t0
        self.actions: deque[OperatorAction] = deque(maxlen=512)

    # -- frames ---------------------------------------------------------------------------------------
    def to_body(self, p_world: np.ndarray) -> np.ndarray:
        """World point (3,) -> body frame (3,)."""
        return self.R_world_body.T @ (np.asarray(p_world, dtype=float) - self.origin_world)

    def to_world(self, p_body: np.ndarray) -> np.ndarray:
        """Body-frame points (..., 3) -> world (..., 3)."""
        return np.asarray(p_body) @ self.R_world_body.T + self.origin_world

    def frame_index(self, t: float) -> int:
        """Index of the newest frame at or before ``t`` (negative before ``t0``)."""
        return math.floor((t - self.t0) * self.fps + 1e-9)

    def frame_at(self, t: float) -> HumanFrame | None:
        """The newest frame at or before ``t`` (``None`` before ``t0``)."""
        k = self.frame_index(t)
        if k < 0:
            return None
        if self._cache is not None and self._cache[0] == k:
            return self._cache[1]
        tk = self.t0 + k / self.fps
        if tk < self._oldest_t - 1e-9:
            raise ValueError(f"frame_at({t}): frames older than {self._oldest_t:.3f} s were discarded")
        self._plan_until(tk)
        joints = self.to_world(self._pose_body(tk))
        if self.noise and self.params.noise_m > 0:
            joints = joints + self._noise(k)
        frame = HumanFrame(t=tk, joints=joints, confidence=np.ones(NUM_JOINTS))
        self._cache = (k, frame)
        if tk - self._oldest_t > 90.0:
            self._oldest_t = tk - 60.0
            for track in self._tracks.values():
                track.prune(self._oldest_t)
        return frame

    def pose_at(self, t: float) -> np.ndarray:
        """The person's true pose (J, 3) (m, world) at any time ``t`` >= ``t0`` (s), between frames too and
        without tracking noise: what the ground-truth monitor judges the robot against."""
        t = max(float(t), self.t0)
        if t < self._oldest_t - 1e-9:
            raise ValueError(f"pose_at({t}): poses older than {self._oldest_t:.3f} s were discarded")
        self._plan_until(t)
        return self.to_world(self._pose_body(t))

    def ground_truth(self) -> Callable[[float], np.ndarray]:
        """The simulated person is the truth: :meth:`pose_at`."""
        return self.pose_at

    def _noise(self, k: int) -> np.ndarray:
        """The tracking noise (J, 3) (m) of frame ``k``: drawn per block of frames from a generator seeded
        by the operator's seed and the block (the same for a frame however it is reached)."""
        block, i = divmod(k, _NOISE_BLOCK)
        if self._noise_block is None or self._noise_block[0] != block:
            rng = np.random.default_rng([self.seed, 0x7015E, block])
            draws = rng.normal(0.0, self.params.noise_m, size=(_NOISE_BLOCK, NUM_JOINTS, 3))
            self._noise_block = (block, draws)
        return self._noise_block[1][i]

    def _pose_body(self, t: float) -> np.ndarray:
        p = self.params
        sway = p.sway_m * np.sin(2 * math.pi * self._sway_f * (t - self.t0) + self._sway_phi)
        sway[2] *= 0.3
        return self.body.pose(
            self._tracks["torso"].value(t),
            self._tracks["left"].value(t),
            self._tracks["right"].value(t),
            sway,
        )

    def hand_positions(self, t: float) -> dict[str, np.ndarray]:
        """Noise-free hand targets (world, (3,) each) at ``t`` (plans ahead as needed)."""
        self._plan_until(t)
        return {h: self.to_world(self._tracks[h].value(t)) for h in ("left", "right")}

    # -- notifications --------------------------------------------------------------------------------
    def notify_block_placed(self, station: str, t: float) -> None:
        """The robot placed a block at drop ``station`` at time ``t``; the person will fetch it.

        A notification for a time the operator has already planned past is acted on at the next decision.

        Raises:
            ValueError: ``station`` is not a drop station of the cell.
        """
        if station not in self.stations_body:
            raise ValueError(f"unknown drop station {station!r}; the cell has {sorted(self.stations_body)}")
        self._notify_count += 1
        bisect.insort(self._future, (float(t), self._notify_count, station))

    # -- behaviour ------------------------------------------------------------------------------------
    def _plan_until(self, t: float) -> None:
        while self._plan_end <= t:
            tau = self._plan_end
            while self._future and self._future[0][0] <= tau:
                t_n, _, station = self._future.pop(0)
                if len(self._pending) == self._pending.maxlen:
                    log.warning(
                        "operator: more than %d blocks waiting; the oldest is dropped", len(self._pending)
                    )
                self._pending.append((t_n, station))
            end = self._decide(tau)
            # Decisions stay on the frame grid, so the same frames are produced however they are queried.
            k_end = max(
                math.ceil((end - self.t0) * self.fps - 1e-9), math.floor((tau - self.t0) * self.fps) + 1
            )
            self._plan_end = self.t0 + k_end / self.fps

    def _decide(self, tau: float) -> float:
        p, rng = self.params, self._rng
        if self._pending and self._work_left_s <= 0:
            t_n, station = self._pending[0]
            if tau >= t_n + p.reaction_s:
                self._pending.popleft()
                end = self._reach(tau, self.stations_body[station], kind="fetch", station=station)
                self._work_left_s = float(p.assemble_s * rng.uniform(0.7, 1.3))
                return end
            chunk = max(min(rng.uniform(0.5, 1.1), t_n + p.reaction_s - tau), 1.0 / self.fps)
        else:
            chunk = float(rng.uniform(0.6, 1.2))
        if rng.random() < 1.0 - math.exp(-p.reach_rate_hz * chunk):
            return self._reach(tau, self._across_target(), kind="reach_across")
        busy = self._work_left_s > 0
        self._work_left_s = max(0.0, self._work_left_s - chunk)
        return self._assemble(tau, chunk, kind="assemble" if busy else "idle")

    def _across_target(self) -> np.ndarray:
        rng, p = self._rng, self.params
        spot_x = 0.5 * (self.home["left"][0] + self.home["right"][0])
        far_x = max(s[0] for s in self.stations_body.values()) + 0.1
        x = rng.uniform(
            spot_x + 0.15, spot_x + 0.15 + (far_x - spot_x - 0.15) * (0.35 + 0.65 * p.reach_depth)
        )
        y = rng.uniform(-0.35, 0.35)
        z = self._block_z - self.origin_world[2] + rng.uniform(0.0, 0.15)
        return np.array([x, y, z])

    def _choose_hand(self, target: np.ndarray) -> str:
        if target[1] > 0.12:
            return "left"
        if target[1] < -0.12:
            return "right"
        return self.params.handedness

    def _reach(self, tau: float, target: np.ndarray, *, kind: str, station: str | None = None) -> float:
        p, rng, body = self.params, self._rng, self.body
        hand = self._choose_hand(target)
        other = "left" if hand == "right" else "right"
        tr, to, torso = self._tracks[hand], self._tracks[other], self._tracks["torso"]
        start = tr.end_value()
        v_peak = p.hand_speed_mps * rng.uniform(0.85, 1.05)
        dist = float(np.linalg.norm(target - start))
        t_out = max(0.35, 1.875 * dist / v_peak)
        arc = min(0.12, 0.25 * dist)
        t1 = tau + t_out
        tr.move(tau, t1, target, arc)
        hands = {hand: target, other: to.end_value()}
        torso.move(tau, t1, body.solve_posture(hands["left"], hands["right"], reaching=hand))
        dwell = rng.uniform(0.15, 0.35) if kind == "fetch" else rng.uniform(0.2, 0.8)
        t2 = t1 + dwell
        back = self.home[hand] + rng.uniform(-0.03, 0.03, size=3) * [1, 1, 0.5]
        dist_back = float(np.linalg.norm(back - target))
        t_back = max(0.35, 1.875 * dist_back / (0.9 * v_peak))
        t3 = t2 + t_back
        tr.move(t2, t3, back, min(0.12, 0.25 * dist_back))
        hands = {hand: back, other: to.end_value()}
        torso.move(t2, t3, body.solve_posture(hands["left"], hands["right"], reaching=None))
        self.actions.append(
            OperatorAction(tau, t3, kind, station, hand, tuple(float(v) for v in self.to_world(target)))
        )
        return t3

    def _assemble(self, tau: float, duration: float, *, kind: str) -> float:
        rng, body = self._rng, self.body
        amp = 0.05 if kind == "assemble" else 0.025
        speed = 1.0 if kind == "assemble" else 0.6
        end = tau + duration
        for hand in ("left", "right"):
            tr = self._tracks[hand]
            t = tau + rng.uniform(0.0, 0.2)
            while True:
                dur = rng.uniform(0.3, 0.6) / speed
                if t + dur > end:
                    break
                target = self.home[hand] + rng.uniform(-amp, amp, size=3) * [1.0, 1.0, 0.5]
                tr.move(t, t + dur, target)
                t += dur + rng.uniform(0.0, 0.25)
        torso = self._tracks["torso"]
        posture = body.solve_posture(self.home["left"], self.home["right"], reaching=None)
        posture = posture + np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.05, 0.05), 0.0, 0.0])
        torso.move(tau, tau + min(0.8, duration), posture)
        self.actions.append(OperatorAction(tau, end, kind))
        return end

    def pending_blocks(self) -> list[str]:
        """Stations whose blocks the person knows about and has not fetched yet."""
        return [s for _, s in self._pending]


class OracleForecaster(Predictor):
    """The simulated operator's own future as the forecast: the bound of what proactive planning can gain
    in a cell, whatever the predictor (an analysis tool; there is no such thing for a real person).

    At each frame a copy of ``operator`` is run ahead over the horizon: the forecast holds the frames the
    tracker *will* report (tracking noise included), exactly, unless the robot places a block within the
    horizon (the copy does not know of it yet; the person fetches a block at least their reaction time
    after it is placed). The real operator is left as it was. Margins: ``margin_m`` at every step (the
    tracking error); beyond the horizon the last pose is held and the margin grows at ``growth_mps`` up to
    ``max_margin_m``, as with the predictor (the oracle does not see further either; a headless trial passes
    the predictor's values).

    A :class:`~app.prediction.forecast.Predictor`, as :class:`app.prediction.predictor.MotionPredictor` is.
    A copy costs a few milliseconds: an oracle trial runs about three times slower
    than one with the predictor.

    Args:
        operator: The simulated person of the trial (the same object the trial's source reads).
        horizon: Forecast steps after the newest frame.
        margin_m: Margin of every step (m).
        growth_mps, max_margin_m: Margin growth beyond the horizon (m/s) and its cap (m).
    """

    def __init__(
        self,
        operator: SimulatedOperator,
        *,
        horizon: int = 30,
        margin_m: float = 0.02,
        growth_mps: float = 1.6,
        max_margin_m: float = 1.0,
    ) -> None:
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        for name, v in (("margin_m", margin_m), ("growth_mps", growth_mps), ("max_margin_m", max_margin_m)):
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        self.operator = operator
        self.horizon = int(horizon)
        self.margin_m = float(margin_m)
        self.growth_mps = float(growth_mps)
        self.max_margin_m = max(float(max_margin_m), self.margin_m)

    #: Its forecast is exact over its horizon (the trial engine's fetch anticipation then adds only what lies
    #: beyond it: :class:`app.control.anticipation.FetchAnticipation`'s ``exact_horizon``).
    exact_within_horizon = True
    effective_kind = "OracleForecaster"

    def reset(self) -> None:
        """Nothing to forget: the forecast comes from the operator itself."""

    def update(self, frame: HumanFrame) -> HumanForecast:
        """The operator's next ``horizon`` frames after ``frame`` (index 0: ``frame`` itself)."""
        dt = 1.0 / self.operator.fps
        twin = copy.deepcopy(self.operator)
        joints = np.empty((self.horizon + 1, NUM_JOINTS, 3))
        joints[0] = frame.joints
        for k in range(1, self.horizon + 1):
            f = twin.frame_at(frame.t + k * dt)
            joints[k] = joints[k - 1] if f is None else f.joints
        return HumanForecast(
            t0=frame.t,
            times=frame.t + dt * np.arange(self.horizon + 1),
            joints=joints,
            margins=np.full(self.horizon + 1, self.margin_m),
            growth_mps=self.growth_mps,
            max_margin_m=self.max_margin_m,
        )
