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


def test_a_chooser_picks_each_drop_within_the_round_when_the_block_is_picked() -> None:
    """With a chooser, every round still serves every station once and never one twice in a row; the
    chooser sees only the stations the round allows, is asked when the robot leaves the conveyor with the
    block, and a pick outside them is refused."""
    cell = load_workcell()
    offered: list[list[str]] = []

    def last_allowed(allowed: list[str]) -> str:
        offered.append(allowed)
        return allowed[-1]

    ex = TaskExecutive(cell, seed=5, chooser=last_allowed)
    placed = []
    for _ in range(6 * 12):
        leg = ex.current
        if leg.goal == "pickup":
            n = len(offered)
            ex.arrived(0.0)
            assert len(offered) == n  # not yet: the robot is still at the conveyor
            continue
        done = ex.arrived(0.0)
        if done.placed:
            placed.append(done.placed)
    assert len(placed) == 12 and len(offered) == 12
    for k in range(0, 12, 4):
        assert sorted(placed[k : k + 4]) == sorted(s.name for s in cell.drop_stations)
    assert all(x != y for x, y in itertools.pairwise(placed))
    assert all(p == o[-1] for p, o in zip(placed, offered, strict=True))
    assert len(offered[0]) == 4 and len(offered[1]) == 3  # the round shrinks as it is served
    assert placed[3] not in offered[4]  # a new round never starts with the station just served

    seq = AssemblySequence(["A", "B", "C"], seed=0)
    with pytest.raises(ValueError, match="not one of"):
        seq.choose(lambda allowed: "Z")


def test_without_a_chooser_the_drops_follow_the_seeded_sequence() -> None:
    cell = load_workcell()
    ex = TaskExecutive(cell, seed=9)
    expected = AssemblySequence([s.name for s in cell.drop_stations], seed=9)
    placed = []
    while len(placed) < 8:
        done = ex.arrived(0.0)
        if done.placed:
            placed.append(done.placed)
    assert placed == [expected.next() for _ in range(8)]


def test_a_block_held_up_on_its_way_goes_to_another_station_of_the_round_by_the_conveyor() -> None:
    """A block whose drop station the person blocks goes to another station the round still allows (not the
    one just served): the robot backs off to the conveyor's approach pose first, its own station goes back
    into the round, and every round still serves every station once."""
    cell = load_workcell()
    ex = TaskExecutive(cell, seed=3)
    assert ex.drop_alternatives() == []  # on the way to the conveyor: nothing to reroute
    placed = []
    while ex.current.goal != "pickup_approach" or not placed:  # the first task, as it comes
        done = ex.arrived(0.0)
        if done.placed:
            placed.append(done.placed)
    ex.arrived(0.0)  # at the conveyor's approach pose
    ex.arrived(0.0)  # picked
    ex.arrived(0.0)  # back at the approach pose, the block for its station
    own = ex.current.station
    assert ex.current.goal == f"{own}_approach"
    others = ex.drop_alternatives()
    assert own not in others and placed[0] not in others and len(others) == 2
    with pytest.raises(ValueError, match="cannot go"):
        ex.reroute(own)
    assert ex.reroute_goal(others[0]) == "pickup_approach"
    leg = ex.reroute(others[0])
    assert (leg.goal, leg.action, leg.station) == ("pickup_approach", "move", others[0])
    assert ex.drop_alternatives() == [s for s in (own, others[1]) if s != placed[0]]  # own is back
    goals = []
    while len(placed) < 8:
        goals.append(ex.current.goal)
        done = ex.arrived(0.0)
        if done.placed:
            placed.append(done.placed)
    assert goals[:4] == ["pickup_approach", f"{others[0]}_approach", others[0], f"{others[0]}_approach"]
    assert placed[1] == others[0]
    for k in (0, 4):
        assert sorted(placed[k : k + 4]) == sorted(s.name for s in cell.drop_stations)
    assert all(x != y for x, y in itertools.pairwise(placed))

    seq = AssemblySequence(["A", "B", "C"], seed=1)
    first = seq.next()
    with pytest.raises(ValueError, match="not a station the round allows"):
        seq.swap(first, first)
