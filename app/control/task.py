"""The task executive: pick a block at the conveyor, place it at the drop station that comes next (the
round's order, or the one the forecast leaves freest), repeat.

A task is a sequence of *legs*, each a motion to a named task pose of the roadmap followed by an action:

    pickup_approach -> pickup (grip) -> pickup_approach -> X_approach -> X (release) -> X_approach

where ``X`` is the drop station of this block and ``<name>_approach`` is the pose ``approach_height_m`` above
a station (:meth:`app.config.WorkCell.approach_offset`: at a drop station also ``approach_retreat_m`` back
from the person, so that the robot rises from a released block on a slope away from them). A task counts as
completed when the block is released at ``X`` (the end of the release dwell). The drop stations are served
in rounds that visit every station once (the participant's assembly gets its blocks evenly), never the same
station twice in a row. Which
station of the round comes next is either the round's seeded, shuffled order (the default), or chosen when
the robot leaves the conveyor with the block, by a ``chooser`` that sees the stations the round still allows
(:meth:`AssemblySequence.choose`): the engine lets the method's forecast choose the one farthest from where
the person will be (``Settings.station_choice``). The paper's participants received their blocks "without
specific instructions", so the order within a round is the robot's to choose.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from app.config import WorkCell

Action = Literal["move", "pick", "place"]


@dataclass(frozen=True, slots=True)
class TaskLeg:
    """One motion of a task.

    Attributes:
        goal: Roadmap task pose to go to (``pickup``, ``A_approach`` ...).
        action: What happens on arrival: ``move`` (nothing), ``pick`` (grip), ``place`` (release).
        station: The station this leg serves (``pickup`` or a drop station).
        dwell_s: How long the robot stays at the goal for the action (s).
    """

    goal: str
    action: Action
    station: str
    dwell_s: float


@dataclass(frozen=True, slots=True)
class LegDone:
    """What :meth:`TaskExecutive.arrived` reports.

    Attributes:
        leg: The leg that was reached.
        placed: The drop station where a block was just released (the task completed), else None.
        index: Number of completed tasks after this leg.
        leave_at: When the robot may leave for the next leg (arrival + dwell) (s).
        next_leg: The following leg.
    """

    leg: TaskLeg
    placed: str | None
    index: int
    leave_at: float
    next_leg: TaskLeg


class AssemblySequence:
    """The participant's order of drop stations: seeded rounds over the stations, shuffled, never the same
    station twice in a row."""

    def __init__(self, stations: Sequence[str], *, seed: int) -> None:
        if not stations:
            raise ValueError("an assembly sequence needs at least one drop station")
        self._stations = list(stations)
        self._rng = np.random.default_rng(seed)
        self._queue: list[str] = []
        self._last: str | None = None
        self._before: str | None = None  # the station served before the last one

    def next(self) -> str:
        """The next drop station in the round's seeded order."""
        return self.choose(_first)

    def allowed(self) -> list[str]:
        """The stations the next drop may serve: those the current round has not served yet (a new round
        when it is over), in the round's seeded order, without the station just served where another is
        left."""
        if not self._queue:
            self._queue = [self._stations[i] for i in self._rng.permutation(len(self._stations))]
        out = [s for s in self._queue if s != self._last]
        return out or list(self._queue)

    def choose(self, chooser: Callable[[list[str]], str]) -> str:
        """The next drop station, picked by ``chooser`` from :meth:`allowed` (and taken from the round).

        Raises:
            ValueError: the chooser picked a station that is not allowed.
        """
        allowed = self.allowed()
        pick = chooser(list(allowed))
        if pick not in allowed:
            raise ValueError(f"the station chooser picked {pick!r}, not one of {allowed}")
        self._queue.remove(pick)
        self._before, self._last = self._last, pick
        return pick

    def others(self, current: str) -> list[str]:
        """The stations the round still allows instead of ``current``, the one just chosen (not the station
        served before it, nor ``current``; none where ``current`` was the last of its round)."""
        return [s for s in self._queue if s not in (current, self._before)]

    def swap(self, current: str, other: str) -> None:
        """Serve ``other`` (one of :meth:`others`) instead of ``current``, which goes back into the round."""
        if other not in self.others(current):
            raise ValueError(f"{other!r} is not a station the round allows instead of {current!r}")
        self._queue.remove(other)
        self._queue.insert(0, current)
        self._last = other

    def peek(self, n: int) -> list[str]:
        """The next ``n`` stations without consuming them (draws rounds as needed)."""
        state = (self._rng.bit_generator.state, list(self._queue), self._last, self._before)
        out = [self.next() for _ in range(n)]
        self._rng.bit_generator.state, self._queue, self._last, self._before = state
        return out


def _first(allowed: list[str]) -> str:
    return allowed[0]


class TaskExecutive:
    """Pick-and-place legs in the participant's order.

    Args:
        cell: The work cell (its pickup and drop stations).
        seed: Seed of the assembly sequence (the participant's).
        pick_dwell_s: Time to grip a block at the conveyor (s).
        place_dwell_s: Time to release a block at a drop station (s).
        use_approach: Go through the approach poses above the stations (vertical descent and rise).
        goals: The goal names the roadmap knows; approach legs are used only for stations whose approach
            pose is among them (None: assume all exist).
        chooser: Picks each block's drop station from those the round allows, when the robot leaves the
            conveyor with it (None: the round's seeded order).
    """

    def __init__(
        self,
        cell: WorkCell,
        *,
        seed: int,
        pick_dwell_s: float = 0.4,
        place_dwell_s: float = 0.4,
        use_approach: bool = True,
        goals: Sequence[str] | None = None,
        chooser: Callable[[list[str]], str] | None = None,
    ) -> None:
        if pick_dwell_s < 0 or place_dwell_s < 0:
            raise ValueError("dwell times must be >= 0")
        self.pickup = cell.conveyor.pickup.name
        self.stations = [s.name for s in cell.drop_stations]
        self.sequence = AssemblySequence(self.stations, seed=seed)
        self.pick_dwell_s = float(pick_dwell_s)
        self.place_dwell_s = float(place_dwell_s)
        self._known = None if goals is None else set(goals)
        self.use_approach = use_approach
        self.chooser = chooser
        self.completed = 0
        self._legs: list[TaskLeg] = []
        self._current: TaskLeg | None = None
        self._carrying = False  # a block in the gripper: the next legs take it to its drop station

    def _approach(self, station: str) -> str | None:
        if not self.use_approach:
            return None
        name = f"{station}_approach"
        if self._known is not None and name not in self._known:
            return None
        return name

    def _pickup_legs(self) -> list[TaskLeg]:
        legs: list[TaskLeg] = []
        pa = self._approach(self.pickup)
        if pa is not None:
            legs.append(TaskLeg(pa, "move", self.pickup, 0.0))
        legs.append(TaskLeg(self.pickup, "pick", self.pickup, self.pick_dwell_s))
        if pa is not None:
            legs.append(TaskLeg(pa, "move", self.pickup, 0.0))
        return legs

    def _drop_legs(self, drop: str) -> list[TaskLeg]:
        legs: list[TaskLeg] = []
        da = self._approach(drop)
        if da is not None:
            legs.append(TaskLeg(da, "move", drop, 0.0))
        legs.append(TaskLeg(drop, "place", drop, self.place_dwell_s))
        if da is not None:
            legs.append(TaskLeg(da, "move", drop, 0.0))
        return legs

    @property
    def current(self) -> TaskLeg:
        """The leg in progress (the first one of the first task before anything happened)."""
        if self._current is None:
            self._current = self._pop()
        return self._current

    def _pop(self) -> TaskLeg:
        if not self._legs:
            if not self._carrying:
                self._legs = self._pickup_legs()
            elif self.chooser is None:
                self._legs = self._drop_legs(self.sequence.next())
            else:
                self._legs = self._drop_legs(self.sequence.choose(self.chooser))
        return self._legs.pop(0)

    def drop_alternatives(self) -> list[str]:
        """The drop stations the block in the gripper could go to instead of its own, before it is placed
        (none on any other leg)."""
        leg = self.current
        if not self._carrying or leg.station == self.pickup:
            return []
        return self.sequence.others(leg.station)

    def reroute_goal(self, station: str) -> str:
        """The goal :meth:`reroute` to ``station`` sets off for: the pickup's approach pose (away from the
        person, where the robot waits for its new station), or the station's own where it is there already."""
        back = self._approach(self.pickup)
        if back is not None and self.current.goal != back:
            return back
        first = self._drop_legs(station)[0]
        return first.goal

    def reroute(self, station: str) -> TaskLeg:
        """Take the block in the gripper to ``station`` (one of :meth:`drop_alternatives`) instead; its
        own station goes back into the round. Returns the new current leg."""
        if station not in self.drop_alternatives():
            raise ValueError(f"the block cannot go to {station!r} instead of {self.current.station!r}")
        self.sequence.swap(self.current.station, station)
        goal = self.reroute_goal(station)
        self._legs = self._drop_legs(station)
        if goal != self._legs[0].goal:  # away from the person first
            self._legs.insert(0, TaskLeg(goal, "move", station, 0.0))
        self._current = self._legs.pop(0)
        return self._current

    def upcoming_drops(self, n: int) -> list[str]:
        """The current task's drop station (if one is chosen) followed by the next ones (with a chooser,
        the round's order: the chooser may pick otherwise)."""
        current = [leg.station for leg in self._legs if leg.action == "place"]
        if self._current is not None and self._current.action == "place":
            current = [self._current.station, *current]
        return (current + self.sequence.peek(n))[:n]

    def arrived(self, t: float) -> LegDone:
        """The robot reached the current leg's goal at time ``t`` (s): do its action, move on."""
        leg = self.current
        placed = None
        if leg.action == "pick":
            self._carrying = True
        if leg.action == "place":
            self._carrying = False
            self.completed += 1
            placed = leg.station
        self._current = self._pop()
        return LegDone(leg, placed, self.completed, t + leg.dwell_s, self._current)
