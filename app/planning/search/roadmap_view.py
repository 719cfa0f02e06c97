"""What one search sees of the roadmap (:class:`RoadmapView`): the planner's precomputed tables, their
compiled packing, the IK branches and the planner's alignment, metric, geometry and static-check functions,
read-only.

The :class:`~app.planning.search.planner.Planner` builds one view when it is constructed
(``Planner.view``); every search (:class:`app.planning.search.search_state._Run`) reads the roadmap only
through it, never through the planner's own attributes."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True, eq=False)
class RoadmapView:
    """The roadmap as a query reads it. Built once by the planner and shared by all its queries (which never
    write into it: a search keeps its state in its own arrays).

    Shapes: ``N`` roadmap nodes, 8 IK branches per node, ``E`` CSR entries (directed edges), ``R`` branch
    options per move (``n_options``), ``L`` robot capsules. An option-table row is ``e * 8 + b``: CSR entry
    ``e`` (u -> v) left from branch ``b`` of ``u``.

    Attributes:
        num_nodes: ``N``.
        n_options: ``R``, the successor branches tried per move (``min(max_branch_tries, 8)``).
        accel: Path acceleration (fraction of full speed per second): the smallest joint
            acceleration/velocity limit ratio times ``accel_fraction``.
        q_min: Lower joint limits (6,) (rad).
        q_max: Upper joint limits (6,) (rad).
        ik: The nodes' IK branch configurations (N, 8, 6) (rad).
        valid: Which IK branches exist (N, 8) bool.
        stations: The station nodes (S,) int64, sorted.
        indptr: CSR row pointers (N + 1,).
        indices: CSR column indices (E,): the successor node of each entry.
        max_degree: The largest number of successors of any node.
        ord_flat: Per option-table row, the successor's branches nearest first (E * 8, R) int64.
        L_flat: Their straight-move lengths (E * 8, R) (s at full joint speed; +inf: no such branch).
        same_flat: Whether the roadmap's static edge check covers the move (E * 8, R) bool.
        delta0: Per row, the nearest branch's configuration minus the parent's, shifted by multiples of
            2 pi next to it without the limits (E * 8, 6) (rad).
        ord_list: ``ord_flat[:, 0]`` as a Python list (the NumPy lookahead reads one entry at a time).
        L_list: ``L_flat[:, 0]`` as a Python list.
        same_list: ``same_flat[:, 0]`` as a Python list.
        indices_list: ``indices`` as a Python list.
        pts_all: Capsule end points per node and branch (N, 8, 2L, 3) (m, world frame).
        cen_all: Bounding-sphere centres per node and branch (N, 8, L, 3) (m, world frame).
        rad_all: Bounding-sphere radii per node and branch (N, 8, L) (m).
        next_rows: Per goal whose heuristic is known, the option-table row of the next move of the static
            shortest path per ``node * 8 + branch`` (-1: none); a live read-only mapping that gains a goal
            when the planner first computes its heuristic.
        next_rows_k: The same rows as int64 arrays, for the compiled lookahead.
        compiled: Whether the compiled checks and bookkeeping are in use (the ``k_*`` fields are set).
        k_roadmap: :class:`app.planning._kernels.RoadmapTables`, packed (None when not ``compiled``).
        k_limits: :class:`app.planning._kernels.KernelJointLimits`, packed (None when not ``compiled``).
        k_tables: :class:`app.planning._kernels.CapsuleBounds` per row ``node * 8 + branch``, packed.
        k_motion: :class:`app.planning._kernels.MotionModel`, packed (None when not ``compiled``).
        k_ik: ``ik`` as the kernels take it (None when not ``compiled``).
        align: ``align(q, q_ref)``: 2 pi-shift every joint of ``q`` (..., 6) next to ``q_ref``
            (broadcastable), within the joint limits.
        metric: ``metric(dq)``: straight-move length (...,) in s at full joint speed of joint steps (..., 6).
        points_and_spheres: ``points_and_spheres(q)``: capsule end points (B, 2L, 3) of configurations
            (B, 6) and their bounding spheres, centres (B, L, 3) and radii (B, L).
        static_check: The planner's memoised static scene check of moves the roadmap did not check
            (:meth:`app.planning.search.tables._StaticTables._static_cached`): 1 free, -1 blocked. Its memo
            only gains entries that are pure functions of the roadmap, so concurrent queries may share it.
        move_samples: The samples of moves against the forecast that the broad phase cannot pass
            (:meth:`app.planning.search.moves._MoveChecks._move_samples`).
    """

    num_nodes: int
    n_options: int
    accel: float
    q_min: np.ndarray
    q_max: np.ndarray
    ik: np.ndarray
    valid: np.ndarray
    stations: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    max_degree: int
    ord_flat: np.ndarray
    L_flat: np.ndarray
    same_flat: np.ndarray
    delta0: np.ndarray
    ord_list: list[int]
    L_list: list[float]
    same_list: list[bool]
    indices_list: list[int]
    pts_all: np.ndarray
    cen_all: np.ndarray
    rad_all: np.ndarray
    next_rows: Mapping[int, list[int]]
    next_rows_k: Mapping[int, np.ndarray]
    compiled: bool
    k_roadmap: tuple[Any, ...] | None
    k_limits: tuple[Any, ...] | None
    k_tables: tuple[Any, ...] | None
    k_motion: tuple[Any, ...] | None
    k_ik: np.ndarray | None
    align: Callable[[np.ndarray, np.ndarray], np.ndarray]
    metric: Callable[[np.ndarray], np.ndarray]
    points_and_spheres: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
    static_check: Callable[..., np.ndarray]
    move_samples: Callable[..., tuple[np.ndarray, ...]]
