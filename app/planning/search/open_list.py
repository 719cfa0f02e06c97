"""The compiled search's open list (:class:`_OpenList`, a binary heap in the order of ``heapq``) and the
result of a search whose open list ran empty (:func:`_exhausted`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.planning import _kernels
from app.planning.search.config import GOAL_BLOCKED, GOAL_WAYS_BLOCKED
from app.planning.search.search_state import _Run


class _OpenList:
    """The compiled search's open list: entries ``(key, -t, state id)`` in an append-only table and a
    binary heap of entry indices (:mod:`app.planning._kernels`: ``heap_add``, ``pop_batch``), plus the
    entries that wait for a state to be accepted (linked lists: ``def_head`` per state, ``def_next`` per
    entry). Pops in exactly the order of ``heapq`` over the tuples."""

    def __init__(self, run: _Run) -> None:
        self.run = run
        cap = 1024
        self.E_key = np.zeros(cap)
        self.E_negt = np.zeros(cap)
        self.E_id = np.zeros(cap, dtype=np.int64)
        self.def_next = np.full(cap, -1, dtype=np.int64)
        self.heap = np.zeros(cap, dtype=np.int64)
        self.hs = np.zeros(2, dtype=np.int64)  # heap size, entries
        self.def_head = np.full(run.t.shape[0], -1, dtype=np.int64)
        self.arrays = self._arrays()

    def _arrays(self) -> tuple[Any, ...]:
        """The arrays as the compiled search loop takes them (:class:`~app.planning._kernels.OpenArrays`,
        packed; rebuilt whenever they grow)."""
        return _kernels.pack(
            _kernels.OpenArrays(
                self.heap, self.hs, self.E_key, self.E_negt, self.E_id, self.def_head, self.def_next
            )
        )

    def push(self, got: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        ids, keys, ts = got
        m = ids.shape[0]
        cap = self.E_key.shape[0]
        grown = False
        if self.hs[1] + m > cap:
            grown = True
            new = max(2 * cap, int(self.hs[1]) + m)
            for name in ("E_key", "E_negt", "E_id", "def_next", "heap"):
                old = getattr(self, name)
                arr = (
                    np.full(new, -1, dtype=old.dtype)
                    if name == "def_next"
                    else np.zeros(new, dtype=old.dtype)
                )
                arr[:cap] = old
                setattr(self, name, arr)
        n_states = self.run.t.shape[0]
        if self.def_head.shape[0] < n_states:
            head = np.full(n_states, -1, dtype=np.int64)
            head[: self.def_head.shape[0]] = self.def_head
            self.def_head = head
            grown = True
        if grown:
            self.arrays = self._arrays()
        if m:  # (the generation kernels' own arrays: int64 / float64, contiguous)
            _kernels.heap_add(ids, keys, ts, self.heap, self.hs, self.E_key, self.E_negt, self.E_id)

    def push_back(self, e: int) -> None:
        _kernels.heap_push(e, self.heap, self.hs, self.E_key, self.E_negt, self.E_id)

    def release(self, sid: int) -> None:
        _kernels.release_deferred(
            sid, self.def_head, self.def_next, self.heap, self.hs, self.E_key, self.E_negt, self.E_id
        )


def _exhausted(
    goal: int | None,
    t_last: float,
    t_start: float,
    max_plan_s: float,
    expanded: int,
    blocked_from: float | None,
) -> tuple[None, int, str]:
    """The result of a search whose open list ran empty."""
    if goal is not None and t_last < t_start + max_plan_s and not expanded:
        if t_last < t_start:
            return None, expanded, f"{GOAL_BLOCKED} for good"
        return None, expanded, f"{GOAL_BLOCKED} from t={t_last - t_start:+.2f} s on"
    what = "goal" if goal is not None else "the emergency horizon"
    if blocked_from is not None:
        return (
            None,
            expanded,
            f"{GOAL_WAYS_BLOCKED} (t={blocked_from - t_start:+.2f} s), no safe path arrives before "
            f"({expanded} expansions)",
        )
    return None, expanded, f"{what} unreachable: no safe path found after {expanded} expansions"
