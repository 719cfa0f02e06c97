"""The planner's :class:`RoadmapView`: read-only, live for the heuristics computed after it, and the only
way a search reads the roadmap."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

import app.planning.search.search_state as search_state_module
from app.planning.search import Planner, RoadmapView
from tests.unit.planning.test_search import PointRobot, config, q_of, roadmap


def test_the_view_is_read_only_and_sees_the_heuristics_computed_after_it() -> None:
    rm = roadmap([(0.0, 0.0), (0.3, 0.0), (0.6, 0.0)], [(0, 1), (1, 2)], s=0)
    planner = Planner(rm, PointRobot(), config=config())
    view = planner.view
    assert isinstance(view, RoadmapView)
    assert view.num_nodes == 3 and view.ik is rm.ik and not view.compiled
    np.testing.assert_array_equal(view.stations, [0])
    with pytest.raises(dataclasses.FrozenInstanceError):
        view.ik = np.zeros_like(rm.ik)  # type: ignore[misc]
    with pytest.raises(TypeError):
        view.next_rows[2] = []  # type: ignore[index]
    assert 2 not in view.next_rows  # node 2 is no station: its heuristic is computed by the first query
    res = planner.plan(q_start=q_of(0.0, 0.0), t_start=0.0, goal=2, forecast=None)
    assert res.ok and 2 in view.next_rows
    # the lookahead's next move from node 0 (branch 0) is the CSR entry 0 -> 1 at parent branch 0
    assert view.next_rows[2][0] == 0 and view.indices_list[0] == 1


def test_a_search_reads_no_private_attribute_but_its_own() -> None:
    tree = ast.parse(Path(search_state_module.__file__).read_text())
    foreign = sorted(
        f"{ast.unparse(node.value)}.{node.attr} (line {node.lineno})"
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and node.attr.startswith("_")
        and not node.attr.startswith("__")
        and ast.unparse(node.value) != "self"
    )
    assert not foreign, f"the run reads other objects' private attributes: {foreign}"
