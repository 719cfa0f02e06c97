"""One assembly of a trial's world: the live runtime and the headless runner build the same world from the
same settings, and the live simulated operator is a participant of the settings' population."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.cell.operator_sim import OperatorParams
from app.cell.population import DEFAULT_POPULATION_PATH
from app.cell.tracker import TrackerModel
from app.config import Settings
from app.control.engine import TrialEngine
from app.control.headless import run_headless_trial
from app.control.runtime import Runtime
from app.control.stack import PlanningStack
from app.control.world import TrialWorld, predictor_info

SEED = 5


@pytest.fixture
def slow_population(tmp_path: Path) -> Path:
    """A population whose participants react in 2-2.5 s (the shipped one: 0.3-1.2 s)."""
    text = DEFAULT_POPULATION_PATH.read_text().replace(
        "[reaction_s]\nuniform = { lo = 0.3, hi = 1.2 }", "[reaction_s]\nuniform = { lo = 2.0, hi = 2.5 }"
    )
    path = tmp_path / "slow.toml"
    path.write_text(text)
    return path


@pytest.fixture
def worlds(monkeypatch: pytest.MonkeyPatch) -> list[tuple[TrialWorld, TrialEngine]]:
    """Every world that a trial's engine is made of, with the engine, in order."""
    built: list[tuple[TrialWorld, TrialEngine]] = []
    engine = TrialWorld.engine

    def record(self: TrialWorld, **kwargs: Any) -> TrialEngine:
        built.append((self, engine(self, **kwargs)))
        return built[-1][1]

    monkeypatch.setattr(TrialWorld, "engine", record)
    return built


def _live_worlds(settings: Settings, stack: PlanningStack, seeds: list[int]) -> list[TrialWorld]:
    """The worlds of live proactive trials with ``seeds`` (each stopped as soon as it started)."""
    out = []
    with Runtime(settings, stack=stack) as rt:
        for k, seed in enumerate(seeds):
            rt.start_trial(trial_id=k + 1, method="proactive", duration_s=5.0, seed=seed)
            assert rt.world is not None and rt.world.seed == seed
            out.append(rt.world)
            rt.stop_trial()
    return out


def test_the_live_and_the_headless_runs_build_the_same_world(
    stack: PlanningStack, slow_population: Path, worlds: list[tuple[TrialWorld, TrialEngine]]
) -> None:
    settings = Settings(human_source="sim", robot="sim", planner_workers=1, population=slow_population)
    (live,) = _live_worlds(settings, stack, [SEED])
    live_engine = next(e for w, e in worlds if w is live)
    run_headless_trial(
        settings=settings, method="proactive", duration_s=0.2, seed=SEED, stack=stack, fixed_compute_s=0.01
    )
    headless, headless_engine = worlds[-1]
    assert headless is not live and headless.seed == SEED
    # the same participant (drawn from the settings' population), behaviour seed and tracker
    assert live.person.params == headless.person.params
    assert live.person.params == OperatorParams.draw(SEED, OperatorParams.population(slow_population))
    assert (live.seed, live.participant_seed) == (headless.seed, headless.participant_seed) == (SEED, SEED)
    assert live.tracker is not None
    assert live.tracker == headless.tracker == TrackerModel.from_settings(settings)
    assert live.truth is not None and headless.truth is not None
    # the same settings, predictor, supervisor and servo period
    assert live.settings == headless.settings
    assert predictor_info(live.predictor) == predictor_info(headless.predictor)
    assert live.supervisor_config("proactive") == headless.supervisor_config("proactive")
    assert live_engine.config == headless_engine.config
    assert live.options.servo_period_s == headless.options.servo_period_s
    assert live_engine.seed == headless_engine.seed == SEED


def test_the_live_simulated_operator_is_a_participant_of_the_population_file(
    stack: PlanningStack, slow_population: Path
) -> None:
    settings = Settings(human_source="sim", robot="sim", planner_workers=1, population=slow_population)
    seeds = [1, 2, 3]
    slow = OperatorParams.population(slow_population)
    for seed, world in zip(seeds, _live_worlds(settings, stack, seeds), strict=True):
        assert world.person.params == OperatorParams.draw(seed, slow)
        assert 2.0 <= world.person.params.reaction_s <= 2.5  # the shipped population's: 0.3-1.2 s


def test_the_proactive_and_the_reactive_trial_differ_only_in_the_forecast(
    stack: PlanningStack, worlds: list[tuple[TrialWorld, TrialEngine]]
) -> None:
    """Like for like: the same participant, settings, planner, plan jobs, speed governor and judge; the
    proactive trial has the predictor (and the task's expected fetch, part of its forecast), the reactive one
    the person held still. Both weigh the same candidate, the held person: for the reactive method that is
    its own forecast, so it weighs nothing more."""
    import dataclasses

    settings = Settings(human_source="sim", robot="sim", planner_workers=1)
    for method in ("proactive", "reactive"):
        run_headless_trial(
            settings=settings, method=method, duration_s=1.0, seed=SEED, stack=stack, fixed_compute_s=0.01
        )
    (pw, pe), (rw, re) = worlds[-2:]
    assert (pe.method, re.method) == ("proactive", "reactive")
    assert pw.settings == rw.settings and pw.person.params == rw.person.params and pw.tracker == rw.tracker
    assert pe.options == re.options and pe.seed == re.seed
    assert dataclasses.replace(pe.config, method="reactive") == re.config  # the method's name apart
    assert pe.supervisor.planner is re.supervisor.planner  # one planner, one roadmap
    assert pe.supervisor.ssm == re.supervisor.ssm
    assert pe.jobs.compute.timing == re.jobs.compute.timing  # the same governor model times the plans
    assert pe.monitor is not None and re.monitor is not None
    for a in ("ssm", "t_r", "stopping", "pfl", "part_names"):  # the same judge
        assert getattr(pe.monitor, a) == getattr(re.monitor, a), a
    # the forecast: the predictor and the expected fetch, or the person held still
    assert pe.predictor is not None and pe.anticipation is not None
    assert re.predictor is None and re.anticipation is None
    assert pe.last_forecast is not None and re.last_forecast is not None
    held = re.last_forecast
    assert held.times.size == 1 and np.array_equal(held.joints[0], re.last_frame.joints)


def test_with_the_exact_future_the_proactive_plan_never_arrives_later_than_the_reactive_one(
    stack: PlanningStack, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every decision of a proactive trial that sets the robot off (a start or a resume), with the simulated
    person's exact future as its forecast (the oracle): wherever the plan the reactive method would take
    passes the check under that future, the plan the proactive method takes is predicted to arrive no later
    (the forecast's own plan, or that one). A backup of a plan under way keeps the forecast's own plan
    without weighing the candidate (:meth:`BackupComputer.compute_raw`), so it is not among them."""
    from app.control.backup import BackupComputer, BackupRequest, PlanOutcome

    compute_raw = BackupComputer.compute_raw
    seen: list[tuple[str | None, float, float]] = []

    def checked(self: BackupComputer, req: BackupRequest) -> PlanOutcome:
        out = compute_raw(self, req)
        if not (req.has_candidate and req.sets_off):
            return out
        assert req.candidate is not None
        alone = self._plan_one(req, req.candidate, None, self.timer())  # the reactive method's plan
        if alone.status == "ok":
            assert alone.traj is not None
            t_v, arrival = self.planner.predicted_check(alone.traj, req.forecast, timing=self.timing)
            if t_v is None:
                assert out.status == "ok" and out.traj is not None
                mine = out.arrival_s if out.arrival_s is not None else out.traj.t_end
                seen.append((out.chosen, mine, arrival))
        return out

    monkeypatch.setattr(BackupComputer, "compute_raw", checked)
    settings = Settings(human_source="sim", robot="sim", planner_workers=1)
    run_headless_trial(
        settings=settings, method="proactive", duration_s=40.0, seed=SEED, stack=stack,
        fixed_compute_s=0.01, forecast="oracle",
    )  # fmt: skip
    assert len(seen) >= 5
    late = [(c, a, b) for c, a, b in seen if a > b + 1e-6]
    assert not late, late
