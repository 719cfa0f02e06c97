"""What is built once per work cell: :class:`PlanningStack` (kinematics, collision model, roadmap and
planner, cached per process, cell and reaction time) and :class:`CellGeometry` (the UR5e's body as the
supervisor and the monitor see it: one part per capsule of the collision model)."""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.config import Settings, WorkCell
from app.planning.ssm_timing import part_speeds
from app.safety.governor import directed_approach
from app.safety.pfl import PFLModel

__all__ = ["CellGeometry", "PlanningStack", "contact_clearance", "contact_only_capsules", "pfl_model"]

log = logging.getLogger(__name__)


class CellGeometry:
    """The UR5e's body as parts, one per capsule of the collision model (the supervisor's
    :class:`~app.control.trajectory_views.RobotGeometry`).

    A part's speed is that of the faster end of its capsule's axis: on a rigid link every point of the axis
    moves no faster than that, so it bounds the speed of the capsule's whole surface.
    """

    def __init__(self, collision: Any, *, fd_step_s: float = 1e-3) -> None:
        self.collision = collision
        self.fd_step_s = float(fd_step_s)

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """(P, L, M) surface distance (m) of each robot part at ``q`` (6,) to each capsule of the person in
        poses (P, J, 3) (:meth:`app.planning.collision.CollisionModel.pair_distances`, which checks the
        shapes)."""
        return self.collision.pair_distances(np.asarray(q, dtype=np.float64).reshape(6), joints)

    def part_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """(P, L) surface distance (m) of each robot part at ``q`` (6,) to the person in poses (P, J, 3)."""
        return self.pair_distances(q, joints).min(axis=2)

    def near_person(
        self, q: np.ndarray, joints: np.ndarray, joints_before: np.ndarray, dt_s: float, *, band_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each part's separation (L,) to the person at ``joints`` and the person's *directed* speed (L,)
        toward it since ``joints_before``, ``dt_s`` earlier
        (:func:`app.safety.governor.directed_approach`)."""
        poses = np.stack([np.asarray(joints, dtype=np.float64), np.asarray(joints_before, dtype=np.float64)])
        d = self.pair_distances(q, poses)  # (2, L, M)
        return directed_approach(d[0], d[1], dt_s, band_m=band_m)

    def human_static_gaps(self, joints: np.ndarray, capsules: np.ndarray | None = None) -> np.ndarray:
        """(M,) each of the person's capsules' gap (m) to the static scene, inf but for ``capsules``
        (:meth:`app.planning.collision.CollisionModel.human_static_gaps`)."""
        return self.collision.human_static_gaps(joints, capsules)

    def path_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """(K, L) surface distance (m) of each part of the robot at each of ``q`` (K, 6) to the person at
        ``joints`` (J, 3)."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
        poses = np.broadcast_to(np.asarray(joints, dtype=np.float64), (q.shape[0], *np.shape(joints)))
        segments = self.collision.robot_segments(q)
        n_parts = segments[0].shape[0]
        return np.stack(
            [
                self.collision.distance_to_human_paired(q, poses, segments=segments, links=np.array([i]))
                for i in range(n_parts)
            ],
            axis=1,
        )

    def separation(self, q: np.ndarray, joints: np.ndarray) -> float:
        """Minimum surface distance (m) robot-person for ``q`` (6,) and ``joints`` (J, 3)."""
        return float(self.part_separations(q, np.asarray(joints)[None]).min())

    def part_speeds(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """(K, L) speed (m/s) of each part for ``q``, ``qd`` (K, 6)
        (:func:`app.planning.ssm_timing.part_speeds`)."""
        return part_speeds(self.collision, q, qd, fd_step_s=self.fd_step_s)


@dataclass(frozen=True)
class PlanningStack:
    """Everything that is built once per work cell: kinematics, collision model, roadmap, planner.

    Build it with :meth:`for_cell` (cached per process and cell).
    """

    cell: WorkCell
    kin: Any
    collision: Any
    roadmap: Any
    planner: Any
    geometry: CellGeometry
    ssm: Any

    @classmethod
    def for_cell(
        cls,
        cell: WorkCell,
        *,
        t_reaction_s: float | None = None,
        cache_dir: str | Path | None = None,
        contact_only: tuple[bool, ...] = (),
        contact_only_search: bool = False,
        contact_speed_mps: tuple[float, ...] = (),
    ) -> PlanningStack:
        """The stack of ``cell`` (roadmap from the on-disk cache, built when missing), its planner's clearance
        with the reaction time ``t_reaction_s`` of the installation
        (:meth:`app.config.Settings.reaction_time_s`: the ``T_r`` of the governor and the monitor; default
        :class:`app.safety.ssm.SSMParams`') and ``contact_only``, ``contact_only_search``
        and ``contact_speed_mps`` (:class:`app.planning.search.PlannerConfig`'s, see
        :func:`contact_clearance`). Cached per process, cell, ``T_r`` and those three."""
        soft = (
            tuple(contact_only),
            bool(contact_only_search) and bool(contact_only),
            tuple(contact_speed_mps) if contact_only else (),
        )
        key = (cell.fingerprint(), None if cache_dir is None else str(cache_dir), t_reaction_s, soft)
        with _STACK_LOCK:
            stack = _STACKS.get(key)
            if stack is None:
                from app.planning.search import PlannerConfig

                config = PlannerConfig(
                    contact_only=soft[0], contact_only_search=soft[1], contact_speed_mps=soft[2]
                )
                stack = _build_stack(cell, key[1], planner_config=config, t_reaction_s=t_reaction_s)
                _STACKS[key] = stack
                while len(_STACKS) > 4:
                    _STACKS.pop(next(iter(_STACKS)))
            return stack

    @classmethod
    def build(
        cls,
        cell: WorkCell,
        *,
        roadmap_config: Any | None = None,
        planner_config: Any | None = None,
        t_reaction_s: float | None = None,
        cache_dir: str | Path | None = None,
    ) -> PlanningStack:
        """A new stack (not cached in the process) with explicit roadmap and planner settings
        (:class:`app.planning.roadmap.RoadmapConfig`, :class:`app.planning.search.PlannerConfig`);
        ``t_reaction_s`` replaces the planner settings' ``T_r`` (see :meth:`for_cell`)."""
        return _build_stack(
            cell,
            None if cache_dir is None else str(cache_dir),
            roadmap_config=roadmap_config,
            planner_config=planner_config,
            t_reaction_s=t_reaction_s,
        )

    def with_reaction_time(self, t_reaction_s: float) -> PlanningStack:
        """This stack with its planner's clearance at the reaction time ``t_reaction_s`` (``T_r``; see
        :meth:`for_cell`): a new planner on the same roadmap and collision model, or this stack when it has
        that ``T_r`` already."""
        from app.planning.search import Planner

        if math.isclose(self.ssm.t_reaction_s, t_reaction_s, rel_tol=0.0, abs_tol=1e-9):
            return self  # the tolerance of TrialEngine's check of the stack's T_r
        config = self.planner.config.with_reaction_time(t_reaction_s)
        planner = Planner(self.roadmap, self.collision, config=config)
        return dataclasses.replace(self, planner=planner, ssm=config.ssm)

    def make_trajectory(self, plan: Any, qd0: np.ndarray | None) -> Any:
        from app.planning.trajectory import Trajectory

        return Trajectory.from_plan(plan, qd0=qd0, kin=self.kin)

    def goal_names(self) -> list[str]:
        return list(self.roadmap.station_nodes)


_STACKS: dict[tuple[str, str | None, float | None, tuple[tuple[bool, ...], bool]], PlanningStack] = {}
_STACK_LOCK = threading.Lock()


def contact_only_capsules(settings: Settings) -> tuple[bool, ...]:
    """Per person capsule (:data:`app.planning.collision.HUMAN_CAPSULES`), whether the planner asks of it
    contact clearance only (:attr:`app.planning.search.PlannerConfig.contact_only`): with power and force
    limiting and ``Settings.plan_contact_regions`` other than ``none``, the capsules whose region admits
    contact (a permissible transient speed above zero: not skull, face or neck); else none (empty)."""
    if not settings.pfl or settings.plan_contact_regions == "none":
        return ()
    return tuple(bool(v > 0.0) for v in pfl_model(settings).transient_mps)


def contact_clearance(settings: Settings) -> dict[str, Any]:
    """The planner's contact clearance under ``settings``, as the keyword arguments of
    :class:`app.planning.search.PlannerConfig` and :meth:`PlanningStack.for_cell` take it:
    ``contact_only`` (:func:`contact_only_capsules`), ``contact_only_search`` (``all``) and, with
    ``Settings.plan_contact_speed``, ``contact_speed_mps``: each contact-only capsule's permissible
    quasi-static speed (the lower of its two: a contact at that speed is permissible even pinned)."""
    soft = contact_only_capsules(settings)
    speeds: tuple[float, ...] = ()
    if soft and settings.plan_contact_speed:
        q = pfl_model(settings).quasi_static_mps
        speeds = tuple(float(v) if f else -1.0 for f, v in zip(soft, q, strict=True))
    return {
        "contact_only": soft,
        "contact_only_search": settings.plan_contact_regions == "all",
        "contact_speed_mps": speeds,
    }


def pfl_model(settings: Settings) -> PFLModel:
    """The power and force limiting of a trial (:class:`app.safety.pfl.PFLModel`): the person's capsules,
    the UR5e's moving mass and the declared payload; ``enabled`` by ``Settings.pfl``."""
    from app.planning.collision import HUMAN_CAPSULES

    return PFLModel.for_capsules(HUMAN_CAPSULES, payload_kg=settings.pfl_payload_kg, enabled=settings.pfl)


def _build_stack(
    cell: WorkCell,
    cache_dir: str | None,
    *,
    roadmap_config: Any | None = None,
    planner_config: Any | None = None,
    t_reaction_s: float | None = None,
) -> PlanningStack:
    from app.planning.collision import CollisionModel
    from app.planning.roadmap import load_or_build_roadmap
    from app.planning.search import Planner, PlannerConfig

    t0 = time.perf_counter()
    collision = CollisionModel(cell)
    roadmap = load_or_build_roadmap(cell, config=roadmap_config, cache_dir=cache_dir, collision=collision)
    config = planner_config or PlannerConfig()
    if t_reaction_s is not None:
        config = config.with_reaction_time(t_reaction_s)
    planner = Planner(roadmap, collision, config=config)
    log.info("planning stack for cell %s ready in %.2f s", cell.name, time.perf_counter() - t0)
    return PlanningStack(
        cell=cell,
        kin=collision.kin,
        collision=collision,
        roadmap=roadmap,
        planner=planner,
        geometry=CellGeometry(collision),
        ssm=config.ssm,
    )
