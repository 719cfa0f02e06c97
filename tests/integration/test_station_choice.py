"""The drop station chosen by the method's forecast (``Settings.station_choice="forecast"``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.config import Settings
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import HumanFrame
from tests.integration.test_same_machine import engine_of


def _engine(method: str, choice: str) -> Any:
    return engine_of(method, Settings(station_choice=choice))


def test_both_methods_choose_with_their_own_forecast_and_only_when_asked() -> None:
    pro, rea = _engine("proactive", "forecast"), _engine("reactive", "forecast")
    assert pro.task.chooser == pro._choose_station and rea.task.chooser == rea._choose_station
    assert _engine("reactive", "sequence").task.chooser is None


def test_the_station_farthest_from_the_forecast_person_is_chosen() -> None:
    engine = _engine("reactive", "forecast")
    poses = engine._stations
    names = sorted(poses)
    far = max(names, key=lambda n: float(np.linalg.norm(poses[n] - poses[names[0]])))
    frame = engine.last_frame
    # the person's every joint at the first station now, then at the farthest one a second later
    at_first = np.broadcast_to(poses[names[0]], frame.joints.shape)
    still = HumanForecast.hold(HumanFrame(frame.t, at_first.copy()), margin_m=0.02)
    engine.last_forecast = still
    assert engine._choose_station(names) != names[0]
    assert engine._choose_station(names) == far  # the farthest from where they are
    moving = HumanForecast(
        t0=frame.t,
        times=frame.t + np.array([0.0, 1.0]),
        joints=np.stack([at_first, np.broadcast_to(poses[far], frame.joints.shape)]),
        margins=np.array([0.02, 0.02]),
    )
    engine.last_forecast = moving  # ... and where they will be: neither end of their way
    assert engine._choose_station(names) not in (names[0], far)
    engine.last_forecast = None
    assert engine._choose_station(names[::-1]) == names[-1]  # no forecast yet: the round's order


def _person(engine: Any, *, head_at: np.ndarray, hands_at: np.ndarray) -> HumanForecast:
    """A forecast person held still: head, neck and chest at ``head_at``, arms and hands at ``hands_at``,
    the rest of the body far from the table."""
    from app.prediction.skeleton import JOINT_INDEX

    frame = engine.last_frame
    joints = np.broadcast_to(np.array([2.5, 0.0, 0.5]), frame.joints.shape).copy()
    for name in ("chest", "neck", "head"):
        joints[JOINT_INDEX[name]] = head_at
    for name in ("l_elbow", "l_wrist", "l_hand", "r_elbow", "r_wrist", "r_hand"):
        joints[JOINT_INDEX[name]] = hands_at
    return HumanForecast.hold(HumanFrame(frame.t, joints), margin_m=0.02)


def test_with_power_and_force_limiting_the_choice_keeps_away_from_the_head_not_the_hands() -> None:
    """The regions that admit no contact hold the robot at S_p: the chosen station is the one farthest
    from the head and neck, even where the hands are (a contact there is allowed at the region's speed);
    with SSM alone every region counts."""
    names = sorted(_engine("reactive", "forecast")._stations)
    for pfl, hands_win in ((True, True), (False, False)):
        engine = engine_of("reactive", Settings(station_choice="forecast", pfl=pfl))
        poses = engine._stations
        head_at = poses[names[0]] + np.array([0.1, 0.0, 0.35])  # leaning over the first station
        far = max(names, key=lambda n: float(np.linalg.norm(poses[n] - poses[names[0]])))
        engine.last_forecast = _person(engine, head_at=head_at, hands_at=poses[far] + np.array([0, 0, 0.05]))
        chosen = engine._choose_station(names)
        assert chosen != names[0]
        assert (chosen == far) is hands_win, (pfl, chosen, far)
