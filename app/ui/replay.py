"""Replay of a recorded trial from the study database in viser, with a time slider.

The database keeps, per trial, the frames at the camera rate (``StudyRepository.load_frames``: time, robot
configuration and the person's skeleton) and the events (state changes, E-stops, replans...).
:class:`ReplayTimeline` turns them into snapshot-like :class:`ReplayFrame` objects at any time ``t`` (pure, no
viser); :class:`TrialReplay` draws them with the live view's :class:`~app.ui.scene.CellView`, so the replay
looks exactly like the live view, and adds a slider, play/pause, a speed choice and the event log.

Example::

    replay = TrialReplay(repo, trial_id=12, cell=load_workcell(), port=8081)
    replay.start()      # http://127.0.0.1:8081
    ...
    replay.stop()
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from app.cell.bodies import frame_bodies, recorded_bodies
from app.config import WorkCell
from app.prediction.skeleton import NUM_JOINTS
from app.ui.scene import CellView, RobotCapsulesFn
from app.ui.viser_server import ViserServerThread

if TYPE_CHECKING:
    import viser

logger = logging.getLogger(__name__)

SPEEDS: dict[str, float] = {"0.25x": 0.25, "0.5x": 0.5, "1x": 1.0, "2x": 2.0, "4x": 4.0}
#: Longest tool trace drawn (segments); longer recordings are subsampled.
MAX_TRACE_SEGMENTS = 1500


class ReplayError(RuntimeError):
    """A trial cannot be replayed (unknown, or recorded without frames); the message says which and why."""


@dataclass(frozen=True, slots=True)
class ReplayFrame:
    """The state of a recorded trial at one instant, with the attributes of a runtime snapshot.

    Attributes:
        t: Seconds since the trial started.
        state: Supervisor state at ``t`` (from the trial's ``state_changed`` events).
        q: Robot configuration (6,) in rad.
        p_world_tcp: Tool position (3,) in the world frame (m).
        skeleton: Every tracked body's joints stacked (B*J, 3) in the world frame (m), or None where
            nobody was seen.
        body_ids: The tracker's id of each body of ``skeleton`` (B,).
        estopped: An E-stop happened at or before ``t``.
    """

    t: float
    state: str
    q: np.ndarray
    p_world_tcp: np.ndarray
    skeleton: np.ndarray | None
    estopped: bool
    method: str | None
    trial_id: int | None
    trial_elapsed_s: float
    trial_duration_s: float
    body_ids: tuple[int, ...] = ()
    forecast: None = None
    plan_tcp: None = None
    backup_tcp: None = None
    required_separation_m: None = None
    separation_m: None = None
    speed_scale: None = None
    stale: bool = False


@dataclass(frozen=True, slots=True)
class ReplayEvent:
    t: float
    kind: str
    payload: dict[str, Any]


class ReplayTimeline:
    """A recorded trial as a function of time.

    Args:
        t: Frame times (T,) in seconds since the trial start, non-decreasing.
        q: Robot configurations (T, 6) in rad.
        p_world_tcp: Tool positions (T, 3) in the world frame (m).
        skeleton: Every tracked body's joints (T, B, J, 3), NaN in the slots a frame does not use (the
            recorded layout of :mod:`app.cell.bodies`), or the single-body layout (T, J, 3) with NaN rows
            where nobody was seen; or None.
        body_ids: (T, B) the ids of ``skeleton``'s slots, -1 where unused (None: the single-body layout).
        events: The trial's events in time order.
        trial_id: The trial's id.
        method: ``"proactive"`` or ``"reactive"``.
    """

    def __init__(
        self,
        *,
        t: np.ndarray,
        q: np.ndarray,
        p_world_tcp: np.ndarray,
        skeleton: np.ndarray | None,
        events: list[ReplayEvent],
        trial_id: int | None = None,
        method: str | None = None,
        body_ids: np.ndarray | None = None,
    ) -> None:
        t = np.asarray(t, dtype=np.float64)
        T = t.shape[0]
        if t.ndim != 1 or T == 0 or np.any(np.diff(t) < 0):
            raise ReplayError(f"frame times must be (T,) non-decreasing with T > 0, got shape {t.shape}")
        q = np.asarray(q, dtype=np.float64)
        p = np.asarray(p_world_tcp, dtype=np.float64)
        if q.shape != (T, 6) or p.shape != (T, 3):
            raise ReplayError(f"q must be ({T}, 6) and p_world_tcp ({T}, 3); got {q.shape} and {p.shape}")
        ids = None
        if skeleton is not None:
            try:
                skeleton, ids = recorded_bodies(skeleton, body_ids, dtype=np.float64)
            except ValueError as exc:
                raise ReplayError(f"skeleton: {exc}") from None
            if skeleton.shape[0] != T:
                raise ReplayError(f"skeleton must have {T} frames, got {skeleton.shape}")
        self.t, self.q, self.p_world_tcp, self.skeleton, self.body_ids = t, q, p, skeleton, ids
        self.events = sorted(events, key=lambda e: e.t)
        self.trial_id = trial_id
        self.method = method
        changes = [e for e in self.events if e.kind == "state_changed"]
        self._state_t = np.array([e.t for e in changes], dtype=np.float64)
        self._state_to = [str(e.payload.get("to", "unknown")) for e in changes]
        first = str(changes[0].payload.get("from", "idle")) if changes else "idle"
        self._state_initial = first
        estops = [e.t for e in self.events if e.kind == "estop"]
        self._first_estop = min(estops) if estops else None

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def index_at(self, t: float) -> int:
        """Index of the newest frame at or before ``t`` (the first frame before the recording starts)."""
        return max(int(np.searchsorted(self.t, t, side="right")) - 1, 0)

    def state_at(self, t: float) -> str:
        k = int(np.searchsorted(self._state_t, t, side="right"))
        return self._state_initial if k == 0 else self._state_to[k - 1]

    def events_until(self, t: float, *, last: int = 6) -> list[ReplayEvent]:
        """The ``last`` events at or before ``t``, oldest first."""
        past = [e for e in self.events if e.t <= t]
        return past[-last:]

    def frame_at(self, t: float) -> ReplayFrame:
        """The recorded state at ``t`` (clamped to the recording)."""
        t = float(min(max(t, 0.0), self.duration_s))
        i = self.index_at(t)
        sk, ids = None, ()
        if self.skeleton is not None and self.body_ids is not None:
            joints, ids = frame_bodies(self.skeleton, self.body_ids, i)
            seen = np.all(np.isfinite(joints.reshape(len(ids), NUM_JOINTS, 3)), axis=(1, 2))
            ids = tuple(b for b, s in zip(ids, seen, strict=True) if s)  # a body partly lost is not drawn
            sk = joints.reshape(-1, NUM_JOINTS, 3)[seen].reshape(-1, 3) if ids else None
        return ReplayFrame(
            t=t,
            state=self.state_at(t),
            q=self.q[i],
            p_world_tcp=self.p_world_tcp[i],
            skeleton=sk,
            body_ids=ids,
            estopped=self._first_estop is not None and t >= self._first_estop,
            method=self.method,
            trial_id=self.trial_id,
            trial_elapsed_s=t,
            trial_duration_s=self.duration_s,
        )

    def tool_trace(self, *, max_segments: int = MAX_TRACE_SEGMENTS) -> np.ndarray:
        """The tool's path over the whole trial as line segments (S, 2, 3), subsampled to ``max_segments``."""
        p = self.p_world_tcp
        if len(p) < 2:
            return np.zeros((0, 2, 3))
        step = max(1, int(np.ceil((len(p) - 1) / max_segments)))
        idx = np.arange(0, len(p), step)
        if idx[-1] != len(p) - 1:
            idx = np.append(idx, len(p) - 1)
        pts = p[idx]
        return np.stack([pts[:-1], pts[1:]], axis=1)


def load_timeline(repo: Any, trial_id: int, cell: WorkCell) -> ReplayTimeline:
    """Read a trial's frames and events from the study database.

    Args:
        repo: A ``StudyRepository``.
        trial_id: The trial to replay.
        cell: The work cell (its robot mount and tool give the tool positions).

    Raises:
        ReplayError: the trial has no recorded frames (live trials are recorded only when the server
            records frames; headless ``hrc study`` trials always are).
    """
    from app.planning.kinematics import UR5e

    trial = repo.get_trial(trial_id)  # NotFoundError for an unknown id
    frames = repo.load_frames(trial_id)
    if frames is None:
        raise ReplayError(f"trial {trial_id} has no recorded frames; nothing to replay")
    q = np.asarray(frames.q, dtype=np.float64)
    p = UR5e.from_workcell(cell).fk_tcp(q)[:, :3, 3]
    events = [ReplayEvent(float(e.t), str(e.kind), dict(e.payload)) for e in repo.list_events(trial_id)]
    return ReplayTimeline(
        t=frames.t,
        q=q,
        p_world_tcp=p,
        skeleton=frames.skeleton,
        body_ids=frames.body_ids,
        events=events,
        trial_id=trial_id,
        method=getattr(trial, "method", None),
    )


def _event_markdown(events: list[ReplayEvent]) -> str:
    if not events:
        return "*no events yet*"
    lines = []
    for e in events:
        detail = ", ".join(f"{k}={v}" for k, v in list(e.payload.items())[:3])
        lines.append(f"`{e.t:7.2f} s` **{e.kind}** {detail}")
    return "  \n".join(lines)


class TrialReplay:
    """A viser server that replays one recorded trial with a time slider, play/pause and speed.

    Args:
        timeline: The recorded trial (see :func:`load_timeline`).
        cell: The work cell.
        port: viser port (0: a free one; read :attr:`port` after :meth:`start`).
        host: Interface to bind.
        robot_capsules: Override of the robot model (default ``CollisionModel(cell).robot_capsules``).
        rate_hz: Playback frame rate.
    """

    def __init__(
        self,
        timeline: ReplayTimeline,
        cell: WorkCell,
        *,
        port: int,
        host: str = "127.0.0.1",
        robot_capsules: RobotCapsulesFn | None = None,
        rate_hz: float = 30.0,
    ) -> None:
        if not 0 < rate_hz <= 120:
            raise ValueError(f"rate_hz must be in (0, 120], got {rate_hz}")
        self.timeline = timeline
        self._cell = cell
        self._srv = ViserServerThread(host=host, port=port, name="hrc-replay")
        self._robot_capsules = robot_capsules
        self._period_s = 1.0 / rate_hz
        self._view: CellView | None = None
        self._lock = threading.Lock()
        self._t = 0.0
        self._playing = False
        self._speed = 1.0
        self._gui: dict[str, Any] = {}

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the viser server, draw the first frame and the controls, and the playback thread."""
        if self._srv.server is not None:
            raise RuntimeError("TrialReplay.start() called twice; call stop() first")
        capsules = self._robot_capsules
        if capsules is None:
            from app.planning.collision import CollisionModel

            capsules = CollisionModel(self._cell).robot_capsules

        def build(server: viser.ViserServer) -> None:
            self._view = CellView(server, self._cell, robot_capsules=capsules)
            trace = self.timeline.tool_trace()
            if len(trace):
                server.scene.add_line_segments("/replay/tool_trace", trace, (150, 160, 170), thickness=0.004)
            self._build_gui(server)
            self.seek(0.0)

        self._srv.start(build, self._run)
        logger.info("replay of trial %s at http://%s:%d", self.timeline.trial_id, self._srv.host, self.port)

    def stop(self) -> None:
        """Stop playback and the server (idempotent)."""
        self._srv.stop()

    def __enter__(self) -> TrialReplay:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def port(self) -> int:
        """The port the viser server is bound to (the requested one until :meth:`start`)."""
        return self._srv.port

    @property
    def view(self) -> CellView:
        if self._view is None:
            raise RuntimeError("TrialReplay.view is available after start()")
        return self._view

    @property
    def t(self) -> float:
        """The replayed time (s since the trial start)."""
        return self._t

    @property
    def playing(self) -> bool:
        return self._playing

    # ------------------------------------------------------------------ controls

    def _build_gui(self, server: Any) -> None:
        tl = self.timeline
        gui = server.gui
        title = f"Replay: trial #{tl.trial_id}" if tl.trial_id is not None else "Replay"
        with gui.add_folder(title):
            step = max(float(np.median(np.diff(tl.t))) if len(tl) > 1 else 0.1, 1e-3)
            slider = gui.add_slider(
                "Time (s)", min=0.0, max=max(tl.duration_s, step), step=step, initial_value=0.0
            )
            play = gui.add_button("Play / pause")
            speed = gui.add_dropdown("Speed", tuple(SPEEDS), initial_value="1x")
            events = gui.add_markdown(_event_markdown([]))

        @slider.on_update
        def _(_event: Any) -> None:
            if not self._gui.get("_setting"):
                self.seek(float(slider.value))

        @play.on_click
        def _(_event: Any) -> None:
            if self._playing:
                self.pause()
            else:
                self.play()

        @speed.on_update
        def _(_event: Any) -> None:
            self.set_speed(SPEEDS.get(str(speed.value), 1.0))

        self._gui.update(slider=slider, play=play, speed=speed, events=events)

    def seek(self, t: float) -> ReplayFrame:
        """Show the recorded state at ``t`` (clamped to the recording) and move the slider there."""
        with self._lock:
            frame = self.timeline.frame_at(t)
            self._t = frame.t
            self.view.apply(frame)
            slider = self._gui.get("slider")
            if slider is not None and abs(float(slider.value) - frame.t) > 1e-9:
                self._gui["_setting"] = True
                try:
                    slider.value = frame.t
                finally:
                    self._gui["_setting"] = False
            if "events" in self._gui:
                self._gui["events"].content = _event_markdown(self.timeline.events_until(frame.t))
            return frame

    def play(self) -> None:
        if self._t >= self.timeline.duration_s:
            self.seek(0.0)
        self._playing = True

    def pause(self) -> None:
        self._playing = False

    def set_speed(self, factor: float) -> None:
        """Playback speed (1.0 = real time)."""
        if not 0 < factor <= 100:
            raise ValueError(f"replay speed must be in (0, 100], got {factor}")
        self._speed = float(factor)

    def advance(self, dt_s: float) -> ReplayFrame | None:
        """Move playback forward by ``dt_s`` wall seconds times the speed (nothing while paused); pauses at
        the end of the recording. Returns the frame shown, or None while paused."""
        if not self._playing:
            return None
        frame = self.seek(self._t + dt_s * self._speed)
        if frame.t >= self.timeline.duration_s:
            self._playing = False
        return frame

    def _run(self, stop: threading.Event) -> None:
        last = time.monotonic()
        while not stop.wait(self._period_s):
            now = time.monotonic()
            dt_s, last = now - last, now
            try:
                self.advance(dt_s)
            except Exception:
                logger.exception("replay: drawing a frame failed; pausing")
                self._playing = False
