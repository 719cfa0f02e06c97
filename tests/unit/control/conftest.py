"""Fixtures of the control tests: one small planning stack of the shipped cell for them all."""

from __future__ import annotations

import pytest

from app.config import Settings, load_workcell
from app.control.stack import PlanningStack


@pytest.fixture(scope="session")
def stack(tmp_path_factory: pytest.TempPathFactory) -> PlanningStack:
    """The shipped cell with a 250-node roadmap (built once, in a temporary cache) and this system's ``T_r``.
    A :class:`PlanningStack` is immutable, so every test may share it."""
    from app.planning.roadmap import RoadmapConfig

    return PlanningStack.build(
        load_workcell(),
        roadmap_config=RoadmapConfig(num_nodes=250),
        t_reaction_s=Settings().reaction_time_s(1 / 125),
        cache_dir=tmp_path_factory.mktemp("roadmaps"),
    )
