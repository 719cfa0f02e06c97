"""Time-variant A* over the static roadmap (sequential and batched-parallel), emergency plans, validity check.

Paper, section II-A, and where this goes further:

- **State.** Per roadmap node ``v`` the search keeps the arrival time ``AT(v)``; every state is a record of
  the search (node, IK branch, time, path speed, parent, departure, and its configuration ``Cfg(v)`` once
  checked), one row of the query's own growable arrays, so a plan is rebuilt from exactly the configurations
  and times that were checked. The roadmap is never written to.
- **Expansion u -> v.** The IK branches of ``v`` (each shifted by multiples of 2 pi next to ``Cfg(u)``) are
  ordered by the time a straight joint move needs (precomputed per edge and branch); the nearest is tried
  first, the others (at most ``max_branch_tries``) when it fails. A move between the same branch at both ends
  uses the roadmap's static edge check; any other move (another branch, the start connection) is checked
  against the static scene on the fly (memoised). Successors of a whole batch of states are generated and
  timed in one vectorised pass.
- **Heuristic.** The static time-to-go over the search's own moves at the cruise speed: a backward Dijkstra
  from the goal's branches over the precomputed move table (once per goal, cached), never above the time of
  any path the search can return (its moves last at least their length over the cruise speed). Without a
  person the search then expands little more than the optimal path; with one, the time-variant search stays
  close to the static one where the person is not in the way.
- **Lazy checking.** Successors are pushed *unchecked*; a move is checked only when its state is popped (its
  key ``t + h`` is a lower bound of any checked path through it, so the order is still A*'s).
- **Edge timing.** The paper lets every edge last as long as the slowest joint needs at its velocity limit.
  With the UR5e's acceleration limits that is too optimistic near starts and stops, and a trajectory fitted to
  it would run late: the forecast person would then be checked at the wrong time. Here the path speed (the
  largest joint speed as a fraction of its limit) follows a 1-D profile: it accelerates with the smallest
  joint acceleration/velocity ratio up to the cruise speed and brakes to rest on the edge into the goal
  (and moves from rest after a wait or a stop).
- **Validity against the forecast.** A move is valid if at every sampled instant (every ``sample_dt_s`` and
  at its end) the surface distance robot-person is at least :func:`app.safety.ssm.forecast_clearance`
  for the robot's speed there and the forecast's margin at that instant (``S_r + S_s + C + Z_r +
  max(Z_d, margin)``; the margin grows with the horizon; beyond the horizon the last pose is held and the
  margin grows at ``growth_mps`` up to a cap) plus ``corridor_margin_m`` (room for the fitted spline's
  deviation from the straight moves). The robot's speed at a sample is the largest the path profile reaches
  since the previous sample, in m/s through the move's largest chord (x ``speed_factor``), so a robot that
  brakes into a station needs less room there than at its peak speed. The forecast takes the place of
  ISO/TS 15066's worst-case ``S_h = v_h (T_r + T_s)`` over the planning horizon; the supervisor applies the
  full ``S_p`` to the current pose on top (speed scaling), so both views hold at run time.
- **Slower, then waiting (safe-interval style).** When the nearest branch fails at the cruise speed, the
  next branches are tried, the nearest one at ``slow_speed_fractions`` (less ``S_r + S_s``; the slowest, a
  creep, also after stopping), and after waiting at ``u`` in steps of ``wait_step_s`` up to ``max_wait_s``
  (if standing still there is itself safe). Once the person holds still (last pose, margin at its cap)
  waiting longer changes nothing, so of the waits that depart then only the first is tried. Without a person
  the search is plain A*.
- **Pruning and early failure.** When the person blocks every goal branch for good after some time, states
  that cannot arrive before it (by the heuristic) are not pushed; a goal blocked from the start fails at
  once. After ``probe_after_expansions`` the search asks whether the goal can still be *entered* once the
  person holds still (:meth:`Planner._approach_probe`); when not, states that could only get there later are
  dropped and the search ends soon with that reason instead of exhausting the roadmap. Plans longer than
  ``max_plan_s`` are not searched for.
- **Parallel.** ``workers = N`` checks up to N moves per step in one vectorised call (the batched
  equivalent of the paper's N threads taking nodes from the open list in turn; in CPython threads would
  serialise on the interpreter lock): the best popped state takes a *lookahead* chain of moves along the
  static shortest path (shorter where such chains keep failing), the other slots go to the next states in
  key order. A chain's states are ordinary states: each is accepted only when popped in key order after its
  parent was. ``AT`` is updated only when a checked arrival improves it and a goal state is accepted only
  when nothing pending can beat it, so the validity guarantees and the result are those of the sequential
  search (up to ties); a node may be expanded again when a later batch improves it.
- **Broad phase.** Whole moves far from the person over their time window, then single samples, are passed
  without forward kinematics (bounding spheres of the robot capsules grown by how far the joints can carry
  them, against a box around the person); the exact distance runs only over the robot and person capsules
  that come near each other, and a sample certainly too close (an upper bound of the distance, from points on
  the capsule axes) fails its move without exact distances for the move's other samples. With the compiled
  UR5e capsule model (:meth:`CollisionModel.kernel_geometry`) the move, sample and trajectory checks run
  fused in :mod:`app.planning._kernels` (the same broad phase and distances; a move stops at its first
  failing sample, a verification at its first failing instant); the NumPy checks are their reference.
- **Compiled bookkeeping.** With the compiled model the search's own bookkeeping runs in
  :mod:`app.planning._kernels` too: successor generation and timing (children, alternatives, the lookahead
  chain) writing straight into the packed state records, the open list (a binary heap of entry indices that
  pops in exactly ``heapq``'s order over the ``(key, -t, id)`` tuples) with the pop loop up to each step that
  needs Python, the batch's check set-up, the wait samples and the acceptance after a check. The NumPy and
  ``heapq`` code is its reference (used with a NumPy model): both expand the same states in the same order
  and return the same waypoints, bit for bit.
- **Shortcuts.** Roadmap paths follow straight TCP segments between samples, so in joint space they
  zig-zag and a spline through them slows down at every reversal. Before the fit, runs of waypoints are
  replaced greedily by one straight joint move where that move is statically free and keeps the forecast
  clearance over time (the search's own move check, timed by the same path-speed profile); the shortened
  path is re-timed, and the search's waypoints stay where no shortcut passes (:meth:`Planner._shortcut`).
  Waits and everything before the last of them are kept as the search timed them. The shortened plan is
  fitted and verified like any plan below; when it fails, the search's own path is fitted instead.
- **Trajectory check.** The waypoints become a C1 spline (:class:`app.planning.trajectory.Trajectory`),
  possibly retimed to the acceleration limits; it is verified against the forecast at ``verify_dt_s``
  with :meth:`Planner.first_violation` (and against the static scene). If the spline fails, a trajectory at
  rest at every waypoint (the straight moves the search checked, slower) is verified instead; if that fails,
  the search is repeated once with a time-robust check (each robot sample against the person over
  ``[t, t + slack]``); if that fails too, the result is a failure. A returned plan carries the verified knots
  (``Plan.qd``).
- **Emergency plan.** The person is held at the current pose; the robot stays put if that is safe for the
  horizon, else the search stops as soon as a state reaches ``t_start + horizon_s`` (paper: ``F + D``).
"""

from __future__ import annotations

from app.planning.search.config import PlannerConfig, PlanResult, RobotModel
from app.planning.search.planner import Planner
from app.planning.search.profiles import _profile_arrays as _profile_arrays
from app.planning.search.profiles import _profile_samples as _profile_samples
from app.planning.search.roadmap_view import RoadmapView
from app.planning.search.search_state import _Run as _Run
from app.planning.trajectory import Plan

__all__ = ["Plan", "PlanResult", "Planner", "PlannerConfig", "RoadmapView", "RobotModel"]
