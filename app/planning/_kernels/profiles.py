"""The path-speed profile of one move, compiled: its duration, exit and peak speed, and its samples
(the formulas of :mod:`app.planning.search.profiles`, in the same order)."""

from __future__ import annotations

import math

from app.planning._kernels.base import _jit


@_jit
def _profile3(u0: float, L: float, f: float, A: float, end_rest: bool) -> tuple[float, float, float]:
    """Duration, exit and peak path speed of one move (:func:`app.planning.search.profiles._profile_arrays`,
    the same formulas in the same order)."""
    u0sq = u0 * u0
    two_al = 2.0 * A * L
    if not end_rest:
        u1 = min(math.sqrt(u0sq + two_al), f)
        return (u1 - u0) / A + max(L - (u1 * u1 - u0sq) / (2.0 * A), 0.0) / f, u1, u1
    up = min(f, math.sqrt((two_al + u0sq) / 2.0))
    if u0sq <= two_al:
        cruise = max(L - (up * up - u0sq) / (2.0 * A) - up * up / (2.0 * A), 0.0)
        return (up - u0) / A + cruise / max(up, 1e-12) + up / A, 0.0, up
    return 2.0 * L / max(u0, 1e-12), 0.0, u0


@_jit
def _profile_sample(
    s: float, s_prev: float, u0: float, L: float, dur: float, f: float, A: float, end_rest: bool
) -> tuple[float, float]:
    """One sample of :func:`app.planning.search.profiles._profile_samples`: path fraction at profile time
    ``s`` and the largest path speed over ``[s_prev, s]``."""
    t1 = (f - u0) / A
    if s <= t1:
        pos = (u0 + 0.5 * A * s) * s
    else:
        pos = (u0 + 0.5 * A * t1) * t1 + f * (s - t1)
    speed = min(u0 + A * s, f)
    if end_rest:
        up = min(f, math.sqrt((2.0 * A * L + u0 * u0) / 2.0))
        if u0 * u0 <= 2.0 * A * L:
            ta = (up - u0) / A
            rem = dur - s
            if s <= ta:
                pos = (u0 + 0.5 * A * s) * s
            elif rem <= up / A:
                pos = L - 0.5 * A * rem * rem
            else:
                pos = (u0 + 0.5 * A * ta) * ta + up * (s - ta)
            speed = min(min(u0 + A * min(s, ta), up), A * (dur - s_prev))
        else:
            a_forced = u0 / max(dur, 1e-12)
            pos = u0 * s - 0.5 * a_forced * s * s
            speed = max(u0 - a_forced * s_prev, 0.0)
    frac = pos / max(L, 1e-12) if L > 1e-12 else 1.0
    return min(max(frac, 0.0), 1.0), speed
