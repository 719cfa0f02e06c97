"""The planner (:class:`Planner`): set-up, the public queries (plan, emergency plan, first violation) and
the forecast check of a query.

Its parts live in the sibling modules, one base class each: :mod:`.tables` (precomputed tables, static
checks, heuristic), :mod:`.moves` (move checks), :mod:`.astar` (the search loops), :mod:`.shortcut` and
:mod:`.verify` (fit and verification)."""

from __future__ import annotations

import copy
import dataclasses
import inspect
import math
import time
from collections.abc import Callable
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from app.planning import _kernels
from app.planning.roadmap import NUM_BRANCHES, Roadmap
from app.planning.search.astar import _Search
from app.planning.search.config import (
    _TWO_PI,
    PHASES,
    START_BLOCKED,
    PlannerConfig,
    PlanResult,
    RobotModel,
    _paired_options,
)
from app.planning.search.moves import _MoveChecks
from app.planning.search.open_list import _OpenList
from app.planning.search.roadmap_view import RoadmapView
from app.planning.search.search_state import _Run
from app.planning.search.separation import _Separation
from app.planning.search.shortcut import _Shortcuts
from app.planning.search.tables import _StaticTables
from app.planning.search.verify import _TrajectoryChecks
from app.planning.trajectory import Plan, Trajectory
from app.prediction.skeleton import NUM_JOINTS
from app.safety.ssm import forecast_clearance

if TYPE_CHECKING:
    from app.prediction.forecast import HumanForecast
    from app.safety.governor import GovernorModel


def _people(forecast: HumanForecast | None) -> HumanForecast | None:
    """``forecast``, or None where it holds no body (a person-free cell: static checks only)."""
    return None if forecast is None or forecast.bodies == 0 else forecast


class Planner(_StaticTables, _MoveChecks, _Search, _Shortcuts, _TrajectoryChecks):
    """Time-variant A* over a roadmap, against a forecast of the person.

    Args:
        roadmap: The static roadmap (shared, never modified).
        collision: The collision model (:class:`app.planning.collision.CollisionModel`, or anything with
            the methods of :class:`RobotModel`).
        config: Search settings.
        timer: Monotonic clock for deadlines and ``compute_s`` (seconds); injectable for tests.
        warm_up: With the compiled checks, load the compiled kernels now with one small query
            (:meth:`_warm_up`) rather than in the first real one.

    Construction precomputes, per roadmap edge and parent branch, the successor branches in order of joint
    distance (and per node and branch the robot's capsule points and bounding box); queries only read them.
    Every query keeps its state in its own arrays: one planner can serve concurrent queries. A query's search
    reads the roadmap through :attr:`view` (a :class:`RoadmapView`, built here once), not through the
    planner's own attributes.
    """

    def __init__(
        self,
        roadmap: Roadmap,
        collision: RobotModel,
        *,
        config: PlannerConfig | None = None,
        timer: Callable[[], float] = time.perf_counter,
        warm_up: bool = True,
    ) -> None:
        self.roadmap = roadmap
        self.collision = collision
        self.config = config or PlannerConfig()
        self._timer = timer
        cfg = self.config
        from app.planning import kinematics

        def pick(value: tuple[float, ...] | None, default: np.ndarray) -> np.ndarray:
            arr = np.asarray(default if value is None else value, dtype=np.float64)
            if arr.shape != (6,):
                raise ValueError(f"Planner: joint limits must have 6 entries, got {arr.shape}")
            return arr

        kin = getattr(collision, "kin", None)  # the cell's joint limits (its kinematics), else the UR5e's
        self.q_min = pick(cfg.q_min, kinematics.Q_MIN if kin is None else kin.q_min)
        self.q_max = pick(cfg.q_max, kinematics.Q_MAX if kin is None else kin.q_max)
        self.qd_max = pick(cfg.qd_max, kinematics.QD_MAX)
        self.qdd_max = pick(cfg.qdd_max, kinematics.QDD_MAX)
        self._inv_qd = 1.0 / self.qd_max
        # the compiled row-wise _align (only with a model that has compiled checks: a NumPy model stays NumPy)
        get_geometry = getattr(collision, "kernel_geometry", None)
        compiled = callable(get_geometry) and get_geometry() is not None
        self._k_align = (_kernels.as_f64(self.q_min), _kernels.as_f64(self.q_max)) if compiled else None
        # path acceleration in "fraction of full speed per second"
        self._A = float(np.min(self.qdd_max / self.qd_max)) * cfg.accel_fraction
        self._ik = roadmap.ik
        self._valid = roadmap.valid
        N = roadmap.num_nodes
        pts, cen, rad = self._points_and_spheres(roadmap.ik.reshape(-1, 6))
        self._pts_all = pts.reshape(N, NUM_BRANCHES, -1, 3)
        self._cen_all = cen.reshape(N, NUM_BRANCHES, -1, 3)
        self._rad_all = rad.reshape(N, NUM_BRANCHES, -1)
        self._n_pts = self._pts_all.shape[2]
        self._n_caps = self._cen_all.shape[2]
        self._lever, self._moved_by = self._lever_model()
        self._R = min(cfg.max_branch_tries, NUM_BRANCHES)
        self._build_edge_tables()
        self._static_boxes = self._static_box_bounds()
        self._rev_graph = self._reverse_move_graph()
        self._h_cache: dict[int, np.ndarray] = {}
        # the exact verification can reuse its forward kinematics when the model takes segments
        opts = _paired_options(collision)
        self._subsets_ok = {"links", "capsules"} <= opts
        self._segments_ok = "segments" in opts and hasattr(collision, "robot_segments")
        self._static_segments_ok = self._segments_ok and all(
            "segments" in inspect.signature(getattr(collision, name)).parameters
            for name in ("in_static_collision", "self_collision")
        )
        self._robot_r = np.asarray(collision.robot_capsules(np.zeros((1, 6)))[2], dtype=np.float64)
        # the fused compiled checks, when the model is the (compiled) UR5e capsule model
        self._kernel_geometry = get_geometry() if callable(get_geometry) and self._segments_ok else None
        if self._kernel_geometry is not None:  # the tables as the compiled checks and search read them
            n_rows = roadmap.num_nodes * NUM_BRANCHES
            pack = _kernels.pack
            self._k_tables = pack(
                _kernels.CapsuleBounds(
                    pts=_kernels.as_f64(self._pts_all.reshape(n_rows, -1, 3)),
                    cen=_kernels.as_f64(self._cen_all.reshape(n_rows, -1, 3)),
                    rad=_kernels.as_f64(self._rad_all.reshape(n_rows, -1)),
                )
            )
            self._k_limits = pack(
                _kernels.KernelJointLimits(_kernels.as_f64(self.q_min), _kernels.as_f64(self.q_max))
            )
            self._k_motion = pack(
                _kernels.MotionModel(
                    lever=_kernels.as_f64(self._lever),
                    moved_by=_kernels.as_i64(self._moved_by),
                    speed_factor=float(cfg.speed_factor),
                    accel=self._A,
                    sample_dt=float(cfg.sample_dt_s),
                )
            )
        self._human_r_max = float(np.max(collision.human_capsules(np.zeros((1, NUM_JOINTS, 3)))[2]))
        # which joints each person capsule runs between (joint indices fed in as coordinates) and its radius
        coded = np.repeat(np.arange(NUM_JOINTS, dtype=np.float64)[None, :, None], 3, axis=2)
        ha, hb, hr = collision.human_capsules(coded)
        self._cap_ends = (
            np.asarray(ha)[0, :, 0].astype(np.int64),
            np.asarray(hb)[0, :, 0].astype(np.int64),
            np.asarray(hr, dtype=np.float64),
        )
        self._next_cache: dict[int, list[int]] = {}
        self._next_cache_k: dict[int, np.ndarray] = {}
        self._static_memo: dict[tuple[int, int, int, int], int] = {}
        #: What a query sees of the roadmap (its tables and the functions over them), read-only.
        self.view = self._roadmap_view()
        for node in roadmap.station_nodes.values():
            if self._valid[node].any():
                self._heuristic_table(node)
        if warm_up and self._kernel_geometry is not None and self._k_align is not None:
            self._warm_up()

    def _roadmap_view(self) -> RoadmapView:
        """The tables and functions a query reads (:class:`RoadmapView`), with the lookahead's per-row data
        and the compiled roadmap tables."""
        rm = self.roadmap
        # per row, the nearest branch's configuration minus the parent's, shifted by multiples of 2 pi next
        # to it (without the limits: a shifted parent gets the same shift, see _Run.speculate)
        q_u = self._ik.reshape(-1, 6)[self._src_state]
        q_v = self._ik[np.repeat(rm.indices, NUM_BRANCHES), self._ord_flat[:, 0]]
        delta0 = q_v + _TWO_PI * np.rint((q_u - q_v) * (1.0 / _TWO_PI)) - q_u
        compiled = self._kernel_geometry is not None
        k_ik = _kernels.as_f64(self._ik) if compiled else None
        k_roadmap = None
        if compiled:
            k_roadmap = _kernels.pack(
                _kernels.RoadmapTables(
                    indptr=_kernels.as_i64(rm.indptr),
                    indices=_kernels.as_i64(rm.indices),
                    ord_flat=self._ord_flat,
                    L_flat=self._L_flat,
                    same_flat=self._same_flat,
                    delta0=delta0,
                    ik=k_ik,
                )
            )
        return RoadmapView(
            num_nodes=rm.num_nodes,
            n_options=self._R,
            accel=self._A,
            q_min=self.q_min,
            q_max=self.q_max,
            ik=self._ik,
            valid=self._valid,
            stations=np.array(sorted(set(rm.station_nodes.values())), dtype=np.int64),
            indptr=self._indptr,
            indices=self._indices,
            max_degree=int(np.diff(rm.indptr).max(initial=0)),
            ord_flat=self._ord_flat,
            L_flat=self._L_flat,
            same_flat=self._same_flat,
            delta0=delta0,
            ord_list=self._ord_flat[:, 0].tolist(),
            L_list=self._L_flat[:, 0].tolist(),
            same_list=self._same_flat[:, 0].tolist(),
            indices_list=rm.indices.tolist(),
            pts_all=self._pts_all,
            cen_all=self._cen_all,
            rad_all=self._rad_all,
            next_rows=MappingProxyType(self._next_cache),
            next_rows_k=MappingProxyType(self._next_cache_k),
            compiled=self._k_align is not None and compiled,
            k_roadmap=k_roadmap,
            k_limits=self._k_limits if compiled else None,
            k_tables=self._k_tables if compiled else None,
            k_motion=self._k_motion if compiled else None,
            k_ik=k_ik,
            align=self._align,
            metric=self._metric,
            points_and_spheres=self._points_and_spheres,
            static_check=self._static_cached,
            move_samples=self._move_samples,
        )

    def _warm_up(self) -> None:
        """One small batched query between two stations with a person far away, so that the compiled
        kernels are loaded (numba's cache) here and not in the first real query (about 0.1 s once per
        process). Its only lasting effect is the static-check memo's entries (pure functions of the
        roadmap)."""
        stations = [n for n in self.roadmap.station_nodes.values() if self._valid[n].any()]
        if len(stations) < 2:
            return
        from app.prediction.forecast import HumanForecast

        far = HumanForecast(
            t0=0.0,
            times=np.array([0.0, 1.0]),
            joints=np.full((2, NUM_JOINTS, 3), 50.0),
            margins=np.array([0.1, 0.1]),
        )
        q0 = self._ik[stations[0]][np.flatnonzero(self._valid[stations[0]])[0]]
        goal = int(stations[1])
        self.plan(q_start=q0, t_start=0.0, goal=goal, forecast=far, workers=2)
        # what that query did not need: failed moves, deferred and pushed-back states, the approach probe
        sep = self._separation(far, extra_m=0.0)
        run = _Run(
            self.view, self.config, q0, 0.0, sep, goal=goal, stop_time=None, hold_s=0.0,
            h_tab=self._heuristic_table(goal), t_last=math.inf,
        )  # fmt: skip
        run.alternatives(np.zeros(0, dtype=np.int64))
        ol = _OpenList(run)
        ol.push((np.zeros(1, dtype=np.int64), np.zeros(1), np.zeros(1)))
        ol.push_back(0)
        ol.release(0)
        self._align(self._ik[:1, 0], self._ik[:1, 0])
        self.collision.distance_to_human_paired(q0[None], far.joints[:1])

    def _separation(
        self,
        forecast: HumanForecast | None,
        *,
        extra_m: float,
        offsets: tuple[float, ...] = (0.0,),
        floor_m: float | None = None,
        ssm_extra: tuple[float, np.ndarray] | None = None,
    ) -> _Separation:
        forecast = _people(forecast)
        return _Separation(
            self.collision,
            forecast,
            self.config.ssm,
            extra_m=extra_m,
            offsets=offsets,
            floor_m=floor_m,
            subsets=self._subsets_ok and self._segments_ok,
            cap_ends=self._cap_ends_for(forecast),
            robot_r=self._robot_r,
            kernel=self._kernel_geometry_for(forecast),
            ssm_extra=ssm_extra,
            stopping=self.config.stopping,
        )

    def _kernel_geometry_for(self, forecast: HumanForecast | None, *, verify: bool = False) -> Any:
        """The compiled geometry for ``forecast``'s bodies (None where the planner checks in NumPy): of the
        search's checks, or (``verify``) of the trajectory checks, with the capsules that
        :attr:`PlannerConfig.contact_only` asks only contact clearance of (the search's with
        :attr:`PlannerConfig.contact_only_search`)."""
        cfg = self.config
        soft = cfg.contact_only if (verify or cfg.contact_only_search) else ()
        if self._kernel_geometry is None or forecast is None or (forecast.bodies == 1 and not soft):
            return self._kernel_geometry
        return self.collision.kernel_geometry_for(forecast.bodies, soft)  # type: ignore[attr-defined]

    def _cap_ends_for(self, forecast: HumanForecast | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which joints each capsule of ``forecast``'s stacked bodies runs between, and its radius."""
        bodies = 1 if forecast is None else forecast.bodies
        if bodies == 1:
            return self._cap_ends
        ia, ib, r = self._cap_ends
        off = (NUM_JOINTS * np.arange(bodies, dtype=np.int64))[:, None]
        return (ia[None] + off).ravel(), (ib[None] + off).ravel(), np.tile(r, bodies)

    # ------------------------------------------------------------------------------------------ public
    def with_timer(self, timer: Callable[[], float]) -> Planner:
        """This planner reading deadlines and compute times from ``timer``: the same tables (a query keeps
        its state in its own arrays, so the two serve queries side by side)."""
        other = copy.copy(self)
        other._timer = timer
        return other

    def plan(
        self,
        *,
        q_start: np.ndarray,
        t_start: float,
        goal: str | int,
        forecast: HumanForecast | None,
        workers: int = 1,
        deadline_s: float | None = None,
        qd0: np.ndarray | None = None,
        timing: GovernorModel | None = None,
    ) -> PlanResult:
        """Plan from a configuration at a time to a station or node, safe against a forecast person.

        Args:
            q_start: Start configuration (6,) (rad); need not be a roadmap node.
            t_start: Start time (s, runtime clock, the same clock as the forecast's).
            goal: Station name (``home``, ``pickup``, ``A``..., ``A_approach``...) or roadmap node index.
            forecast: The person's forecast, or None for a static plan (no person).
            workers: States expanded per search step (1 = sequential A*; N > 1 = batched parallel A*).
            deadline_s: Compute-time budget (s); the query fails with reason ``"deadline"`` past it.
            qd0: Joint velocity (6,) at ``t_start`` (rad/s) of the motion being executed (default: at rest).
            timing: The speed governor's model: when given (with a forecast), the path found is verified
                at the timing the governor is predicted to give it (:mod:`app.planning.ssm_timing`: the
                person where they will be when the robot really gets there), and ``arrival_s`` is that
                timing's arrival; the plan keeps its full-speed timing for the robot to execute. With
                ``PlannerConfig.ssm_aware_search`` the search also asks of each move the clearance the
                governor needs to let it run at its speed, and where that finds no plan within
                ``ssm_fallback_share`` of the budget, searches again without it in the rest.

        Returns:
            A :class:`PlanResult`; ``ok`` only with a trajectory verified against ``forecast``.

        Raises:
            ValueError: ``q_start`` is not a finite (6,) configuration.
            app.planning.roadmap.RoadmapError: unknown goal.
        """
        t0 = self._timer()
        q_start = np.asarray(q_start, dtype=np.float64).reshape(-1)
        if q_start.shape != (6,) or not np.all(np.isfinite(q_start)):
            raise ValueError(f"q_start must be a finite (6,) configuration, got {q_start!r}")
        goal_node = self.roadmap.resolve(goal)
        deadline = None if deadline_s is None else t0 + deadline_s
        cfg = self.config
        if not self._valid[goal_node].any():
            return PlanResult(False, None, "goal node has no valid IK branch", 0, self._timer() - t0)
        if not self._within_limits(q_start[None])[0]:
            return PlanResult(
                False, None, "start configuration outside the joint limits", 0, self._timer() - t0
            )
        start_sep = self._separation(forecast, extra_m=0.0)
        if not start_sep.check(q_start[None], np.array([float(t_start)]), np.zeros(1), np.zeros(1))[0]:
            return PlanResult(False, None, START_BLOCKED, 0, self._timer() - t0)
        ssm_extra = None
        if timing is not None and forecast is not None and cfg.ssm_aware_search:
            table = timing.extra_clearance(v_creep_mps=cfg.ssm_creep_mps, decel_mps2=cfg.ssm_brake_decel_mps2)
            ssm_extra = (0.05, table)
        if ssm_extra is None or cfg.ssm_fallback_share >= 1.0:
            return self._attempts(
                q_start, t_start, goal_node, forecast, workers, deadline, qd0, timing, ssm_extra, t0
            )
        # the clearance the governor needs to let each move run at its speed, within a share of the budget;
        # where that finds no plan in it, the plain clearance with the rest of the budget
        share = None if deadline is None else t0 + cfg.ssm_fallback_share * (deadline - t0)
        first = self._attempts(
            q_start, t_start, goal_node, forecast, workers, share, qd0, timing, ssm_extra, t0
        )
        if first.ok:
            return first
        res = self._attempts(q_start, t_start, goal_node, forecast, workers, deadline, qd0, timing, None, t0)
        assert first.phases_s is not None and res.phases_s is not None  # _attempts times every query
        both = {k: first.phases_s[k] + res.phases_s[k] for k in PHASES}
        return dataclasses.replace(res, expanded=res.expanded + first.expanded, phases_s=both)

    def _attempts(
        self,
        q_start: np.ndarray,
        t_start: float,
        goal_node: int,
        forecast: HumanForecast | None,
        workers: int,
        deadline: float | None,
        qd0: np.ndarray | None,
        timing: GovernorModel | None,
        ssm_extra: tuple[float, np.ndarray] | None,
        t0: float,
    ) -> PlanResult:
        """The searches of :meth:`plan` with the clearance's SSM term ``ssm_extra`` (None: without): the
        search, then, where its path fails verification, the time-robust re-search (``fallback_slack_s``)."""
        cfg = self.config
        attempts: list[tuple[float, ...]] = [(0.0,)]
        if forecast is not None and cfg.fallback_slack_s > 0:
            s = cfg.fallback_slack_s
            attempts.append((-0.25 * s, 0.0, 0.5 * s, s))
        expanded = 0
        reason = "no plan"
        clock = self._timer
        took = dict.fromkeys(PHASES, 0.0)  # where the query's time goes (PlanResult.phases_s)

        def timed(phase: str, fn: Callable[..., Any], *args: Any, **kw: Any) -> Any:
            c = clock()
            out = fn(*args, **kw)
            took[phase] += clock() - c
            return out

        hold = cfg.goal_hold_s
        for offsets in attempts:
            c = clock()
            sep = self._separation(
                forecast, extra_m=cfg.corridor_margin_m, offsets=offsets, ssm_extra=ssm_extra
            )
            waypoints, n_exp, reason = self._search(
                q_start,
                float(t_start),
                sep,
                goal=goal_node,
                stop_time=None,
                hold_s=hold,
                workers=workers,
                deadline=deadline,
            )
            took["search"] += clock() - c
            expanded += n_exp
            if waypoints is None:
                break  # the time-robust check cannot succeed where the plain one failed
            done = None
            if cfg.shortcut and (deadline is None or clock() < deadline):
                short = timed("shortcut", self._shortcut, waypoints, sep, hold_s=hold)
                if short is not None:  # verified like any plan; the search's own path is the fallback
                    done = timed("finish", self._finish, short, qd0, forecast, hold_s=hold, timing=timing)
            if done is None:
                done = timed("finish", self._finish, waypoints, qd0, forecast, hold_s=hold, timing=timing)
            if done is not None:
                return PlanResult(True, done[0], "ok", expanded, clock() - t0, done[1], done[2], took)
            reason = "trajectory failed verification against the forecast"
            if deadline is not None and clock() > deadline:
                reason = "deadline"
                break
        return PlanResult(False, None, reason, expanded, clock() - t0, phases_s=took)

    def emergency(
        self,
        *,
        q_start: np.ndarray,
        t_start: float,
        forecast: HumanForecast,
        horizon_s: float,
        qd0: np.ndarray | None = None,
        workers: int = 4,
    ) -> PlanResult:
        """A short safe motion with the person held still at their pose at ``t_start``.

        Stands still when that is safe for ``horizon_s`` + ``emergency_hold_s`` (reason ``"stay"``);
        otherwise searches until a state reaches ``t_start + horizon_s`` (paper: ``F + D``) whose
        configuration is safe to hold for ``emergency_hold_s``. When the robot already violates the separation
        at ``t_start``, moves are accepted that never bring it closer to the person than it is now.

        Args:
            q_start: Current configuration (6,) (rad).
            t_start: Now (s).
            forecast: The latest forecast: its pose and margin at ``t_start`` are held, growing at its rate.
            horizon_s: ``F + D`` (s).
            qd0: Current joint velocity (6,) (rad/s); the trajectory brakes from it.
            workers: States expanded per search step.
        """
        from app.prediction.forecast import HumanForecast

        t0 = self._timer()
        cfg = self.config
        q_start = np.asarray(q_start, dtype=np.float64).reshape(6)
        t_start = float(t_start)
        joints, margin = forecast.pose_at(t_start)
        held = HumanForecast(
            t0=t_start,
            times=np.array([t_start]),
            joints=joints[None],
            margins=np.array([margin]),
            growth_mps=forecast.growth_mps,
            max_margin_m=forecast.max_margin_m,
            body_ids=forecast.body_ids,
        )
        hold_s = max(cfg.emergency_hold_s, 0.0)
        t_stop = t_start + max(horizon_s, 0.0)
        d0 = float(self.collision.distance_to_human_paired(q_start[None], joints[None])[0])
        # 1. Standing still (braking from qd0) when that is safe.
        at_rest = qd0 is None or not np.any(np.asarray(qd0) != 0.0)
        if at_rest:
            # the distance to a held person is constant; the requirement only grows with the margin
            _, m_end = held.pose_at(t_stop + hold_s)
            if (
                d0 >= float(forecast_clearance(0.0, m_end, cfg.ssm, w_top_radps=0.0))
                and self._within_limits(q_start[None])[0]
            ):
                traj = Trajectory(np.array([t_start]), q_start[None], np.zeros((1, 6)))
                return PlanResult(True, traj.to_plan(), "stay", 0, self._timer() - t0, traj)
        else:
            stay = Plan(times=np.array([t_start]), q=q_start[None], nodes=np.array([-1]))
            traj = self._fit(stay, qd0)
            if (
                traj is not None
                and self._verify(traj, held, t_start, max(t_stop, traj.t_end) + hold_s) is None
            ):
                return PlanResult(True, traj.to_plan(), "stay", 0, self._timer() - t0, traj)
        # 2. Moving: search until t_stop; escape mode if the start already violates.
        req0 = float(forecast_clearance(0.0, margin, cfg.ssm, w_top_radps=0.0))
        floor = d0 - 1e-3 if d0 < req0 else None
        sep = self._separation(held, extra_m=cfg.corridor_margin_m, floor_m=floor)
        waypoints, expanded, reason = self._search(
            q_start, t_start, sep, goal=None, stop_time=t_stop, hold_s=hold_s, workers=workers, deadline=None
        )
        if waypoints is not None:
            done = self._finish(waypoints, qd0, held, hold_s=hold_s, floor_m=floor)
            if done is not None:
                return PlanResult(True, done[0], "ok", expanded, self._timer() - t0, done[1], done[2])
            reason = "trajectory failed verification"
        return PlanResult(False, None, reason, expanded, self._timer() - t0)

    def first_violation(
        self,
        traj: Trajectory,
        forecast: HumanForecast | None,
        *,
        t_from: float,
        t_to: float,
        dt_s: float | None = None,
    ) -> float | None:
        """The earliest time in ``[t_from, t_to]`` at which ``traj`` breaks the required separation.

        The requirement at time t: surface distance robot-person >=
        :func:`app.safety.ssm.forecast_clearance` (``S_r + S_s + C + Z_r + max(Z_d, margin)``) for the
        robot's speeds at t (:meth:`robot_speeds`) and the forecast's margin at t; a
        configuration outside the joint limits counts as a violation too. Sampled every ``dt_s`` (default
        ``verify_dt_s``), both ends included. Returns None when there is no violation.
        """
        return self._verify(traj, forecast, t_from, t_to, dt_s=dt_s, static=False)

    def robot_speeds(self, traj: Trajectory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The robot's speeds at times ``t`` (K,): of its fastest point (K,) (m/s; the largest speed of any
        capsule end point) and of its fastest joint (K,) (rad/s)."""
        eps = 1e-4
        q0, q1 = traj.q(t), traj.q(t + eps)
        p0 = self._points_and_spheres(q0)[0]
        p1 = self._points_and_spheres(q1)[0]
        return np.max(np.linalg.norm(p1 - p0, axis=-1), axis=-1) / eps, np.atleast_1d(
            self.config.stopping.braking_speed((q1 - q0) / eps)
        )
