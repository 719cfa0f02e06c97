"""Trial recording for the server: the runtime's listeners -> the study database, off the control thread.

Per trial started over the API, :meth:`TrialRecorder.begin` opens a batched ``EventWriter`` (flushed at least
once a second by its own thread). The runtime's event listener only appends to that writer's bounded buffer;
its trial listener only puts the result into a bounded queue. One recorder thread then closes the writer and
stores the metrics and the remaining events (``finish_trial``), so a slow database never blocks the runtime.

While a trial runs, the same thread checkpoints it every ``checkpoint_period_s`` (0.5 s): it asks the runtime
for the metrics so far and the frames recorded since the last checkpoint (``checkpoint_of``), flushes the
trial's events and stores both (``checkpoint_trial``). A server killed mid-trial thus loses at most the last
half second or so: at the next start the trial is aborted and ends at its last checkpoint.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from app.control.metrics import TrialEvent, TrialMetrics
from app.study.repository import RecordedFrames, StudyRepository, TrialStateError

logger = logging.getLogger(__name__)

#: Runtime trial statuses stored as they are; anything else ends the trial as ``aborted`` with that reason.
STORED_STATUSES = ("completed", "aborted")
#: Wall-clock seconds between two checkpoints of a running trial (the trial runs on the wall clock).
CHECKPOINT_PERIOD_S = 0.5


@dataclass(frozen=True, slots=True)
class Checkpoint:
    """A running trial's progress as ``checkpoint_of`` returns it.

    Attributes:
        metrics: The metrics so far.
        frames: The frames recorded from index ``first_frame`` on (None: none since).
        first_frame: Index of the first of ``frames`` among the trial's recorded frames.
    """

    metrics: TrialMetrics
    frames: RecordedFrames | None
    first_frame: int


@dataclass(frozen=True, slots=True)
class _TrialEnd:
    trial_id: int
    metrics: TrialMetrics
    events: tuple[TrialEvent, ...]
    status: str
    reason: str | None
    frames: RecordedFrames | None = None


def end_reason(events: Sequence[TrialEvent]) -> str | None:
    """Why a trial ended, from its ``trial_ended`` event (payload ``reason``), or None."""
    for ev in reversed(events):
        if getattr(ev, "kind", None) == "trial_ended":
            reason = (getattr(ev, "payload", None) or {}).get("reason")
            return None if reason is None else str(reason)
    return None


class TrialRecorder:
    """Writes the events and results of live trials into a ``StudyRepository``.

    Args:
        repo: The repository (``event_writer``, ``finish_trial``).
        frames_of: ``frames_of(metrics)`` -> the recorded frames (``RecordedFrames``) of the trial that
            produced ``metrics``, or None; they are stored with the trial for replay.
        checkpoint_of: ``checkpoint_of(trial_id, first_frame)`` -> the running trial's :class:`Checkpoint`
            (frames from ``first_frame`` on), or None when that trial does not run; None: no checkpoints.
        checkpoint_period_s: Seconds between two checkpoints of a running trial.
        queue_size: Bound of the queue of ended trials waiting to be stored.
        put_timeout_s: Longest a trial listener waits when that queue is full (then the result is logged and
            dropped; the trial is marked aborted at the next start).
    """

    def __init__(
        self,
        repo: StudyRepository,
        *,
        frames_of: Callable[[TrialMetrics], RecordedFrames | None] | None = None,
        checkpoint_of: Callable[[int, int], Checkpoint | None] | None = None,
        checkpoint_period_s: float = CHECKPOINT_PERIOD_S,
        queue_size: int = 64,
        put_timeout_s: float = 1.0,
    ) -> None:
        if not checkpoint_period_s > 0:
            raise ValueError(f"checkpoint_period_s must be > 0, got {checkpoint_period_s}")
        self._repo = repo
        self._frames_of = frames_of
        self._checkpoint_of = checkpoint_of
        self._checkpoint_period_s = float(checkpoint_period_s)
        self._current: int | None = None  # the trial begun last (one runs at a time)
        self._frames_stored: dict[int, int] = {}
        self._queue: queue.Queue[_TrialEnd | None] = queue.Queue(maxsize=queue_size)
        self._put_timeout_s = put_timeout_s
        self._lock = threading.Lock()
        self._writers: dict[int, Any] = {}
        self._live_counts: dict[int, int] = {}
        self._done: dict[int, threading.Event] = {}
        self._thread: threading.Thread | None = None
        self.stored = 0
        self.failed = 0
        self.checkpoints = 0

    # ---- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="hrc-trial-recorder", daemon=True)
            self._thread.start()

    def close(self, *, timeout_s: float = 10.0) -> None:
        """Store every queued result, close open event writers and stop the thread (bounded wait)."""
        if self._thread is not None:
            try:
                self._queue.put(None, timeout=timeout_s)
            except queue.Full:
                logger.error("trial recorder queue stayed full for %.1f s at shutdown", timeout_s)
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                logger.error("trial recorder did not finish within %.1f s", timeout_s)
            self._thread = None
        with self._lock:
            writers = list(self._writers.items())
            self._writers.clear()
        for trial_id, writer in writers:
            # A trial still open here never reported its end: keep its events; the next start aborts it.
            with contextlib.suppress(Exception):
                writer.close()
            logger.warning("trial %d had not ended at shutdown; its events up to now are stored", trial_id)

    # ---- trial life ---------------------------------------------------------------------------------
    def begin(self, trial_id: int) -> None:
        """Open the event writer of a trial (before the runtime starts it)."""
        writer = self._repo.event_writer(trial_id)
        with self._lock:
            self._writers[trial_id] = writer
            self._live_counts[trial_id] = 0
            self._done[trial_id] = threading.Event()
            self._current = trial_id
            self._frames_stored[trial_id] = 0

    def abandon(self, trial_id: int, reason: str) -> None:
        """A trial that never started: close its writer and store it as aborted (synchronously)."""
        self._store(_TrialEnd(trial_id, None, (), "aborted", reason))

    def wait_stored(self, trial_id: int, timeout_s: float) -> bool:
        """Wait until the end of ``trial_id`` is stored (True) or ``timeout_s`` passes (False)."""
        with self._lock:
            done = self._done.get(trial_id)
        return True if done is None else done.wait(timeout_s)

    # ---- runtime listeners (called on runtime threads: must not block) --------------------------------
    def on_event(self, trial_id: int | None, event: TrialEvent) -> None:
        if trial_id is None:
            return
        with self._lock:
            writer = self._writers.get(trial_id)
            if writer is None:
                return
            self._live_counts[trial_id] += 1
        try:
            writer.write(event)
        except Exception:
            logger.exception("trial %s: an event could not be queued for the database", trial_id)

    def on_trial_end(
        self, trial_id: int, metrics: TrialMetrics, events: Sequence[TrialEvent], status: str
    ) -> None:
        events = tuple(events or ())
        stored_status = status if status in STORED_STATUSES else "aborted"
        reason = end_reason(events) if status in STORED_STATUSES else str(status)
        frames = None
        if self._frames_of is not None:
            try:
                frames = self._frames_of(metrics)
            except Exception:
                logger.exception("trial %d: its recorded frames could not be taken; stored without", trial_id)
        item = _TrialEnd(trial_id, metrics, events, stored_status, reason, frames)
        try:
            self._queue.put(item, timeout=self._put_timeout_s)
        except queue.Full:
            self.failed += 1
            logger.error("trial %d ended but the recorder queue is full; its result is not stored", trial_id)

    # ---- recorder thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        next_checkpoint = time.monotonic() + self._checkpoint_period_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, min(0.5, next_checkpoint - time.monotonic())))
            except queue.Empty:
                item = None
            else:
                if item is None:
                    return
                self._store(item)
            if time.monotonic() >= next_checkpoint:
                next_checkpoint = time.monotonic() + self._checkpoint_period_s
                self._checkpoint()

    def _checkpoint(self) -> None:
        """Store the running trial's progress (on the recorder thread, so never beside its end)."""
        if self._checkpoint_of is None:
            return
        with self._lock:
            trial_id = self._current
            writer = None if trial_id is None else self._writers.get(trial_id)
            first = 0 if trial_id is None else self._frames_stored.get(trial_id, 0)
        if trial_id is None or writer is None:
            return
        try:
            ck = self._checkpoint_of(trial_id, first)
            if ck is None:
                return
            if ck.first_frame != first:
                raise ValueError(f"checkpoint frames start at {ck.first_frame}, not {first}")
            writer.flush()
            self._repo.checkpoint_trial(trial_id, metrics=ck.metrics, frames=ck.frames)
        except TrialStateError:
            return  # the trial ended meanwhile; its end is stored next
        except Exception:
            logger.exception("trial %d: checkpoint failed (the next one retries)", trial_id)
            return
        with self._lock:
            if trial_id in self._frames_stored:
                self._frames_stored[trial_id] = first + (0 if ck.frames is None else len(ck.frames))
        self.checkpoints += 1

    def _store(self, item: _TrialEnd) -> None:
        with self._lock:
            writer = self._writers.pop(item.trial_id, None)
            n_live = self._live_counts.pop(item.trial_id, 0)
            done = self._done.get(item.trial_id)
            self._frames_stored.pop(item.trial_id, None)
            if self._current == item.trial_id:
                self._current = None
        try:
            if writer is not None:
                writer.close()
            # The events the listener already wrote are the first n_live of the runtime's list.
            rest = item.events[n_live:] if writer is not None else item.events
            kwargs = {"frames": item.frames} if item.frames is not None else {}
            self._repo.finish_trial(
                item.trial_id,
                status=item.status,
                metrics=item.metrics,
                reason=item.reason,
                events=rest,
                **kwargs,
            )
            self.stored += 1
            logger.info("trial %d stored as %s", item.trial_id, item.status)
        except Exception:
            self.failed += 1
            logger.exception("trial %d: storing its result failed", item.trial_id)
        finally:
            if done is not None:
                done.set()
            with self._lock:
                self._done.pop(item.trial_id, None)
