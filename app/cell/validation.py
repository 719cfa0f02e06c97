"""Frame validation in front of every human source, and the stale-stream watchdog.

A frame holds every body the tracker reported (:class:`~app.prediction.skeleton.HumanFrame`); each body is
checked on its own, and a rejection names the body's id (one bad body rejects the capture: the cell is never
shown with a person left out). A frame with no body is a valid, person-free capture: the stream is alive and
the cell empty. Per body id the validator keeps the body's last pose (:class:`BodyTracks`): a body that moved
faster than a person can since the same id's previous pose *jumped* (reported in :attr:`BodyChanges.jumps`,
not rejected: the decision layer treats it as an intrusion); a new id is no jump, and an id that vanished
drops its state.

A frame is validated once, before anything uses it, and rejected (and counted, by reason) when its
timestamp, joints or confidences are not numbers (strings and booleans included), when it has non-finite
values, a timestamp out of range, the wrong joint count, a confidence outside [0, 1], no joint seen with at
least :data:`~app.prediction.skeleton.MIN_JOINT_CONFIDENCE`, a timestamp that is not after the previous
accepted one (duplicate or backwards), or a joint outside the cell volume. Nothing is clipped or coerced: a
value is valid as sent or the frame is rejected. :class:`StaleWatchdog` reports when no valid frame came for
longer than its timeout (100 ms by default), so that the supervisor can stop the robot.
:class:`ValidatedSource` puts both in front of any :class:`~app.cell.source.HumanSource`.
"""

from __future__ import annotations

import math
import numbers
import reprlib
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from app.cell.source import HumanSource
from app.prediction.skeleton import MIN_JOINT_CONFIDENCE, NUM_JOINTS, HumanFrame
from app.safety.monitor import is_intrusion

if TYPE_CHECKING:
    from app.config import WorkCell

__all__ = [
    "MAX_ABS_TIME_S",
    "REJECT_REASONS",
    "BodyChanges",
    "BodyTracks",
    "CellVolume",
    "FrameRejected",
    "FrameValidator",
    "StaleWatchdog",
    "ValidatedSource",
    "checked_timestamp",
    "is_number",
    "short_repr",
]

#: Why a frame can be rejected (the keys of the rejection counters).
REJECT_REASONS: tuple[str, ...] = (
    "non_finite",  # NaN or inf in the timestamp, joints or confidences
    "bad_timestamp",  # a timestamp that is not a number of seconds, or beyond MAX_ABS_TIME_S
    "joint_count",  # not (B*J, 3) joints / (B*J,) confidences for B bodies
    "duplicate_timestamp",  # same time as the previous accepted frame
    "backwards_timestamp",  # earlier than the previous accepted frame
    "out_of_range",  # a joint outside the cell volume
    "bad_confidence",  # confidence outside [0, 1]
    "no_valid_joint",  # no joint seen with at least MIN_JOINT_CONFIDENCE
    "wrong_units",  # a stream message whose joints cannot be in the units it names (metres sent as "mm")
    "malformed",  # a stream message that cannot be parsed
    "unknown_format",  # a stream message with an unknown joint format or frame
    "missing_joints",  # too many joints not seen (null) in a stream message
    "no_camera_pose",  # a camera-frame message but no camera pose configured
)

#: The largest timestamp (s) taken, either side of zero: a sender's clock may count from its boot or from
#: 1970 (1.7e9 s), not from beyond 2286; larger values lose the frame's time to rounding (1e308 - 1e308 = 0).
MAX_ABS_TIME_S = 1e10


def _make_short_repr() -> reprlib.Repr:
    r = reprlib.Repr()
    r.maxlevel, r.maxlist, r.maxtuple, r.maxdict, r.maxstring, r.maxother = 3, 4, 4, 4, 30, 30
    r.maxlong = 30
    return r


#: A short repr of any value for a rejection's detail (nesting, lengths and big integers bounded: a message of
#: 20,000 nested lists or an integer of 400 digits is shown in a few characters, without recursion).
short_repr = _make_short_repr().repr


def is_number(v: object) -> bool:
    """A real number of Python or numpy, not a boolean (``True`` is not 1 m, nor a confidence of 1)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool | np.bool_)


def _numbers(value: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    """``value`` as a float array of ``shape``, element by element: numbers only (no strings, booleans,
    None or nested objects), each within a float.

    Raises:
        FrameRejected: ``malformed`` (not numbers), ``joint_count`` (another shape), ``out_of_range`` (an
            integer too large for a float). Not counted: the caller counts.
    """
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "fiu":
            raise FrameRejected("malformed", f"{what} must be numbers, got an array of {value.dtype}")
        if value.shape != shape:
            raise FrameRejected("joint_count", f"{what} must be {shape}, got {value.shape}")
        return value.astype(np.float64)
    out = np.empty(shape, dtype=np.float64)
    rows = [value] if len(shape) == 1 else value
    if not isinstance(rows, list | tuple) or (len(shape) == 2 and len(rows) != shape[0]):
        n = len(rows) if isinstance(rows, list | tuple) else short_repr(rows)
        raise FrameRejected("joint_count", f"{what} must be {shape} numbers, got {n} rows")
    flat = out.reshape(len(rows), shape[1]) if len(shape) == 2 else out.reshape(1, -1)
    for i, row in enumerate(rows):
        if not isinstance(row, list | tuple | np.ndarray) or len(row) != flat.shape[1]:
            raise FrameRejected("joint_count", f"{what} must be {shape}, got {short_repr(row)} at row {i}")
        for k, v in enumerate(row):
            if not is_number(v):
                raise FrameRejected("malformed", f"{what} must be numbers, got {short_repr(v)}")
            try:
                flat[i, k] = float(v)
            except OverflowError:
                raise FrameRejected("out_of_range", f"{what}: {short_repr(v)} is too large") from None
    return out


def checked_timestamp(t: Any) -> float:
    """``t`` as seconds, checked (see :data:`MAX_ABS_TIME_S`); raises an uncounted :class:`FrameRejected`."""
    if not is_number(t):
        raise FrameRejected("bad_timestamp", f"t must be a number of seconds, got {short_repr(t)}")
    try:
        value = float(t)
    except OverflowError:
        raise FrameRejected("bad_timestamp", f"t = {short_repr(t)} is beyond {MAX_ABS_TIME_S:g} s") from None
    if not math.isfinite(value):
        raise FrameRejected("non_finite", f"timestamp {value}")
    if abs(value) > MAX_ABS_TIME_S:
        raise FrameRejected("bad_timestamp", f"t = {value:g} s is beyond {MAX_ABS_TIME_S:g} s")
    return value


class FrameRejected(ValueError):  # noqa: N818 (the contract's name)
    """A human frame was rejected.

    Attributes:
        reason: One of :data:`REJECT_REASONS`.
        detail: What exactly was wrong.
    """

    def __init__(self, reason: str, detail: str = "") -> None:
        if reason not in REJECT_REASONS:
            raise ValueError(f"unknown rejection reason {reason!r}; expected one of {REJECT_REASONS}")
        self.reason = reason
        self.detail = detail
        super().__init__(f"frame rejected ({reason}){': ' + detail if detail else ''}")


@dataclass(frozen=True)
class CellVolume:
    """An axis-aligned box (world frame, metres) that every tracked joint must lie in.

    Attributes:
        lo: Lower corner (3,).
        hi: Upper corner (3,).
    """

    lo: np.ndarray
    hi: np.ndarray

    def __post_init__(self) -> None:
        lo = np.array(self.lo, dtype=np.float64).reshape(-1)
        hi = np.array(self.hi, dtype=np.float64).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(lo < hi):
            raise ValueError(f"CellVolume needs lo (3,) < hi (3,), got {self.lo} and {self.hi}")
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    @classmethod
    def from_workcell(cls, cell: WorkCell, *, margin_m: float = 1.0, height_m: float = 2.5) -> CellVolume:
        """The box around the table, the static scene and the operator area, grown by ``margin_m`` in x and
        y; z from 0.3 m below the floor to ``height_m`` above it."""
        corners = []
        for box in cell.static_boxes:
            c, h = np.asarray(box.center), np.asarray(box.size) / 2
            r = math.hypot(h[0], h[1])  # covers any yaw
            ext = np.array([r, r, h[2]])
            corners += [c - ext, c + ext]
        op = cell.operator
        oc, oh = np.asarray(op.center_xy), np.asarray(op.size_xy) / 2
        corners += [[*(oc - oh), op.floor_z], [*(oc + oh), op.floor_z]]
        pts = np.asarray(corners, dtype=float)
        grow = np.array([margin_m, margin_m, 0.0])
        lo = pts.min(axis=0) - grow
        hi = pts.max(axis=0) + grow
        lo[2] = op.floor_z - 0.3
        hi[2] = op.floor_z + height_m
        return cls(lo=lo, hi=hi)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which points (..., 3) lie inside, shape (...)."""
        p = np.asarray(points, dtype=float)
        return np.all((p >= self.lo) & (p <= self.hi), axis=-1)


@dataclass(frozen=True, slots=True)
class BodyChanges:
    """How the bodies of a frame relate to those of the frame before (matched by tracker id).

    Attributes:
        jumps: The ids whose body moved faster than a person can since the same id's previous pose, with
            the fastest joint's speed (m/s) (:func:`app.safety.monitor.is_intrusion`).
        appeared: Ids not in the frame before (a new id is no jump).
        vanished: Ids of the frame before that this frame lacks (their state is dropped).
    """

    jumps: dict[int, float] = field(default_factory=dict)
    appeared: tuple[int, ...] = ()
    vanished: tuple[int, ...] = ()


class BodyTracks:
    """The last pose of each tracked body, keyed by its tracker id, and the jump check against it.

    Args:
        jump_speed_mps: A body whose median joint moved faster than this since the same id's previous pose,
            or any joint faster than twice this, jumped (``None``: no jump check).
    """

    def __init__(self, jump_speed_mps: float | None = 5.0) -> None:
        if jump_speed_mps is not None and not jump_speed_mps > 0:
            raise ValueError(f"jump_speed_mps must be > 0 or None, got {jump_speed_mps}")
        self.jump_speed_mps = jump_speed_mps
        self._last: dict[int, tuple[float, np.ndarray]] = {}
        self.jumps = 0

    def pose(self, body_id: int) -> np.ndarray | None:
        """The last pose (J, 3) of ``body_id``, or None (a new id)."""
        last = self._last.get(int(body_id))
        return None if last is None else last[1]

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(self._last)

    def update(self, frame: HumanFrame) -> BodyChanges:
        """Take ``frame`` as every body's newest pose; returns what changed against the frame before."""
        jumps: dict[int, float] = {}
        appeared: list[int] = []
        now: dict[int, tuple[float, np.ndarray]] = {}
        for k, bid in enumerate(frame.body_ids):
            joints = frame.joints[k * NUM_JOINTS : (k + 1) * NUM_JOINTS]
            prev = self._last.get(bid)
            if prev is None:
                appeared.append(bid)
            elif self.jump_speed_mps is not None and frame.t > prev[0]:
                speeds = np.linalg.norm(joints - prev[1], axis=1) / (frame.t - prev[0])
                if is_intrusion(speeds, body_mps=self.jump_speed_mps):
                    jumps[bid] = float(speeds.max())
            now[bid] = (frame.t, joints)
        vanished = tuple(i for i in self._last if i not in now)
        self._last = now
        self.jumps += len(jumps)
        return BodyChanges(jumps=jumps, appeared=tuple(appeared), vanished=vanished)

    def reset(self) -> None:
        self._last = {}
        self.jumps = 0


def _body_ids(body_ids: Any) -> tuple[int, ...]:
    """Tracker ids as sent: integers >= 0 (not booleans), distinct."""
    if not isinstance(body_ids, list | tuple):
        raise FrameRejected("malformed", f"body ids must be a list of integers, got {short_repr(body_ids)}")
    out: list[int] = []
    for k, i in enumerate(body_ids):
        if not isinstance(i, numbers.Integral) or isinstance(i, bool | np.bool_) or i < 0:
            raise FrameRejected("malformed", f"body {k}: id must be an integer >= 0, got {short_repr(i)}")
        if int(i) in out:
            raise FrameRejected("malformed", f"body {k}: id {int(i)} is repeated; ids must differ")
        out.append(int(i))
    return tuple(out)


class FrameValidator:
    """Checks frames before anything else sees them; counts what it accepts and rejects (thread-safe).

    Every body of a frame is checked; a rejection names the body's id. The last pose of each id is kept
    (:attr:`tracks`): :attr:`last_changes` says which bodies of the last accepted frame jumped, appeared or
    vanished.

    Args:
        volume: Every joint must lie in this box (``None``: no range check).
        num_joints: Expected joint count per body (the canonical skeleton by default).
        jump_speed_mps: See :class:`BodyTracks`.
    """

    def __init__(
        self,
        *,
        volume: CellVolume | None = None,
        num_joints: int = NUM_JOINTS,
        jump_speed_mps: float | None = 5.0,
    ) -> None:
        self.volume = volume
        self.num_joints = int(num_joints)
        self.tracks = BodyTracks(jump_speed_mps)
        self.last_changes = BodyChanges()
        self._lock = threading.Lock()
        self._last_t: float | None = None
        self._accepted = 0
        self._rejected = dict.fromkeys(REJECT_REASONS, 0)

    @classmethod
    def for_workcell(
        cls, cell: WorkCell, *, margin_m: float = 1.0, jump_speed_mps: float | None = 5.0
    ) -> FrameValidator:
        """A validator whose volume is :meth:`CellVolume.from_workcell`."""
        return cls(volume=CellVolume.from_workcell(cell, margin_m=margin_m), jump_speed_mps=jump_speed_mps)

    # -- checks -----------------------------------------------------------------------------------------
    def reject(self, reason: str, detail: str = "") -> FrameRejected:
        """Count a rejection decided elsewhere (e.g. a stream parser) and return the exception to raise."""
        exc = FrameRejected(reason, detail)
        with self._lock:
            self._rejected[reason] += 1
        return exc

    def validate(self, t: Any, joints: Any, confidence: Any = None, body_ids: Any = None) -> HumanFrame:
        """Check raw values and build the frame; every input gives a frame or a counted rejection.

        Args:
            t: Timestamp (s, runtime clock): a number (not a boolean) within :data:`MAX_ABS_TIME_S`.
            joints: Joint positions, expected (B*J, 3) numbers, metres, world frame, body after body.
            confidence: Per-joint confidence (B*J,) numbers in [0, 1]; ``None`` means all ones.
            body_ids: The tracker's id of each body (B,), distinct integers >= 0; ``None``: one body, id 0.
                An empty list is a frame with nobody in view (valid).

        Raises:
            FrameRejected: with the reason (counted); a body's fault names its id.
        """
        try:
            return self._validate(t, joints, confidence, body_ids)
        except FrameRejected as exc:
            with self._lock:
                self._rejected[exc.reason] += 1
            raise

    def _validate(self, t: Any, joints: Any, confidence: Any, body_ids: Any) -> HumanFrame:
        J = self.num_joints
        ids = (0,) if body_ids is None else _body_ids(body_ids)
        n = len(ids) * J
        what = "joints" if body_ids is None else f"joints of {len(ids)} bodies"
        j = _numbers(joints, (n, 3), what)
        c = np.ones(n) if confidence is None else _numbers(confidence, (n,), f"confidence{what[6:]}")
        t = checked_timestamp(t)
        for k, bid in enumerate(ids):
            rows = slice(k * J, (k + 1) * J)
            try:
                self._check_body(j[rows], c[rows])
            except FrameRejected as exc:
                raise FrameRejected(exc.reason, f"body {bid}: {exc.detail}") from None
        with self._lock:
            last = self._last_t
            if last is not None and t == last:
                raise FrameRejected("duplicate_timestamp", f"t={t} equals the previous frame's")
            if last is not None and t < last:
                raise FrameRejected(
                    "backwards_timestamp", f"t={t} is {last - t:.3f} s before the previous frame's"
                )
            self._last_t = t
            self._accepted += 1
            frame = HumanFrame(t=t, joints=j, confidence=c, body_ids=ids)
            self.last_changes = self.tracks.update(frame)
        return frame

    def _check_body(self, j: np.ndarray, c: np.ndarray) -> None:
        """One body's joints (J, 3) and confidences (J,)."""
        if not np.all(np.isfinite(j)):
            bad = np.unique(np.nonzero(~np.isfinite(j))[0]).tolist()
            raise FrameRejected("non_finite", f"joints {bad} are NaN or infinite")
        if not np.all(np.isfinite(c)):
            raise FrameRejected("non_finite", "confidence has NaN or inf")
        if np.any((c < 0) | (c > 1)):
            raise FrameRejected(
                "bad_confidence", f"confidence must be within [0, 1], got {c.min()}..{c.max()}"
            )
        if not np.any(c >= MIN_JOINT_CONFIDENCE):
            raise FrameRejected(
                "no_valid_joint",
                f"no joint is seen with a confidence of {MIN_JOINT_CONFIDENCE} or more (highest "
                f"{c.max():g}): nothing to track yet",
            )
        if self.volume is not None:
            inside = self.volume.contains(j)
            if not np.all(inside):
                k = int(np.argmin(inside))
                raise FrameRejected(
                    "out_of_range",
                    f"joint {k} at {np.round(j[k], 3).tolist()} is outside the cell volume "
                    f"{self.volume.lo.tolist()}..{self.volume.hi.tolist()}",
                )

    def check(self, frame: HumanFrame) -> HumanFrame:
        """Check a built frame (same rules as :meth:`validate`); returns it when valid.

        Raises:
            FrameRejected: with the reason (counted).
        """
        return self.validate(frame.t, frame.joints, frame.confidence, frame.body_ids)

    # -- counters ---------------------------------------------------------------------------------------
    @property
    def accepted(self) -> int:
        return self._accepted

    @property
    def rejected(self) -> int:
        with self._lock:
            return sum(self._rejected.values())

    @property
    def counters(self) -> dict[str, int]:
        """``{"accepted": n, "rejected": n, "rejected_<reason>": n, ...}`` (every reason, zeros included)."""
        with self._lock:
            out = {"accepted": self._accepted, "rejected": sum(self._rejected.values())}
            out.update({f"rejected_{k}": v for k, v in self._rejected.items()})
            return out

    def reset_counters(self) -> None:
        """Zero the counters and keep the last timestamp (a new trial on the same stream)."""
        with self._lock:
            self._accepted = 0
            self._rejected = dict.fromkeys(REJECT_REASONS, 0)

    @property
    def last_t(self) -> float | None:
        """Timestamp of the last accepted frame."""
        return self._last_t

    def reset(self) -> None:
        """Forget the last timestamp and the bodies' poses and zero the counters (a new trial, a new
        stream)."""
        with self._lock:
            self._last_t = None
            self.tracks.reset()
            self.last_changes = BodyChanges()
            self._accepted = 0
            self._rejected = dict.fromkeys(REJECT_REASONS, 0)


class StaleWatchdog:
    """Reports "no valid frame for more than ``timeout_s``" (the supervisor then stops the robot).

    Feed it the time (runtime clock) at which each valid frame arrived. Before the first frame the stream
    counts as stale.

    Args:
        timeout_s: Longest allowed gap (s) between valid frames.
    """

    def __init__(self, timeout_s: float = 0.1) -> None:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        self._last: float | None = None
        self._stale_reported = True
        self.stale_events = 0

    def feed(self, t: float) -> None:
        """A valid frame arrived at time ``t`` (s)."""
        if self._last is None or t > self._last:
            self._last = float(t)

    def age(self, now: float) -> float:
        """Seconds since the last valid frame (``inf`` before the first)."""
        return math.inf if self._last is None else max(0.0, now - self._last)

    def expect_from(self, t: float) -> None:
        """Frames are expected from ``t`` on (a trial starts): a watchdog that has seen no frame yet counts
        the timeout from ``t`` (the first frame of a tracker arrives after its latency), not as stale at
        once. One that has seen frames keeps counting from the last."""
        if self._last is None:
            self._last = float(t)
            self._stale_reported = False

    def is_stale(self, now: float) -> bool:
        """True when no valid frame arrived within ``timeout_s`` before ``now``."""
        return self.age(now) > self.timeout_s + 1e-9  # tolerance for float time arithmetic

    def poll(self, now: float) -> Literal["stale", "resumed"] | None:
        """Edge detector: ``"stale"`` once when the stream goes stale, ``"resumed"`` once when it recovers."""
        stale = self.is_stale(now)
        if stale and not self._stale_reported:
            self._stale_reported = True
            self.stale_events += 1
            return "stale"
        if not stale and self._stale_reported:
            self._stale_reported = False
            return "resumed"
        return None

    def reset(self) -> None:
        self._last = None
        self._stale_reported = True


class ValidatedSource:
    """A human source behind a :class:`FrameValidator` and a :class:`StaleWatchdog`.

    :meth:`frame_at` returns the newest *valid* frame at or before ``t``; each distinct frame of the inner
    source is checked once (asking again for the same frame is not a duplicate). A source with
    ``validates_frames = True`` (the stream source, which validates every pushed message) is not checked
    again: its frames only feed the watchdog, and :attr:`counters` are its own. :meth:`poll` is the
    runtime's per-tick call: it returns a frame only when a new valid one arrived, and :attr:`last_changes`
    says which of its bodies jumped, appeared or vanished since the frame it returned before (matched by
    tracker id, :class:`BodyTracks`).

    Args:
        source: The inner source.
        validator: Frame checks (default: no range check).
        watchdog: Stale detection (default 100 ms).
    """

    def __init__(
        self,
        source: HumanSource,
        *,
        validator: FrameValidator | None = None,
        watchdog: StaleWatchdog | None = None,
    ) -> None:
        self.source = source
        self.validator = validator if validator is not None else FrameValidator()
        self.watchdog = watchdog if watchdog is not None else StaleWatchdog()
        # A source that validates its own frames (StreamSource: it must answer the sender) is not checked
        # twice; its counters are reported instead.
        self._prevalidated = bool(getattr(source, "validates_frames", False))
        self._seen: HumanFrame | None = None
        self._valid: HumanFrame | None = None
        self.last_rejection: FrameRejected | None = None
        self.tracks = BodyTracks(self.validator.tracks.jump_speed_mps)
        self.last_changes = BodyChanges()
        #: When the inner source handed over its newest frame (``time.perf_counter()``): where the frame's
        #: time in the software starts (a tracker's frame received; the simulated person's frame made).
        self.handed_over = time.perf_counter()
        self._lock = threading.Lock()

    def frame_at(self, t: float) -> HumanFrame | None:
        with self._lock:
            frame = self.source.frame_at(t)
            if frame is not None and frame is not self._seen:
                self.handed_over = time.perf_counter()
                self._seen = frame
                self._accept(frame, t)
            valid = self._valid
        if valid is not None and valid.t > t:
            return None
        return valid

    def _accept(self, frame: HumanFrame, now: float) -> None:
        if (
            self._valid is not None
            and frame.t == self._valid.t
            and frame.body_ids == self._valid.body_ids
            and np.array_equal(frame.joints, self._valid.joints)
        ):
            return  # the same frame, rebuilt by the inner source: not a new one
        if self._prevalidated:
            self._valid = frame
            self.watchdog.feed(max(now, frame.t))
            self.last_changes = self.tracks.update(frame)
        else:
            try:
                self._valid = self.validator.check(frame)
                self.watchdog.feed(max(now, frame.t) if math.isfinite(frame.t) else now)
            except FrameRejected as exc:
                self.last_rejection = exc
                return
            # the validator has matched the bodies to those of the frame it accepted before: this one
            self.last_changes = self.validator.last_changes

    def poll(self, now: float) -> HumanFrame | None:
        """The newest valid frame if it is new since the previous :meth:`poll`, else ``None``."""
        before = self._valid
        frame = self.frame_at(now)
        return frame if frame is not None and frame is not before else None

    def is_stale(self, now: float) -> bool:
        return self.watchdog.is_stale(now)

    def expect_frames_from(self, t: float) -> None:
        """A trial starts at ``t``: before its first frame the stream is stale only after the watchdog's
        timeout (:meth:`StaleWatchdog.expect_from`)."""
        self.watchdog.expect_from(t)

    def notify_block_placed(self, station: str, t: float) -> None:
        """Forwarded to the inner source (the simulated operator reacts to it; others ignore it)."""
        notify = getattr(self.source, "notify_block_placed", None)
        if notify is not None:
            notify(station, t)

    def reset_counters(self) -> None:
        """Zero the validation counters (also a self-validating source's), keeping the last timestamps: a
        new trial on the same source counts its own rejections."""
        if self._prevalidated:
            reset = getattr(self.source, "reset_counters", None)
            if reset is not None:
                reset()
            return
        self.validator.reset_counters()

    @property
    def counters(self) -> dict[str, int]:
        """The validation counters (those of a self-validating source such as the stream source)."""
        if self._prevalidated:
            return dict(self.source.counters)  # type: ignore[attr-defined]
        return self.validator.counters
