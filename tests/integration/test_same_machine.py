"""Proactive and reactive are the same machine with a different forecast (the paper's definition).

The reactive baseline is the identical planner, supervisor, governor, SSM-aware timing and plan jobs, with
the forecast replaced by the person's current pose held still; nothing else may differ, or the comparison
of the two methods is not clean. Checked twice: their configurations compared, and a proactive trial fed the
reactive forecast run against the reactive trial, event by event.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from app.config import Settings, load_workcell
from app.control.engine import EngineOptions
from app.control.headless import run_headless_trial
from app.prediction.forecast import HumanForecast, Predictor

EXAMPLE_CELL = Path(__file__).resolve().parents[2] / "examples" / "workcell_stations_moved.toml"


def engine_of(method: str, settings: Settings | None = None) -> Any:
    """The engine of a 1-s headless trial of ``method`` (default settings unless given)."""
    seen: list[Any] = []

    def observe(t: float, engine: Any) -> None:
        if not seen:
            seen.append(engine)

    run_headless_trial(
        settings=settings or Settings(),
        method=method,
        duration_s=1.0,
        seed=11,
        observer=observe,
        fixed_compute_s=0.01,
    )
    return seen[0]


def test_proactive_and_reactive_differ_only_in_the_forecast() -> None:
    pro, rea = engine_of("proactive"), engine_of("reactive")
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


class _HeldPose(Predictor):
    """A predictor that forecasts what the reactive baseline assumes: the current pose, held still, with the
    tracking margin."""

    effective_kind = "held_pose"

    def __init__(self, margin_m: float) -> None:
        self.margin_m = margin_m

    def reset(self) -> None:
        """Nothing to forget."""

    def update(self, frame: Any) -> HumanForecast:
        return HumanForecast.hold(frame, margin_m=self.margin_m)


def test_the_proactive_method_fed_the_held_pose_runs_the_reactive_trial() -> None:
    # end to end: with its forecast replaced by the reactive one (and without the fetch anticipation, which
    # is part of the proactive forecast), the proactive method must run exactly the reactive trial; any
    # other difference between the methods would show in its plans, stops or time budget
    settings = Settings(anticipate_fetch=False)
    margin = EngineOptions().tracking_margin_m
    cell = load_workcell(EXAMPLE_CELL)  # a cell where the robot completes tasks (about one a minute)
    kw: dict[str, Any] = dict(settings=settings, cell=cell, duration_s=120.0, seed=11, fixed_compute_s=0.01)
    pro = run_headless_trial(method="proactive", predictor=_HeldPose(margin), **kw)
    rea = run_headless_trial(method="reactive", **kw)
    assert rea.metrics.completed_tasks >= 1 and rea.metrics.stop_replans >= 1  # the trial exercises both
    for field in ("completed_tasks", "stop_replans", "online_replans", "plans_computed", "violations"):
        assert getattr(pro.metrics, field) == getattr(rea.metrics, field), field
    assert pro.time_budget_s == rea.time_budget_s
    assert [(e.t, e.kind) for e in pro.events] == [(e.t, e.kind) for e in rea.events]
