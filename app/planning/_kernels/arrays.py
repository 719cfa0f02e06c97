"""The arguments of the planning kernels, grouped: ``NamedTuple``\\ s of arrays and scalars that the Python
side builds once (per model, planner, forecast, search or open list) and the kernels read by field name.

Every array is C-contiguous and float64 (index arrays int64, flags bool) unless said otherwise, as
:func:`app.planning._kernels.base.as_f64` makes them: numba compiles one signature per combination of field
types, so a tuple must always be built from the same array types. Shapes: ``L`` robot capsules, ``P``
capsule end points, ``M`` person capsules, ``J`` person joints, ``H`` forecast samples, ``R`` node-table rows
(``node * 8 + branch``), ``N`` search states (the records' capacity).

Packed: the Python side hands each group to a kernel as a plain tuple in the order of its fields
(:func:`pack`), and the kernel names the fields again on entry (``state = SearchState(*state)``, free in
compiled code). numba's dispatcher types a ``NamedTuple`` argument a few microseconds more slowly than a
plain tuple of the same arrays (it fingerprints the class and its field names on every call), and the
search's loop calls its kernels several times per expansion: passed named, they cost the sequential search
tens of percent of its CPU time on the benchmark queries.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "CapsuleBounds",
    "Clearance",
    "ForecastPoses",
    "KernelGeometry",
    "KernelJointLimits",
    "Knots",
    "MotionModel",
    "Moves",
    "OpenArrays",
    "PersonCapsules",
    "PersonForecast",
    "Requirement",
    "RoadmapTables",
    "RobotArrays",
    "SearchContext",
    "SearchState",
    "pack",
]


def pack(group: tuple[Any, ...]) -> tuple[Any, ...]:
    """``group`` (one of the ``NamedTuple``\\ s below) as the plain tuple the kernels take (see the module
    docstring): its fields in order."""
    return tuple(group)


# --------------------------------------------------------------------------------------- robot and person
class RobotArrays(NamedTuple):
    """The UR5e capsule model (:meth:`app.planning.collision.CollisionModel.kernel_geometry`)."""

    T_base: np.ndarray  #: (4, 4) pose of DH frame 0 in the world
    t_tcp: np.ndarray  #: (3,) where the tool capsule's axis ends, in the flange frame (m)
    dh_d: np.ndarray  #: (6,) DH offsets (m)
    dh_a: np.ndarray  #: (6,) DH lengths (m)
    twist: np.ndarray  #: (6,) sign of each DH twist (+1: pi/2, -1: -pi/2, 0: none)
    off_shoulder: float  #: offset of the upper arm's centre line along the shoulder axis (m)
    off_forearm: float  #: offset of the forearm's centre line along the shoulder axis (m)
    ext: np.ndarray  #: (L, 2) each capsule's extension beyond its start and end, fractions of its length
    ra: np.ndarray  #: (L,) capsule radii (m)


class PersonCapsules(NamedTuple):
    """The person's capsules: capsule ``m`` runs from joint ``ia[m]`` to joint ``ib[m]``."""

    ia: np.ndarray  #: (M,) int64
    ib: np.ndarray  #: (M,) int64
    rh: np.ndarray  #: (M,) radii (m)
    #: (M,) 1.0 where the capsule is checked for contact only (a body region that power and force limiting
    #: lets the robot touch at its permissible speed: the governor slows the robot to it at run time), 0.0
    #: where it needs the whole clearance (skull, face, neck; every capsule with SSM alone)
    soft: np.ndarray


class KernelGeometry(NamedTuple):
    """Robot and person, as a compiled collision model hands them to the planner's checks (a Python-side
    pair: the kernels take its two fields)."""

    robot: tuple[Any, ...]  #: :class:`RobotArrays`, packed
    person: tuple[Any, ...]  #: :class:`PersonCapsules`, packed


# -------------------------------------------------------------------------------------------- the forecast
class PersonForecast(NamedTuple):
    """A forecast person as the planner's separation checks read it
    (:class:`app.planning.search.separation._Separation`): its poses, linearly interpolated between the
    samples (the ends held), its margins, and boxes around it."""

    times: np.ndarray  #: (H,) sample times (s)
    joints: np.ndarray  #: (H, J, 3) poses (m)
    djoints: np.ndarray  #: (max(H - 1, 1), J, 3) pose differences (zeros for one sample)
    dtimes: np.ndarray  #: (max(H - 1, 1),) time differences (ones for one sample)
    lo_pair: np.ndarray  #: (n, 3) lower corners of the boxes around two consecutive samples
    hi_pair: np.ndarray  #: (n, 4) their upper corners and largest margin
    margins: np.ndarray  #: (H,) the forecast's margins (m)
    lo_tab: np.ndarray  #: (K, H, 3) sparse table of unions of the lower corners (level k: ranges of 2^k)
    hi_tab: np.ndarray  #: (K, H, 4) the same of the upper corners and margins


class Requirement(NamedTuple):
    """How much separation a sample needs, and when it is checked (relative to its own time)."""

    offsets: np.ndarray  #: (n_off,) time offsets at which every sample is checked (s)
    #: ``growth_mps, max_margin_m, t_reaction_s, intrusion_m, z_robot_m, z_human_m, extra_m, floor_m``
    #: (+inf: none), the stopping model's ``decel_mps2, joint_decel_radps2, delay_s``, then optionally the
    #: SSM-aware table: its step in m/s and its values
    params: np.ndarray
    #: (6,) the stopping model's joint weights (:attr:`app.safety.stopping.StoppingModel.joint_weights`)
    joint_weights: np.ndarray


class ForecastPoses(NamedTuple):
    """A forecast as :meth:`app.prediction.forecast.HumanForecast.poses_at` interpolates it (the last pose
    held, the margin growing at ``growth`` m/s up to ``cap``), for the trajectory check."""

    times: np.ndarray  #: (H,) s
    joints: np.ndarray  #: (H, J, 3) m
    margins: np.ndarray  #: (H,) m
    growth: float  #: m/s
    cap: float  #: m
    r_max: float  #: the largest person capsule radius (m): a pose's joint box grown by it holds the person


class Clearance(NamedTuple):
    """The terms of :func:`app.safety.ssm.forecast_clearance` (its stopping model's figures with them) and
    its cap."""

    t_reaction_s: float
    intrusion_m: float
    z_robot_m: float
    z_human_m: float
    floor_m: float  #: +inf: none
    decel_mps2: float
    joint_decel_radps2: float  #: the slowest joint's
    delay_s: float
    joint_weights: np.ndarray  #: (6,) each joint's speed in units of the slowest-braking joint's
    #: (M,) per person capsule checked for contact only: the robot's fastest-point speed (m/s) at or below
    #: which it asks no clearance at all (a contact would stay within the region's quasi-static permissible
    #: speed); -1: always the contact clearance
    free_mps: np.ndarray


# ------------------------------------------------------------------------------------ the planner's tables
class KernelJointLimits(NamedTuple):
    """The planner's joint position limits (6,) each (rad), as the kernels read them (the cell's are
    :class:`app.cell.joint_tracking.JointLimits`)."""

    lo: np.ndarray
    hi: np.ndarray


class CapsuleBounds(NamedTuple):
    """Capsule end points and bounding spheres: of ``R`` rows (``(R, P, 3)``, ``(R, L, 3)``, ``(R, L)``; the
    node tables) or of one configuration (``(P, 3)``, ``(L, 3)``, ``(L,)``; a search's start)."""

    pts: np.ndarray
    cen: np.ndarray
    rad: np.ndarray


class MotionModel(NamedTuple):
    """How a straight joint-space move carries the capsules
    (:meth:`app.planning.search.Planner._move_prep`)."""

    lever: np.ndarray  #: (6,) how far a joint's unit turn moves any point (m/rad)
    moved_by: np.ndarray  #: (L,) int64: the last joint that moves each capsule
    speed_factor: float  #: robot speed per path speed and chord per unit of path
    accel: float  #: path acceleration (fraction of full speed per second)
    sample_dt: float  #: time between a move's samples (s)


class Moves(NamedTuple):
    """``M`` moves to check against the forecast (:func:`app.planning._kernels.moves_separation_ok`)."""

    q_a: np.ndarray  #: (M, 6) start configurations
    target: np.ndarray  #: (M, 6) end configurations
    pts_a: np.ndarray  #: (M, P, 3) capsule end points at the start
    cen_a: np.ndarray  #: (M, L, 3) bounding sphere centres at the start
    rad_a: np.ndarray  #: (M, L) bounding sphere radii at the start
    rows: np.ndarray  #: (M,) int64: the target's row of the tables
    t_dep: np.ndarray  #: (M,) departure (s)
    h: np.ndarray  #: (M,) duration (s)
    u0: np.ndarray  #: (M,) entry path speed
    L: np.ndarray  #: (M,) path length
    f: np.ndarray  #: (M,) cruise path speed
    end_rest: np.ndarray  #: (M,) bool: ends at rest
    hold: np.ndarray  #: (M,) bool: then stands at the target for the hold time


class Knots(NamedTuple):
    """A cubic Hermite trajectory (:class:`app.planning.trajectory.Trajectory`)."""

    times: np.ndarray  #: (K,) knot times (s)
    q: np.ndarray  #: (K, 6) configurations (rad)
    qd: np.ndarray  #: (K, 6) velocities (rad/s)
    h: np.ndarray  #: (K - 1,) knot intervals (s)


class RoadmapTables(NamedTuple):
    """The roadmap as the search's generation reads it
    (:attr:`app.planning.search.roadmap_view.RoadmapView.k_roadmap`): CSR adjacency and, per row ``e * 8 + b``
    (CSR entry, parent branch), the branch options."""

    indptr: np.ndarray  #: (N_nodes + 1,) int64
    indices: np.ndarray  #: (E,) int64
    ord_flat: np.ndarray  #: (E * 8, R_opt) int64: the successor's branches, nearest first
    L_flat: np.ndarray  #: (E * 8, R_opt) their path lengths (+inf: invalid)
    same_flat: np.ndarray  #: (E * 8, R_opt) bool: the roadmap's static check covers the move
    delta0: np.ndarray  #: (E * 8, 6) the nearest branch's configuration minus the parent's (2 pi-shifted)
    ik: np.ndarray  #: (N_nodes, 8, 6) the nodes' branch configurations


# ------------------------------------------------------------------------------------------ one search
class SearchContext(NamedTuple):
    """The successor generation's constants of one search
    (:meth:`app.planning.search.search_state._Run._context`)."""

    #: ``goal`` (-2: none), path acceleration, shortest move, heuristic weight, stop time (NaN: none),
    #: latest arrival, latest arrival at other nodes than the goal, cruise speed
    ctx: np.ndarray
    h_tab: np.ndarray  #: (N_nodes, 8) the heuristic ((0, 8): none)
    h_pred: np.ndarray  #: (N_nodes, 8) time lower bound to a neighbour of the goal ((0, 8): none)


class SearchState(NamedTuple):
    """The records of one search (:class:`app.planning.search.search_state._Run`): one column per state."""

    F: np.ndarray  #: (9, N) float fields (``REC_T`` ...)
    I: np.ndarray  #: (5, N) int64 fields (``REC_NODE`` ...)  # noqa: E741
    B: np.ndarray  #: (4, N) bool fields (``REC_END`` ...)
    alts: np.ndarray  #: (N,) int8: the alternative each state is
    q: np.ndarray  #: (N, 6) the configuration once checked (or precomputed)
    status: np.ndarray  #: (N,) int8: 0 not checked, 1 passed, 2 failed
    AT: np.ndarray  #: (N_nodes,) the earliest accepted arrival at each node (s)


class OpenArrays(NamedTuple):
    """The compiled open list (:class:`app.planning.search.open_list._OpenList`): entries ``(key, -t, state
    id)`` in an append-only table, a binary heap of entry indices, and the entries deferred until a state
    is accepted (linked lists)."""

    heap: np.ndarray  #: (cap,) int64
    hs: np.ndarray  #: (2,) int64: heap size, entries
    E_key: np.ndarray  #: (cap,)
    E_negt: np.ndarray  #: (cap,)
    E_id: np.ndarray  #: (cap,) int64
    def_head: np.ndarray  #: (N,) int64: per state, its first deferred entry (-1: none)
    def_next: np.ndarray  #: (cap,) int64: per entry, the next deferred one
