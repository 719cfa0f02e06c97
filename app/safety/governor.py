"""The speed governor of ISO/TS 15066 speed and separation monitoring, per servo tick: the protective
separation and the braking envelope built on it (:class:`SeparationModel`), and the standard's constant-speed
scaling law (:class:`SpeedScaleLaw`). Their compiled loops are in :mod:`app.safety._kernels`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.safety._kernels import max_scale as _kernel_max_scale

# ----------------------------------------------------------------------------------------------------
# Speed governor: ISO/TS 15066 separation at every servo tick
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SeparationModel:
    """ISO/TS 15066 protective separation, and the braking envelope built on it.

    ``S_p = S_h + S_r + S_s + C + Z_d + Z_r`` with ``S_h = v_h (T_r + T_s)``, ``S_r = v_r T_r``,
    ``S_s = v_r T_s / 2``, where ``v_r`` is the speed of the robot part, ``v_h`` the person's speed toward it
    (ISO/TS 15066 5.5.4.2.3: the measured speed where the system monitors it, as here) and ``T_s`` the
    robot's stopping time *from its current speed*: ``T_s = v_top / stop_decel_mps2`` with ``v_top`` the
    speed of the robot's fastest part (a robot creeping at 1 cm/s stops in milliseconds, not in the 0.2 s
    it needs at 1 m/s). With :class:`app.safety.ssm.SSMParams` (:meth:`from_ssm`):
    ``s0 = C + Z_d + Z_r``, ``T_r = t_reaction_s``.

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
        v_part = np.maximum(v_part, 0.0)
        t_s = np.maximum(v_top, 0.0) / self.stop_decel_mps2
        t_r = self.t_reaction_s
        return self.s0_m + np.maximum(v_human, 0.0) * (t_r + t_s) + v_part * (t_r + 0.5 * t_s)

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
    ) -> float:
        """Largest path-speed scale in [0, 1] that is safe for every part: part i moves at
        ``s * v_parts_mps[i]`` and a brake lowers the scale at ``rate`` (1/s), so every part stops after
        ``s / rate``. Arrays (L,) (the parts that move).

        Only scales in ``[lo, hi]`` are examined (the grid's and both ends; the servo passes the range it
        can reach within one tick): the answer is the largest of them up to which every one is safe, ``hi``
        at most, and 0 when ``lo`` is not safe. Compiled (:func:`app.safety._kernels.max_scale`); the same
        numbers as :meth:`max_scale_reference`."""
        return float(
            _kernel_max_scale(
                np.ascontiguousarray(separation_m, dtype=np.float64).reshape(-1),
                np.ascontiguousarray(v_human_mps, dtype=np.float64).reshape(-1),
                np.ascontiguousarray(v_parts_mps, dtype=np.float64).reshape(-1),
                float(rate),
                float(lo),
                float(hi),
                SCALE_GRID,
                BRAKE_INSTANTS,
                self._kernel_params,
            )
        )

    def max_scale_reference(
        self,
        separation_m: np.ndarray,
        *,
        v_human_mps: np.ndarray,
        v_parts_mps: np.ndarray,
        rate: float,
        lo: float = 0.0,
        hi: float = 1.0,
    ) -> float:
        """:meth:`max_scale` in NumPy over the whole envelope at once (the reference of the tests)."""
        d1 = np.asarray(separation_m, dtype=np.float64)
        vh1 = np.asarray(v_human_mps, dtype=np.float64)
        vp1 = np.asarray(v_parts_mps, dtype=np.float64)
        if d1.size == 0:
            return 1.0
        vtop = float(vp1.max())
        lo, hi = max(float(lo), 0.0), min(float(hi), 1.0)
        # quick accept (most ticks): every term at its largest over a brake from the highest scale asked for
        t_b = hi / max(rate, 1e-6)
        x_b, v_b = self.human_approach(vh1, t_b)
        worst = self.sp(hi * vp1, hi * vtop, v_b) + x_b + hi * vp1 * t_b
        if bool(np.all(d1 >= worst)):
            return hi
        inside = (SCALE_GRID - lo > 0.0) & (SCALE_GRID - hi < 0.0)
        scales = SCALE_GRID[inside]
        scales = np.concatenate([[lo], scales, [hi]]) if hi > lo else np.array([lo])
        d, vh0, vp = d1[:, None, None], vh1[:, None, None], vp1[:, None, None]
        sc = scales[None, :, None]
        t = BRAKE_INSTANTS[None, None, :] * sc / max(rate, 1e-6)
        x_h, v_h = self.human_approach(vh0, t)
        a = rate * vp
        v = sc * vp
        travel = v * t - 0.5 * a * t**2
        s_t = sc - rate * t  # the scale during the brake
        need = self.sp(s_t * vp, s_t * vtop, v_h)
        ok = np.all(d - x_h - travel - need >= 0.0, axis=2).all(axis=0)  # (NS,) every part
        n_ok = int(np.cumprod(ok).sum())
        return float(scales[n_ok - 1]) if n_ok > 0 else 0.0


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


#: The governor's law parameters when it applies no scaling law (the braking envelope alone).
NO_LAW = np.zeros(0)
#: The speed scales the governor chooses from.
SCALE_GRID = np.linspace(0.0, 1.0, 41)
_ENV_NV = 97
#: Instants of a brake, as fractions of its duration (its end: the robot is at rest).
BRAKE_INSTANTS = np.linspace(0.0, 1.0, 25)[:-1]
