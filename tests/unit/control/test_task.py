from __future__ import annotations

import itertools

import pytest

from app.config import load_workcell
from app.control.task import AssemblySequence, TaskExecutive


def test_assembly_sequence_is_seeded_rounds_without_repeats() -> None:
    a = AssemblySequence(["A", "B", "C", "D"], seed=3)
    b = AssemblySequence(["A", "B", "C", "D"], seed=3)
    seq_a = [a.next() for _ in range(40)]
    assert seq_a == [b.next() for _ in range(40)]
    assert seq_a != [AssemblySequence(["A", "B", "C", "D"], seed=4).next() for _ in range(40)]
    for k in range(0, 40, 4):  # every round serves every station once
        assert sorted(seq_a[k : k + 4]) == ["A", "B", "C", "D"]
    assert all(x != y for x, y in itertools.pairwise(seq_a))


def test_peek_does_not_consume() -> None:
    s = AssemblySequence(["A", "B", "C"], seed=1)
    ahead = s.peek(5)
    assert [s.next() for _ in range(5)] == ahead


def test_task_legs_go_through_the_approach_poses_and_count_on_release() -> None:
    cell = load_workcell()
    ex = TaskExecutive(cell, seed=2, pick_dwell_s=0.3, place_dwell_s=0.5)
    drop = ex.upcoming_drops(1)[0]
    goals, placed = [], []
    t = 0.0
    for _ in range(6):
        leg = ex.current
        goals.append(leg.goal)
        done = ex.arrived(t)
        assert done.leg == leg and done.leave_at == pytest.approx(t + leg.dwell_s)
        if done.placed:
            placed.append((done.placed, done.index))
        t += 1.0
    assert goals == [
        "pickup_approach",
        "pickup",
        "pickup_approach",
        f"{drop}_approach",
        drop,
        f"{drop}_approach",
    ]
    assert placed == [(drop, 1)] and ex.completed == 1
    assert ex.current.goal == "pickup_approach"  # the next task begins


def test_without_approach_poses_the_legs_are_direct() -> None:
    cell = load_workcell()
    ex = TaskExecutive(cell, seed=0, goals=["pickup", "A", "B", "C", "D"])
    legs = []
    for _ in range(2):
        legs.append(ex.current)
        ex.arrived(0.0)
    assert [leg.action for leg in legs] == ["pick", "place"]
    with pytest.raises(ValueError, match="dwell"):
        TaskExecutive(cell, seed=0, pick_dwell_s=-1.0)
