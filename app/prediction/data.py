"""Clips of joint positions for training and evaluating motion predictors, and their augmentation.

A clip file is an ``.npz`` with ``positions`` (T, K, 3) in metres, z up, ``fps`` and ``joint_names`` (K,), or
one of the app's own recordings (``joints`` with their times ``t``). Two joint sets are understood: the
38-joint CMU skeleton of the shared ``cmu_mocap`` clips (converted with
:func:`~app.prediction.adapters.from_cmu38`, orientation fix included) and the canonical joint set itself
(``joint_names == JOINTS``), which is the format users add their own recordings in. :func:`read_clip_file`
is the one reader of these files (training here, replay in :mod:`app.cell.human`). For training, clips at
another frame rate are resampled to 30 Hz by linear interpolation.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.prediction.adapters import CMU38_NAMES, from_cmu38
from app.prediction.skeleton import JOINTS, MIRROR_PERMUTATION, NUM_JOINTS

log = logging.getLogger(__name__)

FPS = 30.0

#: Train-split clips held out for validation (early stopping and the shipped error quantiles):
#: one clip of every action of the CMU train split.
DEFAULT_VAL_CLIPS: tuple[str, ...] = (
    "basketball_5",
    "basketball_signal_5",
    "directing_traffic_4",
    "jumping_5",
    "running_5",
    "soccer_5",
    "walking_5",
)


class ClipError(ValueError):
    """A clip file or folder could not be used; the message says which and why."""


@dataclass(frozen=True)
class Clip:
    """One recording in the canonical joint set.

    Clip names repeat across split folders (the CMU ``train/walking_1`` and ``test/walking_1`` are different
    recordings), so a clip is identified by :attr:`key`, its split and its name, never by its name alone.

    Attributes:
        name: Clip name (file stem).
        positions: Joint positions (T, J, 3) in metres, z up, at :data:`FPS`.
        action: Action label, or ``""``.
        split: The split (folder below the clip folder, e.g. ``train``, ``test``; ``sim`` for simulated
            operators) it came from, or ``""``.
    """

    name: str
    positions: np.ndarray
    action: str = ""
    split: str = ""

    def __post_init__(self) -> None:
        if self.positions.ndim != 3 or self.positions.shape[1:] != (NUM_JOINTS, 3):
            raise ClipError(
                f"clip {self.name!r}: positions must be (T, {NUM_JOINTS}, 3), got {self.positions.shape}"
            )

    @property
    def frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def key(self) -> tuple[str, str]:
        """``(split, name)``: the clip's identity."""
        return (self.split, self.name)

    @property
    def label(self) -> str:
        """``split/name`` (or the name where there is no split), for reports."""
        return f"{self.split}/{self.name}" if self.split else self.name


def resample(positions: np.ndarray, factor: float) -> np.ndarray:
    """Resample (T, J, 3) in time: output frame k is input time ``k * factor`` (linear interpolation).

    ``factor > 1`` speeds the motion up (fewer frames), ``factor < 1`` slows it down.
    """
    if factor <= 0:
        raise ValueError(f"resample factor must be positive, got {factor}")
    return _at_frames(positions, np.arange(0.0, positions.shape[0] - 1 + 1e-9, factor))


def _at_frames(positions: np.ndarray, src: np.ndarray) -> np.ndarray:
    """Poses (T, J, 3) at fractional frame indices ``src`` (K,): linear between neighbouring frames."""
    T = positions.shape[0]
    i0 = np.clip(np.floor(src).astype(np.int64), 0, T - 1)
    i1 = np.clip(i0 + 1, 0, T - 1)
    w = (src - i0)[:, None, None]
    return positions[i0] * (1.0 - w) + positions[i1] * w


@dataclass(frozen=True)
class ClipFile:
    """A clip file as recorded (:func:`read_clip_file`): canonical joints and when each frame was taken.

    Attributes:
        joints: Joint positions (T, J, 3) in the canonical joint set, metres, z up.
        times: Frame times (T,), seconds from the first frame (strictly increasing, ``times[0] == 0``).
        confidence: Per-joint confidence (T, J) (1 where the file has none).
        rate_hz: The nominal frame rate (the file's ``fps``, the median of its ``t`` steps, or 30).
        uniform: The frames are evenly spaced at :attr:`rate_hz` (not a recording with its own ``t``).
        source: ``"cmu38"`` (converted from the CMU skeleton) or ``"canonical"``.
    """

    joints: np.ndarray
    times: np.ndarray
    confidence: np.ndarray
    rate_hz: float
    uniform: bool
    source: str


#: The most a person's joints span in one frame (m, the largest extent along x, y or z): a clip whose median
#: frame spans more is not in metres (millimetres, most likely).
MAX_BODY_SPAN_M = 4.0


def read_clip_file(path: str | Path, *, fps: float | None = None) -> ClipFile:
    """Read a clip file, the one reader of the formats this project understands:

    - ``positions`` (T, 38, 3) of the shared CMU clips (``joint_names`` the CMU 38-joint skeleton's, or
      none), with ``fps``; converted with :func:`~app.prediction.adapters.from_cmu38`;
    - ``positions`` (T, J, 3) of the canonical joint set (``joint_names == JOINTS``, or none), with ``fps``:
      users' own recordings and ``hrc export --clips``;
    - ``joints`` (T, J, 3) of the canonical joint set with ``t`` (T,) or ``fps``, optional ``confidence``
      (T, J) and ``joint_names``: the app's recordings (:func:`app.cell.human.save_clip`).

    ``fps`` overrides the file's rate (and its ``t``). A file without ``fps`` or ``t`` is taken at 30 Hz.

    Raises:
        ClipError: the file cannot be read, is none of these formats, names another joint set, or holds
            NaN or infinite positions (the message names the file and says what was found).
    """
    p = Path(path)
    pos = t = conf = None
    try:
        with np.load(p, allow_pickle=False) as data:
            keys = set(data.files)
            names = tuple(str(n) for n in data["joint_names"]) if "joint_names" in keys else None
            file_fps = float(data["fps"]) if "fps" in keys else None
            recording = "positions" not in keys and "joints" in keys
            if recording:
                pos = np.asarray(data["joints"], dtype=np.float64)
                t = np.asarray(data["t"], dtype=np.float64) if "t" in keys else None
                conf = np.asarray(data["confidence"], dtype=np.float64) if "confidence" in keys else None
            elif "positions" in keys:
                pos = np.asarray(data["positions"], dtype=np.float64)
    except (OSError, ValueError, KeyError) as exc:
        raise ClipError(f"cannot read clip {p}: {exc}") from exc
    if pos is None:
        raise ClipError(
            f"clip {p} has neither 'positions' (the CMU skeleton (T, 38, 3) or the canonical joints "
            f"(T, {NUM_JOINTS}, 3)) nor 'joints' (a canonical recording); found {sorted(keys)}"
        )
    k = pos.shape[1] if pos.ndim == 3 and pos.shape[2] == 3 else None
    if k == 38 and names in (None, CMU38_NAMES) and not recording:
        joints, source = from_cmu38(pos), "cmu38"
    elif k == NUM_JOINTS and names in (None, JOINTS):
        joints, source = pos, "canonical"
    else:
        named = f"{len(names)} joint_names" if names is not None else "no joint_names"
        raise ClipError(
            f"clip {p}: unknown joint set: {pos.shape} with {named}; expected the CMU skeleton (T, 38, 3) or "
            f"the canonical joints (T, {NUM_JOINTS}, 3) named in joint_names"
        )
    if len(joints) < 1:
        raise ClipError(f"clip {p} has no frames")
    if not np.all(np.isfinite(joints)):
        raise ClipError(f"clip {p}: positions contain NaN or infinite values")
    span_m = float(np.median(np.max(np.ptp(joints, axis=1), axis=-1)))
    if span_m > MAX_BODY_SPAN_M:
        raise ClipError(
            f"clip {p}: a frame's joints span {span_m:.4g} (median), more than a person's "
            f"{MAX_BODY_SPAN_M:g} m: the positions look like millimetres; convert them to metres"
        )
    if conf is None:
        conf = np.ones(joints.shape[:2])
    elif conf.shape != joints.shape[:2]:
        raise ClipError(f"clip {p}: confidence must be (T, {NUM_JOINTS}), got {conf.shape}")
    if t is not None and fps is None:
        if t.shape != (len(joints),) or np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)):
            raise ClipError(f"clip {p}: t must be (T,) finite and strictly increasing")
        rate = 1.0 / float(np.median(np.diff(t))) if len(t) > 1 else FPS
        return ClipFile(joints, t - t[0], conf, rate, False, source)
    rate = float(fps or file_fps or FPS)
    if not (np.isfinite(rate) and rate > 0):
        raise ClipError(f"clip {p}: fps must be a positive number, got {rate}")
    return ClipFile(joints, np.arange(len(joints)) / rate, conf, rate, True, source)


def load_clip(path: str | Path, *, name: str | None = None, action: str = "", split: str = "") -> Clip:
    """Load one ``.npz`` clip (:func:`read_clip_file`) in the canonical joint set at 30 Hz: evenly spaced
    frames at another rate are resampled (:func:`resample`), a recording's own frame times interpolated."""
    path = Path(path)
    f = read_clip_file(path)
    joints = f.joints
    if not f.uniform:  # the 30 Hz instants as fractional indices into the recording's own frame times
        grid = np.arange(0.0, f.times[-1] + 1e-9, 1.0 / FPS)
        joints = _at_frames(joints, np.interp(grid, f.times, np.arange(len(f.times), dtype=np.float64)))
    elif abs(f.rate_hz - FPS) > 1e-6:
        joints = resample(joints, f.rate_hz / FPS)
    return Clip(name=name or path.stem, positions=joints, action=action, split=split)


def load_clip_dir(directory: str | Path, *, split: str | None = None) -> list[Clip]:
    """All clips under ``directory`` (sorted by :attr:`Clip.key`), optionally only those of ``split``
    (train/test).

    With an ``index.json`` (as in the shared CMU folder) its entries are used; otherwise every ``*.npz`` below
    the folder (a split selects the sub-folder of that name when there is one). Each clip's split is the
    folder it lies in below ``directory`` (``""`` at the top).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise ClipError(f"clip folder {directory} does not exist")
    clips: list[Clip] = []
    index = directory / "index.json"
    if index.is_file():
        entries = json.loads(index.read_text())
        for e in entries:
            rel = Path(e["file"])
            if split is not None and rel.parts[0] != split:
                continue
            clips.append(
                load_clip(
                    directory / rel, name=rel.stem, action=str(e.get("action", "")), split=_split_of(rel)
                )
            )
    else:
        root = directory / split if split is not None and (directory / split).is_dir() else directory
        for p in sorted(root.rglob("*.npz")):
            clips.append(load_clip(p, name=p.stem, split=_split_of(p.relative_to(directory))))
    if not clips:
        raise ClipError(f"no clips found in {directory}" + (f" for split {split!r}" if split else ""))
    return sorted(clips, key=lambda c: c.key)


def _split_of(rel: Path) -> str:
    """The split of a clip file at ``rel`` below its clip folder: the folder(s) it lies in."""
    parent = rel.parent.as_posix()
    return "" if parent == "." else parent


def default_cmu_dir() -> Path | None:
    """The shared CMU clips if present: ``$HRC_CMU_DIR`` if set, else ``../shared/data/cmu_mocap``."""
    env = os.environ.get("HRC_CMU_DIR")
    repo = Path(__file__).resolve().parents[2]
    shared = [
        repo.parent / "shared" / "data" / "cmu_mocap",
        Path.cwd().parent / "shared" / "data" / "cmu_mocap",
    ]
    candidates = [Path(env)] if env else shared
    for c in candidates:
        if (c / "index.json").is_file() or (c.is_dir() and any(c.rglob("*.npz"))):
            return c
    return None


def require_cmu_dir(path: str | Path | None) -> Path:
    """``path`` if given, else the shared CMU clips; raises :class:`ClipError` with what to do if absent."""
    if path is not None:
        return Path(path)
    found = default_cmu_dir()
    if found is None:
        raise ClipError(
            "no clip set given and the CMU clips were not found (looked at $HRC_CMU_DIR and "
            "../shared/data/cmu_mocap); pass --clips DIR with .npz clips (positions, fps, joint_names)"
        )
    return found


def split_clips(clips: Sequence[Clip], val_names: Iterable[str]) -> tuple[list[Clip], list[Clip]]:
    """(train, validation): a clip is held out for validation if ``val_names`` names it by ``split/name``
    or, where its name is unique among ``clips``, by its name alone."""
    val_set = set(val_names)
    counts: dict[str, int] = {}
    for c in clips:
        counts[c.name] = counts.get(c.name, 0) + 1
    ambiguous = sorted(n for n in val_set if counts.get(n, 0) > 1)
    if ambiguous:
        raise ClipError(
            f"validation clip name(s) {', '.join(ambiguous)} match clips of several splits; name them as "
            "split/name"
        )

    def held_out(c: Clip) -> bool:
        return c.label in val_set or c.name in val_set

    return [c for c in clips if not held_out(c)], [c for c in clips if held_out(c)]


def check_disjoint(**sets: Sequence[Clip]) -> None:
    """Raise :class:`ClipError` if a clip (by :attr:`Clip.key`) is in two of the named sets, or twice in
    one: training and evaluation never share a clip."""
    seen: dict[tuple[str, str], str] = {}
    for set_name, clips in sets.items():
        for c in clips:
            if c.key in seen:
                raise ClipError(f"clip {c.label} is in {seen[c.key]} and {set_name}: sets must not share it")
            seen[c.key] = set_name


def windows(clips: Sequence[Clip], length: int, *, stride: int = 1) -> np.ndarray:
    """Every window of ``length`` consecutive frames (stride ``stride``): (N, length, J, 3)."""
    out = [c.positions[s : s + length] for c in clips for s in range(0, c.frames - length + 1, stride)]
    if not out:
        return np.zeros((0, length, NUM_JOINTS, 3))
    return np.stack(out)


def rotate_z(x: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotate poses (B, ..., 3) about the world z axis by ``yaw`` (B,) radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((yaw.shape[0], 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    flat = x.reshape(x.shape[0], -1, 3)
    return np.einsum("bij,bnj->bni", R, flat).reshape(x.shape)


def mirror(x: np.ndarray) -> np.ndarray:
    """Mirror poses (..., J, 3) across the world x-z plane and swap left and right joints."""
    y = x[..., MIRROR_PERMUTATION, :].copy()
    y[..., 1] = -y[..., 1]
    return y


@dataclass(frozen=True)
class Augmentation:
    """Random augmentation of training windows.

    Besides the usual geometric ones, two stand for the motion of a work cell that sports clips lack:
    slow arm work (a window played at ``slow_speed``) and pauses (the person comes to rest for a while
    inside the window, then moves on). Each window is either of them, or neither.

    Attributes:
        rotate: Rotate about the vertical by a uniform angle in [-pi, pi).
        translate_m: Uniform horizontal shift in [-translate_m, translate_m] (m) per axis.
        mirror_p: Probability of mirroring (x-z plane, left and right swapped).
        speed: Range of the playback speed factor (resampled by linear interpolation).
        noise_m: Standard deviation of Gaussian noise (m) added to the observed frames only.
        slow_p: Probability that a window is slow work: its speed factor drawn from ``slow_speed`` instead.
        slow_speed: Range of the slow-work speed factor.
        pause_p: Probability that a window holds a pause: the playback slows to rest over ``PAUSE_RAMP``
            frames at a uniform frame of the window, rests for a uniform ``pause_frames`` frames (those past
            the window's end cut) and speeds up again the same way.
        pause_frames: Range of the pause's length (frames at rest).
    """

    rotate: bool = True
    translate_m: float = 2.0
    mirror_p: float = 0.5
    speed: tuple[float, float] = (0.8, 1.25)
    noise_m: float = 0.0
    slow_p: float = 0.15
    slow_speed: tuple[float, float] = (0.3, 0.8)
    pause_p: float = 0.15
    pause_frames: tuple[int, int] = (3, 30)


#: Frames over which a pause of :class:`Augmentation` brings the playback to rest (and back), with a cosine
#: profile: at 30 Hz 0.13 s, so a joint at 1 m/s stops at up to 9.3 m/s^2, within the 12 m/s^2 a person's
#: speed may change by (the governor's bound, measured on the CMU clips).
PAUSE_RAMP = 4


def _playback_rates(rng: np.random.Generator, length: int, aug: Augmentation | None) -> np.ndarray:
    """Clip frames advanced per window frame (``length - 1`` steps): the window's time warp."""
    if aug is None:
        return np.ones(length - 1)
    kind = rng.random()
    if kind < aug.slow_p:
        return np.full(length - 1, rng.uniform(*aug.slow_speed))
    speed = rng.uniform(*aug.speed)
    rates = np.full(length - 1, speed)
    if kind < aug.slow_p + aug.pause_p:
        at = int(rng.integers(0, length - 1))
        rest = int(rng.integers(aug.pause_frames[0], aug.pause_frames[1] + 1))
        ramp = 0.5 * (1.0 + np.cos(np.pi * np.arange(1, PAUSE_RAMP + 1) / (PAUSE_RAMP + 1)))
        profile = np.concatenate([ramp, np.zeros(rest), ramp[::-1]])
        end = min(length - 1, at + profile.size)
        rates[at:end] *= profile[: end - at]
    return rates


class WindowSampler:
    """Draws augmented training windows (B, t_in + horizon, J, 3) from clips, seeded.

    Args:
        clips: Training clips (each at least long enough for one window at the fastest speed).
        length: Frames per window (observed + predicted).
        augmentation: What to randomise; ``None`` draws plain windows.
        seed: Seed of the sampler's generator.
    """

    def __init__(
        self, clips: Sequence[Clip], length: int, *, augmentation: Augmentation | None = None, seed: int = 0
    ) -> None:
        self.length = length
        self.aug = augmentation
        self.rng = np.random.default_rng(seed)
        max_speed = max(augmentation.speed[1], augmentation.slow_speed[1]) if augmentation else 1.0
        need = int(np.ceil((length - 1) * max_speed)) + 2
        self.clips = [c for c in clips if c.frames >= need]
        if not self.clips:
            raise ClipError(f"no clip has the {need} frames one training window needs")
        weights = np.array([c.frames - need + 1 for c in self.clips], dtype=np.float64)
        self.p = weights / weights.sum()

    def sample(self, batch: int) -> np.ndarray:
        """A batch (B, length, J, 3) of windows, world frame, metres."""
        out = np.empty((batch, self.length, NUM_JOINTS, 3))
        aug = self.aug
        idx = self.rng.choice(len(self.clips), size=batch, p=self.p)
        for b, ci in enumerate(idx):
            pos = self.clips[ci].positions
            steps = np.concatenate([[0.0], np.cumsum(_playback_rates(self.rng, self.length, aug))])
            start = self.rng.uniform(0.0, pos.shape[0] - 1 - steps[-1])
            t = start + steps
            i0 = np.minimum(np.floor(t).astype(np.int64), pos.shape[0] - 2)
            w = (t - i0)[:, None, None]
            out[b] = pos[i0] * (1.0 - w) + pos[i0 + 1] * w
        if aug is None:
            return out
        if aug.mirror_p > 0:
            m = self.rng.random(batch) < aug.mirror_p
            out[m] = mirror(out[m])
        if aug.rotate:
            out = rotate_z(out, self.rng.uniform(-np.pi, np.pi, size=batch))
        if aug.translate_m > 0:
            shift = self.rng.uniform(-aug.translate_m, aug.translate_m, size=(batch, 1, 1, 3))
            shift[..., 2] = 0.0
            out = out + shift
        return out
