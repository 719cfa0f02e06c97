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
