"""Human sources: where the person's skeleton comes from, as canonical :class:`HumanFrame` at 30 Hz.

- :class:`~app.cell.operator_sim.SimulatedOperator`: a simulated participant (re-exported here).
- :class:`ReplaySource`: a recorded clip (the shared CMU npz format or the app's own canonical recordings),
  placed and turned into the operator's area, looped.
- :class:`StreamSource`: frames pushed by an external tracker as JSON (``docs/stream-protocol.md``), e.g. a
  ZED body-tracking client over ``/api/ingest``.

Every source answers ``frame_at(t)`` with the newest frame at or before ``t`` (``None`` when there is none
yet). Put :class:`~app.cell.validation.ValidatedSource` in front of the simulated and replayed sources;
the stream source validates every pushed message itself (it must answer the sender).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.cell.operator_sim import OperatorParams, SimulatedOperator
from app.cell.source import HumanSource
from app.cell.validation import FrameRejected, FrameValidator
from app.prediction.skeleton import JOINT_INDEX, JOINTS, NUM_JOINTS, PARENTS, HumanFrame

if TYPE_CHECKING:
    from app.config import Settings, WorkCell

__all__ = [
    "FrameRejected",
    "HumanSource",
    "OperatorParams",
    "ReplayClip",
    "ReplaySource",
    "SimulatedOperator",
    "StreamSource",
    "load_replay_clip",
    "make_human_source",
    "place_clip",
    "save_clip",
]

log = logging.getLogger(__name__)

#: Height of the ankle joint above the floor (m), used to put a clip's feet on the cell's floor.
ANKLE_HEIGHT_M = 0.08


# ---------------------------------------------------------------------------------------------------------
# Clips
# ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ReplayClip:
    """A recorded motion to replay, in the canonical joint set (a training clip is
    :class:`app.prediction.data.Clip`).

    Attributes:
        times: Frame times (T,), seconds from the clip's start (strictly increasing, ``times[0] == 0``).
        joints: Joint positions (T, J, 3), metres, z up.
        confidence: Per-joint confidence (T, J).
        period_s: Loop period (s): the last frame's time plus one nominal frame period.
        source: ``"cmu38"`` or ``"canonical"``.
    """

    times: np.ndarray
    joints: np.ndarray
    confidence: np.ndarray
    period_s: float
    source: str

    def __post_init__(self) -> None:
        T = len(self.times)
        if T < 1 or self.joints.shape != (T, NUM_JOINTS, 3) or self.confidence.shape != (T, NUM_JOINTS):
            raise ValueError(
                f"Clip needs times (T,), joints (T, {NUM_JOINTS}, 3), confidence (T, {NUM_JOINTS}); got "
                f"{self.times.shape}, {self.joints.shape}, {self.confidence.shape}"
            )


def load_replay_clip(path: str | Path, *, fps: float | None = None) -> ReplayClip:
    """Read a clip for replay (:func:`app.prediction.data.read_clip_file`, the one reader of clip files:
    the shared CMU format, ``hrc export --clips`` and the app's own recordings), at its own frame times.

    Raises:
        ValueError: the file is not a clip (:class:`app.prediction.data.ClipError`; the message says what
            was found).
    """
    from app.prediction.data import read_clip_file

    f = read_clip_file(path, fps=fps)
    return ReplayClip(
        times=f.times,
        joints=f.joints,
        confidence=f.confidence,
        period_s=float(f.times[-1] + 1.0 / f.rate_hz),
        source=f.source,
    )


def save_clip(path: str | Path, frames: Sequence[HumanFrame], *, fps: float = 30.0) -> Path:
    """Write frames as a canonical recording (``t``, ``joints``, ``confidence``, ``joint_names``, ``parents``,
    ``fps``): the format :func:`load_replay_clip` and :class:`ReplaySource` read back."""
    if not frames:
        raise ValueError("save_clip needs at least one frame")
    p = Path(path)
    np.savez_compressed(
        p,
        t=np.array([f.t for f in frames], dtype=np.float64),
        joints=np.stack([f.joints for f in frames]).astype(np.float32),
        confidence=np.stack([f.confidence for f in frames]).astype(np.float32),
        joint_names=np.array(JOINTS),
        parents=PARENTS.astype(np.int16),
        fps=np.float64(fps),
    )
    return p if p.suffix == ".npz" else p.with_suffix(p.suffix + ".npz")


def _facing_yaw(joints: np.ndarray) -> float:
    """Mean facing direction (rad about z) of poses (T, J, 3): forward = (left hip - right hip) x up."""
    lr = joints[:, JOINT_INDEX["l_hip"]] - joints[:, JOINT_INDEX["r_hip"]]
    lr += joints[:, JOINT_INDEX["l_shoulder"]] - joints[:, JOINT_INDEX["r_shoulder"]]
    fwd = np.stack([lr[:, 1], -lr[:, 0]], axis=-1)  # (lr x z) in the xy plane
    fwd /= np.maximum(np.linalg.norm(fwd, axis=-1, keepdims=True), 1e-9)
    m = fwd.mean(axis=0)
    return math.atan2(m[1], m[0])


def place_clip(joints: np.ndarray, cell: WorkCell, *, yaw_offset: float = 0.0) -> np.ndarray:
    """Put a clip (T, J, 3) into the operator's area: turned to face ``facing_yaw + yaw_offset``, the mean
    pelvis position on the area's centre, the lowest ankle on the floor."""
    j = np.asarray(joints, dtype=np.float64)
    op = cell.operator
    dyaw = op.facing_yaw + yaw_offset - _facing_yaw(j)
    c, s = math.cos(dyaw), math.sin(dyaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pelvis = j[:, JOINT_INDEX["pelvis"]]
    center = np.array([pelvis[:, 0].mean(), pelvis[:, 1].mean(), 0.0])
    out = (j - center) @ R.T
    out[..., 0] += op.center_xy[0]
    out[..., 1] += op.center_xy[1]
    ankles = out[:, [JOINT_INDEX["l_ankle"], JOINT_INDEX["r_ankle"]], 2]
    out[..., 2] += op.floor_z + ANKLE_HEIGHT_M - float(np.percentile(ankles, 1.0))
    return out


class ReplaySource(HumanSource):
    """Replays a clip as the operator, played forth and back (or held on its last frame).

    A looped clip that jumped back to its first frame would make the person teleport every pass (a real
    person never does; the monitor would count the jump as the robot's violation). So the clip plays
    through, then plays backwards from its last frame to its first, then forwards again: the person's
    motion stays continuous (it reverses at each end) and every frame keeps a later timestamp than the one
    before.

    Args:
        path: The clip (see :func:`load_replay_clip`).
        cell: The work cell (for the placement).
        t0: Time of the clip's first frame (s, runtime clock).
        loop: Go on after the end, backwards then forwards (ping-pong); otherwise hold the last frame (the
            stream then goes stale).
        place: Place and turn the clip into the operator area (see :func:`place_clip`); off for recordings
            already in this cell's world frame.
        yaw_offset: Extra turn (rad) on top of facing the robot.
        fps: Override the clip's frame rate.
    """

    def __init__(
        self,
        path: str | Path,
        cell: WorkCell,
        *,
        t0: float = 0.0,
        loop: bool = True,
        place: bool = True,
        yaw_offset: float = 0.0,
        fps: float | None = None,
    ) -> None:
        self.path = Path(path)
        self.clip = load_replay_clip(self.path, fps=fps)
        self.joints = place_clip(self.clip.joints, cell, yaw_offset=yaw_offset) if place else self.clip.joints
        self.t0 = float(t0)
        self.loop = bool(loop)
        self._cache: tuple[int, HumanFrame] | None = None

    @property
    def duration_s(self) -> float:
        """Length of one pass (s): first to last frame."""
        return float(self.clip.times[-1])

    def frame_at(self, t: float) -> HumanFrame | None:
        u = t - self.t0
        if u < 0:
            return None
        times, n = self.clip.times, len(self.clip.times)
        span = float(times[-1])
        if n == 1 or not self.loop:
            cycle, k = 0, max(int(np.searchsorted(times, min(u, span) + 1e-9, side="right")) - 1, 0)
            t_frame = float(times[k])
        else:
            cycle = math.floor(u / span)
            within = u - cycle * span
            if cycle % 2 == 0:  # forwards: the newest frame at or before ``within``
                k = max(int(np.searchsorted(times, within + 1e-9, side="right")) - 1, 0)
                t_frame = float(times[k])
            else:  # backwards: frame k is shown at span - times[k]
                k = min(int(np.searchsorted(times, span - within - 1e-9, side="left")), n - 1)
                t_frame = span - float(times[k])
        key = cycle * n + k
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        frame = HumanFrame(
            t=self.t0 + cycle * span + t_frame,
            joints=self.joints[k],
            confidence=self.clip.confidence[k],
        )
        self._cache = (key, frame)
        return frame

    def pose_at(self, t: float) -> np.ndarray:
        """The recorded pose (J, 3) at any time ``t`` (s), interpolated linearly between the clip's frames
        and played forth and back like :meth:`frame_at`: the true person of a replay."""
        times = self.clip.times
        span = float(times[-1])
        u = max(float(t) - self.t0, 0.0)
        if len(times) == 1 or span <= 0:
            return self.joints[0].copy()
        if self.loop:
            cycle = math.floor(u / span)
            within = u - cycle * span
            s = within if cycle % 2 == 0 else span - within
        else:
            s = min(u, span)
        k = min(max(int(np.searchsorted(times, s, side="right")) - 1, 0), len(times) - 2)
        w = (s - float(times[k])) / max(float(times[k + 1] - times[k]), 1e-12)
        w = min(max(w, 0.0), 1.0)
        return (1.0 - w) * self.joints[k] + w * self.joints[k + 1]

    def notify_block_placed(self, station: str, t: float) -> None:
        """A recorded person does not react to the robot: ignored."""

    def ground_truth(self) -> Callable[[float], np.ndarray]:
        """The recorded person is the truth: :meth:`pose_at`."""
        return self.pose_at


# ---------------------------------------------------------------------------------------------------------
# Stream
# ---------------------------------------------------------------------------------------------------------
class StreamSource(HumanSource):
    """Frames pushed by an external tracker (thread-safe; :meth:`push` from the server, :meth:`frame_at`
    from the runtime).

    Each message is parsed, converted to canonical world coordinates, completed, timed and validated before it
    is queued; a rejected message raises :class:`~app.cell.validation.FrameRejected` (counted).

    - Bodies: every body of a message, with its tracker id (a message with none is a person-free frame).
    - Missing keypoints (``null``): the canonical joints they feed are filled from the same body id's pose
      in the previous valid frame (confidence 0); more than ``max_missing_joints`` missing, or none to fill
      from (a new id): rejected (``missing_joints``, naming the body).
    - Time: a message's ``t`` (the sender's clock) is mapped onto the runtime clock by the smallest observed
      ``t_received - t`` over the last ``offset_window`` messages (the least-delayed message), keeping the
      sender's frame spacing; a forward jump of the sender's clock by more than 1 s restarts the estimate.
      A ``t`` before the previous frame's is rejected (``backwards_timestamp``) until the sender's clock
      has stayed back for ``REBASE_AFTER_S`` (it restarted): then the estimate restarts. Without ``t`` the
      receive time is the frame time.

    Args:
        max_queue: Frames kept (the oldest are dropped first, and counted).
        validator: The frame checks (default: no range check).
        T_world_camera: Camera pose (4, 4) for messages in the camera frame.
        max_missing_joints: Most canonical joints that may be filled from the previous frame.
        offset_window: Messages over which the clock offset is estimated.
    """

    #: Frames are validated on push (see :class:`~app.cell.validation.ValidatedSource`).
    validates_frames = True
    #: How far (s) the sender's ``t`` may go back before a message is rejected (``backwards_timestamp``);
    #: a frame that lands before the previous one on the runtime clock is rejected by validation anyway.
    BACKWARDS_TOLERANCE_S = 0.001
    #: A sender whose ``t`` stays back this long (s, receive time) restarted its clock: the offset is
    #: estimated again (the stream was stale meanwhile, and the robot stopped).
    REBASE_AFTER_S = 1.0

    def __init__(
        self,
        *,
        max_queue: int = 64,
        validator: FrameValidator | None = None,
        T_world_camera: np.ndarray | None = None,
        max_missing_joints: int = 6,
        offset_window: int = 300,
    ) -> None:
        if max_queue < 1:
            raise ValueError(f"max_queue must be >= 1, got {max_queue}")
        self.validator = validator if validator is not None else FrameValidator()
        self.T_world_camera = None if T_world_camera is None else np.asarray(T_world_camera, dtype=float)
        if self.T_world_camera is not None and self.T_world_camera.shape != (4, 4):
            raise ValueError(f"T_world_camera must be (4, 4), got {self.T_world_camera.shape}")
        self.max_missing_joints = int(max_missing_joints)
        self._frames: deque[HumanFrame] = deque(maxlen=int(max_queue))
        self._offsets: deque[float] = deque(maxlen=int(offset_window))
        self._last_sender_t: float | None = None
        self._backwards_since: float | None = None
        self._lock = threading.Lock()
        self.received = 0
        self.dropped = 0

    def push(self, message: dict[str, Any] | str | bytes, t_received: float) -> HumanFrame:
        """Take one message (a dict, or its JSON text as received) received at ``t_received`` (s, runtime
        clock); returns the queued frame. Every message is either queued or rejected with a reason and
        counted, whatever it holds.

        Raises:
            FrameRejected: the message is malformed or the frame invalid (the reason is counted).
        """
        from app.cell.stream_protocol import canonical_bodies, parse_message

        with self._lock:
            self.received += 1
            try:
                msg = parse_message(message)
                bodies = canonical_bodies(msg, T_world_camera=self.T_world_camera)
                completed = [self._completed(bid, j, c) for bid, j, c in bodies]
                ids = tuple(bid for bid, _, _ in bodies)
                joints = np.concatenate([j for j, _ in completed]) if bodies else np.zeros((0, 3))
                conf = np.concatenate([c for _, c in completed]) if bodies else np.zeros(0)
                t = self._frame_time(msg.t, float(t_received))
            except FrameRejected as exc:
                raise self.validator.reject(exc.reason, exc.detail) from None
            frame = self.validator.validate(t, joints, conf, ids)
            if msg.t is not None:
                self._last_sender_t = msg.t
            self._backwards_since = None
            if len(self._frames) == self._frames.maxlen:
                self.dropped += 1
            self._frames.append(frame)
            return frame

    def _completed(self, body_id: int, joints: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A body's joints (J, 3) and confidences (J,) with the unseen joints filled from the same id's
        previous accepted pose (confidence 0).

        Raises:
            FrameRejected: ``missing_joints``: too many unseen, or some unseen on an id not seen before.
        """
        missing = ~np.all(np.isfinite(joints), axis=1)
        if not np.any(missing):
            return joints, conf
        prev = self.validator.tracks.pose(body_id)
        n_missing = int(missing.sum())
        if prev is None or n_missing > self.max_missing_joints:
            why = f"no previous pose of body {body_id} to fill them from" if prev is None else "too many"
            names = [JOINTS[i] for i in np.nonzero(missing)[0]]
            raise FrameRejected(
                "missing_joints", f"body {body_id}: {n_missing} joints not seen ({why}): {names}"
            )
        return np.where(missing[:, None], prev, joints), np.where(missing, 0.0, conf)

    def _frame_time(self, t_sender: float | None, t_received: float) -> float:
        """The frame's time on the runtime clock (see the class docstring).

        Raises:
            FrameRejected: ``backwards_timestamp``, the sender's ``t`` went back by more than
                ``BACKWARDS_TOLERANCE_S`` and has not stayed back for ``REBASE_AFTER_S`` yet.
        """
        if t_sender is None:
            return t_received
        last = self._last_sender_t
        if last is not None and t_sender < last - self.BACKWARDS_TOLERANCE_S:
            since = self._backwards_since
            if since is None:
                self._backwards_since = since = t_received
            if t_received - since < self.REBASE_AFTER_S:
                raise FrameRejected(
                    "backwards_timestamp",
                    f"t={t_sender:.3f} s is {last - t_sender:.3f} s before the previous frame's (the "
                    f"sender's clock is taken as restarted once it stays back for {self.REBASE_AFTER_S:g} s)",
                )
            log.warning(
                "stream: the sender's clock went back by %.3f s and stayed back; re-estimating the offset",
                last - t_sender,
            )
            self._offsets.clear()
        sample = t_received - t_sender
        if self._offsets:
            jump = sample - min(self._offsets)
            if abs(jump) > 1.0:
                log.warning("stream: the sender's clock jumped by %.3f s; re-estimating the offset", -jump)
                self._offsets.clear()
        self._offsets.append(sample)
        return t_sender + min(self._offsets)

    def frame_at(self, t: float) -> HumanFrame | None:
        with self._lock:
            for frame in reversed(self._frames):
                if frame.t <= t:
                    return frame
        return None

    def frames_after(self, t: float) -> list[HumanFrame]:
        """Queued frames newer than ``t`` (oldest first): every frame, not only the newest."""
        with self._lock:
            return [f for f in self._frames if f.t > t]

    def notify_block_placed(self, station: str, t: float) -> None:
        """A tracked person reacts on their own: ignored."""

    def reset(self) -> None:
        """Drop queued frames, the clock offset and the validator's last timestamp and counters."""
        with self._lock:
            self._frames.clear()
            self._offsets.clear()
            self._last_sender_t = None
            self._backwards_since = None
            self.validator.reset()
            self.received = 0
            self.dropped = 0

    def reset_counters(self) -> None:
        """Zero the counters, keeping the queue, the clock offset and the last timestamps (a new trial)."""
        with self._lock:
            self.validator.reset_counters()
            self.received = 0
            self.dropped = 0

    @property
    def counters(self) -> dict[str, int]:
        return {**self.validator.counters, "received": self.received, "dropped": self.dropped}


# ---------------------------------------------------------------------------------------------------------
# Factory
# ---------------------------------------------------------------------------------------------------------
def camera_pose_from_settings(settings: Settings) -> np.ndarray | None:
    """``T_world_camera`` (4, 4) from ``settings.camera_pose`` (x, y, z, roll, pitch, yaw), or ``None``."""
    from app.config import pose_matrix

    pose = settings.camera_pose
    if pose is None:
        return None
    return pose_matrix(pose[:3], pose[3:])


def make_human_source(
    settings: Settings,
    cell: WorkCell,
    *,
    seed: int = 0,
    t0: float = 0.0,
    params: OperatorParams | None = None,
    noise: bool = True,
) -> HumanSource:
    """The source ``settings.human_source`` selects (``sim``, a participant of ``settings.population``
    drawn from ``seed`` unless ``params`` are given; ``replay`` with ``settings.replay_clip``; ``stream``).
    Simulated and replayed frames start at ``t0``; ``noise=False``: the simulated operator without tracking
    noise (the truth behind a tracker model).

    Raises:
        ValueError: ``replay`` without a clip, or an unknown source.
    """
    kind = settings.human_source
    if kind == "sim":
        if params is None:
            params = OperatorParams.draw(seed, OperatorParams.population(settings.population))
        return SimulatedOperator(cell, params, seed=seed, t0=t0, noise=noise)
    if kind == "replay":
        if settings.replay_clip is None:
            raise ValueError("HRC_HUMAN_SOURCE=replay needs HRC_REPLAY_CLIP (an .npz clip)")
        return ReplaySource(settings.replay_clip, cell, t0=t0)
    if kind == "stream":
        return StreamSource(
            validator=FrameValidator.for_workcell(cell), T_world_camera=camera_pose_from_settings(settings)
        )
    raise ValueError(f"unknown human source {kind!r}; expected 'sim', 'replay' or 'stream'")
