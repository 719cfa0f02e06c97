"""Every person in the cell: the bodies a tracker reports, followed from capture to capture, and what the
decisions take of them.

A tracker reports every body it sees with an id (the ZED SDK's body tracking does). :class:`People` keeps a
*track* per person and gives the trial engine, at every capture, the people that every decision takes at
once (:class:`PeopleUpdate`):

- **A new body** starts a track. Until it has been tracked for ``settle_s`` (long enough for the predictor's
  history) it is *settling*; a settling body within ``near_m`` of the robot is an intrusion, and the engine
  makes a protective stop (:meth:`app.control.supervisor.Supervisor.intrusion`). The first body of a trial
  is not new: the trial starts with it.
- **A lost body** (its id is missing from a capture) is held where it was last seen for ``hold_s``, with
  its age: the decisions count it as present, and its forecast margin grows at ISO 13855's body speed. Then
  it is dropped.
- **An id that changes** (the tracker loses a person and finds them again under a new id): a new id whose
  pelvis lies within ``rematch_m`` of where a lost body was last seen takes over that body's track, history
  and predictor. The person is not lost, and not new.

Bodies keep their track's id in what the decisions see (the first tracker id the person had), so that the
speeds measured from one capture to the next compare the same person.

The proactive method forecasts every body: one predictor per track (the engine's own for the first,
:meth:`~app.prediction.forecast.Predictor.spawn` for the others), the forecasts stacked on one time grid
(:func:`~app.prediction.forecast.stack_forecasts`). A lost body is held with the growing margin. Only the
person expected to fetch (and a new body) is forecast before the capture's decision; the others' forecasts,
made from an earlier capture, stand in at the decision, and they catch up after it
(:meth:`People.catch_up`), so that the frame's latency does not grow with the number of people.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from app.prediction.forecast import HumanForecast, Predictor, stack_forecasts
from app.prediction.skeleton import JOINT_INDEX, HumanFrame

_PELVIS = JOINT_INDEX["pelvis"]


@dataclass(frozen=True, slots=True)
class PeopleOptions:
    """How :class:`People` follows the bodies.

    Attributes:
        settle_s: A body tracked for less than this is new (s): the predictor's history, 10 frames at
            30 Hz.
        hold_s: A lost body is held where it was last seen for this long (s), then dropped: the stale
            stream's timeout, the time the runtime waits for any frame before it stops the robot.
        rematch_m: A new id whose pelvis lies within this of a lost body's last pelvis (m) is that body
            under a new id: half a metre, what a person moves in the hold time at ISO 13855's body speed
            (1.6 m/s x 0.35 s = 0.56 m), rounded down.
        near_m: A new body within this of the robot (surface to surface, m) is an intrusion: the protective
            separation of the UR5e at full speed (about 1.2 m, see the safety model).
        growth_mps: A lost body's margin grows at this speed (m/s): ISO 13855's body speed.
        fresh_per_frame: At most this many bodies are forecast anew per capture (:meth:`People.forecast`
            and :meth:`People.catch_up`; new bodies apart): two keeps the forecast of the person expected to
            fetch fresh at every decision and refreshes one other person per capture, after the decision,
            in turn; what is forecast before the decision then costs about as much with four people as
            with two (``hrc bench hmp``, ``people_forecast_ms``).
    """

    settle_s: float = 10 / 30
    hold_s: float = 0.35
    rematch_m: float = 0.5
    near_m: float = 1.2
    growth_mps: float = 1.6
    fresh_per_frame: int = 2

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"PeopleOptions.{f.name} must be a finite number >= 0, got {v!r}")


@dataclass
class _Track:
    id: int  #: the track's id (the body's first tracker id)
    tracker_id: int  #: the id the tracker gives the body now
    first_t: float
    last_t: float
    last: HumanFrame  #: the body as last seen (one body, the track's id)
    predictor: Predictor | None = None
    forecast: HumanForecast | None = None  #: the body's newest forecast


@dataclass(frozen=True, slots=True)
class PeopleUpdate:
    """The people of one capture as the decisions take them.

    Attributes:
        frame: Every body seen in the capture and every lost body still held, stacked, with their track ids
            (a lost body at its last pose, with the capture's time).
        ages_s: (B,) How old each body's pose is (s): 0 for a body seen in this capture.
        appeared: Track ids of the bodies that are new in this capture.
        settling: Track ids of the bodies tracked for less than ``settle_s`` (new ones included).
        renamed: ``{tracker id: track id}`` of the ids that changed in this capture.
        dropped: Track ids of the lost bodies dropped in this capture.
    """

    frame: HumanFrame
    ages_s: np.ndarray
    appeared: tuple[int, ...] = ()
    settling: tuple[int, ...] = ()
    renamed: dict[int, int] = field(default_factory=dict)
    dropped: tuple[int, ...] = ()

    @property
    def seen(self) -> HumanFrame:
        """The bodies seen in this capture (the lost ones left out)."""
        keep = [k for k in range(self.frame.bodies) if self.ages_s[k] == 0.0]
        if len(keep) == self.frame.bodies:
            return self.frame
        return HumanFrame.stack(self.frame.t, [self.frame.body(k) for k in keep])


class People:
    """The tracks of the people in the cell (see the module's docstring).

    Args:
        predictor: The proactive method's predictor (its first track's; the others spawn from it), None for
            the reactive method.
        options: How the bodies are followed.
    """

    def __init__(self, predictor: Predictor | None = None, options: PeopleOptions | None = None) -> None:
        self.options = options if options is not None else PeopleOptions()
        self.predictor = predictor
        self._tracks: dict[int, _Track] = {}  # by track id
        self._started = False
        self._started_forecasts = False
        self.appeared = 0  #: bodies that appeared after the first capture
        self.renamed = 0  #: id changes bridged
        self.dropped = 0  #: lost bodies dropped
        self.max_bodies = 0  #: the most bodies (seen and held) of one capture
        # the bodies of the last capture that take it after the decision (:meth:`catch_up`)
        self._pending: list[tuple[_Track, HumanFrame]] = []
        self._pending_shape: Callable[[HumanFrame, HumanForecast], HumanForecast] | None = None
        self._pending_budget = 0

    def reset(self) -> None:
        """Forget every track (a new trial)."""
        self._tracks.clear()
        self._pending.clear()
        self._started = self._started_forecasts = False
        if self.predictor is not None:
            self.predictor.reset()

    def held(self, update: PeopleUpdate, body: HumanFrame, *, margin_m: float) -> HumanForecast:
        """The people of ``body`` (``update``'s frame as the geometry sees it) held still: the reactive
        method's forecast; a lost body's margin grown by its age, growing on."""
        if not np.any(update.ages_s > 0.0):
            return HumanForecast.hold(body, margin_m=margin_m)
        return stack_forecasts(
            [
                self._lost(body.body(k), margin_m, age)
                if age > 0.0
                else HumanForecast.hold(body.body(k), margin_m=margin_m)
                for k, age in enumerate(update.ages_s.tolist())
            ],
            t0=body.t,
        )

    def _lost(self, body: HumanFrame, margin_m: float, age_s: float) -> HumanForecast:
        """A lost body held where it was last seen, ``age_s`` ago: its margin grown since, growing on."""
        grown = margin_m + self.options.growth_mps * age_s
        return HumanForecast.hold(
            body, margin_m=grown, growth_mps=self.options.growth_mps, max_margin_m=max(grown, 1.0)
        )

    def _predictor_of(self, track: _Track) -> Predictor:
        """The track's predictor: the first track's is the engine's, the others spawn from it."""
        assert self.predictor is not None
        if track.predictor is None:
            owned = any(tr.predictor is self.predictor for tr in self._tracks.values())
            if owned:
                track.predictor = self.predictor.spawn()
            else:  # the first track's, or one whose person has left the cell
                track.predictor = self.predictor
                if self._started_forecasts:
                    self.predictor.reset()
            self._started_forecasts = True
        return track.predictor

    def track_id(self, tracker_id: int) -> int | None:
        """The track of the body the tracker calls ``tracker_id`` now (None: none)."""
        for tr in self._tracks.values():
            if tr.tracker_id == tracker_id:
                return tr.id
        return None

    def reset_forecast(self, track_ids: list[int]) -> None:
        """Forget what the predictors of these tracks have seen (a body that jumped: another person, or the
        tracker's mistake)."""
        for tid in track_ids:
            tr = self._tracks.get(tid)
            if tr is not None and tr.predictor is not None:
                tr.predictor.reset()
                tr.forecast = None

    @property
    def tracks(self) -> tuple[int, ...]:
        """The track ids followed now."""
        return tuple(self._tracks)

    def update(self, frame: HumanFrame) -> PeopleUpdate:
        """Take a capture: follow its bodies, hold and drop the lost ones."""
        opts, t = self.options, frame.t
        by_tracker = {tr.tracker_id: tr for tr in self._tracks.values()}
        seen: list[tuple[_Track, HumanFrame]] = []
        fresh: list[HumanFrame] = []
        for body in frame.split():
            tr = by_tracker.get(body.body_ids[0])
            if tr is not None:
                seen.append((tr, body))
            else:
                fresh.append(body)
        taken = {id(tr) for tr, _ in seen}
        renamed: dict[int, int] = {}
        appeared: list[int] = []
        for body in fresh:
            tid = body.body_ids[0]
            lost = [tr for tr in self._tracks.values() if id(tr) not in taken and tr.last_t < t]
            near = _nearest(lost, body, opts.rematch_m)
            if near is not None:  # the same person under a new id
                renamed[tid] = near.id
                near.tracker_id = tid
                self.renamed += 1
                seen.append((near, body))
                taken.add(id(near))
                continue
            track_id = tid
            while track_id in self._tracks:  # an id the tracker reused for someone else
                track_id = max(self._tracks) + 1
            tr = _Track(track_id, tid, t, t, body, None)
            if self._started:
                appeared.append(track_id)
                self.appeared += 1
            else:
                tr.first_t = -math.inf  # the trial starts with the people already there
            self._tracks[track_id] = tr
            seen.append((tr, body))
            taken.add(id(tr))
        self._started = True
        for tr, body in seen:
            tr.last_t = t
            tr.last = dataclasses.replace(body, body_ids=(tr.id,))
        dropped = []
        for tr in list(self._tracks.values()):
            if id(tr) not in taken and t - tr.last_t > opts.hold_s:
                dropped.append(tr.id)
                del self._tracks[tr.id]
        self.dropped += len(dropped)
        bodies = [tr.last for tr, _ in seen]
        ages = [0.0] * len(seen)
        for tr in self._tracks.values():
            if id(tr) not in taken:
                bodies.append(dataclasses.replace(tr.last, t=t))
                ages.append(t - tr.last_t)
        settling = tuple(tr.id for tr, _ in seen if t - tr.first_t < opts.settle_s)
        people = HumanFrame.stack(t, bodies)
        self.max_bodies = max(self.max_bodies, people.bodies)
        return PeopleUpdate(people, np.array(ages), tuple(appeared), settling, renamed, tuple(dropped))

    def forecast(
        self,
        update: PeopleUpdate,
        *,
        margin_m: float,
        shape: Callable[[HumanFrame, HumanForecast], HumanForecast] | None = None,
        first: int | None = None,
    ) -> HumanForecast:
        """The proactive method's forecast of every body of ``update`` for this capture's decision: each body
        seen through its track's predictor (``shape``: what the engine does to a body's forecast, e.g. the
        fetch it expects), each lost one held with a margin of ``margin_m`` grown by its age, growing on;
        stacked.

        Only the track ``first`` (the engine's: the person expected to fetch; None: every body) and the
        tracks without a forecast yet are forecast anew from this capture. The others keep the forecast they
        have, made from an earlier capture (its times are absolute: it forecasts the same instants, from a
        frame older); they take this capture after the decision, in :meth:`catch_up`, which also forecasts
        the stalest of them anew for the next capture's decision, up to
        :attr:`PeopleOptions.fresh_per_frame` bodies per capture in all.
        """
        assert self.predictor is not None, "forecasting needs a predictor"
        if self._pending:  # the capture before was not caught up (its decision failed): take it now
            self.catch_up()
        frame = update.frame
        out: list[HumanForecast] = []
        fresh = 0
        for k in range(frame.bodies):
            body = frame.body(k)
            track = self._tracks[body.body_ids[0]]
            age = float(update.ages_s[k])
            if age > 0.0:
                out.append(self._lost(body, margin_m, age))
                continue
            predictor = self._predictor_of(track)
            if first is None or body.body_ids[0] == first or track.forecast is None:
                self._made(track, body, predictor.update(body), shape)
                fresh += 1
            else:
                self._pending.append((track, body))
            out.append(track.forecast)  # type: ignore[arg-type]
        self._pending_shape, self._pending_budget = shape, self.options.fresh_per_frame - fresh
        return stack_forecasts(out, t0=frame.t)

    def catch_up(self) -> None:
        """After the decision: the bodies :meth:`forecast` did not forecast anew take the capture into their
        predictors' history, and the stalest of them are forecast anew from it (for the next capture's
        decision), within the capture's budget of :attr:`PeopleOptions.fresh_per_frame`. Nothing to do
        after a capture :meth:`forecast` did not take (the reactive method's, the oracle's)."""
        pending, self._pending = self._pending, []
        budget = max(self._pending_budget, 0)
        stalest = sorted(pending, key=lambda tb: -math.inf if tb[0].forecast is None else tb[0].forecast.t0)
        anew = {id(track) for track, _ in stalest[:budget]}
        for track, body in pending:
            predictor = self._predictor_of(track)
            if id(track) in anew:
                self._made(track, body, predictor.update(body), self._pending_shape)
            else:
                predictor.observe(body)

    @staticmethod
    def _made(
        track: _Track,
        body: HumanFrame,
        forecast: HumanForecast,
        shape: Callable[[HumanFrame, HumanForecast], HumanForecast] | None,
    ) -> None:
        """Keep ``forecast`` as ``track``'s newest, with its id and shaped by ``shape``."""
        fc = dataclasses.replace(forecast, body_ids=body.body_ids)
        track.forecast = fc if shape is None else shape(body, fc)


def _nearest(tracks: list[_Track], body: HumanFrame, within_m: float) -> _Track | None:
    """The track whose last pelvis lies nearest ``body``'s, if within ``within_m``."""
    best, best_d = None, within_m
    p = body.joints[_PELVIS]
    for tr in tracks:
        d = float(np.linalg.norm(tr.last.joints[_PELVIS] - p))
        if d <= best_d:
            best, best_d = tr, d
    return best
