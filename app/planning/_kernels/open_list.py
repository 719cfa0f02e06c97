"""The search's open list, compiled: a binary heap over an append-only table of entries, and the loops of
the search that pop a batch to check (:func:`pop_batch`) and accept what passed (:func:`accept_checked`).

Entries (key, -t, state id) live in an append-only table (``E_key``, ``E_negt``, ``E_id``); the heap holds
entry indices ordered as Python compares the tuples (the order is total: a state has one entry), so it pops
in exactly the order of ``heapq`` over the tuples. ``hs`` = [heap size, entries].
"""

from __future__ import annotations

import numpy as np

from app.planning._kernels.arrays import OpenArrays, SearchState
from app.planning._kernels.base import _EPS_T, _jit
from app.planning._kernels.records import REC_ACCEPTED, REC_BRANCH, REC_NODE, REC_PARENT, REC_T

__all__ = [
    "POP_ACCEPT",
    "POP_ALTERNATIVES",
    "POP_BREAK",
    "POP_DONE",
    "POP_SPECULATE",
    "accept_checked",
    "heap_add",
    "heap_push",
    "pop_batch",
    "release_deferred",
]

POP_DONE, POP_BREAK, POP_ACCEPT, POP_ALTERNATIVES, POP_SPECULATE = range(5)


@_jit
def _less(a: int, b: int, E_key: np.ndarray, E_negt: np.ndarray, E_id: np.ndarray) -> bool:
    if E_key[a] != E_key[b]:
        return E_key[a] < E_key[b]
    if E_negt[a] != E_negt[b]:
        return E_negt[a] < E_negt[b]
    return E_id[a] < E_id[b]


@_jit
def heap_push(
    e: int, heap: np.ndarray, hs: np.ndarray, E_key: np.ndarray, E_negt: np.ndarray, E_id: np.ndarray
) -> None:
    """Push entry ``e`` (sift up)."""
    pos = hs[0]
    hs[0] = pos + 1
    while pos > 0:
        up = (pos - 1) >> 1
        if _less(e, heap[up], E_key, E_negt, E_id):
            heap[pos] = heap[up]
            pos = up
        else:
            break
    heap[pos] = e


@_jit
def _heap_pop(
    heap: np.ndarray, hs: np.ndarray, E_key: np.ndarray, E_negt: np.ndarray, E_id: np.ndarray
) -> int:
    top = heap[0]
    n = hs[0] - 1
    hs[0] = n
    if n == 0:
        return top
    e = heap[n]
    pos = 0
    while True:
        c = 2 * pos + 1
        if c >= n:
            break
        if c + 1 < n and _less(heap[c + 1], heap[c], E_key, E_negt, E_id):
            c += 1
        if _less(heap[c], e, E_key, E_negt, E_id):
            heap[pos] = heap[c]
            pos = c
        else:
            break
    heap[pos] = e
    return top


@_jit
def heap_add(
    ids: np.ndarray,
    keys: np.ndarray,
    ts: np.ndarray,
    heap: np.ndarray,
    hs: np.ndarray,
    E_key: np.ndarray,
    E_negt: np.ndarray,
    E_id: np.ndarray,
) -> None:
    """New entries (key, -t, id) for the states ``ids``, pushed in order (capacity is the caller's)."""
    for k in range(ids.shape[0]):
        e = hs[1]
        hs[1] = e + 1
        E_key[e] = keys[k]
        E_negt[e] = -ts[k]
        E_id[e] = ids[k]
        heap_push(e, heap, hs, E_key, E_negt, E_id)


@_jit
def release_deferred(
    sid: int,
    def_head: np.ndarray,
    def_next: np.ndarray,
    heap: np.ndarray,
    hs: np.ndarray,
    E_key: np.ndarray,
    E_negt: np.ndarray,
    E_id: np.ndarray,
) -> None:
    """Push back the entries that waited for state ``sid`` to be accepted."""
    e = def_head[sid]
    def_head[sid] = -1
    while e >= 0:
        nxt = def_next[e]
        heap_push(e, heap, hs, E_key, E_negt, E_id)
        e = nxt


# ----------------------------------------------------------------------------------------- the search loop


@_jit
def pop_batch(
    ol: OpenArrays,
    state: SearchState,
    ctx: np.ndarray,
    h_pred: np.ndarray,
    batch_len: int,
    W_b: int,
    n_popped: int,
    spec: bool,
    out: np.ndarray,
) -> tuple[int, int, int, int]:
    """The pop loop of :meth:`app.planning.search.Planner._search` up to the next step that needs Python.

    Pops entries while the heap is not empty and the batch (``batch_len`` states) is shorter than ``W_b``:
    skips states that cannot improve their node or are pruned, defers states whose parent is not accepted
    yet (dropped if it failed), pushes back a final state popped after others (and stops), and collects the
    states to check into ``out[0]`` (and the entries of the final ones among them into ``out[1]``). Returns
    ``(code, n_out, entry, n_final)``: ``POP_DONE``/``POP_BREAK`` (batch
    complete), ``POP_ACCEPT`` (``entry``'s state passed its check ahead of time: accept it),
    ``POP_ALTERNATIVES`` (it failed: push its alternatives), ``POP_SPECULATE`` (the last collected state is
    the batch's first: add its lookahead chain). ``ctx``: goal node (-2: none), stop time, pruned after the
    approach probe (0/1), latest arrival at other nodes, latest arrival, heuristic weight."""
    ol = OpenArrays(*ol)
    state = SearchState(*state)
    heap, hs, E_key, E_negt, E_id = ol.heap, ol.hs, ol.E_key, ol.E_negt, ol.E_id
    def_head, def_next = ol.def_head, ol.def_next
    I, B, status, AT = state.I, state.B, state.status, state.AT  # noqa: E741
    goal_i = int(ctx[0])
    stop = ctx[1]
    blocked = ctx[2] != 0.0
    t_nongoal = ctx[3]
    t_last = ctx[4]
    w_h = ctx[5]
    n_out = 0
    n_fin = 0
    while hs[0] > 0 and batch_len < W_b:
        e = _heap_pop(heap, hs, E_key, E_negt, E_id)
        sid = E_id[e]
        node = I[REC_NODE, sid]
        t = -E_negt[e]
        if t >= AT[node] - _EPS_T:
            continue
        if blocked and (
            (node != goal_i and t + h_pred[node, I[REC_BRANCH, sid]] >= t_nongoal)
            or t + (E_key[e] - t) / w_h > t_last + _EPS_T
        ):
            continue
        par = I[REC_PARENT, sid]
        if not B[REC_ACCEPTED, par]:
            if status[par] != 2:
                def_next[e] = def_head[par]
                def_head[par] = e
            continue
        final = node == goal_i or t >= stop
        st = status[sid]
        if final and batch_len > 0 and st != 0:
            heap_push(e, heap, hs, E_key, E_negt, E_id)
            return POP_BREAK, n_out, -1, n_fin
        if st == 1:
            return POP_ACCEPT, n_out, e, n_fin
        if st == 2:
            return POP_ALTERNATIVES, n_out, e, n_fin
        out[0, n_out] = sid
        n_out += 1
        batch_len += 1
        n_popped += 1
        if final:
            out[1, n_fin] = e
            n_fin += 1
        elif n_popped == 1 and spec:
            return POP_SPECULATE, n_out, e, n_fin
    return POP_DONE, n_out, -1, n_fin


@_jit
def accept_checked(
    popped: np.ndarray, state: SearchState, goal_i: int, stop: float, ol: OpenArrays
) -> tuple[int, np.ndarray, np.ndarray, int]:
    """After a batch's check (:meth:`app.planning.search.Planner._search`): the popped states, in order,
    that passed and still improve their node are accepted (``AT``, the accepted flag, their deferred
    entries pushed back); a final state is accepted only when popped first (it then ends the search).
    Returns ``(accepted, failed states, states to expand, the final state accepted or -1)``."""
    state = SearchState(*state)
    ol = OpenArrays(*ol)
    heap, hs, E_key, E_negt, E_id = ol.heap, ol.hs, ol.E_key, ol.E_negt, ol.E_id
    def_head, def_next = ol.def_head, ol.def_next
    status, F, I, B, AT = state.status, state.F, state.I, state.B, state.AT  # noqa: E741
    M = popped.shape[0]
    failed = np.empty(M, dtype=np.int64)
    expand = np.empty(M, dtype=np.int64)
    nf = 0
    ne = 0
    n_acc = 0
    for k in range(M):
        sid = popped[k]
        if status[sid] != 1:
            failed[nf] = sid
            nf += 1
            continue
        node = I[REC_NODE, sid]
        t = F[REC_T, sid]
        if t >= AT[node] - _EPS_T:
            continue
        if node == goal_i or t >= stop:
            if k == 0:
                AT[node] = t
                B[REC_ACCEPTED, sid] = True
                return n_acc + 1, failed[:nf], expand[:ne], sid
            continue
        AT[node] = t
        B[REC_ACCEPTED, sid] = True
        n_acc += 1
        if def_head[sid] >= 0:
            release_deferred(sid, def_head, def_next, heap, hs, E_key, E_negt, E_id)
        expand[ne] = sid
        ne += 1
    return n_acc, failed[:nf], expand[:ne], -1
