"""Safety over long seeded headless trials, judged by the ground-truth monitor.

The simulated operator is the truth; the runtime sees them only through the default tracker model (60 ms
latency, 1 cm noise, lost frames and bursts). At every servo tick the monitor (:mod:`app.safety.monitor`)
takes the robot's reported state and the person's *true* pose and requires ISO/TS 15066's protective
separation per robot part, with the directed speeds of both and the one stopping model. There must be no
violation and no contact, for either method, and the run must be meaningful: the robot worked near the
person.
"""

from __future__ import annotations

import pytest

from app.config import Settings, load_workcell
from app.control.engine import EngineOptions
from app.control.headless import run_headless_trial
from app.control.stack import PlanningStack

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> PlanningStack:
    from app.planning.roadmap import RoadmapConfig

    cache = tmp_path_factory.mktemp("roadmaps")
    return PlanningStack.build(
        load_workcell(),
        roadmap_config=RoadmapConfig(num_nodes=250),
        t_reaction_s=Settings().reaction_time_s(1 / 125),
        cache_dir=cache,
    )


@pytest.mark.parametrize(("method", "seed"), [("proactive", 1), ("reactive", 2)])
def test_the_moving_robot_never_comes_closer_than_the_protective_distance(
    stack: PlanningStack, method: str, seed: int
) -> None:
    res = run_headless_trial(
        settings=Settings(),
        method=method,  # type: ignore[arg-type]
        duration_s=45.0,
        seed=seed,
        stack=stack,
        fixed_compute_s=0.03,
        options=EngineOptions(record_frames=False),
    )
    assert res.status == "completed"
    safety = res.safety
    assert safety is not None and safety.checks >= 45 * 125
    # the run is meaningful: the robot worked, and worked near the person
    assert res.metrics.time_moving_s > 0.1 * res.metrics.duration_s
    assert safety.min_separation_moving_m < 0.5
    assert res.metrics.stop_replans + res.metrics.online_replans + res.metrics.completed_tasks > 0
    worst = None if safety.worst is None else safety.worst.to_json()
    assert safety.violations == 0, f"{safety.violations} violations; worst: {worst}"
    assert safety.contacts == 0
    assert res.metrics.violations == 0 and res.metrics.contacts == 0
