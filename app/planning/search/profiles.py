"""The 1-D path-speed profile of the search's moves (duration, exit and peak speed, the path fraction at a
sample), the wait grid, and the small array helpers the search shares."""

from __future__ import annotations

import math

import numpy as np

from app.planning import _kernels
from app.planning.search.config import (
    PlannerConfig,
)
from app.planning.trajectory import Plan, Trajectory


def _profile_samples(
    s: np.ndarray,
    s_prev: np.ndarray,
    u0: np.ndarray,
    L: np.ndarray,
    dur: np.ndarray,
    f: np.ndarray,
    A: float,
    end_rest: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Path fraction (0..1) covered at profile time ``s`` and the largest path speed over ``[s_prev, s]``
    (fraction of full speed) of moves timed by :func:`_profile_arrays` (one entry per sample, ``u0 <= f``).

    The profile accelerates at ``A`` from ``u0`` to the cruise speed ``f``; a move that ends at rest brakes
    at ``A`` to stop at ``dur`` (or, when it cannot, uniformly from ``u0``). Its path speed is unimodal, so
    the largest speed over an interval is the speed at the interval's point nearest the peak.
    """
    t1 = (f - u0) / A  # end of the acceleration toward the cruise speed
    pos = np.where(s <= t1, (u0 + 0.5 * A * s) * s, (u0 + 0.5 * A * t1) * t1 + f * (s - t1))
    speed = np.minimum(u0 + A * s, f)  # increasing: the largest at the interval's end
    if end_rest.any():
        up = np.minimum(f, np.sqrt((2.0 * A * L + u0 * u0) / 2.0))
        can = u0 * u0 <= 2.0 * A * L
        ta = (up - u0) / A
        rem = dur - s
        p_rest = np.where(
            s <= ta,
            (u0 + 0.5 * A * s) * s,
            np.where(rem <= up / A, L - 0.5 * A * rem * rem, (u0 + 0.5 * A * ta) * ta + up * (s - ta)),
        )
        a_forced = u0 / np.maximum(dur, 1e-12)
        p_forced = u0 * s - 0.5 * a_forced * s * s
        # speed: up (plateau or apex) from ta on, braking over the last up / A seconds
        sp = np.minimum(np.minimum(u0 + A * np.minimum(s, ta), up), A * (dur - s_prev))
        sp_forced = np.maximum(u0 - a_forced * s_prev, 0.0)  # decreasing: largest at the start
        pos = np.where(end_rest, np.where(can, p_rest, p_forced), pos)
        speed = np.where(end_rest, np.where(can, sp, sp_forced), speed)
    frac = np.where(L > 1e-12, pos / np.maximum(L, 1e-12), 1.0)
    return np.minimum(np.maximum(frac, 0.0), 1.0), speed


_NO_IDS = np.zeros(0, dtype=np.int64)
_NO_ROW = -(2**62)  # option-table row of the start state (it has no alternatives)


def _per_move(x: np.ndarray | float | bool, m: int, dtype: type = np.float64) -> np.ndarray:
    """A per-move argument of the compiled checks: (m,) contiguous and writeable, broadcast if scalar."""
    if isinstance(x, np.ndarray) and x.shape == (m,) and x.dtype == dtype and x.flags.c_contiguous:
        return _kernels.as_bool(x) if dtype is np.bool_ else _kernels.as_f64(x)
    return np.array(np.broadcast_to(np.asarray(x, dtype=dtype), (m,)), order="C")


def _wait_grid(cfg: PlannerConfig) -> tuple[int, int]:
    """The waits of a search: how many ``wait_step_s`` steps fit in ``max_wait_s`` (``K``), and into how
    many samples each step is cut so that none is longer than ``sample_dt_s`` (``sub``)."""
    K = math.floor(cfg.max_wait_s / cfg.wait_step_s + 1e-9)
    sub = max(1, math.ceil(cfg.wait_step_s / cfg.sample_dt_s - 1e-9))
    return K, sub


def _profile_arrays(
    u0: np.ndarray, L: np.ndarray, f: np.ndarray, A: float, end_rest: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D path-speed profile of moves: duration, exit speed and peak speed (arrays of one shape).

    Path position is the max-norm joint distance in "seconds at full joint speed" (``L``); speeds are
    fractions of full speed (``u0 <= f``, the cruise speed ``f`` per move), ``A`` is the path acceleration
    (1/s). A move starts at ``u0``, accelerates at ``A`` toward ``f`` and, where ``end_rest``, brakes at ``A``
    to stop at its end (a move that cannot stop in time brakes uniformly; the spline fit retimes it and the
    verification has the last word).
    """
    u0sq = u0 * u0
    two_al = 2.0 * A * L
    u1 = np.minimum(np.sqrt(u0sq + two_al), f)
    dur = (u1 - u0) / A + np.maximum(L - (u1 * u1 - u0sq) / (2.0 * A), 0.0) / f
    if not end_rest.any():
        return dur, u1, u1
    up = np.minimum(f, np.sqrt((two_al + u0sq) / 2.0))
    can = u0sq <= two_al
    cruise = np.maximum(L - (up * up - u0sq) / (2.0 * A) - up * up / (2.0 * A), 0.0)
    t_rest = (up - u0) / A + cruise / np.maximum(up, 1e-12) + up / A
    dur_rest = np.where(can, t_rest, 2.0 * L / np.maximum(u0, 1e-12))
    return (
        np.where(end_rest, dur_rest, dur),
        np.where(end_rest, 0.0, u1),
        np.where(end_rest, np.where(can, up, u0), u1),
    )


def _profile_py(u0: float, L: float, f: float, A: float, end_rest: bool) -> tuple[float, float, float]:
    """:func:`_profile_arrays` for one move, in plain Python (the same formulas)."""
    u0 = min(u0, f)
    u0sq = u0 * u0
    if not end_rest:
        u1 = min(math.sqrt(u0sq + 2.0 * A * L), f)
        return (u1 - u0) / A + max(L - (u1 * u1 - u0sq) / (2.0 * A), 0.0) / f, u1, u1
    up = min(f, math.sqrt((2.0 * A * L + u0sq) / 2.0))
    if u0sq <= 2.0 * A * L:
        cruise = max(L - (up * up - u0sq) / (2.0 * A) - up * up / (2.0 * A), 0.0)
        return (up - u0) / A + cruise / max(up, 1e-12) + up / A, 0.0, up
    return 2.0 * L / max(u0, 1e-12), 0.0, u0


def _map_nodes(waypoints: Plan, traj: Trajectory) -> np.ndarray:
    """Roadmap node of each trajectory knot (matched in order by configuration; -1 for added knots)."""
    kq = traj.knot_q
    out = np.full(kq.shape[0], -1, dtype=np.int64)
    # match[i, jj]: knot i is waypoint jj (within 1e-9 rad, as np.allclose with atol=1e-9)
    match = (np.abs(kq[:, None, :] - waypoints.q[None, :, :]) <= 1e-9 + 1e-5 * np.abs(waypoints.q[None])).all(
        2
    )
    j = 0
    for i, row in enumerate(match.tolist()):
        for jj in range(j, len(row)):
            if row[jj]:
                out[i] = waypoints.nodes[jj]
                j = jj
                break
    return out
