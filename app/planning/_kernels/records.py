"""The search's bookkeeping, compiled: its state records (:class:`app.planning.search.search_state._Run`) as
the kernels see them, successor generation and timing (children, alternatives, the lookahead chain), the
per-batch set-up and storing of the move check, and the samples of standing still."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from app.planning._kernels.arrays import (
    CapsuleBounds,
    KernelJointLimits,
    PersonForecast,
    Requirement,
    RoadmapTables,
    SearchContext,
    SearchState,
)
from app.planning._kernels.base import _EPS_T, _jit
from app.planning._kernels.geometry import _align1
from app.planning._kernels.profiles import _profile3
from app.planning._kernels.separation import _margin_at, _required

__all__ = [
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
    "alternative_moves",
    "check_prepare",
    "check_store",
    "children_moves",
    "speculate_chain",
    "wait_finish",
    "wait_samples",
]

# The search's state records (:class:`app.planning.search.search_state._Run`) as the kernels see them: one row
# per field of three packed arrays (float, int, bool) and one column per state.
REC_T, REC_U, REC_U0, REC_DEP, REC_FC, REC_L, REC_H, REC_PEAK, REC_WAIT_OK = range(9)
REC_NODE, REC_BRANCH, REC_PARENT, REC_ROW, REC_SPEC_CHILD = range(5)
REC_END, REC_SAME, REC_ACCEPTED, REC_QSET = range(4)


class _Move(NamedTuple):
    """One move to time and record (built inside the kernels)."""

    parent: int  #: the parent state
    node: int  #: the roadmap node it goes to
    branch: int  #: at this IK branch
    L: float  #: path length
    same: bool  #: the roadmap's static check covers it
    t_dep: float  #: departure (s)
    u0: float  #: entry path speed
    fc: float  #: cruise path speed
    alt: int  #: the alternative it is (0: nearest branch at cruise speed)
    row: int  #: the option-table row it came from


# ------------------------------------------------------------------------------------------- generation


@_jit
def _record_move(
    n: int,
    mv: _Move,
    search: SearchContext,
    state: SearchState,
    keys: np.ndarray,
    tas: np.ndarray,
    n0: int,
) -> int:
    """Time one move and record it as state ``n`` if it can improve its node and passes the prune (the
    per-move body of :meth:`app.planning.search.search_state._Run.moves`); returns the next free state. Its
    key and arrival time go to ``keys``/``tas`` at ``n - n0``."""
    par, node, branch, L, same = mv.parent, mv.node, mv.branch, mv.L, mv.same
    t_dep, u0, fc, alt, row = mv.t_dep, mv.u0, mv.fc, mv.alt, mv.row
    ctx, h_tab, h_pred = search.ctx, search.h_tab, search.h_pred
    F, I, B, alts, AT = state.F, state.I, state.B, state.alts, state.AT  # noqa: E741
    if not math.isfinite(L):
        return n
    goal = int(ctx[0])
    A = ctx[1]
    end = node == goal
    u0 = min(u0, fc)
    h, u1, peak = _profile3(u0, L, fc, A, end)
    if L > 1e-12:
        h = max(h, ctx[2])
    ta = t_dep + h
    w = ctx[3]
    stop_time = ctx[4]
    if h_tab.shape[0] > 0:
        hv = h_tab[node, branch]
    elif stop_time == stop_time:
        hv = max(stop_time - ta, 0.0)
        w = 1.0
    else:
        hv = 0.0
    if not (ta < AT[node] - _EPS_T and ta + hv <= ctx[5]):
        return n
    t_nongoal = ctx[6]
    if t_nongoal < math.inf and node != goal:
        hp = h_pred[node, branch] if h_pred.shape[0] > 0 else 0.0
        if not ta + hp < t_nongoal:
            return n
    F[REC_T, n] = ta
    F[REC_U, n] = u1
    F[REC_U0, n] = u0
    F[REC_DEP, n] = t_dep
    F[REC_FC, n] = fc
    F[REC_L, n] = L
    F[REC_H, n] = h
    F[REC_PEAK, n] = peak
    I[REC_NODE, n] = node
    I[REC_BRANCH, n] = branch
    I[REC_PARENT, n] = par
    I[REC_ROW, n] = row
    B[REC_END, n] = end
    B[REC_SAME, n] = same
    alts[n] = alt
    keys[n - n0] = ta + w * hv
    tas[n - n0] = ta
    return n + 1


@_jit
def children_moves(
    sids: np.ndarray,
    roadmap: RoadmapTables,
    f: float,
    n_branches: int,
    search: SearchContext,
    state: SearchState,
    n0: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """:meth:`app.planning.search.search_state._Run.children` (then ``moves``): the moves from the states
    ``sids`` to all roadmap neighbours (nearest branch, cruise speed ``f``; a speculative chain's move is not
    made twice), recorded from state ``n0`` on in the same order. Returns (next free state, keys, arrival
    times) of the recorded states. ``search.ctx``: ``goal`` (-2: none), path acceleration, shortest move,
    heuristic weight, stop time (NaN: none), latest arrival, latest arrival at other nodes than the goal,
    cruise speed."""
    roadmap = RoadmapTables(*roadmap)
    search = SearchContext(*search)
    state = SearchState(*state)
    indptr, indices = roadmap.indptr, roadmap.indices
    ord_flat, L_flat, same_flat = roadmap.ord_flat, roadmap.L_flat, roadmap.same_flat
    F, I = state.F, state.I  # noqa: E741
    total = 0
    for s in sids:
        u = I[REC_NODE, s]
        total += indptr[u + 1] - indptr[u]
    keys = np.empty(total)
    tas = np.empty(total)
    n = n0
    for s in sids:
        u = I[REC_NODE, s]
        bu = I[REC_BRANCH, s]
        spec = I[REC_SPEC_CHILD, s]
        skip = I[REC_NODE, spec] if spec >= 0 else -1
        t = F[REC_T, s]
        us = F[REC_U, s]
        for e in range(indptr[u], indptr[u + 1]):
            v = indices[e]
            if v == skip:
                continue
            row = e * n_branches + bu
            mv = _Move(s, v, ord_flat[row, 0], L_flat[row, 0], same_flat[row, 0], t, us, f, 0, row)
            n = _record_move(n, mv, search, state, keys, tas, n0)
    return n, keys[: n - n0], tas[: n - n0]


@_jit
def alternative_moves(
    failed: np.ndarray,
    kinds: np.ndarray,
    no_row: int,
    wait_step: float,
    t_static: float,
    start_b: np.ndarray,
    start_L: np.ndarray,
    roadmap: RoadmapTables,
    search: SearchContext,
    state: SearchState,
    n0: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """:meth:`app.planning.search.search_state._Run.alternatives` (then ``moves``): for each failed
    nearest-branch move the alternatives ``kinds`` (A, 4) = (kind, option, cruise speed, wait steps),
    alternative-major as there, recorded from state ``n0`` on; the options of the start's rows (-1 - j) are
    ``start_b``/``start_L`` (branch, length). Returns as :func:`children_moves`."""
    roadmap = RoadmapTables(*roadmap)
    search = SearchContext(*search)
    state = SearchState(*state)
    ord_flat, L_flat, same_flat = roadmap.ord_flat, roadmap.L_flat, roadmap.same_flat
    F, I, alts = state.F, state.I, state.alts  # noqa: E741
    fl = np.empty(failed.shape[0], dtype=np.int64)
    m = 0
    for s in failed:
        if alts[s] == 0 and I[REC_ROW, s] != no_row:
            fl[m] = s
            m += 1
    keys = np.empty(m * kinds.shape[0])
    tas = np.empty(m * kinds.shape[0])
    n = n0
    for a in range(kinds.shape[0]):
        kind = int(kinds[a, 0])
        opt = int(kinds[a, 1])
        fc = kinds[a, 2]
        wait = kinds[a, 3]
        for j in range(m):
            s = fl[j]
            par = I[REC_PARENT, s]
            t = F[REC_T, par]
            if not (wait <= 1 or t + (wait - 1) * wait_step < t_static):
                continue
            row = I[REC_ROW, s]
            if row >= 0:
                b = ord_flat[row, opt]
                L = L_flat[row, opt]
                same = same_flat[row, opt]
            else:
                b = start_b[-1 - row, opt]
                L = start_L[-1 - row, opt]
                same = False
            u0 = 0.0 if wait != 0 else min(F[REC_U, par], fc)
            t_dep = t + max(wait, 0.0) * wait_step
            mv = _Move(par, I[REC_NODE, s], b, L, same, t_dep, u0, fc, kind, row)
            n = _record_move(n, mv, search, state, keys, tas, n0)
    return n, keys[: n - n0], tas[: n - n0]


@_jit
def speculate_chain(
    sid: int,
    max_len: int,
    nxt: np.ndarray,
    roadmap: RoadmapTables,
    limits: KernelJointLimits,
    search: SearchContext,
    state: SearchState,
    n0: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """:meth:`app.planning.search.search_state._Run.speculate`: the lookahead chain of up to ``max_len`` moves
    from the unchecked state ``sid`` along ``nxt`` (per node branch, the option row of the static shortest
    path's next move, or -1), recorded from state ``n0`` on (the capacity is the caller's). ``search`` as in
    :func:`children_moves`. Returns (next free state, keys, arrival times)."""
    roadmap = RoadmapTables(*roadmap)
    limits = KernelJointLimits(*limits)
    search = SearchContext(*search)
    state = SearchState(*state)
    indices, ord_flat, L_flat = roadmap.indices, roadmap.ord_flat, roadmap.L_flat
    same_flat, delta0, ik = roadmap.same_flat, roadmap.delta0, roadmap.ik
    q_lo, q_hi = limits.lo, limits.hi
    ctx, h_tab, h_pred = search.ctx, search.h_tab, search.h_pred
    F, I, B, alts, q, AT = state.F, state.I, state.B, state.alts, state.q, state.AT  # noqa: E741
    goal = int(ctx[0])
    A = ctx[1]
    min_edge = ctx[2]
    w_h = ctx[3]
    t_last = ctx[5]
    t_nongoal = ctx[6]
    f = ctx[7]
    nb = ik.shape[1]
    node = I[REC_NODE, sid]
    b = I[REC_BRANCH, sid]
    par = I[REC_PARENT, sid]
    q_prev = np.empty(6)
    if B[REC_QSET, sid]:
        for j in range(6):
            q_prev[j] = q[sid, j]
    else:
        for j in range(6):
            q_prev[j] = _align1(ik[node, b, j], q[par, j], q_lo[j], q_hi[j])
    for j in range(6):
        q[sid, j] = q_prev[j]
    B[REC_QSET, sid] = True
    t = F[REC_T, sid]
    u = F[REC_U, sid]
    keys = np.empty(max_len)
    tas = np.empty(max_len)
    n = n0
    prev = sid
    while n - n0 < max_len and node != goal:
        row = nxt[node * nb + b]
        if row < 0:
            break
        v = indices[row // nb]
        bv = ord_flat[row, 0]
        L = L_flat[row, 0]
        end = v == goal
        u0 = min(u, f)
        h, u1, peak = _profile3(u0, L, f, A, end)
        if L > 1e-12:
            h = max(h, min_edge)
        ta = t + h
        hv = h_tab[v, bv]
        if ta >= AT[v] - _EPS_T or ta + hv > t_last:
            break
        if v != goal and ta + (h_pred[v, bv] if h_pred.shape[0] > 0 else 0.0) >= t_nongoal:
            break
        inside = True
        for j in range(6):
            x = q_prev[j] + delta0[row, j]
            inside = inside and (x >= q_lo[j]) and (x <= q_hi[j])
        if inside:
            for j in range(6):
                q_prev[j] = q_prev[j] + delta0[row, j]
        else:
            for j in range(6):
                q_prev[j] = _align1(ik[v, bv, j], q_prev[j], q_lo[j], q_hi[j])
        for j in range(6):
            q[n, j] = q_prev[j]
        F[REC_DEP, n] = t
        F[REC_H, n] = h
        F[REC_T, n] = t + h
        F[REC_U, n] = u1
        F[REC_U0, n] = u0
        F[REC_FC, n] = f
        F[REC_L, n] = L
        F[REC_PEAK, n] = peak
        I[REC_ROW, n] = row
        I[REC_NODE, n] = v
        I[REC_BRANCH, n] = bv
        I[REC_PARENT, n] = prev
        I[REC_SPEC_CHILD, prev] = n
        B[REC_SAME, n] = same_flat[row, 0]
        B[REC_END, n] = end
        B[REC_QSET, n] = True
        alts[n] = 0
        keys[n - n0] = ta + w_h * hv
        tas[n - n0] = ta
        prev = n
        n += 1
        node, b, t, u = v, bv, ta, u1
    return n, keys[: n - n0], tas[: n - n0]


# ------------------------------------------------------------------------------------------ the move check


@_jit
def check_prepare(
    batch: np.ndarray,
    state: SearchState,
    ik: np.ndarray,
    limits: KernelJointLimits,
    tables: CapsuleBounds,
    start: CapsuleBounds,
    goal: int,
    hold_default: bool,
) -> tuple[np.ndarray, ...]:
    """The per-batch set-up of :meth:`app.planning.search.search_state._Run.check` for the states ``batch``
    (M,) (``ik``: :attr:`RoadmapTables.ik`).

    Returns ``target`` (M, 6): the state's branch aligned next to its parent's configuration (or its
    precomputed configuration), ``same`` (M,): the roadmap's static edge check covers the move (the record's
    flag, cleared where the move differs from the roadmap's), the parent's configuration ``q_par`` (M, 6)
    and capsule points/spheres ``pts_a`` (M, P, 3), ``cen_a`` (M, L, 3), ``rad_a`` (M, L) (of the node
    ``tables``; the ``start``'s where the parent is not a roadmap node), the per-move floats (5, M):
    departure, duration, entry speed, length, cruise speed, and whether each move must hold at its end (M,)
    (at the goal; without one ``hold_default``), ends at rest (M,), waits before it (departs after its
    parent's arrival) (M,), the target's row ``node * 8 + branch`` (M,), the parent state (M,) and whether
    the move is the one between the stored branch configurations (M,) (the static-check memo's
    condition)."""
    state = SearchState(*state)
    limits = KernelJointLimits(*limits)
    tables = CapsuleBounds(*tables)
    start = CapsuleBounds(*start)
    F, I, B, q = state.F, state.I, state.B, state.q  # noqa: E741
    q_lo, q_hi = limits.lo, limits.hi
    pts_tab, cen_tab, rad_tab = tables.pts, tables.cen, tables.rad
    start_pts, start_cen, start_rad = start.pts, start.cen, start.rad
    M = batch.shape[0]
    NP = pts_tab.shape[1]
    NL = cen_tab.shape[1]
    nb = ik.shape[1]
    target = np.empty((M, 6))
    same = np.empty(M, dtype=np.bool_)
    q_par = np.empty((M, 6))
    pts_a = np.empty((M, NP, 3))
    cen_a = np.empty((M, NL, 3))
    rad_a = np.empty((M, NL))
    fl = np.empty((5, M))
    hold = np.empty(M, dtype=np.bool_)
    end = np.empty(M, dtype=np.bool_)
    waits = np.empty(M, dtype=np.bool_)
    rows = np.empty(M, dtype=np.int64)
    pars = np.empty(M, dtype=np.int64)
    stored = np.empty(M, dtype=np.bool_)
    for k in range(M):
        s = batch[k]
        par = I[REC_PARENT, s]
        pars[k] = par
        cv = I[REC_NODE, s]
        b = I[REC_BRANCH, s]
        pn = I[REC_NODE, par]
        pb = I[REC_BRANCH, par]
        for j in range(6):
            q_par[k, j] = q[par, j]
        if B[REC_QSET, s]:
            for j in range(6):
                target[k, j] = q[s, j]
        else:
            for j in range(6):
                target[k, j] = _align1(ik[cv, b, j], q_par[k, j], q_lo[j], q_hi[j])
        mv = pn >= 0  # the move is the one between the stored branch configurations
        if mv:
            for j in range(6):
                ref = ik[pn, pb, j]
                ref_t = _align1(ik[cv, b, j], ref, q_lo[j], q_hi[j])
                if not abs((ref_t - ref) - (target[k, j] - q_par[k, j])) <= 1e-9:
                    mv = False
        stored[k] = mv
        same[k] = B[REC_SAME, s] and mv
        if pn >= 0:
            r = pn * nb + pb
            for p in range(NP):
                for j in range(3):
                    pts_a[k, p, j] = pts_tab[r, p, j]
            for l in range(NL):  # noqa: E741
                for j in range(3):
                    cen_a[k, l, j] = cen_tab[r, l, j]
                rad_a[k, l] = rad_tab[r, l]
        else:
            for p in range(NP):
                for j in range(3):
                    pts_a[k, p, j] = start_pts[p, j]
            for l in range(NL):  # noqa: E741
                for j in range(3):
                    cen_a[k, l, j] = start_cen[l, j]
                rad_a[k, l] = start_rad[l]
        fl[0, k] = F[REC_DEP, s]
        fl[1, k] = F[REC_H, s]
        fl[2, k] = F[REC_U0, s]
        fl[3, k] = F[REC_L, s]
        fl[4, k] = F[REC_FC, s]
        hold[k] = cv == goal if goal != -2 else hold_default
        end[k] = B[REC_END, s]
        waits[k] = F[REC_DEP, s] > F[REC_T, par] + _EPS_T
        rows[k] = cv * nb + b
    return target, same, q_par, pts_a, cen_a, rad_a, fl, hold, end, waits, rows, pars, stored


@_jit
def check_store(
    batch: np.ndarray, ok: np.ndarray, target: np.ndarray, q: np.ndarray, status: np.ndarray
) -> None:
    """The end of :meth:`app.planning.search.search_state._Run.check`: the configurations of the moves that
    passed and every move's status (1 passed, 2 failed)."""
    for k in range(batch.shape[0]):
        s = batch[k]
        if ok[k]:
            for j in range(6):
                q[s, j] = target[k, j]
            status[s] = 1
        else:
            status[s] = 2


# ---------------------------------------------------------------------------------------------- waiting


@_jit
def wait_samples(
    todo: np.ndarray,
    state: SearchState,
    tables: CapsuleBounds,
    start: CapsuleBounds,
    n_w: int,
    step: float,
    requirement: Requirement,
    forecast: PersonForecast,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The samples of standing still at each state of ``todo`` for :func:`sample_separation_ok` (as
    :meth:`app.planning.search.search_state._Run._check_waits` builds them): every ``step`` s after its
    arrival, ``n_w`` of them, at rest. Returns ``(q (S, 6), t (n_off, S), req (n_off, S), cen (S, L, 3), rad
    (S, L), ts (n, n_w))`` with ``S = n * n_w``; ``req`` is :func:`_required` at speed 0 and the margin at
    each time (the spheres: of the node ``tables``, the ``start``'s where the state is not at a roadmap
    node)."""
    state = SearchState(*state)
    tables = CapsuleBounds(*tables)
    start = CapsuleBounds(*start)
    requirement = Requirement(*requirement)
    forecast = PersonForecast(*forecast)
    F, I, q = state.F, state.I, state.q  # noqa: E741
    cen_tab, rad_tab, start_cen, start_rad = tables.cen, tables.rad, start.cen, start.rad
    offsets, prm = requirement.offsets, requirement.params
    times, margins = forecast.times, forecast.margins
    n = todo.shape[0]
    NL = cen_tab.shape[1]
    n_off = offsets.shape[0]
    nb = 8  # branches per node (app.planning.roadmap.NUM_BRANCHES)
    S = n * n_w
    qs = np.empty((S, 6))
    t_all = np.empty((n_off, S))
    req = np.empty((n_off, S))
    cen = np.empty((S, NL, 3))
    rad = np.empty((S, NL))
    ts = np.empty((n, n_w))
    growth = prm[0]
    cap = prm[1]
    for k in range(n):
        s = todo[k]
        node = I[REC_NODE, s]
        r = node * nb + I[REC_BRANCH, s]
        t0 = F[REC_T, s]
        for i in range(n_w):
            x = k * n_w + i
            ts[k, i] = t0 + step * (i + 1)
            for j in range(6):
                qs[x, j] = q[s, j]
            for l in range(NL):  # noqa: E741
                if node >= 0:
                    for j in range(3):
                        cen[x, l, j] = cen_tab[r, l, j]
                    rad[x, l] = rad_tab[r, l]
                else:
                    for j in range(3):
                        cen[x, l, j] = start_cen[l, j]
                    rad[x, l] = start_rad[l]
            for o in range(n_off):
                to = ts[k, i] + offsets[o]
                t_all[o, x] = to
                req[o, x] = _required(0.0, 0.0, _margin_at(to, times, margins, growth, cap), prm)
    return qs, t_all, req, cen, rad, ts


@_jit
def wait_finish(todo: np.ndarray, ok: np.ndarray, ts: np.ndarray, wait_ok: np.ndarray) -> None:
    """``wait_ok`` of each state of ``todo``: the time of its first unsafe sample (+inf: none)."""
    n_w = ts.shape[1]
    for k in range(todo.shape[0]):
        w = math.inf
        for i in range(n_w):
            if not ok[k * n_w + i]:
                w = ts[k, i]
                break
        wait_ok[todo[k]] = w
