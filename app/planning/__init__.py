"""Motion planning for the UR5e beside a person: pure computation over numpy arrays, no I/O threads.

The public surface (everything else lives in the modules and may change):

- kinematics and collision: :class:`UR5e`, :class:`CollisionModel`;
- the roadmap: :class:`Roadmap`, :class:`RoadmapConfig`, :func:`load_or_build_roadmap`;
- the time-variant search: :class:`Planner`, :class:`PlannerConfig`, :class:`PlanResult`;
- plans and trajectories: :class:`Plan`, :class:`Trajectory`.

Example::

    from app.config import load_workcell
    from app.planning import CollisionModel, Planner, Trajectory, load_or_build_roadmap

    cell = load_workcell()
    model = CollisionModel(cell)
    planner = Planner(load_or_build_roadmap(cell, collision=model), model)
    result = planner.plan(q_start=cell.robot.home_q, t_start=0.0, goal="A", forecast=None, workers=8)
    if result.ok:
        traj = result.trajectory  # == Trajectory.from_plan(result.plan)
"""

from __future__ import annotations

from app.planning.collision import CollisionModel
from app.planning.kinematics import UR5e
from app.planning.roadmap import Roadmap, RoadmapConfig, RoadmapError, load_or_build_roadmap
from app.planning.search import Planner, PlannerConfig, PlanResult
from app.planning.trajectory import Plan, Trajectory, TrajectoryError

__all__ = [
    "CollisionModel",
    "Plan",
    "PlanResult",
    "Planner",
    "PlannerConfig",
    "Roadmap",
    "RoadmapConfig",
    "RoadmapError",
    "Trajectory",
    "TrajectoryError",
    "UR5e",
    "load_or_build_roadmap",
]
