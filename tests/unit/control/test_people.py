"""The tracks of the people in the cell (:mod:`app.control.people`): new, lost, renamed and dropped bodies,
and one predictor per person."""

from __future__ import annotations

import numpy as np
import pytest

from app.control.people import People, PeopleOptions
from app.prediction.forecast import HumanForecast, Predictor
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS, HumanFrame

DT = 1 / 30


def _body(x: float, y: float = 0.0) -> np.ndarray:
    """A stick body standing with its pelvis at (x, y, 1.0)."""
    j = np.zeros((NUM_JOINTS, 3))
    j[:, 0], j[:, 1] = x, y
    j[:, 2] = np.linspace(0.1, 1.7, NUM_JOINTS)
    j[JOINT_INDEX["pelvis"]] = (x, y, 1.0)
    return j


def _frame(t: float, bodies: dict[int, np.ndarray]) -> HumanFrame:
    return HumanFrame.stack(t, [HumanFrame(t, j, body_ids=(i,)) for i, j in bodies.items()])


class _Counting(Predictor):
    """Holds the pose, 3 samples; counts the frames it saw."""

    effective_kind = "counting"

    def __init__(self) -> None:
        self.seen = 0
        self.forecasts = 0
        self.spawned: list[_Counting] = []

    def reset(self) -> None:
        self.seen = 0

    def spawn(self) -> _Counting:
        twin = _Counting()
        self.spawned.append(twin)
        return twin

    def observe(self, frame: HumanFrame) -> None:
        assert frame.bodies == 1
        self.seen += 1

    def update(self, frame: HumanFrame) -> HumanForecast:
        self.observe(frame)
        self.forecasts += 1
        times = frame.t + DT * np.arange(3)
        return HumanForecast(frame.t, times, np.repeat(frame.joints[None], 3, axis=0), np.full(3, 0.05))


def test_the_first_bodies_are_not_new_and_a_later_one_is_until_it_settles() -> None:
    people = People()
    first = people.update(_frame(0.0, {3: _body(1.4)}))
    assert first.appeared == () and first.settling == () and first.frame.body_ids == (3,)
    t = DT
    up = people.update(_frame(t, {3: _body(1.4), 5: _body(0.3, -0.9)}))
    assert up.appeared == (5,) and up.settling == (5,)
    while t < 10 / 30 - 1e-9:
        t += DT
        up = people.update(_frame(t, {3: _body(1.4), 5: _body(0.3, -0.9)}))
    assert up.appeared == () and up.settling == (5,)  # tracked for 9 frames
    up = people.update(_frame(t + 2 * DT, {3: _body(1.4), 5: _body(0.3, -0.9)}))
    assert up.settling == () and people.appeared == 1


def test_a_lost_body_is_held_with_its_age_then_dropped() -> None:
    people = People(options=PeopleOptions(hold_s=0.3))
    people.update(_frame(0.0, {1: _body(1.4), 2: _body(1.0, 0.6)}))
    up = people.update(_frame(0.2, {1: _body(1.4)}))
    assert up.frame.body_ids == (1, 2)
    assert up.ages_s.tolist() == pytest.approx([0.0, 0.2])
    np.testing.assert_allclose(up.frame.body(1).joints, _body(1.0, 0.6))
    assert up.seen.body_ids == (1,)
    up = people.update(_frame(0.4, {1: _body(1.4)}))
    assert up.dropped == (2,) and up.frame.body_ids == (1,) and people.dropped == 1


def test_an_id_that_changes_keeps_its_track_and_predictor() -> None:
    pred = _Counting()
    people = People(pred)
    for k in range(5):
        up = people.update(_frame(k * DT, {4: _body(1.4 - 0.01 * k)}))
        people.forecast(up, margin_m=0.02)
    up = people.update(_frame(5 * DT, {11: _body(1.35)}))  # the tracker's new id, where 4 was
    assert up.renamed == {11: 4} and up.appeared == () and up.frame.body_ids == (4,)
    fc = people.forecast(up, margin_m=0.02)
    assert fc.body_ids == (4,) and pred.seen == 6 and not pred.spawned
    # a new id far from any lost body is a new person, with a predictor of their own
    up = people.update(_frame(6 * DT, {11: _body(1.34), 12: _body(0.2, -1.0)}))
    assert up.appeared == (12,)
    fc = people.forecast(up, margin_m=0.02)
    assert fc.body_ids == (4, 12) and fc.joints.shape == (3, 2 * NUM_JOINTS, 3)
    assert len(pred.spawned) == 1 and pred.spawned[0].seen == 1 and pred.seen == 7


def test_a_lost_body_is_forecast_held_with_a_margin_grown_by_its_age() -> None:
    people = People(_Counting(), PeopleOptions(hold_s=1.0, growth_mps=1.6))
    people.update(_frame(0.0, {1: _body(1.4), 2: _body(1.0, 0.6)}))
    up = people.update(_frame(0.25, {1: _body(1.4)}))
    fc = people.forecast(up, margin_m=0.02)
    assert fc.body_ids == (1, 2)
    # the shared margin at t0 is the lost body's: 0.02 + 1.6 x 0.25
    assert fc.margins[0] == pytest.approx(0.02 + 1.6 * 0.25)
    np.testing.assert_allclose(fc.joints[-1, NUM_JOINTS:], _body(1.0, 0.6))


def test_no_body_is_an_empty_cell() -> None:
    people = People(_Counting())
    up = people.update(HumanFrame.stack(0.0, []))
    assert up.frame.bodies == 0
    fc = people.forecast(up, margin_m=0.02)
    assert fc.bodies == 0 and fc.joints.shape == (1, 0, 3)


def test_the_first_person_is_forecast_before_the_decision_and_the_others_in_turn_after_it() -> None:
    pred = _Counting()
    people = People(pred)
    bodies = {0: _body(1.4), 1: _body(1.4, 1.2), 2: _body(1.4, -1.2), 3: _body(2.1, 0.4)}
    made: list[tuple[float, ...]] = []  # when each body's forecast at the decision was made
    for k in range(7):
        t = k * DT
        fc = people.forecast(people.update(_frame(t, bodies)), margin_m=0.02, first=0)
        assert fc.body_ids == (0, 1, 2, 3) and fc.t0 == pytest.approx(t)
        made.append(tuple(people._tracks[i].forecast.t0 for i in range(4)))  # type: ignore[union-attr]
        preds = [pred, *pred.spawned]
        # at the decision, the others have not taken this capture yet (except at the first: everyone new)
        assert [p.seen for p in preds] == ([1, 1, 1, 1] if k == 0 else [k + 1, k, k, k])
        people.catch_up()
        assert all(p.seen == k + 1 for p in preds)  # every capture in every person's history
    # the first capture forecasts everyone; then two per capture: body 0 before every decision, the others in
    # turn after it, for the next decision
    assert [p.forecasts for p in preds] == [7, 3, 3, 3]
    assert [m[0] for m in made] == pytest.approx([k * DT for k in range(7)])
    assert made[1][1:] == pytest.approx((0.0, 0.0, 0.0))
    assert made[2][1:] == pytest.approx((DT, 0.0, 0.0))
    assert made[4][1:] == pytest.approx((DT, 2 * DT, 3 * DT))
    assert made[6][1:] == pytest.approx((4 * DT, 5 * DT, 3 * DT))


def test_a_capture_not_caught_up_is_taken_before_the_next_forecast() -> None:
    pred = _Counting()
    people = People(pred)
    bodies = {0: _body(1.4), 1: _body(1.4, 1.2)}
    people.forecast(people.update(_frame(0.0, bodies)), margin_m=0.02, first=0)
    # no catch_up after this one: its decision failed
    people.forecast(people.update(_frame(DT, bodies)), margin_m=0.02, first=0)
    people.forecast(people.update(_frame(2 * DT, bodies)), margin_m=0.02, first=0)
    other = pred.spawned[0]
    assert other.seen == 2 and other.forecasts == 2  # the capture at DT taken late and forecast from
    people.catch_up()
    assert other.seen == 3 and pred.seen == 3
