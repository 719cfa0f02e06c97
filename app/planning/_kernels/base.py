"""What every planning kernel shares: the one way they are compiled, the array types they are compiled for,
and the scalar helpers (clamping, the segment-segment distance, bisection, interpolation).

Numerics: every kernel is ``fastmath=False`` float64. The closest points of two segments follow the same
three clamped steps as :func:`app.planning.collision._closest_sq` (Ericson, Real-Time Collision Detection,
5.1.9), but the distance is then taken from the closest points themselves (``|r + s d1 - t d2|``) instead
of the expansion in dot products: it agrees with the NumPy reference to round-off (below 1e-12 m) wherever
the axes are more than a micrometre apart, and is exact to round-off where they touch (the expansion's
square root of a cancelled difference is off by up to a few 1e-8 m there).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from app.jit import jit

__all__ = ["as_bool", "as_f64", "as_i64"]

_TINY = 1e-18  # m^4: as app.planning.collision._TINY (parallel segments, points)
_NL = 9  # robot capsules (app.planning.collision.ROBOT_LINKS)
_EPS_T = 1e-9  # s: arrival times closer than this are the same (app.planning.search.config._EPS_T)


def _jit(fn: Callable[..., Any]) -> Any:
    """:func:`app.jit.jit` with the options of every planning kernel."""
    return jit(fn, fastmath=False, nogil=True)


def as_f64(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous, writeable float64 array (a copy only where needed): the one array type the
    kernels are compiled for (numba compiles read-only and strided arrays separately)."""
    if isinstance(x, np.ndarray) and x.dtype == np.float64 and x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, dtype=np.float64, order="C")


def as_bool(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous, writeable bool array (see :func:`as_f64`)."""
    if isinstance(x, np.ndarray) and x.dtype == np.bool_ and x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, dtype=np.bool_, order="C")


def as_i64(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous, writeable int64 array (see :func:`as_f64`)."""
    if isinstance(x, np.ndarray) and x.dtype == np.int64 and x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, dtype=np.int64, order="C")


@_jit
def _clip01(x: float) -> float:
    if x < 0.0:
        return 0.0
    if x > 1.0:
        return 1.0
    return x  # NaN stays NaN (as np.maximum / np.minimum)


@_jit
def _seg_dist(
    p1x: float,
    p1y: float,
    p1z: float,
    d1x: float,
    d1y: float,
    d1z: float,
    p2x: float,
    p2y: float,
    p2z: float,
    d2x: float,
    d2y: float,
    d2z: float,
) -> float:
    """Distance between segments p1 + s d1 and p2 + t d2 (s, t in [0, 1]), m."""
    rx = p1x - p2x
    ry = p1y - p2y
    rz = p1z - p2z
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    b = d1x * d2x + d1y * d2y + d1z * d2z
    c = d1x * rx + d1y * ry + d1z * rz
    f = d2x * rx + d2y * ry + d2z * rz
    inv_a = 1.0 / a if a > _TINY else 0.0
    inv_e = 1.0 / e if e > _TINY else 0.0
    den = a * e - b * b
    if den < _TINY:
        den = _TINY
    s = _clip01((b * f - c * e) / den)
    t = _clip01((b * s + f) * inv_e)
    s = _clip01((b * t - c) * inv_a)
    dx = rx + s * d1x - t * d2x
    dy = ry + s * d1y - t * d2y
    dz = rz + s * d1z - t * d2z
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@_jit
def _nan_min(best: float, d: float) -> float:
    """min(best, d) that keeps a NaN once one appears (as ndarray.min)."""
    if d < best or d != d:
        return d
    return best


@_jit
def _pose_index(times: np.ndarray, t: float) -> int:
    """``searchsorted(times, t, side="right")`` by bisection."""
    lo = 0
    hi = times.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if t < times[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


@_jit
def _searchsorted_left(times: np.ndarray, t: float) -> int:
    """``searchsorted(times, t, side="left")`` by bisection."""
    lo = 0
    hi = times.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if times[mid] < t:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_jit
def _interp(x: float, xp: np.ndarray, fp: np.ndarray) -> float:
    """``np.interp(x, xp, fp)`` for one ``x`` and increasing ``xp`` (NumPy's algorithm, without its
    per-call arrays)."""
    n = xp.shape[0]
    if n == 1:
        return fp[0]
    if x != x:
        return x
    if x < xp[0]:
        return fp[0]
    if x > xp[n - 1]:
        return fp[n - 1]
    j = _pose_index(xp, x) - 1
    if j >= n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    r = slope * (x - xp[j]) + fp[j]
    if r != r:
        r = slope * (x - xp[j + 1]) + fp[j + 1]
        if r != r and fp[j] == fp[j + 1]:
            r = fp[j]
    return r
