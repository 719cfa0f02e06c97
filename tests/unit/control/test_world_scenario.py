"""A scenario in the settings puts its people in the trial's world: the truth, the tracked source and the
oracle are those of every person; no scenario leaves the operator alone; a scenario that cannot be used is
an error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.cell.clock import SimClock
from app.cell.operator_sim import OperatorParams, OracleForecaster, SimulatedOperator
from app.cell.people_sim import FIRST_WALKER_ID, OPERATOR_ID, PeopleOracle, SimulatedPeople
from app.cell.robot import SimRobot
from app.cell.tracker import TrackedSource
from app.config import Settings, load_workcell
from app.control.stack import PlanningStack
from app.control.world import TrialWorld, build_trial_world, make_operator

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"
PASSER_BY = EXAMPLES / "scenario_passer_by.toml"


def _world(settings: Settings, stack: PlanningStack, **kw: object) -> TrialWorld:
    return build_trial_world(
        settings,
        load_workcell(),
        seed=5,
        participant_seed=3,
        stack=stack,
        make_robot=lambda q: SimRobot(SimClock(0.0), q0=q),
        **kw,  # type: ignore[arg-type]
    )


def test_the_scenario_of_the_settings_puts_its_people_in_the_world(stack: PlanningStack) -> None:
    world = _world(Settings(human_source="sim", scenario=PASSER_BY), stack, method="reactive")
    people = world.person
    assert isinstance(people, SimulatedPeople)
    assert people.operators[OPERATOR_ID].params == OperatorParams.draw(3)  # the trial's participant
    assert not people.operators[OPERATOR_ID].noise  # the truth carries no noise
    walker = people.walkers[FIRST_WALKER_ID]
    t = walker.passes_until(60.0)[0].t_closest
    truth = world.truth(t)  # every person present, with their ids
    assert truth.body_ids == (OPERATOR_ID, FIRST_WALKER_ID)
    assert np.array_equal(truth.joints, people.pose_at(t))
    tracked = world.source.source
    assert isinstance(tracked, TrackedSource) and tracked.truth is people
    frame = tracked.frame_at(t)
    assert frame is not None and frame.body_ids == (OPERATOR_ID, FIRST_WALKER_ID)
    # the block placements reach the operator through the tracked source
    tracked.notify_block_placed("B", t)
    people.pose_at(t + 8.0)
    assert [a.station for a in people.operators[OPERATOR_ID].actions if a.kind == "fetch"] == ["B"]


def test_the_oracle_of_a_scenario_forecasts_every_person(stack: PlanningStack) -> None:
    settings = Settings(human_source="sim", scenario=PASSER_BY)
    world = _world(settings, stack, method="proactive", forecast="oracle")
    assert isinstance(world.predictor, PeopleOracle) and world.predictor.people is world.person
    alone = _world(Settings(human_source="sim"), stack, method="proactive", forecast="oracle")
    assert isinstance(alone.predictor, OracleForecaster) and isinstance(alone.person, SimulatedOperator)


def test_without_a_scenario_the_operator_is_alone_and_a_scenario_needs_the_simulated_cell(
    tmp_path: Path,
) -> None:
    cell = load_workcell()
    op = make_operator(cell, source="sim", seed=5, participant_seed=3, noise=False)
    assert isinstance(op, SimulatedOperator)
    people = make_operator(cell, source="sim", seed=5, participant_seed=3, noise=False, scenario=PASSER_BY)
    assert isinstance(people, SimulatedPeople)
    # the operator of the scenario is the operator alone, pose for pose
    for t in np.arange(0.0, 10.0, 0.5):
        assert np.array_equal(people.operators[OPERATOR_ID].pose_at(float(t)), op.pose_at(float(t)))
    with pytest.raises(ValueError, match="needs the simulated operator"):
        make_operator(cell, source="replay", seed=5, participant_seed=3, clip="x.npz", scenario=PASSER_BY)
    bad = tmp_path / "bad.toml"
    bad.write_text("[passers_by]\ncount = 0\n")
    with pytest.raises(ValueError, match=r"passers_by\.count"):
        make_operator(cell, source="sim", seed=5, participant_seed=3, scenario=bad)
