"""Proactive and reactive are the same machine with a different forecast (the paper's definition).

The reactive baseline is the identical planner, supervisor, governor, SSM-aware timing and plan jobs, with
the forecast replaced by the person's current pose held still; nothing else may differ, or the comparison
of the two methods is not clean.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from app.config import Settings
from app.control.headless import run_headless_trial
from app.prediction.forecast import HumanForecast


def _engine(method: str) -> Any:
    seen: list[Any] = []

    def observe(t: float, engine: Any) -> None:
        if not seen:
            seen.append(engine)

    run_headless_trial(
        settings=Settings(), method=method, duration_s=1.0, seed=11, observer=observe, fixed_compute_s=0.01
    )
    return seen[0]


def test_proactive_and_reactive_differ_only_in_the_forecast() -> None:
    pro, rea = _engine("proactive"), _engine("reactive")
    # the supervisor's configuration: equal but for the method's name
    assert dataclasses.replace(pro.config, method="reactive") == rea.config
    # one planner (the same object), the same governor, law, separation model and SSM-aware timing
    assert pro.supervisor.planner is rea.supervisor.planner
    assert pro.separation == rea.separation
    assert pro.supervisor.speed_scale_law == rea.supervisor.speed_scale_law
    assert pro.governor_model == rea.governor_model
    assert pro.jobs.compute.timing == rea.jobs.compute.timing
    assert pro.jobs.compute.timing is not None  # SSM-aware timing is on for both by default
    assert (pro.jobs.compute.workers, pro.jobs.compute.deadline_s) == (
        rea.jobs.compute.workers,
        rea.jobs.compute.deadline_s,
    )
    assert pro.reaction_time_s == rea.reaction_time_s
    assert pro.options == rea.options
    # the forecast is what differs: a predictor (and the fetch anticipation) against the held pose
    assert pro.predictor is not None and rea.predictor is None
    assert rea.anticipation is None
    held = rea.last_forecast
    assert isinstance(held, HumanForecast)
    assert np.all(held.joints == held.joints[0])  # the current pose, held still
