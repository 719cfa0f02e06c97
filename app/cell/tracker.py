"""A model of the body tracker between the true person and everything that decides.

In simulation the simulated operator (or a replayed clip) is the *truth*. A real tracker does not hand the
runtime the truth: it sees the person at its own frame rate, delivers each skeleton some time after the
image was taken, adds per-joint noise and now and then loses frames, alone or in bursts.
:class:`TrackedSource` puts that between a true :class:`~app.cell.source.HumanSource` and the runtime, so the
supervisor and the predictor see only what a real cell would give them, while the ground-truth monitor
judges the robot against the truth.

Frame ``k`` of the tracker shows the person at capture time ``t_k = t0 + k / rate_hz`` and is delivered at
``t_k + latency_s``; it carries its capture time (what a ZED stamps its skeletons with). ``frame_at(t)``
returns the newest frame delivered at or before ``t``, so between deliveries the runtime keeps seeing the
last one, and a dropped frame is never delivered. Noise and drops are drawn from generators seeded by
``seed`` and the frame index, so a frame is the same however often and in whatever order it is asked for.

Defaults (:class:`TrackerModel`):

- ``latency_s = 0.06``: capture to delivery, the figure this project takes for a ZED 2/2i's body tracking
  at 30 Hz (not measured here: measure your own tracker by comparing its frames' capture stamps with
  their arrival on the runtime's clock, and set it);
- ``noise_m = 0.01``: per-joint, per-axis standard deviation, about 1 cm (stereo body tracking at 1-2 m);
- ``drop_p = 0.01`` single dropped frames, and bursts (occlusions) starting with ``burst_p = 0.002`` per
  frame, lasting up to ``max_burst_s = 0.3`` s;
- ``rate_hz = 30``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from app.cell.source import HumanSource
from app.prediction.skeleton import NUM_JOINTS, HumanFrame

if TYPE_CHECKING:
    from app.config import Settings

__all__ = ["TrackedSource", "TrackerModel"]

_BLOCK = 256  # frames whose noise and drops are drawn at once


@dataclass(frozen=True, slots=True)
class TrackerModel:
    """What the tracker does to the truth.

    Attributes:
        rate_hz: Frames per second.
        latency_s: Capture to delivery (s).
        noise_m: Per-joint, per-axis standard deviation of the position noise (m).
        drop_p: Probability that a single frame is lost.
        burst_p: Probability per frame that a burst of lost frames (an occlusion) starts there.
        max_burst_s: Longest burst (s); a burst lasts a uniformly drawn 1 frame to ``max_burst_s``.
    """

    rate_hz: float = 30.0
    latency_s: float = 0.06
    noise_m: float = 0.01
    drop_p: float = 0.01
    burst_p: float = 0.002
    max_burst_s: float = 0.3

    def __post_init__(self) -> None:
        limits = {
            "rate_hz": (1.0, 1000.0),
            "latency_s": (0.0, 1.0),
            "noise_m": (0.0, 0.1),
            "drop_p": (0.0, 0.5),
            "burst_p": (0.0, 0.5),
            "max_burst_s": (0.0, 5.0),
        }
        for f in fields(self):
            value = getattr(self, f.name)
            lo, hi = limits[f.name]
            if not (isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"TrackerModel.{f.name} must be in [{lo}, {hi}], got {value!r}")
        if self.max_burst_s * self.rate_hz > _BLOCK:
            raise ValueError(
                f"TrackerModel: a burst of {self.max_burst_s} s at {self.rate_hz} Hz is longer than "
                f"{_BLOCK} frames; use a shorter max_burst_s"
            )

    @property
    def period_s(self) -> float:
        """Frame period (s)."""
        return 1.0 / self.rate_hz

    @classmethod
    def from_settings(cls, settings: Settings) -> TrackerModel:
        """The tracker model of ``settings`` (its rate is the camera's, ``1 / frame_period_s``)."""
        return cls(
            rate_hz=1.0 / settings.frame_period_s,
            latency_s=settings.tracker_latency_s,
            noise_m=settings.tracker_noise_m,
            drop_p=settings.tracker_drop_p,
            burst_p=settings.tracker_burst_p,
            max_burst_s=settings.tracker_max_burst_s,
        )

    @classmethod
    def ideal(cls, rate_hz: float = 30.0) -> TrackerModel:
        """A tracker that delivers the truth at once, every frame, without noise."""
        return cls(rate_hz=rate_hz, latency_s=0.0, noise_m=0.0, drop_p=0.0, burst_p=0.0, max_burst_s=0.0)


class TrackedSource(HumanSource):
    """The frames a tracker with :class:`TrackerModel` delivers of a true human source.

    Every body of the truth is tracked: each gets its own per-joint noise and keeps its id; a lost frame
    loses every body (the camera's image is lost), a body the truth does not hold is not in the frame.

    Args:
        truth: The true people: ``true_frame(t)`` (every person at any instant, with their ids:
            :class:`~app.cell.people_sim.SimulatedPeople`), else ``pose_at(t)`` (one person's pose at any
            instant, id 0), else ``frame_at(t)``; it should carry no noise of its own.
        model: The tracker's latency, noise, drops and rate.
        seed: Seeds the noise and the drops.
        t0: Capture time of frame 0 (s).
    """

    def __init__(self, truth: Any, model: TrackerModel | None = None, *, seed: int = 0, t0: float = 0.0):
        self.truth = truth
        self.model = model if model is not None else TrackerModel()
        self.seed = int(seed)
        self.t0 = float(t0)
        self._block: tuple[int, np.ndarray, np.ndarray] | None = None
        self._cache: tuple[int, HumanFrame | None] | None = None
        self._body_noise: dict[tuple[int, int], np.ndarray] = {}

    # ------------------------------------------------------------------ the source protocol
    def frame_at(self, t: float) -> HumanFrame | None:
        """The newest frame delivered at or before ``t`` (s), stamped with its capture time, or None."""
        k = math.floor((t - self.model.latency_s - self.t0) * self.model.rate_hz + 1e-9)
        # the newest frame captured by then that was not lost
        for j in range(k, max(k - self._max_gap(), -1), -1):
            if not self.dropped(j):
                return self._frame(j)
        return None

    def notify_block_placed(self, station: str, t: float) -> None:
        """Passed on to the truth (the simulated operator reacts to the robot's placements)."""
        notify = getattr(self.truth, "notify_block_placed", None)
        if notify is not None:
            notify(station, t)

    # ------------------------------------------------------------------ frames
    def capture_time(self, k: int) -> float:
        """Capture time (s) of frame ``k``."""
        return self.t0 + k / self.model.rate_hz

    def dropped(self, k: int) -> bool:
        """Whether frame ``k`` is lost."""
        if k < 0:
            return True
        return bool(self._draws(k)[1])

    def _max_gap(self) -> int:
        # the longest run of lost frames that can occur: a burst plus single drops around it
        return math.ceil(self.model.max_burst_s * self.model.rate_hz) + 64

    def _frame(self, k: int) -> HumanFrame | None:
        if self._cache is not None and self._cache[0] == k:
            return self._cache[1]
        t_k = self.capture_time(k)
        true_frame = getattr(self.truth, "true_frame", None)
        pose_at = getattr(self.truth, "pose_at", None)
        ids: tuple[int, ...] = (0,)
        if true_frame is not None:  # every true person at the capture instant, with their ids
            true = true_frame(t_k)
            joints, confidence = (None, None) if true is None else (true.joints, true.confidence)
            ids = () if true is None else true.body_ids
        elif pose_at is not None:  # the true motion at the capture instant
            seen = t_k >= getattr(self.truth, "t0", 0.0)
            joints, confidence = (pose_at(t_k), np.ones(NUM_JOINTS)) if seen else (None, None)
        else:
            true = self.truth.frame_at(t_k)
            joints, confidence = (None, None) if true is None else (true.joints, true.confidence)
            ids = () if true is None else true.body_ids
        if joints is None:
            frame = None
        else:
            frame = HumanFrame(
                t=t_k, joints=joints + self._noise(k, ids), confidence=confidence, body_ids=ids
            )
        self._cache = (k, frame)
        return frame

    def _noise(self, k: int, ids: tuple[int, ...]) -> np.ndarray:
        """The noise (B*J, 3) of frame ``k`` for the bodies ``ids``: body 0's from the frame's block draw
        (as ever), another body's from a generator of its own (seeded by the seed, the block and its id)."""
        block, i = divmod(k, _BLOCK)
        parts = []
        for bid in ids:
            if bid == 0:
                parts.append(self._draws(k)[0])
                continue
            key = (block, bid)
            if key not in self._body_noise:
                if len(self._body_noise) > 64:
                    self._body_noise.clear()
                m = self.model
                rng = np.random.default_rng([self.seed, 0x7AC4E5, block, bid])
                self._body_noise[key] = (
                    rng.normal(0.0, m.noise_m, size=(_BLOCK, NUM_JOINTS, 3))
                    if m.noise_m > 0
                    else np.zeros((_BLOCK, NUM_JOINTS, 3))
                )
            parts.append(self._body_noise[key][i])
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def _draws(self, k: int) -> tuple[np.ndarray, bool]:
        """Noise (J, 3) and the dropped flag of frame ``k``, drawn per block of frames."""
        block, i = divmod(k, _BLOCK)
        if self._block is None or self._block[0] != block:
            self._block = (block, *self._draw_block(block))
        return self._block[1][i], bool(self._block[2][i])

    def _draw_block(self, block: int) -> tuple[np.ndarray, np.ndarray]:
        m = self.model
        rng = np.random.default_rng([self.seed, 0x7AC4E5, block])
        noise = rng.normal(0.0, m.noise_m, size=(_BLOCK, NUM_JOINTS, 3)) if m.noise_m > 0 else None
        drop = rng.random(_BLOCK) < m.drop_p
        # bursts may start in the previous block and reach into this one: draw them from its generator too
        max_frames = max(1, math.floor(m.max_burst_s * m.rate_hz))
        for b in (block - 1, block):
            if b < 0 or m.burst_p <= 0 or m.max_burst_s <= 0:
                continue
            brng = np.random.default_rng([self.seed, 0xB0257, b])
            starts = np.flatnonzero(brng.random(_BLOCK) < m.burst_p)
            lengths = brng.integers(1, max_frames + 1, size=starts.size)
            for s, n in zip(starts, lengths, strict=True):
                lo = (b - block) * _BLOCK + int(s)
                drop[max(lo, 0) : max(min(lo + int(n), _BLOCK), 0)] = True
        if noise is None:
            noise = np.zeros((_BLOCK, NUM_JOINTS, 3))
        return noise, drop
