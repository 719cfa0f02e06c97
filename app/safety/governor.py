"""The speed governor of ISO/TS 15066 speed and separation monitoring, per servo tick: the protective
separation and the braking envelope built on it (:class:`SeparationModel`), and the standard's constant-speed
scaling law (:class:`SpeedScaleLaw`). Their compiled loops are in :mod:`app.safety._kernels`; this module is
their public face for the other packages: the kernels' inputs (:class:`PartSeparation`, :class:`PFLLevels`,
:class:`RobotMotion`, :class:`ServoGovernor`), the servo tick's scale (:func:`governed_scale`), the envelope
and the law (:func:`max_scale`, :func:`law_scale`) and the person's worst-case approach (:func:`approach`),
which compiled code elsewhere (the SSM-aware timing) inlines as the governor does."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.safety._kernels import (
    PartSeparation,
    PFLLevels,
    RobotMotion,
    ServoGovernor,
    approach,
    governed_scale,
    law_scale,
    max_scale,
)
from app.safety._kernels import max_scale as _kernel_max_scale
from app.safety.pfl import per_body
from app.safety.ssm import max_safe_speed, required_separation

__all__ = [
    "BRAKE_INSTANTS",
    "NO_LAW",
    "SCALE_GRID",
    "GovernorModel",
    "PFLLevels",
    "PartSeparation",
    "PathClosing",
    "RobotMotion",
    "SeparationModel",
    "ServoGovernor",
    "SpeedScaleLaw",
    "approach",
    "brake_rate",
    "closing_bound",
    "directed_approach",
    "directed_pairs",
    "governed_scale",
    "law_scale",
    "max_scale",
    "nearest_approach",
    "ssm_alone",
]

# ----------------------------------------------------------------------------------------------------
# Speed governor: ISO/TS 15066 separation at every servo tick
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SeparationModel:
    """ISO/TS 15066 protective separation, and the braking envelope built on it.

    ``S_p = S_h + S_r + S_s + C + Z_d + Z_r`` with ``S_h = v_h (T_r + T_s)``, ``S_r = v_r T_r``,
    ``S_s = v_r T_s / 2``, where ``v_r`` is the speed of the robot part, ``v_h`` the person's speed toward it
    (ISO/TS 15066 5.5.4.2.3: the measured speed where the system monitors it, as here) and ``T_s`` the
    robot's stopping time *from its current speed* (a robot creeping at 1 cm/s stops in milliseconds, not
    in the 0.2 s it needs at 1 m/s): in :meth:`max_scale`, the governor's check, the duration of the brake
    itself, the stopping model's (:mod:`app.safety.stopping`: the slower of the fastest point's and the
    fastest joint's deceleration); in :meth:`sp` and :meth:`max_speed`, of a robot moving as one part,
    ``T_s = v_top / stop_decel_mps2`` with ``v_top`` the speed of its fastest part. With
    :class:`app.safety.ssm.SSMParams` (:meth:`from_ssm`): ``s0 = C + Z_d + Z_r``, ``T_r = t_reaction_s``.

    The *envelope* answers: how fast may the robot move at separation ``d`` so that, braking now, the
    separation stays at or above ``S_p`` at every instant until it is at rest, while the person approaches
    as fast as a person can: speeding up from ``v_h0`` at ``human_accel_mps2`` to at most
    ``human_speed_max_mps`` (their approach and the robot's own travel both counted)?

    Attributes:
        s0_m: ``C + Z_d + Z_r`` (m).
        t_reaction_s: ``T_r`` (s).
        stop_decel_mps2: The robot's stopping deceleration for ``T_s`` (m/s^2).
        human_speed_max_mps: Fastest approach of a person (m/s).
        human_accel_mps2: Fastest change of a person's speed (m/s^2).
    """

    s0_m: float = 0.11
    t_reaction_s: float = 0.1
    stop_decel_mps2: float = 2.0
    human_speed_max_mps: float = 2.0
    human_accel_mps2: float = 8.0
    _kernel_params: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        names = ("s0_m", "t_reaction_s", "stop_decel_mps2", "human_speed_max_mps", "human_accel_mps2")
        for name in names:
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"SeparationModel.{name} must be finite and >= 0, got {v}")
        if self.stop_decel_mps2 <= 0:
            raise ValueError("SeparationModel.stop_decel_mps2 must be > 0")
        object.__setattr__(self, "_kernel_params", np.array([float(getattr(self, n)) for n in names]))

    @property
    def kernel_params(self) -> np.ndarray:
        """``(s0_m, t_reaction_s, stop_decel_mps2, human_speed_max_mps, human_accel_mps2)``, as the compiled
        envelope (:func:`app.safety._kernels.max_scale`) reads them (a copy)."""
        return self._kernel_params.copy()

    @classmethod
    def from_ssm(
        cls,
        params: Any,
        *,
        human_speed_max_mps: float = 2.0,
        human_accel_mps2: float = 8.0,
        stop_decel_mps2: float = 2.0,
    ) -> SeparationModel:
        """From :class:`app.safety.ssm.SSMParams` (``C``, ``Z_d``, ``Z_r``, ``T_r``)."""
        return cls(
            s0_m=float(params.intrusion_m + params.z_human_m + params.z_robot_m),
            t_reaction_s=float(params.t_reaction_s),
            stop_decel_mps2=stop_decel_mps2,
            human_speed_max_mps=human_speed_max_mps,
            human_accel_mps2=human_accel_mps2,
        )

    def sp(self, v_part: Any, v_top: Any, v_human: Any) -> Any:
        """``S_p`` (m) of a part moving at ``v_part`` on a robot whose fastest part moves at ``v_top``, the
        person approaching at ``v_human`` (arrays broadcast)."""
        t_s = np.maximum(v_top, 0.0) / self.stop_decel_mps2
        return required_separation(
            v_human, v_part, t_reaction_s=self.t_reaction_s, t_stop_s=t_s, constant_m=self.s0_m
        )

    def required(self, v_robot_mps: float, v_human_mps: float = 0.0) -> float:
        """``S_p`` (m) of the robot's fastest part."""
        return float(self.sp(v_robot_mps, v_robot_mps, v_human_mps))

    def human_approach(self, v_h0: Any, dt: Any) -> tuple[np.ndarray, np.ndarray]:
        """Worst-case approach distance (m) and speed (m/s) of the person ``dt`` (s) after moving at
        ``v_h0`` toward the robot (both broadcast)."""
        v_h0 = np.asarray(v_h0, dtype=np.float64)
        dt = np.maximum(np.asarray(dt, dtype=np.float64), 0.0)
        vmax = np.maximum(self.human_speed_max_mps, v_h0)
        a = self.human_accel_mps2
        if a <= 0:
            return v_h0 * dt, np.broadcast_to(v_h0, np.broadcast(v_h0, dt).shape).copy()
        t1 = (vmax - v_h0) / a
        acc = np.minimum(dt, t1)
        dist = v_h0 * acc + 0.5 * a * acc**2 + vmax * np.maximum(dt - t1, 0.0)
        return dist, np.minimum(v_h0 + a * dt, vmax)

    def max_speed(
        self, separation_m: Any, *, v_human_mps: Any, decel_mps2: Any, v_cap_mps: float = 3.0
    ) -> Any:
        """Largest safe speed (m/s) of a robot moving as one part at ``separation_m`` with the person
        approaching at ``v_human_mps`` now, braking at ``decel_mps2`` (0 when even a creeping robot is not
        safe). Arguments broadcast; a float for scalar arguments."""
        d, vh0, a = np.broadcast_arrays(
            np.asarray(separation_m, dtype=np.float64),
            np.asarray(v_human_mps, dtype=np.float64),
            np.maximum(np.asarray(decel_mps2, dtype=np.float64), 1e-3),
        )
        shape = d.shape
        d, vh0, a = d.reshape(-1, 1, 1), vh0.reshape(-1, 1, 1), a.reshape(-1, 1, 1)
        v = np.linspace(0.0, v_cap_mps, _ENV_NV)[None, :, None]
        t = BRAKE_INSTANTS[None, None, :] * v / a
        x_h, v_h = self.human_approach(vh0, t)
        travel = v * t - 0.5 * a * t**2
        vt = v - a * t
        need = self.sp(vt, vt, v_h)
        ok = np.all(d - x_h - travel - need >= 0.0, axis=2)  # (P, NV)
        ok &= np.isfinite(d[:, :, 0]) | (d[:, :, 0] > 0)
        n_ok = np.cumprod(ok, axis=1).sum(axis=1)  # leading feasible speeds
        out = np.where(n_ok > 0, v[0, np.maximum(n_ok - 1, 0), 0], 0.0)
        out = np.where(~np.isfinite(d[:, 0, 0]) & (d[:, 0, 0] > 0), v_cap_mps, out)
        out = out.reshape(shape)
        return float(out) if out.ndim == 0 else out

    def max_scale(
        self,
        separation_m: np.ndarray,
        *,
        v_human_mps: np.ndarray,
        v_parts_mps: np.ndarray,
        rate: float,
        lo: float = 0.0,
        hi: float = 1.0,
        pfl: PFLLevels | None = None,
    ) -> float:
        """Largest path-speed scale in [0, 1] that is safe for every part: part i closes on the person at
        ``s * v_parts_mps[i]`` (its speed toward the person, ISO/TS 15066's directed ``v_r``; its whole
        speed where the direction is not known) and a brake lowers the scale at ``rate`` (1/s), so every
        part stops after ``s / rate``: that is the robot's stopping time ``T_s`` in ``S_p`` (the brake's rate
        is the stopping model's, the slower of its fastest point's and fastest joint's deceleration, as
        :func:`brake_rate` gives it). Arrays (L,) (the parts that move).

        Only scales in ``[lo, hi]`` are examined (the grid's and both ends; the servo passes the range it
        can reach within one tick): the answer is the largest of them up to which every one is safe, ``hi``
        at most, and 0 when ``lo`` is not safe. ``pfl``: power and force limiting inside ``S_p``
        (:class:`app.safety._kernels.PFLLevels`); None: SSM alone. Compiled
        (:func:`app.safety._kernels.max_scale`); the tests
        compare it with a NumPy reference (``tests/governor_reference.py``)."""
        d = np.ascontiguousarray(separation_m, dtype=np.float64).reshape(-1)
        if pfl is None:
            pfl = ssm_alone(d.shape[0])
        return float(
            _kernel_max_scale(
                d,
                np.ascontiguousarray(v_human_mps, dtype=np.float64).reshape(-1),
                np.ascontiguousarray(v_parts_mps, dtype=np.float64).reshape(-1),
                float(rate),
                float(lo),
                float(hi),
                SCALE_GRID,
                BRAKE_INSTANTS,
                self._kernel_params,
                np.ascontiguousarray(pfl.levels, dtype=np.float64),
                np.ascontiguousarray(pfl.extra, dtype=np.float64),
                np.ascontiguousarray(pfl.v_h, dtype=np.float64),
            )
        )


@dataclass(frozen=True, slots=True)
class SpeedScaleLaw:
    """The ISO/TS 15066 speed-scaling law (:func:`app.safety.ssm.speed_scale`) as the speed governor
    applies it per servo tick: the smallest scale over the moving parts.

    Attributes:
        params: :class:`app.safety.ssm.SSMParams` (``T_r``, ``T_s``, ``C``, ``Z_d``, ``Z_r``).
        kernel_params: ``(T_r + T_s, C + Z_d + Z_r, T_r + T_s / 2)`` as the compiled governor reads them.
    """

    params: Any
    kernel_params: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        p = self.params
        kernel = np.array([p.t_reaction_s + p.t_stop_s, p.constant_m, p.robot_time_s], dtype=np.float64)
        object.__setattr__(self, "kernel_params", kernel)

    def __call__(self, separation_m: np.ndarray, v_nominal_mps: np.ndarray, v_human_mps: np.ndarray) -> float:
        """The smallest scale over parts (L,) (1 for no part), in NumPy: the compiled governor's reference."""
        from app.safety.ssm import speed_scale

        d = np.asarray(separation_m, dtype=np.float64)
        if d.size == 0:
            return 1.0
        return float(np.min(speed_scale(d, v_nominal_mps, self.params, v_human_mps=v_human_mps)))


def ssm_alone(n_parts: int) -> PFLLevels:
    """Power and force limiting off for ``n_parts`` robot parts: each keeps ``S_p`` from every capsule."""
    return PFLLevels(np.array([-1.0]), np.zeros((n_parts, 1)), np.full((n_parts, 1), np.inf))


#: The governor's law parameters when it applies no scaling law (the braking envelope alone).
NO_LAW = np.zeros(0)
#: The speed scales the governor chooses from.
SCALE_GRID = np.linspace(0.0, 1.0, 41)
_ENV_NV = 97
#: Instants of a brake, as fractions of its duration (its end: the robot is at rest).
BRAKE_INSTANTS = np.linspace(0.0, 1.0, 25)[:-1]


# ----------------------------------------------------------------------------------------------------
# The governor's speed scale predicted from a forecast (SSM-aware timing of plans)
# ----------------------------------------------------------------------------------------------------


def brake_rate(v_top_mps: float, w_top_radps: float, decel_mps2: float, joint_decel_radps2: float) -> float:
    """How fast (1/s) a brake lowers the path scale of a path whose fastest point moves at ``v_top_mps``
    and fastest joint at ``w_top_radps`` at scale 1, braking at ``decel_mps2`` (fastest point) and
    ``joint_decel_radps2`` (fastest joint); inf for a path at rest. The supervisor's brake and the
    governor's model both take it from here."""
    rate = math.inf
    if v_top_mps > 1e-9:
        rate = decel_mps2 / v_top_mps
    if w_top_radps > 1e-9:
        rate = min(rate, joint_decel_radps2 / w_top_radps)
    return rate


def directed_approach(
    d_now: np.ndarray,
    d_before: np.ndarray,
    dt_s: float,
    *,
    band_m: float,
    floor_mps: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Each robot part's separation (L,) and the person's *directed* speed toward it (L,), from the surface
    distances (L, M) of the robot's parts to the person's capsules now and ``dt_s`` earlier.

    ISO/TS 15066 5.5.4.2.3 asks for the operator's speed in the direction of the robot. Of the person's
    capsules within ``band_m`` of the nearest one to a part, the fastest rate at which the distance to the
    part shrank counts (not only the nearest pair, so the value does not jump when the nearest pair
    changes); a limb that moves sideways or away does not count. ``floor_mps`` (M,): each capsule's least
    approach speed (ISO 13855's; the measured one where it is faster, never lower). The supervisor
    measures the person with it, and :class:`GovernorModel` predicts the governor from a forecast with it."""
    d_now = np.asarray(d_now, dtype=np.float64)
    approach = np.maximum(np.asarray(d_before, dtype=np.float64) - d_now, 0.0) / max(float(dt_s), 1e-6)
    if floor_mps is not None:
        approach = np.maximum(approach, per_body(floor_mps, d_now.shape[-1], "floor_mps"))
    return nearest_approach(d_now, approach, band_m=band_m)


def nearest_approach(
    d_now: np.ndarray, v_pairs: np.ndarray, *, band_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each robot part's separation (L,) and the fastest approach ``v_pairs`` (L, M) of the person's
    capsules within ``band_m`` of its nearest one, from the distances ``d_now`` (L, M)
    (:func:`directed_approach`)."""
    sep = d_now.min(axis=-1)
    near = d_now <= sep[..., None] + band_m
    return sep, np.where(near, v_pairs, 0.0).max(axis=-1)


def directed_pairs(
    geometry: Any,
    q: np.ndarray,
    joints: np.ndarray,
    joints_before: np.ndarray | None,
    dt_s: float | None,
    *,
    v_unknown_mps: float,
    floor_mps: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The surface distances (L, M) of the robot's parts at ``q`` to the person's capsules at ``joints``,
    and the person's speed toward each part per capsule (L, M): how fast each distance shrank since
    ``joints_before``, ``dt_s`` earlier (``v_unknown_mps`` without an earlier pose), at least ``floor_mps``
    (M,), ISO 13855's speed of each capsule's region (None: the measured speed alone). Several bodies stacked
    (B*J joints): (L, B*M), the floor of each body's capsules the same."""
    if joints_before is None or dt_s is None:
        d_now = np.asarray(geometry.pair_distances(q, np.asarray(joints)[None]), dtype=np.float64)[0]
        v = np.full(d_now.shape, float(v_unknown_mps))
    else:
        d2 = np.asarray(geometry.pair_distances(q, np.stack([joints, joints_before])), dtype=np.float64)
        d_now = d2[0]
        v = np.maximum(d2[1] - d_now, 0.0) / max(float(dt_s), 1e-6)
    if floor_mps is not None:  # per capsule of one body, for every body of a stacked pose
        v = np.maximum(v, per_body(floor_mps, d_now.shape[1], "floor_mps")[None, :])
    return d_now, v


def closing_bound(taus: np.ndarray, d: np.ndarray, v_lip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How fast a robot's own motion along its path can close each part's separation from a person held
    where they were measured: ISO/TS 15066's speed of the robot *in the direction of the operator*.

    ``d`` (K, L) is each part's separation from the held person at the path times ``taus`` (K,) (increasing,
    ``taus[0]`` the robot's place now) and ``v_lip`` (L,) a bound of each part's speed over them (m/s). The
    result ``(v_toward, slack)`` (L,) bounds the separation *between* the samples too:
    ``d(tau) >= d[0] - v_toward * (tau - taus[0]) - slack`` for every ``tau`` in ``[taus[0], taus[-1]]``.
    A separation changes no faster than the part's points move, so between two samples it stays above the
    "V" of slopes ``-v_lip`` and ``+v_lip`` through them, whose lowest point (time ``t_k``, value ``e_k``) is
    where a line of slope at most ``v_lip`` comes closest: ``v_toward`` is the largest of
    ``(d[0] - slack - e_k) / (t_k - taus[0])``, ``slack`` covers the first interval. A part moving away has a
    negative ``v_toward``: the separation it is sure to gain (the person's own approach is bounded apart:
    the true separation is at least this one less how far the person has moved)."""
    taus = np.asarray(taus, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    n_parts = d.shape[1]
    if taus.shape[0] < 2:
        return np.zeros(n_parts), np.zeros(n_parts)
    h = np.diff(taus)[:, None]
    dd = d[1:] - d[:-1]
    # the samples themselves bound the speed from below (a coarse profile must not undercut them)
    v = np.maximum(np.asarray(v_lip, dtype=np.float64)[None, :], np.abs(dd) / np.maximum(h, 1e-12))
    low = 0.5 * (d[:-1] + d[1:] - v * h)  # (K - 1, L) the V's lowest value in each interval
    with np.errstate(divide="ignore", invalid="ignore"):
        t_low = taus[:-1, None] + np.where(v > 0.0, 0.5 * (h - dd / v), 0.5 * h)  # ... and its time
    slack = np.maximum(d[0] - low[0], 0.0)  # the first interval
    if taus.shape[0] < 3:
        return np.zeros(n_parts), slack
    el = np.maximum(t_low[1:] - taus[0], 1e-12)
    rate = np.maximum(((d[0] - slack - low[1:]) / el).max(axis=0), -v.max(axis=0))
    # a gain must hold over the first interval too: what it credits there goes into the slack
    return rate, slack + np.maximum(-rate, 0.0) * h[0]


@dataclass(frozen=True, slots=True)
class PathClosing:
    """Each robot part's closing on the person along a path, measured at a frame
    (:func:`closing_bound`): what the part's own motion closes of its separation from the person as seen,
    ``closed(tau) <= v_toward * (tau - tau0) + slack``, for path times ``tau0 <= tau <= tau_valid``.

    Attributes:
        tau0: Path time of the robot at the frame (s).
        tau_valid: The last path time the bound covers (s; inf: to the path's end, where the robot stays).
        v_toward: (L,) each part's speed toward the person at scale 1 (m/s; negative: moving away).
        slack: (L,) what the first sample interval may close (m).
    """

    tau0: float
    tau_valid: float
    v_toward: np.ndarray
    slack: np.ndarray

    @classmethod
    def measure(
        cls, traj: Any, profile: Any, tau: float, joints: np.ndarray, geometry: Any, *, horizon_s: float
    ) -> PathClosing | None:
        """Along ``traj`` from path time ``tau`` over ``horizon_s`` (path time), every ``profile.step_s``,
        against the person at ``joints`` (J, 3): ``geometry.path_separations`` gives each part's
        separation, ``profile.v_mps`` (the parts' speeds along ``traj``, sampled from ``profile.tau0``)
        bounds how fast it changes. None past the path's end."""
        t_end = float(traj.t_end)
        if tau >= t_end:
            return None
        horizon = tau + horizon_s
        taus = np.append(np.arange(tau, min(horizon, t_end), profile.step_s), min(horizon, t_end))
        q = np.asarray(traj.q(taus), dtype=np.float64).reshape(-1, 6)
        d = np.asarray(geometry.path_separations(q, joints), dtype=np.float64)
        # a bound of each part's speed over the samples: the profile's, one sample either side
        i0 = max(int((tau - profile.tau0) / profile.step_s) - 1, 0)
        i1 = int((taus[-1] - profile.tau0) / profile.step_s) + 2
        v = profile.v_mps
        v_lip = v[i0:i1].max(axis=0) if i0 < v.shape[0] else np.zeros(d.shape[1])
        v_toward, slack = closing_bound(taus, d, v_lip)
        # beyond the end the robot is at rest: the bound holds for ever there
        return cls(float(tau), math.inf if horizon >= t_end else horizon, v_toward, slack)

    def motion(
        self, tau: float, vmax: np.ndarray, travel_m: np.ndarray, *, dt: float, rate: float, hi: float
    ) -> RobotMotion | None:
        """The robot's motion for the governor's tick (:class:`app.safety._kernels.RobotMotion`) at path time
        ``tau``, the parts' whole speeds ``vmax`` (L,) over the look-ahead and travel ``travel_m`` (L,)
        since the frame: per part, this bound or the whole speed's (not a mix), whichever closes less by the
        end of a brake from scale ``hi`` (braking at ``rate``, 1/s) after a tick of ``dt``. None where this
        bound does not cover that brake."""
        brake_path = 0.0 if not math.isfinite(rate) else hi * hi / (2.0 * max(rate, 1e-9))
        ahead = hi * dt + brake_path
        if tau < self.tau0 - 1e-9 or tau + ahead > self.tau_valid:
            return None
        closed = self.v_toward * (tau - self.tau0) + self.slack
        # A part that closes at all counts at its whole speed: the bound is the closing rate of its separation
        # from the nearest capsule of the tracked pose, and toward another capsule, or the true person a
        # frame's age later, it may close faster (a CMU replay: 0.32 m/s seen, 0.38 m/s true, inside S_p of
        # a leg whose permissible contact speed is 0.36 m/s). A part moving away keeps its directed speed
        # (at most its whole speed).
        toward = np.where(self.v_toward > 0.0, vmax, np.minimum(self.v_toward, vmax))
        use = closed + toward * ahead < travel_m + vmax * ahead
        return RobotMotion(vmax, np.where(use, toward, vmax), np.where(use, closed, travel_m))


@dataclass(frozen=True, slots=True)
class GovernorModel:
    """What the speed governor of the supervisor will do, as the planner predicts it (SSM-aware timing).

    The governor (``Supervisor._governed_scale``) measures, at each frame, every robot part's separation
    to the person less the tracking margin and the person's directed approach speed over a window; from
    then on it assumes the person's worst case (:meth:`SeparationModel.human_approach`) and runs the path
    at the largest scale from which braking keeps ``S_p`` (:meth:`SeparationModel.max_scale`). Given the
    separation and the directed speed that a *forecast* says the person will have when the robot is at a
    point of its path, :meth:`scale` returns the scale the governor will then allow, with the frame as old
    as it gets at a decision (:attr:`sensing_age_s`). The planner stretches a path's timing by
    it, so that a plan says when the robot will really arrive and the governor only corrects deviations.

    Attributes:
        separation: The governor's :class:`SeparationModel` (the same object as the supervisor's).
        brake_decel_mps2: Deceleration of the robot's fastest point when braking (m/s^2).
        brake_joint_decel: Largest joint deceleration when braking (rad/s^2).
        tracking_margin_m: Subtracted from every separation, as the supervisor does.
        speed_window_s: The window over which the supervisor measures the person's speed (s).
        sensing_age_s: Age of the newest frame when the governor decides, from its capture, as old as it
            gets before the next one arrives: tracker latency + a frame period + processing (s). (With
            half a frame period, the typical age, the prediction runs about 15-25 % fast in the supervisor
            test; with a whole one it is within 20 % either way.)
        near_band_m: :func:`directed_approach`'s band (m).
        speed_noise_mps: What the noise of the tracked joints adds to the measured directed speed of a
            person (m/s): the governor measures the person's speed from two noisy frames, so it sees a
            standing person approach at a few tenths of a metre per second; a forecast does not.
        lookahead_s: The governor's look-ahead along the path (s): it brakes for the fastest speed of each
            part over the next ``lookahead_s`` of path time (``SupervisorConfig.profile_window_s``).
        law: The standard's speed-scaling law that the governor also applies (with the measured speed),
            or None when it applies the braking envelope alone.
        min_scale: The smallest scale a plan is timed with: where the forecast leaves the robot no speed
            at all, the plan is timed as if it crept at this scale (the governor holds it until the
            person has moved; a plan timed as standing still forever would never arrive).
        robot_toward: The governor takes each part's speed toward the person
            (``SupervisorConfig.robot_toward``); False: their whole speeds.
        pfl_caps_mps: Each person capsule's permissible contact speed (m/s; -1: no contact permitted), power
            and force limiting inside ``S_p`` (:class:`app.safety.pfl.PFLModel`); empty: SSM alone.
        approach_floor_mps: Each person capsule's least approach speed (m/s), ISO 13855's
            (:attr:`app.safety.pfl.PFLModel.iso_speeds_mps`); empty: the measured speed alone.
    """

    separation: SeparationModel
    brake_decel_mps2: float
    brake_joint_decel: float
    tracking_margin_m: float
    speed_window_s: float
    sensing_age_s: float
    near_band_m: float = 0.25
    speed_noise_mps: float = 0.0
    lookahead_s: float = 0.6
    law: SpeedScaleLaw | None = None
    min_scale: float = 0.1
    robot_toward: bool = True
    pfl_caps_mps: tuple[float, ...] = ()
    approach_floor_mps: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("brake_decel_mps2", "brake_joint_decel", "speed_window_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"GovernorModel.{name} must be finite and > 0, got {v}")
        for name in ("tracking_margin_m", "sensing_age_s", "near_band_m", "lookahead_s", "speed_noise_mps"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"GovernorModel.{name} must be finite and >= 0, got {v}")
        if not 0.0 < self.min_scale <= 1.0:
            raise ValueError(f"GovernorModel.min_scale must be in (0, 1], got {self.min_scale}")

    def caps_for(self, n_caps: int) -> np.ndarray:
        """(B*M,) the capsules' permissible contact speeds (m/s) for ``n_caps`` capsules of B stacked bodies,
        -1 everywhere for SSM alone."""
        if not self.pfl_caps_mps:
            return np.full(n_caps, -1.0)
        return per_body(self.pfl_caps_mps, n_caps, "GovernorModel.pfl_caps_mps")

    def floors_for(self, n_caps: int) -> np.ndarray:
        """(B*M,) the capsules' least approach speeds (m/s) for ``n_caps`` capsules of B stacked bodies, 0
        everywhere without a floor."""
        if not self.approach_floor_mps:
            return np.zeros(n_caps)
        return per_body(self.approach_floor_mps, n_caps, "GovernorModel.approach_floor_mps")

    @property
    def approach_floor_max_mps(self) -> float:
        """The fastest of the capsules' least approach speeds (m/s; 0 without a floor)."""
        return max(self.approach_floor_mps, default=0.0)

    def extra_clearance(
        self, *, v_creep_mps: float, decel_mps2: float, dv_mps: float = 0.05, v_max_mps: float = 3.0
    ) -> np.ndarray:
        """How much more separation (m) than a robot creeping at ``v_creep_mps`` the governor needs to let
        a robot part move at each speed ``v = i * dv_mps`` up to ``v_max_mps`` (0 up to the creep speed),
        braking at ``decel_mps2``, the person as the governor sees a still one (:attr:`speed_noise_mps`
        after a frame of typical age). The planner adds it to the clearance it asks of a move at speed
        ``v`` from the forecast person: a move near the person at full speed, which the governor would slow
        to a crawl, fails the search's check, and the search takes it slower or goes round."""
        vh0 = max(self.speed_noise_mps, self.approach_floor_max_mps)
        _, v1 = self.separation.human_approach(vh0, 0.5 * self.speed_window_s + self.sensing_age_s)
        d = np.arange(0.0, 4.0 + 1e-9, 0.005)
        vmax = np.maximum.accumulate(
            np.asarray(
                self.separation.max_speed(
                    d, v_human_mps=float(v1), decel_mps2=decel_mps2, v_cap_mps=v_max_mps
                )
            )
        )
        v = np.arange(0.0, v_max_mps + 1e-9, dv_mps)
        need = d[np.minimum(np.searchsorted(vmax, v, side="left"), d.size - 1)]
        creep = d[min(int(np.searchsorted(vmax, v_creep_mps, side="left")), d.size - 1)]
        return np.where(v <= v_creep_mps, 0.0, np.maximum(need - creep, 0.0))

    def max_speed(self, sep_m: Any, v_human_mps: Any, *, v_cap_mps: float = 3.0) -> np.ndarray:
        """The fastest (m/s) the governor lets a robot part move toward the person, braking at
        :attr:`brake_decel_mps2`, at the separation ``sep_m`` (as measured, before the tracking margin) from a
        person whose directed speed toward it was *measured* at ``v_human_mps`` over the speed window (from
        tracked frames: their noise is in it already, unlike a forecast's in :meth:`scale`): the braking
        envelope with the person's worst case since the middle of the window and the frame's age, and the
        speed-scaling law where this model has one. Arrays broadcast."""
        vh0 = np.maximum(np.asarray(v_human_mps, dtype=np.float64), self.approach_floor_max_mps)
        sep_lb, v1 = self._worst_case(sep_m, vh0)
        v = np.asarray(
            self.separation.max_speed(
                sep_lb, v_human_mps=v1, decel_mps2=self.brake_decel_mps2, v_cap_mps=v_cap_mps
            ),
            dtype=np.float64,
        )
        if self.law is not None:
            v = np.minimum(v, max_safe_speed(sep_lb, self.law.params, v_human_mps=vh0))
        return v

    def _worst_case(self, sep_m: Any, vh0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The separation's lower bound and the person's speed toward the part when the governor decides,
        from a separation ``sep_m`` and a directed speed ``vh0`` measured over the speed window: from the
        middle of the window the approach until the frame was taken is already in the measured separation,
        the rest of the frame's age is the person's worst case."""
        half = 0.5 * self.speed_window_s
        x0, _ = self.separation.human_approach(vh0, half)
        x1, v1 = self.separation.human_approach(vh0, half + self.sensing_age_s)
        return np.asarray(sep_m, dtype=np.float64) - self.tracking_margin_m - (x1 - x0), v1

    def brake_rate(self, v_top_mps: float, w_top_radps: float) -> float:
        """:func:`brake_rate` with this governor's brake."""
        return brake_rate(v_top_mps, w_top_radps, self.brake_decel_mps2, self.brake_joint_decel)

    def scale(
        self,
        sep_m: np.ndarray,
        v_human_mps: np.ndarray,
        v_parts_mps: np.ndarray,
        w_top_radps: float,
        v_toward_mps: np.ndarray | None = None,
    ) -> float:
        """The governor's scale in [0, 1] for parts (L,) at separations ``sep_m`` (as measured, before the
        tracking margin), the person approaching each at ``v_human_mps`` (measured over the window), the
        parts moving at ``v_parts_mps`` at scale 1 (over the governor's look-ahead), closing on the person
        at ``v_toward_mps`` (default: their whole speed) and the fastest joint at ``w_top_radps``."""
        v_parts = np.asarray(v_parts_mps, dtype=np.float64)
        vtop = float(v_parts.max(initial=0.0))
        if vtop <= 1e-4:
            return 1.0
        toward = v_parts if v_toward_mps is None else np.asarray(v_toward_mps, dtype=np.float64)
        vh0 = np.maximum(
            np.asarray(v_human_mps, dtype=np.float64) + self.speed_noise_mps, self.approach_floor_max_mps
        )
        sep_lb, v1 = self._worst_case(sep_m, vh0)
        rate = self.brake_rate(vtop, float(w_top_radps))
        s = self.separation.max_scale(sep_lb, v_human_mps=v1, v_parts_mps=toward, rate=rate)
        if self.law is not None:
            s = min(s, max(self.law(sep_lb, toward, vh0), 0.0))
        return s
