"""Compiled (numba) kernels for the geometric hot paths: UR5e forward kinematics to capsule segments,
segment-segment distances, robot-person minimum distances, and the planner's time-sampled separation checks.

The NumPy implementations in :mod:`app.planning.kinematics` and :mod:`app.planning.collision` stay the
reference (the tests compare against them); the public functions route through these kernels.

One module per concept: :mod:`~app.planning._kernels.arrays` (the ``NamedTuple``\\ s the kernels take),
:mod:`~app.planning._kernels.base` (compilation, array types, scalar helpers),
:mod:`~app.planning._kernels.geometry` (forward kinematics, capsule distances),
:mod:`~app.planning._kernels.separation` (the planner's sample and move checks),
:mod:`~app.planning._kernels.trajectory` (the verification of a trajectory),
:mod:`~app.planning._kernels.profiles` (a move's path-speed profile),
:mod:`~app.planning._kernels.records` (the search's records and successor generation),
:mod:`~app.planning._kernels.open_list` (the search's open list and its loops) and
:mod:`~app.planning._kernels.timing` (the SSM-aware timing's walk along a path, which
:mod:`app.planning.ssm_timing` imports from there). Everything else is re-exported here: callers write
``from app.planning import _kernels`` and ``_kernels.name``.

Calling convention: arrays are C-contiguous float64 (index arrays int64); the callers make sure of it so that
each kernel compiles for one signature only. A kernel takes a few ``NamedTuple``\\ s of arrays (robot model,
person, forecast, requirement, tables, search state), built once where the caller prepares its arguments,
not dozens of positional arrays; they are passed packed (:func:`~app.planning._kernels.arrays.pack`: plain
tuples, which numba's dispatcher types faster) and named again on entry. Compiled code is cached next to
each module (``cache=True``); where that directory is not writable numba falls back to its per-user cache,
and where no cache location can be written at all the kernels are compiled in memory on first use (a
warning is logged once).
"""

from __future__ import annotations

from app.planning._kernels.arrays import (
    CapsuleBounds,
    Clearance,
    ForecastPoses,
    KernelGeometry,
    KernelJointLimits,
    Knots,
    MotionModel,
    Moves,
    OpenArrays,
    PersonCapsules,
    PersonForecast,
    Requirement,
    RoadmapTables,
    RobotArrays,
    SearchContext,
    SearchState,
    pack,
)
from app.planning._kernels.base import as_bool, as_f64, as_i64
from app.planning._kernels.geometry import (
    align_rows,
    chain_frames,
    cross_min_distance,
    pair_distances,
    paired_min_distance,
    robot_segments,
    segment_distances,
    self_distances,
)
from app.planning._kernels.open_list import (
    POP_ACCEPT,
    POP_ALTERNATIVES,
    POP_BREAK,
    POP_DONE,
    POP_SPECULATE,
    accept_checked,
    heap_add,
    heap_push,
    pop_batch,
    release_deferred,
)
from app.planning._kernels.open_list import _heap_pop as _heap_pop
from app.planning._kernels.records import (
    REC_ACCEPTED,
    REC_BRANCH,
    REC_DEP,
    REC_END,
    REC_FC,
    REC_H,
    REC_L,
    REC_NODE,
    REC_PARENT,
    REC_PEAK,
    REC_QSET,
    REC_ROW,
    REC_SAME,
    REC_SPEC_CHILD,
    REC_T,
    REC_U,
    REC_U0,
    REC_WAIT_OK,
    alternative_moves,
    check_prepare,
    check_store,
    children_moves,
    speculate_chain,
    wait_finish,
    wait_samples,
)
from app.planning._kernels.separation import moves_separation_ok, sample_separation_ok
from app.planning._kernels.trajectory import trajectory_first_violation

__all__ = [
    "POP_ACCEPT",
    "POP_ALTERNATIVES",
    "POP_BREAK",
    "POP_DONE",
    "POP_SPECULATE",
    "REC_ACCEPTED",
    "REC_BRANCH",
    "REC_DEP",
    "REC_END",
    "REC_FC",
    "REC_H",
    "REC_L",
    "REC_NODE",
    "REC_PARENT",
    "REC_PEAK",
    "REC_QSET",
    "REC_ROW",
    "REC_SAME",
    "REC_SPEC_CHILD",
    "REC_T",
    "REC_U",
    "REC_U0",
    "REC_WAIT_OK",
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
    "accept_checked",
    "align_rows",
    "alternative_moves",
    "as_bool",
    "as_f64",
    "as_i64",
    "chain_frames",
    "check_prepare",
    "check_store",
    "children_moves",
    "cross_min_distance",
    "heap_add",
    "heap_push",
    "moves_separation_ok",
    "pack",
    "pair_distances",
    "paired_min_distance",
    "pop_batch",
    "release_deferred",
    "robot_segments",
    "sample_separation_ok",
    "segment_distances",
    "self_distances",
    "speculate_chain",
    "trajectory_first_violation",
    "wait_finish",
    "wait_samples",
]
