"""Compiled per-frame work of :class:`app.prediction.arbitration.ForecastArbiter` (numba).

:func:`step_quantiles` finds each horizon step's margin quantile by keeping the values above it in a heap
instead of sorting every step's recent errors every frame, with the numbers of ``np.quantile``'s linear
interpolation.
:func:`score_due` measures the stored forecasts that are due against a new frame in one pass. The NumPy code
in :mod:`app.prediction.arbitration` is the reference that the tests compare these with.
"""

from __future__ import annotations

import math

import numpy as np

from app.jit import jit

__all__ = ["score_due", "step_quantiles"]

_EXACT = {"error_model": "numpy"}  # no fastmath: the NumPy reference's numbers


@jit(**_EXACT)
def _largest(err: np.ndarray, rows: int, size: int, sign: float, heap: np.ndarray) -> None:
    """``heap[:size]``: a min-heap of the ``size`` largest values of ``sign * err[:rows]`` (rows, J)."""
    J = err.shape[1]
    n = 0
    for row in range(rows):
        for j in range(J):
            x = sign * err[row, j]
            if n < size:
                i = n
                heap[i] = x
                n += 1
                while i > 0:
                    p = (i - 1) // 2
                    if heap[p] <= heap[i]:
                        break
                    heap[p], heap[i] = heap[i], heap[p]
                    i = p
            elif x > heap[0]:
                heap[0] = x
                i = 0
                while True:
                    c = 2 * i + 1
                    if c >= n:
                        break
                    if c + 1 < n and heap[c + 1] < heap[c]:
                        c += 1
                    if heap[i] <= heap[c]:
                        break
                    heap[i], heap[c] = heap[c], heap[i]
                    i = c


@jit(**_EXACT)
def step_quantiles(err: np.ndarray, count: np.ndarray, level: np.ndarray, hint: np.ndarray) -> np.ndarray:
    """Per step ``k`` the ``level[k]`` quantile (linear interpolation, like ``np.quantile``) of the first
    ``count[k]`` rows of ``err[k]`` (n, W, J) flattened; ``inf`` where ``count[k]`` is 0.

    Only the two order statistics around the quantile are needed: the smaller side of the values beyond them
    is kept in a heap (the values above them for a level near 1, as a margin's is), whose root and smaller
    child are those two. ``hint`` (n,): a guess of the quantiles (last frame's; ``inf``: none): only the
    values above 0.8 times it go through the heap when there are enough of them (the same numbers)."""
    n, W, J = err.shape
    out = np.full(n, np.inf)
    heap = np.empty(W * J)
    tail = np.empty((W * J, 1))
    for k in range(n):
        m = count[k] * J
        if m == 0:
            continue
        pos = min(max(level[k], 0.0), 1.0) * (m - 1)
        lo = math.floor(pos)
        w = pos - lo
        if m - lo <= lo + 2:  # the m - lo largest: heap[0] is sorted[lo], the smaller child sorted[lo + 1]
            size = m - lo
            c = 0
            if hint[k] < np.inf:  # only the values from a little below last frame's quantile can be in it
                pivot = 0.8 * hint[k]
                for row in range(count[k]):
                    for j in range(J):
                        if err[k, row, j] >= pivot:
                            tail[c, 0] = err[k, row, j]
                            c += 1
            if c >= size:
                _largest(tail, c, size, 1.0, heap)
            else:
                _largest(err[k], count[k], size, 1.0, heap)
            v = heap[0]
            nxt = v if size < 2 else (heap[1] if size == 2 else min(heap[1], heap[2]))
        else:  # the lo + 2 smallest (negated): heap[0] is -sorted[lo + 1], the smaller child -sorted[lo]
            size = lo + 2
            _largest(err[k], count[k], size, -1.0, heap)
            nxt = -heap[0]
            v = -(heap[1] if size == 2 else min(heap[1], heap[2]))
        out[k] = v * (1.0 - w) + nxt * w if w > 0.0 else v
    return out


@jit(**_EXACT)
def score_due(
    slots: np.ndarray,
    ks: np.ndarray,
    futures: np.ndarray,
    combined: np.ndarray,
    margins_at: np.ndarray,
    joints: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each due forecast ``slots[v]`` scored at its step ``ks[v]`` against ``joints`` (J, 3): every
    candidate's mean joint error (V, C), the combined forecast's joint errors (V, J) and the fraction of
    joints outside the margin it was handed on with (V,)."""
    V = slots.shape[0]
    C, J = futures.shape[1], joints.shape[0]
    cand = np.empty((V, C))
    per_joint = np.empty((V, J))
    miss = np.empty(V)
    for v in range(V):
        s, k = slots[v], ks[v]
        for c in range(C):
            acc = 0.0
            for j in range(J):
                d0 = futures[s, c, k, j, 0] - joints[j, 0]
                d1 = futures[s, c, k, j, 1] - joints[j, 1]
                d2 = futures[s, c, k, j, 2] - joints[j, 2]
                acc += math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            cand[v, c] = acc / J
        outside = 0
        for j in range(J):
            d0 = combined[s, k, j, 0] - joints[j, 0]
            d1 = combined[s, k, j, 1] - joints[j, 1]
            d2 = combined[s, k, j, 2] - joints[j, 2]
            e = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            per_joint[v, j] = e
            if e > margins_at[s, k]:
                outside += 1
        miss[v] = outside / J
    return cand, per_joint, miss
