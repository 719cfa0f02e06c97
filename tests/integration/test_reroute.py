"""A robot that the person holds still on its way to a drop station takes the block elsewhere
(``Settings.reroute_after_s``), and without the setting it waits.

End to end in the shipped cell with the elbow left free (both of its branches: the shipped cell keeps it
on home's side, and there this trial does not stall): a study participant (seed 7's second) who stands idle
beside station C while the robot brings its first block there holds the robot still within the ``S_p`` of
their neck. With ``reroute_after_s`` the robot gives up C for another station of the round after that long,
by way of the conveyor's approach pose; without it the robot keeps waiting for C. The judge stays clean
either way.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from app.config import Settings, WorkCell
from app.control.headless import run_headless_trial
from app.study.runner import participant_seeds

DURATION_S = 30.0
SHIPPED = Path(__file__).resolve().parents[2] / "app/assets/workcell.toml"


@pytest.fixture(scope="module")
def cell(elbow_free: Callable[[Path], WorkCell]) -> WorkCell:
    return elbow_free(SHIPPED)


def _trial(cell: WorkCell, **settings: object) -> object:
    p_seed, t_seed = participant_seeds(7, 10)[1]
    return run_headless_trial(
        settings=Settings(**settings),  # type: ignore[arg-type]
        cell=cell,
        method="proactive",
        duration_s=DURATION_S,
        seed=t_seed,
        participant_seed=p_seed,
        fixed_compute_s=0.012,
    )


def test_a_robot_held_still_on_its_way_to_a_station_takes_the_block_to_another(cell: WorkCell) -> None:
    waits = _trial(cell)
    assert not [e for e in waits.events if e.kind == "rerouted"]
    assert waits.metrics.completed_tasks == 0  # held beside the person, on its way to C, all along

    res = _trial(cell, reroute_after_s=3.0)
    rerouted = [e for e in res.events if e.kind == "rerouted"]
    assert rerouted and rerouted[0].payload == {"goal": "pickup_approach"}
    assert rerouted[0].t > 3.0
    for r in (waits, res):
        assert r.safety is not None
        assert r.safety.violations == 0 and r.safety.harmful_contacts == 0
