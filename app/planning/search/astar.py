"""The time-variant A* loop (part of :class:`app.planning.search.planner.Planner`): the NumPy/``heapq``
search and its compiled bookkeeping, the latest goal arrival and the approach probe."""

from __future__ import annotations

import heapq
import itertools
import math

import numpy as np

from app.planning import _kernels
from app.planning.roadmap import NUM_BRANCHES
from app.planning.search.config import (
    _EPS_T,
)
from app.planning.search.open_list import _exhausted, _OpenList
from app.planning.search.profiles import (
    _NO_IDS,
    _NO_ROW,
    _profile_arrays,
)
from app.planning.search.search_state import _Run
from app.planning.search.separation import _Separation
from app.planning.trajectory import Plan


class _Search:
    """The search loops of :class:`~app.planning.search.planner.Planner`."""

    # ------------------------------------------------------------------------------------------ search
    def _search(
        self,
        q_start: np.ndarray,
        t_start: float,
        sep: _Separation,
        *,
        goal: int | None,
        stop_time: float | None,
        hold_s: float,
        workers: int,
        deadline: float | None,
    ) -> tuple[Plan | None, int, str]:
        """Lazy time-variant A*. Returns (waypoints or None, validated expansions, reason).

        Successor moves are generated for whole batches of states at once from the precomputed tables and
        pushed unchecked, timed by the path-speed profile; a move is checked (static scene where the roadmap
        did not check it, forecast person, wait, goal hold) only when its state is popped, ``workers``
        states at a time in one vectorised check. A failed move pushes its alternatives: the next branches,
        the slower speeds, the waits. The f-values of unchecked states are their times + the heuristic, so
        the order and the result are those of A* over the checked moves.
        """
        cfg = self.config
        W = max(int(workers), 1)
        h_tab = None if goal is None else self._heuristic_table(goal)
        # the latest arrival after which the person blocks the goal for good
        t_last = math.inf if goal is None else self._latest_goal_arrival(sep, goal, t_start, hold_s)
        t_last = min(t_last, t_start + cfg.max_plan_s)
        run = _Run(
            self.view,
            self.config,
            q_start,
            t_start,
            sep,
            goal=goal,
            stop_time=stop_time,
            hold_s=hold_s,
            h_tab=h_tab,
            t_last=t_last,
        )
        run.row[0] = _NO_ROW
        if run.compiled:
            return self._search_compiled(run, t_start, sep, goal=goal, hold_s=hold_s, W=W, deadline=deadline)
        AT = run.AT
        heap: list[tuple[float, float, int]] = []

        def push(got: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
            ids, keys, ts = got
            for item in zip(keys.tolist(), (-ts).tolist(), ids.tolist(), strict=True):
                heapq.heappush(heap, item)

        push(run.start_moves())
        goal_i = -2 if goal is None else goal
        stop = math.inf if stop_time is None else stop_time
        # lookahead: the best popped state of a batch takes a chain of moves ahead along the static
        # shortest path into the same batch (the batch's other slots go to the next states in order)
        spec_len = W // 2 if goal is not None and W > 1 else 0
        n_batches = 0
        spec_rate = 1.0  # recent share of lookahead moves that passed (with the state they start from)
        chain_ids = _NO_IDS
        expanded = 0
        w_h = cfg.heuristic_weight
        # when the search gets long: can the goal still be entered once the person comes to rest?
        probed = goal is None or sep.forecast is None
        t_static = sep.t_static
        blocked_from: float | None = None

        # states popped before their (speculative) parent was accepted wait here for it
        deferred: dict[int, list[tuple[float, float, int]]] = {}

        def accept(sid: int, t: float, node: int) -> bool:
            """Mark a checked state expanded; True when it ends the search."""
            nonlocal expanded
            AT[node] = t
            run.accepted[sid] = True
            expanded += 1
            if node == goal_i or t >= stop:
                return True
            for entry in deferred.pop(sid, ()):
                heapq.heappush(heap, entry)
            return False

        while heap:
            if deadline is not None and self._timer() > deadline:
                return None, expanded, "deadline"
            if expanded >= cfg.max_expansions:
                return None, expanded, f"no plan within {cfg.max_expansions} expansions"
            batch: list[int] = []
            popped: list[int] = []
            finals: list[tuple[float, float, int]] = []
            n_batches += 1
            W_b = min(W, 8 + 4 * n_batches)  # the batch grows: the first steps have few states worth checking
            while heap and len(batch) < W_b:
                entry = heapq.heappop(heap)
                sid = entry[2]
                node = int(run.node[sid])
                t = -entry[1]
                if t >= AT[node] - _EPS_T:
                    continue  # a checked state reached this node no later
                if blocked_from is not None and (
                    (node != goal_i and t + run.h_pred[node, run.branch[sid]] >= run.t_nongoal)
                    or t + (entry[0] - t) / w_h > run.t_last + _EPS_T
                ):
                    continue  # pruned after the approach probe
                par = int(run.parent[sid])
                if not run.accepted[par]:  # a speculative chain's state whose parent is not through yet
                    if run.status[par] != 2:
                        deferred.setdefault(par, []).append(entry)
                    continue
                final = node == goal_i or t >= stop
                st = int(run.status[sid])
                if final and batch and st != 0:  # states popped before it (f <= its f) may improve it
                    heapq.heappush(heap, entry)
                    break
                if st == 1:  # checked ahead of time (a speculative chain): passed
                    if accept(sid, t, node):
                        return run.reconstruct(sid), expanded, "ok"
                    push(run.children(np.array([sid], dtype=np.int64)))
                    continue
                if st == 2:
                    push(run.alternatives(np.array([sid], dtype=np.int64)))
                    continue
                batch.append(sid)
                popped.append(sid)
                if final:  # checked now, accepted only once nothing pending can beat it
                    finals.append(entry)
                    continue
                if len(popped) == 1 and spec_len:
                    length = max(1, round(min(spec_len, W - 1) * spec_rate))
                    chain = run.speculate(sid, length)
                    chain_ids = chain[0]
                    push(chain)
                    batch.extend(chain[0].tolist())
            if not batch:
                continue
            run.check(np.array(batch, dtype=np.int64))
            if chain_ids.size:  # shorter lookahead where the way ahead keeps being blocked
                passed = float(np.mean(run.status[chain_ids] == 1)) * float(run.status[popped[0]] == 1)
                spec_rate = 0.5 * spec_rate + 0.5 * passed
                chain_ids = _NO_IDS
            # the popped states now (the chains wait in the heap for their turn)
            expand: list[int] = []
            failed: list[int] = []
            for k, sid in enumerate(popped):
                if run.status[sid] != 1:
                    failed.append(sid)
                    continue
                node = int(run.node[sid])
                t = float(run.t[sid])
                if t >= AT[node] - _EPS_T:
                    continue
                if node == goal_i or t >= stop:
                    if k == 0:  # popped first: nothing in this batch can reach its node sooner
                        accept(sid, t, node)
                        return run.reconstruct(sid), expanded, "ok"
                    continue  # back to the heap below, checked
                if accept(sid, t, node):
                    return run.reconstruct(sid), expanded, "ok"
                expand.append(sid)
            for entry in finals:
                if run.status[entry[2]] == 1 and entry[2] != popped[0]:
                    heapq.heappush(heap, entry)
            if failed:
                push(run.alternatives(np.array(failed, dtype=np.int64)))
            if expand:
                push(run.children(np.array(expand, dtype=np.int64)))
            if not probed and expanded >= cfg.probe_after_expansions and goal is not None:
                probed = True
                t_probe = max(t_static, t_start)
                longest = self._approach_probe(sep, goal, t_probe, hold_s, run.t_last)
                if longest is not None:  # no way into the goal once the person holds still
                    blocked_from = t_probe
                    run.t_nongoal = min(run.t_nongoal, t_probe)
                    run.t_last = min(run.t_last, t_probe + longest)
                    run.h_pred = self._to_goal_neighbours(goal)
        return _exhausted(goal, t_last, t_start, cfg.max_plan_s, expanded, blocked_from)

    def _search_compiled(
        self,
        run: _Run,
        t_start: float,
        sep: _Separation,
        *,
        goal: int | None,
        hold_s: float,
        W: int,
        deadline: float | None,
    ) -> tuple[Plan | None, int, str]:
        """The loop of :meth:`_search` over the compiled open list (:class:`_OpenList`): the same states
        popped, checked and accepted in the same order (the pop loop runs in
        :func:`app.planning._kernels.pop_batch` up to each step that needs Python), the same result."""
        cfg = self.config
        t_last = run.t_last
        AT = run.AT
        ol = _OpenList(run)
        ol.push(run.start_moves())
        goal_i = -2 if goal is None else goal
        stop = math.inf if run.stop_time is None else run.stop_time
        spec_len = W // 2 if goal is not None and W > 1 else 0
        n_batches = 0
        spec_rate = 1.0
        chain_ids = _NO_IDS
        expanded = 0
        probed = goal is None or sep.forecast is None
        t_static = sep.t_static
        blocked_from: float | None = None
        ctx = np.array([goal_i, stop, 0.0, run.t_nongoal, run.t_last, cfg.heuristic_weight])
        h_pred = np.zeros((0, NUM_BRANCHES))
        out = np.empty((2, W), dtype=np.int64)

        def accept(sid: int, t: float, node: int) -> bool:
            nonlocal expanded
            AT[node] = t
            run.accepted[sid] = True
            expanded += 1
            if node == goal_i or t >= stop:
                return True
            if ol.def_head[sid] >= 0:
                ol.release(sid)
            return False

        while ol.hs[0]:
            if deadline is not None and self._timer() > deadline:
                return None, expanded, "deadline"
            if expanded >= cfg.max_expansions:
                return None, expanded, f"no plan within {cfg.max_expansions} expansions"
            batch: list[int] = []
            popped: list[int] = []
            finals: list[int] = []  # entries
            n_batches += 1
            W_b = min(W, 8 + 4 * n_batches)
            while True:
                code, n_out, e, n_fin = _kernels.pop_batch(
                    ol.arrays, run._k_state, ctx, h_pred, len(batch), W_b, len(popped), spec_len > 0, out
                )
                E_id = ol.E_id
                if n_out:
                    got = out[0, :n_out].tolist()
                    batch.extend(got)
                    popped.extend(got)
                    if n_fin:
                        finals.extend(out[1, :n_fin].tolist())
                if code == _kernels.POP_SPECULATE:
                    length = max(1, round(min(spec_len, W - 1) * spec_rate))
                    chain = run.speculate(popped[0], length)
                    chain_ids = chain[0]
                    ol.push(chain)
                    batch.extend(chain[0].tolist())
                elif code == _kernels.POP_ACCEPT:
                    sid = int(E_id[e])
                    if accept(sid, -float(ol.E_negt[e]), int(run.node[sid])):
                        return run.reconstruct(sid), expanded, "ok"
                    ol.push(run.children(np.array([sid], dtype=np.int64)))
                elif code == _kernels.POP_ALTERNATIVES:
                    ol.push(run.alternatives(np.array([E_id[e]], dtype=np.int64)))
                else:
                    break
            if not batch:
                continue
            run.check(np.array(batch, dtype=np.int64))
            if chain_ids.size:
                n_pass = int(np.count_nonzero(run.status[chain_ids] == 1))
                passed = n_pass / chain_ids.size * float(run.status[popped[0]] == 1)
                spec_rate = 0.5 * spec_rate + 0.5 * passed
                chain_ids = _NO_IDS
            n_acc, failed, expand, final_sid = _kernels.accept_checked(
                np.array(popped, dtype=np.int64), run._k_state, goal_i, stop, ol.arrays
            )
            expanded += n_acc
            if final_sid >= 0:
                return run.reconstruct(int(final_sid)), expanded, "ok"
            for ek in finals:
                if run.status[ol.E_id[ek]] == 1 and ol.E_id[ek] != popped[0]:
                    ol.push_back(ek)
            if failed.size:
                ol.push(run.alternatives(failed))
            if expand.size:
                ol.push(run.children(expand))
            if not probed and expanded >= cfg.probe_after_expansions and goal is not None:
                probed = True
                t_probe = max(t_static, t_start)
                longest = self._approach_probe(sep, goal, t_probe, hold_s, run.t_last)
                if longest is not None:
                    blocked_from = t_probe
                    run.t_nongoal = min(run.t_nongoal, t_probe)
                    run.t_last = min(run.t_last, t_probe + longest)
                    run.h_pred = self._to_goal_neighbours(goal)
                    h_pred = _kernels.as_f64(run.h_pred)
                    ctx[2:5] = (1.0, run.t_nongoal, run.t_last)
        return _exhausted(goal, t_last, t_start, cfg.max_plan_s, expanded, blocked_from)

    def _latest_goal_arrival(self, sep: _Separation, goal: int, t_start: float, hold_s: float) -> float:
        """The latest arrival at the goal from which the robot could stand there for ``hold_s``, when the
        forecast person blocks every goal branch for good after some time (their last pose is held and the
        margin stops growing at its cap); +inf when some branch stays free or without a forecast."""
        fc = sep.forecast
        if fc is None:
            return math.inf
        cfg = self.config
        m_end = float(fc.margins[-1])
        cap = max(fc.max_margin_m, float(fc.margins.max()))
        t_sat = fc.horizon_end + (max(cap - m_end, 0.0) / fc.growth_mps if fc.growth_mps > 0 else 0.0)
        t_sat = max(t_sat, t_start) + hold_s
        n = max(math.ceil((t_sat - t_start) / cfg.sample_dt_s), 1)
        ts = t_start + (t_sat - t_start) * np.arange(n + 1) / n
        branches = np.flatnonzero(self._valid[goal])
        nb = branches.size
        # usually some branch is free once the person holds still: then nothing more to find out
        last = sep.check(
            self._ik[goal, branches],
            np.full(nb, ts[-1]),
            np.zeros(nb),
            np.zeros(nb),
            self._cen_all[goal, branches],
            self._rad_all[goal, branches],
        )
        if np.any(last):
            return math.inf
        rep = np.repeat(branches, n + 1)
        ok = sep.check(
            self._ik[goal, rep],
            np.tile(ts, nb),
            np.zeros(rep.size),
            np.zeros(rep.size),
            self._cen_all[goal, rep],
            self._rad_all[goal, rep],
        ).reshape(nb, n + 1)
        if np.any(ok[:, -1]):
            return math.inf
        k_hold = math.ceil(hold_s / ((t_sat - t_start) / n) - 1e-9)
        best = -math.inf
        for row in ok:
            # latest i with row[i .. i + k_hold] all safe
            run = 0
            for i in range(n, -1, -1):
                run = run + 1 if row[i] else 0
                if run >= k_hold + 1:
                    best = max(best, float(ts[i]))
                    break
        return best

    def _approach_probe(
        self, sep: _Separation, goal: int, t_static: float, hold_s: float, t_last: float
    ) -> float | None:
        """Whether the goal can still be entered once the forecast has come to rest (``t_static``).

        Checks every move the search could make into the goal (each roadmap neighbour, each valid branch
        there, the ``max_branch_tries`` nearest goal branches) the slowest way the search makes it (the
        nearest branch at the slowest of ``slow_speed_fractions``, the others at the cruise speed), from
        rest, with the goal hold, departing at ``t_static``. From then on the person and the margin no
        longer change, and a faster move needs at least as much separation at every point of its path, so
        when even these fail no move into the goal that departs later passes. Moves that could not arrive
        by ``t_last`` (the search's bound) are left out. Returns None when some move passes, else the
        longest of the moves (s): a plan must then arrive within that long after ``t_static``.
        """
        rm = self.roadmap
        entries = np.flatnonzero(rm.indices == goal)
        if entries.size == 0:
            return None
        src = np.searchsorted(rm.indptr, entries, side="right") - 1
        e = np.repeat(entries, NUM_BRANCHES * self._R)
        u = np.repeat(src, NUM_BRANCHES * self._R)
        bu = np.tile(np.repeat(np.arange(NUM_BRANCHES), self._R), entries.size)
        k = np.tile(np.arange(self._R), entries.size * NUM_BRANCHES)
        row = e * NUM_BRANCHES + bu
        L = self._L_flat[row, k]
        keep = np.isfinite(L) & self._valid[u, bu]
        if not keep.any():
            return None
        u, bu, row, k, L = u[keep], bu[keep], row[keep], k[keep], L[keep]
        b = self._ord_flat[row, k]
        q_a = self._ik[u, bu]
        target = self._align(self._ik[goal, b], q_a)
        m = u.size
        # the slowest move the search makes there: the nearest branch at the slowest speed, the others at
        # the cruise speed (it tries no other branch slower); from rest, slower than any entry speed
        f_min = min((self.config.speed_fraction, *self.config.slow_speed_fractions))
        f = np.where(k == 0, f_min, self.config.speed_fraction)
        end = np.ones(m, dtype=bool)
        h, _, _ = _profile_arrays(np.zeros(m), L, f, self._A, end)
        h = np.where(L > 1e-12, np.maximum(h, self.config.min_edge_s), h)
        fits = t_static + h <= t_last
        if not fits.any():
            return 0.0
        u, bu, b, q_a, target, L, h, f = (x[fits] for x in (u, bu, b, q_a, target, L, h, f))
        m = u.size
        # the moves from the roomiest configurations first: one that passes ends the probe early
        assert sep.forecast is not None
        pose = sep._poses(np.full(m, t_static))
        room = self.collision.distance_to_human_paired(q_a, pose)
        order = np.argsort(-room, kind="stable")
        bounds = [0, 4, 16, *range(32, m, 32), m]
        for c0, c1 in itertools.pairwise(bounds):
            if c0 >= m:
                break
            i = order[c0:c1]
            n = i.size
            ones = np.ones(n, dtype=bool)
            ok = self._moves_ok(
                sep,
                q_a[i],
                self._pts_all[u[i], bu[i]],
                self._cen_all[u[i], bu[i]],
                self._rad_all[u[i], bu[i]],
                np.full(n, goal),
                b[i],
                target[i],
                np.full(n, t_static),
                h[i],
                np.zeros(n),
                L[i],
                ones,
                f[i],
                ones,
                hold_s,
            )
            if ok.any():
                return None
        return float(h.max())
