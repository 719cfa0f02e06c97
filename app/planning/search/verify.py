"""Fitting the search's waypoints to a trajectory and verifying it against the forecast (part of
:class:`app.planning.search.planner.Planner`): the fit, the NumPy and compiled verification, the finish."""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from app.planning import _kernels
from app.planning.search.config import (
    _STRETCH_FACTORS,
)
from app.planning.search.profiles import (
    _map_nodes,
)
from app.planning.ssm_timing import PredictedTiming
from app.planning.trajectory import Plan, Trajectory, TrajectoryError, fit_knots
from app.safety.ssm import forecast_clearance

if TYPE_CHECKING:
    from app.prediction.forecast import HumanForecast
    from app.safety.governor import GovernorModel

logger = logging.getLogger(__name__)


class _TrajectoryChecks:
    """Fit and verification of :class:`~app.planning.search.planner.Planner`."""

    # ------------------------------------------------------------------------------------------ fit & verify
    def _fit(self, plan: Plan, qd0: np.ndarray | None) -> Trajectory | None:
        try:
            times, q, qd = fit_knots(plan.times, plan.q, qd0=qd0, qd_max=self.qd_max, qdd_max=self.qdd_max)
        except TrajectoryError as exc:
            logger.debug("trajectory fit failed: %s", exc)
            return None
        return Trajectory(times, q, qd)

    def _verify(
        self,
        traj: Trajectory,
        forecast: HumanForecast | None,
        t_from: float,
        t_to: float,
        *,
        dt_s: float | None = None,
        static: bool = True,
        floor_m: float | None = None,
    ) -> float | None:
        dt = self.config.verify_dt_s if dt_s is None else dt_s
        if forecast is not None and forecast.bodies == 0:
            forecast = None  # a person-free cell
        ts = traj.sample(dt, t_from=t_from, t_to=max(t_to, t_from))
        if self._kernel_geometry is not None and forecast is not None:
            view = _compiled_view(traj)
            if view is not None:
                return self._verify_compiled(traj, view, forecast, ts, static=static, floor_m=floor_m)
        q = traj.q(ts)
        bad = ~self._within_limits(q)
        # forward kinematics once for the static scene and the person (when the model takes segments)
        segs = self.collision.robot_segments(q) if self._static_segments_ok else None
        if static:
            moving = np.flatnonzero((ts >= traj.t_start) & (ts <= traj.t_end))
            if moving.size:
                sub = None if segs is None else (segs[0][..., moving], segs[1][..., moving])
                bad[moving] |= self._static_bad(q[moving], sub)
        if forecast is not None:
            joints, margins = forecast.poses_at(ts)
            if self._segments_ok:
                bad |= self._separation_bad(traj, ts, q, joints, margins, floor_m, segs)
            else:
                v, w = self.robot_speeds(traj, ts)
                d = self.collision.distance_to_human_paired(q, joints)
                req = forecast_clearance(
                    v, margins, self.config.ssm, w_top_radps=w, stopping=self.config.stopping
                )
                if floor_m is not None:
                    req = np.minimum(req, floor_m)
                bad |= d < req
        if not np.any(bad):
            return None
        return float(ts[np.argmax(bad)])

    def _contact_speeds(self, bodies: int) -> np.ndarray:
        """(M,) :attr:`PlannerConfig.contact_speed_mps` for ``bodies`` stacked bodies (-1: none)."""
        return _contact_speeds(self.config.contact_speed_mps, len(self._cap_ends[0]), max(int(bodies), 1))

    def _verify_compiled(
        self,
        traj: Any,
        view: tuple[Trajectory, Callable[[np.ndarray], np.ndarray]],
        forecast: HumanForecast,
        ts: np.ndarray,
        *,
        static: bool,
        floor_m: float | None,
    ) -> float | None:
        """:meth:`_verify` with the limits and the separation in one compiled pass that stops at the first
        failing sample (:func:`app.planning._kernels.trajectory_first_violation`); the static scene, where
        asked for, in NumPy first (the compiled pass then only looks at the samples before its first
        failure). ``view``: the :class:`Trajectory` that ``traj`` evaluates and the map from wall times to
        its times (:func:`_compiled_view`)."""
        n = ts.shape[0]
        first = n
        base, path_times = view
        if static:
            moving = np.flatnonzero((ts >= traj.t_start) & (ts <= traj.t_end))
            if moving.size and base is traj:
                q = traj.q(ts[moving])
                bad = ~self._within_limits(q)
                segs = self.collision.robot_segments(q) if self._static_segments_ok else None
                bad |= self._static_bad(q, segs)
                if bad.any():
                    first = int(moving[np.argmax(bad)])
            elif moving.size:
                first = self._first_static_bad_of_view(base, path_times, ts, moving, first)
        ssm, stopping = self.config.ssm, self.config.stopping
        f64 = _kernels.as_f64
        eps = 1e-4
        t_wall = f64(ts[:first])
        geo = self._kernel_geometry_for(forecast, verify=True)
        assert geo is not None
        pack = _kernels.pack
        fc = pack(
            _kernels.ForecastPoses(
                times=f64(forecast.times),
                joints=f64(forecast.joints),
                margins=f64(forecast.margins),
                growth=float(forecast.growth_mps),
                cap=max(float(forecast.max_margin_m), float(forecast.margins.max())),
                r_max=self._human_r_max,
            )
        )
        clearance = pack(
            _kernels.Clearance(
                t_reaction_s=ssm.t_reaction_s,
                intrusion_m=ssm.intrusion_m,
                z_robot_m=ssm.z_robot_m,
                z_human_m=ssm.z_human_m,
                floor_m=math.inf if floor_m is None else float(floor_m),
                decel_mps2=stopping.decel_mps2,
                joint_decel_radps2=stopping.slowest_joint_decel_radps2,
                joint_weights=f64(stopping.joint_weights),
                free_mps=self._contact_speeds(forecast.bodies),
                delay_s=stopping.delay_s,
            )
        )
        k = _kernels.trajectory_first_violation(
            t_wall,
            f64(path_times(t_wall)),
            f64(path_times(t_wall + eps)),
            eps,
            pack(_kernels.Knots(*base._kernel_knots())),
            self._k_limits,
            fc,
            clearance,
            geo.robot,
            geo.person,
        )
        if k >= 0:
            first = k
        return None if first == n else float(ts[first])

    def _first_static_bad_of_view(
        self,
        base: Trajectory,
        path_times: Callable[[np.ndarray], np.ndarray],
        ts: np.ndarray,
        moving: np.ndarray,
        first: int,
    ) -> int:
        """The first wall-time sample (index into ``ts``) at which a view of ``base`` in another timing
        breaks the joint limits or touches the static scene (``first`` if none): the path is ``base``'s,
        whatever its timing, so it is checked at ``base``'s own sample spacing in path time (the density at
        which every trajectory is checked at full speed), not at the view's, which a slow predicted timing
        makes many times denser."""
        tau = path_times(ts[moving])
        lo, hi = float(tau[0]), float(tau[-1])
        dt = self.config.verify_dt_s
        tau_s = np.unique(np.concatenate([np.arange(lo, hi, dt), [hi]]))
        q = base.q(tau_s)
        bad = ~self._within_limits(q)
        segs = self.collision.robot_segments(q) if self._static_segments_ok else None
        bad |= self._static_bad(q, segs)
        if not bad.any():
            return first
        tau_bad = float(tau_s[np.argmax(bad)])
        # the last wall sample at or before the path reaches the bad path time (so that the failure is not
        # reported later than the path gets there)
        k = int(np.searchsorted(tau, tau_bad, side="right")) - 1
        return int(moving[max(k, 0)])

    def _separation_bad(
        self,
        traj: Trajectory,
        ts: np.ndarray,
        q: np.ndarray,
        joints: np.ndarray,
        margins: np.ndarray,
        floor_m: float | None,
        segs: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """(K,) bool: samples of ``traj`` at ``ts`` (configurations ``q``) closer to the person (poses
        ``joints`` (K, J, 3), margins (K,)) than :func:`forecast_clearance` for the robot's speed there.

        The same requirement as :meth:`robot_speeds` + ``distance_to_human_paired`` (exact), with the forward
        kinematics done once per sample time and the exact distance only where a capsule's bounding sphere
        comes within the requirement of the box around the person's pose."""
        eps = 1e-4
        model = self.collision
        a0, d0 = model.robot_segments(q) if segs is None else segs  # (L, 3, K)
        q1 = traj.q(ts + eps)
        a1, d1 = model.robot_segments(q1)
        step = np.maximum(
            np.sqrt(np.einsum("lik,lik->lk", a1 - a0, a1 - a0)),
            np.sqrt(np.einsum("lik,lik->lk", (a1 + d1) - (a0 + d0), (a1 + d1) - (a0 + d0))),
        )
        v = step.max(axis=0) / eps
        w = self.config.stopping.braking_speed((q1 - q) / eps)
        req = forecast_clearance(v, margins, self.config.ssm, w_top_radps=w, stopping=self.config.stopping)
        if floor_m is not None:
            req = np.minimum(req, floor_m)
        cen = a0 + 0.5 * d0
        rad = 0.5 * np.sqrt(np.einsum("lik,lik->lk", d0, d0)) + self._robot_r[:, None]
        jt = joints.transpose(2, 0, 1)  # (3, K, J)
        lo = (jt.min(axis=2) - self._human_r_max)[None]  # (1, 3, K)
        hi = (jt.max(axis=2) + self._human_r_max)[None]
        g = np.maximum(np.maximum(lo - cen, cen - hi), 0.0)
        gap = np.sqrt(np.einsum("lik,lik->lk", g, g)) - rad
        close = gap < req[None]  # (L, K)
        near = np.flatnonzero(close.any(axis=0))
        bad = np.zeros(q.shape[0], dtype=bool)
        if near.size == 0:
            return bad
        segments = (a0[..., near], d0[..., near])
        if not self._subsets_ok:
            d = model.distance_to_human_paired(q[near], joints[near], segments=segments)
        else:
            # only the capsules that come near: robot links near the person's box at some sample, person
            # capsules whose box over those samples comes near the box of those links
            links = np.flatnonzero(close[:, near].any(axis=1))
            r_max = float(req[near].max())
            cl, rl = cen[links][..., near], rad[links][:, near, None].transpose(0, 2, 1)
            r_lo = (cl - rl).min(axis=2).min(axis=0) - r_max
            r_hi = (cl + rl).max(axis=2).max(axis=0) + r_max
            jn = joints[near]
            ha, hb, hr = model.human_capsules(np.stack([jn.min(axis=0), jn.max(axis=0)]))
            # a capsule between two joints lies within the box of their ranges over the samples
            c_lo = np.minimum(ha[0], hb[0]) - hr[:, None]
            c_hi = np.maximum(ha[1], hb[1]) + hr[:, None]
            caps = np.flatnonzero(np.all((c_lo <= r_hi) & (c_hi >= r_lo), axis=1))
            d = model.distance_to_human_paired(
                q[near], joints[near], segments=segments, links=links, capsules=caps
            )
        bad[near] = d < req[near]
        return bad

    def _finish(
        self,
        waypoints: Plan,
        qd0: np.ndarray | None,
        forecast: HumanForecast | None,
        *,
        hold_s: float,
        floor_m: float | None = None,
        timing: GovernorModel | None = None,
    ) -> tuple[Plan, Trajectory, float] | None:
        """The search's waypoints as a verified trajectory: the fitted spline, else straight moves that stop
        at each waypoint, else the spline slower; with the predicted arrival (s, runtime clock).

        With ``timing`` (and a forecast) each candidate is verified at the timing the governor is predicted
        to give it (:class:`app.planning.ssm_timing.PredictedTiming`), and the arrival is the predicted
        one; without, at its own timing."""

        def check(traj: Trajectory) -> tuple[float | None, float]:
            return self._judge_timed(traj, forecast, timing=timing, hold_s=hold_s, floor_m=floor_m)

        traj = self._fit(waypoints, qd0)
        if traj is None:
            return None
        viol, arrival = check(traj)
        if viol is not None and (qd0 is None or not np.any(np.asarray(qd0) != 0.0)):
            # the spline cuts a corner: stopping at every waypoint keeps the robot on the straight moves
            # the search checked (slower, so it is verified again)
            logger.debug("fitted trajectory violates at t=%.3f; trying straight moves", viol)
            straight = self._fit_stops(waypoints)
            if straight is not None:
                viol, arrival = check(straight)
                if viol is None:
                    traj = straight
        if viol is not None:
            # the fitted spline peaks faster than the search's constant-speed moves, and the clearance grows
            # with the speed: the same path, slower, asks for less (and is verified again)
            for factor in _STRETCH_FACTORS:
                t0 = float(waypoints.times[0])
                times = t0 + (np.asarray(waypoints.times) - t0) * factor
                slower = Plan(times=times, q=waypoints.q, nodes=waypoints.nodes)
                retimed = self._fit(slower, qd0)
                if retimed is None:
                    continue
                viol_r, arrival_r = check(retimed)
                if viol_r is None:
                    return retimed.to_plan(_map_nodes(slower, retimed)), retimed, arrival_r
            logger.debug("fitted trajectory violates at t=%.3f (%.3f..%.3f)", viol, traj.t_start, traj.t_end)
            return None
        return traj.to_plan(_map_nodes(waypoints, traj)), traj, arrival

    def predicted_check(
        self, traj: Trajectory, forecast: HumanForecast | None, *, timing: GovernorModel | None = None
    ) -> tuple[float | None, float]:
        """``traj`` as the governor is predicted to run it against ``forecast`` (at its own timing without
        ``timing``): its first violation of the forecast person (None: none), through its arrival and the
        goal's hold (``PlannerConfig.goal_hold_s``), and its predicted arrival (s, runtime clock). The check
        of :meth:`plan`'s own result, for a trajectory planned against another forecast."""
        return self._judge_timed(traj, forecast, timing=timing, hold_s=self.config.goal_hold_s)

    def _judge_timed(
        self,
        traj: Trajectory,
        forecast: HumanForecast | None,
        *,
        timing: GovernorModel | None,
        hold_s: float,
        floor_m: float | None = None,
    ) -> tuple[float | None, float]:
        view: Any = traj
        # (a path of no duration, the robot already at its goal, has no motion to govern)
        if timing is not None and forecast is not None and forecast.bodies > 0 and traj.t_end > traj.t_start:
            view = PredictedTiming.of(traj, forecast, self.collision, timing)
        end = view.t_end + hold_s
        return self._verify(view, forecast, view.t_start, end, floor_m=floor_m), view.t_end

    def _fit_stops(self, plan: Plan) -> Trajectory | None:
        """A trajectory at rest at every waypoint: each segment a straight joint move with zero end
        velocities (cubic Hermite), at the waypoints' times or later where the limits need longer
        (peak velocity 1.5 dq / h, peak acceleration 6 dq / h^2 per joint)."""
        times, q = plan.times, plan.q
        if times.shape[0] < 2:
            return None
        dq = np.abs(np.diff(q, axis=0))
        need = np.maximum(
            np.max(1.5 * dq / self.qd_max, axis=1), np.sqrt(np.max(6.0 * dq / self.qdd_max, axis=1))
        )
        h = np.maximum(np.maximum(np.diff(times), need), 1e-3)
        t = np.concatenate([[times[0]], times[0] + np.cumsum(h)])
        return Trajectory(t, q.copy(), np.zeros_like(q))


@functools.lru_cache(maxsize=32)
def _contact_speeds(speeds: tuple[float, ...], n_caps: int, bodies: int) -> np.ndarray:
    """(M,) ``speeds`` (one per capsule, -1 for all where empty) for ``bodies`` stacked bodies, read-only:
    built once, not at every check (the supervisor checks the plan in execution at every frame)."""
    one = np.asarray(speeds, dtype=np.float64) if speeds else np.full(n_caps, -1.0)
    out = np.ascontiguousarray(np.tile(one, bodies))
    out.setflags(write=False)
    return out


def _wall_times(t: np.ndarray) -> np.ndarray:
    return t


def _compiled_view(traj: Any) -> tuple[Trajectory, Callable[[np.ndarray], np.ndarray]] | None:
    """The :class:`Trajectory` whose knots the compiled check evaluates for ``traj``, and the map from wall
    times to its times: ``traj`` itself, or a view of one in another timing that names it
    (``base_trajectory``) and maps wall times to its times (``path_times``, e.g. the supervisor's
    speed-scaled view of the plan in execution); None for anything else (checked in NumPy)."""
    if isinstance(traj, Trajectory):
        return traj, _wall_times
    base = getattr(traj, "base_trajectory", None)
    path_times = getattr(traj, "path_times", None)
    if isinstance(base, Trajectory) and callable(path_times):
        return base, path_times
    return None
