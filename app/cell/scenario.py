"""Who else is in the simulated cell: the scenario file.

By default a simulated trial has one person, the operator across the table
(:class:`~app.cell.operator_sim.SimulatedOperator`). A scenario (a TOML file, ``HRC_SCENARIO`` or
``--scenario``) adds people around them; :class:`~app.cell.people_sim.SimulatedPeople` makes them::

    # passers-by: people who walk past the robot now and then, and leave the cell again
    [passers_by]
    count = 1                    # distinct walkers, each with its own body and tracker id
    interval_s = [20.0, 40.0]    # from one walker's pass to their next (start to start), drawn uniformly
    speed_mps = [1.0, 1.5]       # walking speed of a pass, drawn uniformly
    clearance_m = [0.2, 0.5]     # closest approach of the walker's path (the pelvis, on the floor) to the
                                 # robot's reach envelope, drawn uniformly per pass
    reach_m = 0.85               # the robot's reach from its base (a UR5e's)
    curve_m = [0.0, 0.15]        # how far the path bows towards the robot (0: straight), per pass
    enter_from = ["left", "right"]   # where a pass enters, drawn per pass (below)

    # a second participant at the table, at another work spot
    [second_operator]
    side = "left"                # the table's left (+y) or right (-y) side, seen from the robot
    along_m = 0.7                # where along that side their work spot lies (x, m)
    stations = []                # the drop stations whose blocks they fetch; empty: those nearer their
                                 # work spot than the operator's (the shipped cell, left side: D)

``enter_from`` (sides seen from the robot, whose x axis points to the operator): ``left`` enters on the
robot's left (+y) and walks across the cell behind the robot (-x) to leave on its right; ``right`` the
other way; ``back`` enters behind the robot and walks along its left or right side (drawn) towards the
operator's end and out; ``front`` the other way. A walker is in the cell (in the frames and the truth) while
every joint of theirs lies in the tracked volume (:func:`app.cell.people_sim.tracked_volume`).

Every draw is seeded: the walkers' and the second operator's bodies come from the participant's seed (the
same population as the operator's), their passes and behaviour from the trial's seed.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

__all__ = ["PassersBy", "Scenario", "ScenarioError", "SecondOperator", "load_scenario"]

EnterFrom = Literal["left", "right", "back", "front"]


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the file, the field and the reason."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _range(lo: float, hi: float) -> type:
    """A ``[lo, hi]`` pair of floats within the bounds (checked ordered by :func:`_ordered`)."""
    return Annotated[list[Annotated[float, Field(ge=lo, le=hi)]], Field(min_length=2, max_length=2)]


def _ordered(model: BaseModel, *names: str) -> None:
    for name in names:
        lo, hi = getattr(model, name)
        if lo > hi:
            raise ValueError(f"{name} = [{lo}, {hi}]: the first value must not exceed the second")


class PassersBy(_Strict):
    """People walking past the robot (see the module's docstring for the fields)."""

    count: int = Field(1, ge=1, le=8, description="distinct walkers")
    interval_s: _range(2.0, 3600.0) = Field(  # type: ignore[valid-type]
        [20.0, 40.0], description="time from one walker's pass to their next, start to start (s)"
    )
    first_s: _range(0.0, 3600.0) | None = Field(  # type: ignore[valid-type]
        None, description="when each walker's first pass starts (s after t0); default: like interval_s"
    )
    speed_mps: _range(0.3, 2.5) = Field([1.0, 1.5], description="walking speed (m/s)")  # type: ignore[valid-type]
    clearance_m: _range(0.0, 3.0) = Field(  # type: ignore[valid-type]
        [0.2, 0.5], description="closest approach of the pelvis path to the robot's reach envelope (m)"
    )
    reach_m: float = Field(0.85, gt=0.0, le=3.0, description="the robot's reach from its base (m)")
    curve_m: _range(0.0, 0.5) = Field(  # type: ignore[valid-type]
        [0.0, 0.0], description="how far the path bows towards the robot (m)"
    )
    enter_from: Annotated[list[EnterFrom], Field(min_length=1)] = ["left", "right"]

    @model_validator(mode="after")
    def _ranges_ordered(self) -> PassersBy:
        _ordered(self, "interval_s", "speed_mps", "clearance_m", "curve_m")
        if self.first_s is not None:
            _ordered(self, "first_s")
        return self


class SecondOperator(_Strict):
    """A second simulated participant at a side of the table (see the module's docstring)."""

    side: Literal["left", "right"] = "left"
    along_m: float = Field(0.7, ge=-3.0, le=3.0, description="x of their work spot along the table side (m)")
    stations: list[str] = Field(
        [], description="the drop stations they fetch from; empty: those nearer them than the operator"
    )


class Scenario(_Strict):
    """Who is in the simulated cell besides the operator: passers-by and/or a second operator.

    Attributes:
        name: A label for the records (default: the file's stem).
        passers_by: People who walk past (None: nobody).
        second_operator: A second participant at the table (None: nobody).
    """

    name: str = ""
    passers_by: PassersBy | None = None
    second_operator: SecondOperator | None = None

    @model_validator(mode="after")
    def _someone(self) -> Scenario:
        if self.passers_by is None and self.second_operator is None:
            raise ValueError("a scenario declares [passers_by] and/or [second_operator]")
        return self


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file.

    Raises:
        ScenarioError: the file is missing, is not TOML, or a field is unknown or invalid (the message
            names the file, the dotted field and the reason).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ScenarioError(f"cannot read the scenario file {p}: {exc.strerror or exc}") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"the scenario file {p} is not valid TOML: {exc}") from exc
    data.setdefault("name", p.stem)
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        msgs = "; ".join(f"{'.'.join(map(str, e['loc'])) or '<root>'}: {e['msg']}" for e in exc.errors())
        raise ScenarioError(f"invalid scenario file {p}: {msgs}") from None
