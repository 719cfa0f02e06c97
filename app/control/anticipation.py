"""Task-aware anticipation: the person comes for the block the robot has just placed.

The motion predictor forecasts from the person's past motion alone, so it sees a fetch only once the hand
is on its way: a few tenths of a second before the hand reaches the station, while the robot is still
rising from that station at the speed the speed monitoring allows near the person. The task knows more:
the robot placed the block there, and the person will come for it. :class:`FetchAnticipation` adds that
to the proactive method's forecast:

- When the robot arrives at a drop station to release a block at ``t_release``, the station is *expected*
  (:meth:`FetchAnticipation.expect`).
- While a station is expected, the forecast's nearer hand reaches for it: on a minimum-jerk profile ``s``
  from 0 to 1 the predicted hand moves to ``(1 - s) * predicted + s * station`` (the wrist with it, the
  elbow by half as much). The reach starts at ``t_release + reaction_s`` (or now, if that has passed) and
  lasts as long as one from where the hand is now at the peak hand speed ``hand_speed_mps`` (a minimum-jerk
  reach of length ``L`` and duration ``T`` peaks at ``1.875 L / T``). The rest of the body keeps the
  predictor's forecast, and so do the margins.
- A reach that is not over by the end of the forecast's horizon extends the forecast until it is, at the
  forecast's step: beyond the horizon the rest of the body is held at its last pose and the margin grows,
  as they would be anyway (:meth:`HumanForecast.poses_at`). Without it, the hand would be held wherever it
  was at the horizon's end, short of the station: a plan could leave the station "before the hand comes"
  and meet it there a second later (on tuning seeds 1000-1002 in the example cell, every one of 9 fetches
  ended in a stop & replan so; with it, none of 8).
- Once a hand has come within ``reached_radius_m`` of the station, the forecast holds it there until the
  hands have withdrawn by another ``withdraw_m``: then the fetch is over and the next expected station (if
  the robot has placed another block meanwhile) takes its turn. An expected fetch that has not happened
  ``timeout_s`` after the release is forgotten.

The timing is learned online, per participant: every fetch seen (the hand leaving for the station after a
release and reaching it) gives an observed reaction time and peak hand speed (:func:`observed_fetch`), and
the forecast uses their running mean, starting from a prior (``reaction_s``, ``hand_speed_mps``) that
counts as ``prior_weight`` fetches. The prior: 0.6 s from the release to the start of the reach (simple
visual reaction times are 0.2-0.3 s; noticing that a placement is over and deciding to reach takes longer)
and a 1.2 m/s peak hand speed (unhurried reaches of 30-50 cm at table height peak at about 1-1.5 m/s).

A plan that would leave the station through the hand's way then fails its check against the forecast, and
the robot waits at rest for the fetch (the supervisor starts a robot at rest only on a plan the forecast
leaves clear, :attr:`app.control.supervisor.SupervisorConfig.clear_start`) instead of setting off into the
arriving hand, where the speed monitoring would stop it. The reactive baseline never sees this: it is fed
the current pose held still.

A forecast that is exact over its horizon (the simulated operator's own future,
:class:`app.cell.operator_sim.OracleForecaster`, an analysis tool) needs only what lies beyond it: with
``exact_horizon`` the forecast is left as it is within the horizon. Where it does not bring a hand to the
station, the fetch comes after the horizon: from the horizon's end (or the expected start of the reach, if
later) the hand goes on from where the forecast leaves it to the station, on the expected reach of that
length. So the oracle knows what the task tells the proactive method, and nothing of the person's motion is
guessed where it is known: the bound it gives is like for like.

This is a forecast, not a safety function: the speed governor, the stop distance and the safety monitor
work on the measured person, whatever the forecast says.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace

import numpy as np

from app.prediction.forecast import HumanForecast
from app.prediction.profiles import MIN_JERK_PEAK_SPEED, min_jerk
from app.prediction.skeleton import JOINT_INDEX, HumanFrame

_ARM = {
    side: (JOINT_INDEX[f"{side}_wrist"], JOINT_INDEX[f"{side}_hand"], JOINT_INDEX[f"{side}_elbow"])
    for side in ("l", "r")
}
_HANDS = np.array([JOINT_INDEX["l_hand"], JOINT_INDEX["r_hand"]])


@dataclass(frozen=True, slots=True)
class FetchAnticipationParams:
    """How :class:`FetchAnticipation` expects a person to fetch a block.

    Attributes:
        reaction_s: The prior of when the reach starts after the release (s): the person's reaction time
            (``Settings.fetch_reaction_s``). Earlier makes the robot wait for more fetches that come later;
            later lets it set off into more of the early ones.
        hand_speed_mps: The prior of the reach's peak hand speed (m/s).
        min_reach_s: Shortest reach (s).
        reached_radius_m: A hand this close to the station has reached it (m).
        withdraw_m: ... and has withdrawn when both hands are this much farther (m).
        timeout_s: An expected fetch that has not happened this long after the release is forgotten (s).
        prior_weight: How many observed fetches the prior of ``reaction_s`` and ``hand_speed_mps`` counts
            as (0: the first observation replaces it).
        min_reach_m: A fetch from nearer than this teaches nothing about the timing (m).
    """

    reaction_s: float = 0.6
    hand_speed_mps: float = 1.2
    min_reach_s: float = 0.35
    reached_radius_m: float = 0.12
    withdraw_m: float = 0.1
    timeout_s: float = 4.0
    prior_weight: float = 3.0
    min_reach_m: float = 0.15

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"FetchAnticipationParams.{f.name} must be finite and >= 0, got {v!r}")
        for name in ("hand_speed_mps", "reached_radius_m", "timeout_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"FetchAnticipationParams.{name} must be > 0")


#: Progress of a minimum-jerk reach at which its start is detected: 10 % of the way.
_START_PROGRESS = 0.1


def _min_jerk_time(progress: float) -> float:
    """The normalised time (0..1) at which a minimum-jerk profile reaches ``progress`` (0..1)."""
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if float(min_jerk(np.array([mid]))[0]) < progress:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def observed_fetch(
    t_release: float, t_start10: float, t_reached: float, length_m: float, reached_radius_m: float
) -> tuple[float, float] | None:
    """The reaction time (s) and peak hand speed (m/s) of one observed fetch, or None when the observation
    says nothing: the hand covered 10 % of its ``length_m`` reach at ``t_start10`` and came within
    ``reached_radius_m`` of the station at ``t_reached``. Fitted to a minimum-jerk reach: both instants fix
    its duration ``T`` and its start, and a reach of ``L`` in ``T`` peaks at ``1.875 L / T``."""
    if not (length_m > reached_radius_m and t_reached > t_start10 >= t_release):
        return None
    tau_10 = _min_jerk_time(_START_PROGRESS)
    tau_reached = _min_jerk_time(1.0 - reached_radius_m / length_m)
    if tau_reached <= tau_10 + 1e-6:
        return None
    duration = (t_reached - t_start10) / (tau_reached - tau_10)
    start = t_start10 - tau_10 * duration
    return max(start - t_release, 0.0), MIN_JERK_PEAK_SPEED * length_m / duration


class FetchAnticipation:
    """Adds the expected fetch of a placed block to a forecast (see the module docstring).

    Thread-safe: the live runtime's servo thread expects fetches while its frame thread applies them.

    Args:
        stations: Drop station name -> where the robot releases the block (3,), world frame (m).
        params: How a fetch is expected.
        exact_horizon: The forecasts are exact over their horizon (the oracle): add only the part of an
            expected reach beyond it (see the module docstring).
    """

    def __init__(
        self,
        stations: Mapping[str, np.ndarray],
        params: FetchAnticipationParams | None = None,
        *,
        exact_horizon: bool = False,
    ) -> None:
        self.params = params or FetchAnticipationParams()
        self.exact_horizon = bool(exact_horizon)
        self.stations: dict[str, np.ndarray] = {}
        for name, xyz in stations.items():
            p = np.asarray(xyz, dtype=np.float64)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise ValueError(f"station {name!r}: expected a finite (3,) position, got {xyz!r}")
            self.stations[name] = p
        self._expected: deque[tuple[float, str]] = deque()
        self._reached = False
        self._watch: dict[str, float] | None = None  # the fetch under way: its start distance and instants
        self._observed: list[tuple[float, float]] = []
        self._lock = threading.Lock()

    def reset(self) -> None:
        """Forget every expected fetch and what was learned (a new participant)."""
        with self._lock:
            self._expected.clear()
            self._reached = False
            self._watch = None
            self._observed.clear()

    def timing(self) -> tuple[float, float]:
        """The expected reaction time (s) and peak hand speed (m/s): the running mean of the fetches seen,
        with the prior counted ``prior_weight`` times."""
        with self._lock:
            return self._timing()

    def _timing(self) -> tuple[float, float]:
        p = self.params
        n = len(self._observed)
        if n == 0:
            return p.reaction_s, p.hand_speed_mps
        w = p.prior_weight
        reaction = (w * p.reaction_s + sum(r for r, _ in self._observed)) / (w + n)
        speed = (w * p.hand_speed_mps + sum(v for _, v in self._observed)) / (w + n)
        return reaction, speed

    @property
    def fetches_seen(self) -> int:
        """How many fetches the timing has learned from."""
        with self._lock:
            return len(self._observed)

    def expect(self, station: str, t_release: float) -> None:
        """The robot releases a block at ``station`` at ``t_release`` (s); the person will come for it.

        Raises:
            ValueError: ``station`` is not a drop station, or ``t_release`` is not finite.
        """
        if station not in self.stations:
            raise ValueError(f"unknown drop station {station!r}; the cell has {sorted(self.stations)}")
        if not math.isfinite(t_release):
            raise ValueError(f"t_release must be finite, got {t_release!r}")
        with self._lock:
            self._expected.append((float(t_release), station))

    def expected(self) -> list[str]:
        """The stations whose fetch is expected, the next one first."""
        with self._lock:
            return [s for _, s in self._expected]

    def _advance(self, frame: HumanFrame) -> None:
        """Drop the fetches that are over (the hand came and withdrew) or overdue. Caller holds the lock."""
        p = self.params
        while self._expected:
            t_release, station = self._expected[0]
            d = float(np.min(np.linalg.norm(frame.joints[_HANDS] - self.stations[station], axis=1)))
            self._learn(t_release, frame.t, d)
            if d <= p.reached_radius_m:
                self._reached = True
            done = self._reached and d > p.reached_radius_m + p.withdraw_m
            if done or frame.t > t_release + p.timeout_s:
                self._expected.popleft()
                self._reached = False
                self._watch = None
                continue
            return

    def _learn(self, t_release: float, t: float, d: float) -> None:
        """Follow the fetch of the next expected station; when the hand reaches it, learn its timing.
        Caller holds the lock."""
        p = self.params
        if t < t_release:
            return
        w = self._watch
        if w is None:  # the first frame after the release: the reach's length
            self._watch = {"t_release": t_release, "d0": d, "t10": math.nan, "done": 0.0}
            return
        if w["done"] or w["t_release"] != t_release:
            return
        length = w["d0"]
        if math.isnan(w["t10"]) and w["d0"] - d >= _START_PROGRESS * length:
            w["t10"] = t
        if d <= p.reached_radius_m:
            w["done"] = 1.0
            if length >= p.min_reach_m and not math.isnan(w["t10"]):
                seen = observed_fetch(t_release, w["t10"], t, length, p.reached_radius_m)
                if seen is not None:
                    reaction, speed = seen
                    self._observed.append((min(reaction, 3.0), min(max(speed, 0.2), 3.0)))

    def apply(self, frame: HumanFrame, forecast: HumanForecast) -> HumanForecast:
        """``forecast`` (made from ``frame``) with the nearer hand reaching for the next expected station;
        ``forecast`` itself when no fetch is expected."""
        with self._lock:
            self._advance(frame)
            if not self._expected:
                return forecast
            t_release, station = self._expected[0]
            reached = self._reached
            reaction_s, hand_speed_mps = self._timing()
        p = self.params
        target = self.stations[station]
        t_on = max(frame.t, t_release + reaction_s)
        start = frame.joints
        if self.exact_horizon:
            near = np.linalg.norm(forecast.joints[:, _HANDS] - target, axis=-1) <= p.reached_radius_m
            if reached or bool(near.any()):
                return forecast  # the forecast itself brings a hand to the station (or away from it)
            # the fetch comes after the horizon, from where the forecast leaves the hands
            start = forecast.joints[-1]
            t_on = max(t_on, float(forecast.times[-1]))
        d_hands = np.linalg.norm(start[_HANDS] - target, axis=1)
        wrist, hand, elbow = _ARM["l" if d_hands[0] <= d_hands[1] else "r"]
        if reached:
            progress = np.ones_like(forecast.times)
        else:
            duration = max(p.min_reach_s, MIN_JERK_PEAK_SPEED * float(d_hands.min()) / hand_speed_mps)
            forecast = _extended(forecast, t_on + duration)
            progress = min_jerk((forecast.times - t_on) / duration)
        joints = np.array(forecast.joints, dtype=np.float64, copy=True)
        # the predicted hand is drawn to the station: (1 - s) * predicted + s * station
        disp = progress[:, None] * (target[None, :] - joints[:, hand])  # (H, 3)
        joints[:, hand] += disp
        joints[:, wrist] += disp
        joints[:, elbow] += 0.5 * disp
        return replace(forecast, joints=joints)


def _extended(forecast: HumanForecast, t_end: float) -> HumanForecast:
    """``forecast`` with samples beyond its horizon up to ``t_end`` (s), when that is later: the last pose
    held and the margin grown as :meth:`HumanForecast.poses_at` holds and grows them there, at the
    forecast's coarsest spacing (its steps, not its half steps)."""
    times = forecast.times
    if t_end <= times[-1] + 1e-9 or times.shape[0] < 2:
        return forecast
    dt = float(np.max(np.diff(times)))
    n = math.ceil((t_end - times[-1]) / dt - 1e-9)
    extra_t = times[-1] + dt * np.arange(1, n + 1)
    joints, margins = forecast.poses_at(extra_t)
    return replace(
        forecast,
        times=np.concatenate([times, extra_t]),
        joints=np.concatenate([forecast.joints, joints]),
        margins=np.concatenate([forecast.margins, margins]),
    )
