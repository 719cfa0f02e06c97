"""The records of one search (:class:`_Run`): its states in growable arrays, successor generation and
timing, the batched move check and the plan's reconstruction."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from app.planning import _kernels
from app.planning.roadmap import NUM_BRANCHES
from app.planning.search.config import (
    _EPS_T,
    PlannerConfig,
)
from app.planning.search.profiles import (
    _NO_IDS,
    _NO_ROW,
    _profile_arrays,
    _profile_py,
    _wait_grid,
)
from app.planning.search.roadmap_view import RoadmapView
from app.planning.search.separation import _Separation
from app.planning.trajectory import Plan


class _Run:
    """The records of one search: every generated state in growable numpy arrays (one row per state).

    Owned by one query (never shared, never written to the roadmap). A state is a move from a parent state
    to a roadmap node at an IK branch: departure, duration, entry/exit path speed, cruise speed, the
    alternative it is (0 = nearest branch at cruise speed; others are generated when it fails) and the row of
    the option table it came from (its successor branches, for the alternatives). Row 0 is the start.
    Generation, timing and checking work on whole arrays of states at once.

    It reads the roadmap only through ``view`` (the planner's :class:`RoadmapView`, shared and read-only), the
    search settings from ``config`` and the person through ``sep``.
    """

    _FLOAT = ("t", "u", "u0", "dep", "fc", "L", "h", "peak", "wait_ok")
    _INT = ("node", "branch", "parent", "row", "spec_child")
    _BOOL = ("end", "same", "accepted", "qset")

    def __init__(
        self,
        view: RoadmapView,
        config: PlannerConfig,
        q_start: np.ndarray,
        t_start: float,
        sep: _Separation,
        *,
        goal: int | None,
        stop_time: float | None,
        hold_s: float,
        h_tab: np.ndarray | None,
        t_last: float,
    ) -> None:
        self.view = view
        self.config = config
        self.sep = sep
        self.goal = goal
        self.stop_time = stop_time
        self.hold_s = hold_s
        self.h_tab = h_tab
        self.t_last = t_last
        self.t_nongoal = math.inf  # states at other nodes than the goal must arrive before this (s)
        self.h_pred: np.ndarray | None = None  # (N, 8) time lower bound to a roadmap neighbour of the goal
        self.f = config.speed_fraction
        self.A = view.accel
        self.min_edge = config.min_edge_s
        self.w_h = config.heuristic_weight
        self.AT = np.full(view.num_nodes, np.inf)
        cap = 256
        # the records, packed: one row per field (the attributes named in _FLOAT/_INT/_BOOL are views)
        self._F = np.zeros((len(self._FLOAT), cap))
        self._I = np.full((len(self._INT), cap), -1, dtype=np.int64)
        self._B = np.zeros((len(self._BOOL), cap), dtype=bool)
        self._bind()
        self.alt = np.zeros(cap, dtype=np.int8)
        self.status = np.zeros(cap, dtype=np.int8)  # check result: 0 not yet, 1 passed, 2 failed
        self.q = np.empty((cap, 6))  # the configuration once checked (or precomputed: ``qset``)
        self.n = 1
        self.t[0] = self.dep[0] = t_start
        self.fc[0] = self.f
        self.same[0] = self.accepted[0] = self.qset[0] = True
        self.status[0] = 1
        self.next_rows = None if goal is None else view.next_rows.get(goal)
        # the compiled bookkeeping (with the compiled model; the NumPy code below is its reference)
        self.compiled = view.compiled
        self._h_tab_k = _kernels.as_f64(h_tab) if h_tab is not None else np.zeros((0, NUM_BRANCHES))
        self._kinds: np.ndarray | None = None
        self._ctx_key: tuple[float, float, bool] | None = None
        self._ctx: tuple[Any, ...] | None = None  # SearchContext, packed
        self.wait_ok[:] = np.nan  # per checked state: until when standing still there is safe (NaN: unknown)
        self.q[0] = q_start
        pts, cen, rad = view.points_and_spheres(q_start[None])
        self.start_pts, self.start_cen, self.start_rad = pts[0], cen[0], rad[0]
        self._start_k = _kernels.pack(
            _kernels.CapsuleBounds(*(_kernels.as_f64(x) for x in (pts[0], cen[0], rad[0])))
        )
        # option tables: rows e * 8 + b of the planner's edge tables, then the start's rows (-1 - j)
        self.start_b = np.zeros((1, view.n_options), dtype=np.int64)
        self.start_L = np.full((1, view.n_options), np.inf)
        self._k_state = self._state()

    # -- records
    def _grow(self, m: int) -> None:
        cap = self.t.shape[0]
        if self.n + m <= cap:
            return
        new = max(2 * cap, self.n + m)
        F = np.zeros((len(self._FLOAT), new))
        F[:, :cap] = self._F
        F[_kernels.REC_WAIT_OK, cap:] = np.nan
        I = np.full((len(self._INT), new), -1, dtype=np.int64)  # noqa: E741
        I[:, :cap] = self._I
        B = np.zeros((len(self._BOOL), new), dtype=bool)
        B[:, :cap] = self._B
        self._F, self._I, self._B = F, I, B
        self._bind()
        for name in ("alt", "status", "q"):
            old = getattr(self, name)
            arr = np.zeros((new, *old.shape[1:]), dtype=old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)
        self._k_state = self._state()

    def _state(self) -> tuple[Any, ...]:
        """The records as the compiled bookkeeping takes them (:class:`~app.planning._kernels.SearchState`,
        packed; rebuilt whenever they grow)."""
        return _kernels.pack(
            _kernels.SearchState(
                F=self._F, I=self._I, B=self._B, alts=self.alt, q=self.q, status=self.status, AT=self.AT
            )
        )

    def _bind(self) -> None:
        """The record attributes as views of the packed arrays."""
        for group, names in ((self._F, self._FLOAT), (self._I, self._INT), (self._B, self._BOOL)):
            for k, name in enumerate(names):
                setattr(self, name, group[k])

    def _options(self, row: np.ndarray, k: int | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Branch, length and roadmap-checked flag of option ``k`` of each option-table row."""
        view = self.view
        glob = row >= 0
        if glob.all():
            return view.ord_flat[row, k], view.L_flat[row, k], view.same_flat[row, k]
        g = np.where(glob, row, 0)
        s = np.where(glob, 0, -1 - row)
        b = np.where(glob, view.ord_flat[g, k], self.start_b[s, k])
        L = np.where(glob, view.L_flat[g, k], self.start_L[s, k])
        return b, L, glob & view.same_flat[g, k]

    def moves(
        self,
        parent: np.ndarray,
        node: np.ndarray,
        branch: np.ndarray,
        L: np.ndarray,
        same: np.ndarray,
        t_dep: np.ndarray,
        u0: np.ndarray,
        fc: np.ndarray | float,
        alt: int | np.ndarray,
        row: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Time moves (arrays of one entry per move), keep those that could improve their node's arrival
        and pass the prune, and record them. Returns (state ids, keys t + w h, arrival times)."""
        fin = np.isfinite(L)
        if not fin.all():
            parent, node, branch, L, same, t_dep, u0, row = (
                x[fin] for x in (parent, node, branch, L, same, t_dep, u0, row)
            )
            if isinstance(fc, np.ndarray):
                fc = fc[fin]
            if isinstance(alt, np.ndarray):
                alt = alt[fin]
        m = parent.shape[0]
        fc = np.broadcast_to(np.asarray(fc, dtype=np.float64), (m,))
        end = node == self.goal if self.goal is not None else np.zeros(m, dtype=bool)
        u0 = np.minimum(u0, fc)
        h, u1, peak = _profile_arrays(u0, L, fc, self.A, end)
        h = np.where(L > 1e-12, np.maximum(h, self.min_edge), h)
        ta = t_dep + h
        w = self.w_h
        if self.h_tab is not None:
            hv = self.h_tab[node, branch]
        elif self.stop_time is not None:
            hv, w = np.maximum(self.stop_time - ta, 0.0), 1.0
        else:
            hv = np.zeros(m)
        # an admissible prune: with a weight w > 1 the key t + w h >= t + h, so compare t + h itself
        keep = (ta < self.AT[node] - _EPS_T) & (ta + hv <= self.t_last)
        if self.t_nongoal < math.inf:
            h_pred = self.h_pred[node, branch] if self.h_pred is not None else 0.0
            keep &= (node == self.goal) | (ta + h_pred < self.t_nongoal)
        if not keep.all():
            idx = np.flatnonzero(keep)
            parent, node, branch, L, same, t_dep, u0, row, fc, end, h, u1, peak, ta, hv = (
                x[idx] for x in (parent, node, branch, L, same, t_dep, u0, row, fc, end, h, u1, peak, ta, hv)
            )
            m = idx.size
            if isinstance(alt, np.ndarray):
                alt = alt[idx]
        self._grow(m)
        ids = np.arange(self.n, self.n + m)
        self.n += m
        self.node[ids] = node
        self.branch[ids] = branch
        self.parent[ids] = parent
        self.t[ids] = ta
        self.u[ids] = u1
        self.u0[ids] = u0
        self.dep[ids] = t_dep
        self.fc[ids] = fc
        self.L[ids] = L
        self.h[ids] = h
        self.peak[ids] = peak
        self.end[ids] = end
        self.same[ids] = same
        self.alt[ids] = alt
        self.row[ids] = row
        return ids, ta + w * hv, ta

    # -- generation
    def start_moves(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Moves from the start to its nearest roadmap nodes (each checked against the scene when popped)."""
        view = self.view
        q = self.q[0]
        # a robot at rest at a task pose is common: try the stations before the whole roadmap
        st = view.stations
        Ls = np.where(view.valid[st], view.metric(view.align(view.ik[st], q[None, None, :]) - q), np.inf)
        hit = np.flatnonzero(Ls.min(axis=1) <= 1e-9)
        if hit.size and int(st[hit[0]]) != self.goal:
            n = int(st[hit[0]])
            self.node[0], self.branch[0] = n, int(np.argmin(Ls[hit[0]]))
            self.AT[n] = self.t[0]
            return self.children(np.zeros(1, dtype=np.int64))
        aligned = view.align(view.ik, q[None, None, :])
        L = np.where(view.valid, view.metric(aligned - q), np.inf)
        best = L.min(axis=1)
        k = min(self.config.start_neighbors, int(np.isfinite(best).sum()))
        if k == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        nodes = np.argpartition(best, k - 1)[:k]
        at_node = nodes[best[nodes] <= 1e-9]
        if at_node.size:  # the start is a roadmap configuration: the roadmap's edges take it from there
            nodes, k = at_node[:1], 1
            n = int(nodes[0])
            if n != self.goal:  # the start state is that node (statically free, checked against the person)
                self.node[0], self.branch[0] = n, int(np.argmin(L[n]))
                self.AT[n] = self.t[0]
                return self.children(np.zeros(1, dtype=np.int64))
        order = np.argsort(L[nodes], axis=1, kind="stable")[:, : view.n_options]
        self.start_b = order.astype(np.int64)
        self.start_L = np.take_along_axis(L[nodes], order, axis=1)
        row = -1 - np.arange(k)
        zeros = np.zeros(k)
        return self.moves(
            np.zeros(k, dtype=np.int64),
            nodes.astype(np.int64),
            self.start_b[:, 0],
            self.start_L[:, 0],
            np.zeros(k, dtype=bool),
            zeros + self.t[0],
            zeros,
            self.f,
            0,
            row,
        )

    def _context(self) -> tuple[Any, ...]:
        """The compiled generation's scalars (see :func:`app.planning._kernels.children_moves`), heuristic
        table and ``h_pred`` ((0, 8) where there is none): :class:`~app.planning._kernels.SearchContext`,
        packed."""
        key = (self.t_last, self.t_nongoal, self.h_pred is None)
        # the prune's bounds change only after the approach probe
        if self._ctx is None or self._ctx_key != key:
            goal = -2 if self.goal is None else self.goal
            stop = math.nan if self.stop_time is None else self.stop_time
            ctx = np.array([goal, self.A, self.min_edge, self.w_h, stop, self.t_last, self.t_nongoal, self.f])
            h_pred = self.h_pred if self.h_pred is not None else np.zeros((0, NUM_BRANCHES))
            self._ctx = _kernels.pack(_kernels.SearchContext(ctx, self._h_tab_k, _kernels.as_f64(h_pred)))
            self._ctx_key = key
        return self._ctx

    def _recorded(
        self, n: int, keys: np.ndarray, ta: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ids = np.arange(self.n, n)
        self.n = n
        return ids, keys, ta

    def children(self, sids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Moves from checked states to all their roadmap neighbours (nearest branch, cruise speed)."""
        view = self.view
        if self.compiled:
            self._grow(view.max_degree * sids.size)
            return self._recorded(
                *_kernels.children_moves(
                    sids, view.k_roadmap, self.f, NUM_BRANCHES, self._context(), self._k_state, self.n
                )
            )
        u, bu = self.node[sids], self.branch[sids]
        a, z = view.indptr[u], view.indptr[u + 1]
        cnt = z - a
        owner = np.repeat(np.arange(sids.size), cnt)
        e = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt - a, cnt)
        row = e * NUM_BRANCHES + bu[owner]
        par = sids[owner]
        spec = self.spec_child[par]
        has = spec >= 0
        if has.any():  # the speculative chain already holds that move
            keep = ~has | (view.indices[e] != self.node[np.maximum(spec, 0)])
            e, row, par = e[keep], row[keep], par[keep]
        return self.moves(
            par,
            view.indices[e],
            view.ord_flat[row, 0],
            view.L_flat[row, 0],
            view.same_flat[row, 0],
            self.t[par],
            self.u[par],
            self.f,
            0,
            row,
        )

    def speculate(self, sid: int, max_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A chain of moves ahead of the unchecked state ``sid`` along the static shortest path (nearest
        branch, cruise speed: the moves a search would try first), to be checked in the same batch as
        ``sid`` (lookahead: when the way is clear, one batch checks the whole rest of the path).

        The chain's states are ordinary states (timed like children, pushed with their keys); their parent
        must still be accepted before they are. Stops at the goal, at a node already reached no later, at
        the prune, after ``max_len`` moves.
        """
        nxt = self.next_rows
        if nxt is None or max_len <= 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        view = self.view
        if self.compiled:
            self._grow(max_len)
            return self._recorded(
                *_kernels.speculate_chain(
                    sid, max_len, view.next_rows_k[self.goal], view.k_roadmap, view.k_limits, self._context(),
                    self._k_state, self.n,
                )
            )  # fmt: skip
        node, b = int(self.node[sid]), int(self.branch[sid])
        par = int(self.parent[sid])
        q_prev = view.align(view.ik[node, b], self.q[par]) if not self.qset[sid] else self.q[sid]
        self.q[sid] = q_prev
        self.qset[sid] = True
        t, u = float(self.t[sid]), float(self.u[sid])
        f, A, goal, AT, h_tab = self.f, self.A, self.goal, self.AT, self.h_tab
        assert h_tab is not None
        chain: list[tuple[int, int, int, float, bool, float, float, float, float, float]] = []
        qs = []
        while len(chain) < max_len and node != goal:
            row = nxt[node * NUM_BRANCHES + b]
            if row < 0:
                break
            v = view.indices_list[row // NUM_BRANCHES]
            bv = view.ord_list[row]
            L = view.L_list[row]
            end = v == goal
            h, u1, peak = _profile_py(u, L, f, A, end)
            if L > 1e-12:
                h = max(h, self.min_edge)
            ta = t + h
            hv = float(h_tab[v, bv])
            if ta >= AT[v] - _EPS_T or ta + hv > self.t_last:
                break
            if v != goal and ta + (0.0 if self.h_pred is None else self.h_pred[v, bv]) >= self.t_nongoal:
                break
            q_next = q_prev + view.delta0[row]  # the nearest 2 pi shift, as _align finds it within the limits
            if not np.all((q_next >= view.q_min) & (q_next <= view.q_max)):
                q_next = view.align(view.ik[v, bv], q_prev)
            q_prev = q_next
            qs.append(q_prev)
            chain.append((row, v, bv, L, view.same_list[row], t, min(u, f), h, u1, peak))
            node, b, t, u = v, bv, ta, u1
        m = len(chain)
        if m == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        self._grow(m)
        ids = np.arange(self.n, self.n + m)
        self.n += m
        cols = list(zip(*chain, strict=True))
        self.row[ids] = cols[0]
        self.node[ids] = cols[1]
        self.branch[ids] = cols[2]
        self.L[ids] = cols[3]
        self.same[ids] = cols[4]
        self.dep[ids] = cols[5]
        self.u0[ids] = cols[6]
        self.h[ids] = cols[7]
        self.u[ids] = cols[8]
        self.peak[ids] = cols[9]
        self.t[ids] = self.dep[ids] + self.h[ids]
        self.parent[ids] = np.concatenate([[sid], ids[:-1]])
        self.spec_child[self.parent[ids]] = ids
        self.fc[ids] = f
        self.end[ids] = self.node[ids] == goal
        self.alt[ids] = 0
        self.q[ids] = qs
        self.qset[ids] = True
        ta = self.t[ids]
        return ids, ta + self.w_h * h_tab[self.node[ids], self.branch[ids]], ta

    def alternatives(self, failed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """When the nearest branch at cruise speed fails: the next branches (alternative 1), the nearest one
        slower (2), after waiting (3), after stopping at the slowest speed (4)."""
        cfg = self.config
        if self.compiled:
            if self._kinds is None:
                self._kinds = np.array(self._alternative_kinds(), dtype=np.float64).reshape(-1, 4)
            view = self.view
            self._grow(failed.size * self._kinds.shape[0])
            return self._recorded(
                *_kernels.alternative_moves(
                    failed, self._kinds, _NO_ROW, float(cfg.wait_step_s), float(self.sep.t_static),
                    self.start_b, _kernels.as_f64(self.start_L), view.k_roadmap, self._context(),
                    self._k_state, self.n,
                )
            )  # fmt: skip
        failed = failed[(self.alt[failed] == 0) & (self.row[failed] != _NO_ROW)]
        if failed.size == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        par, node, row = self.parent[failed], self.node[failed], self.row[failed]
        t, u = self.t[par], self.u[par]
        n = failed.size
        kinds = self._alternative_kinds()
        if not kinds:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        spec = np.array(kinds, dtype=np.float64)  # (A, 4)
        a = spec.shape[0]
        alt = np.repeat(spec[:, 0].astype(np.int8), n)
        opt = np.repeat(spec[:, 1].astype(np.int64), n)
        fc = np.repeat(spec[:, 2], n)
        wait = np.repeat(spec[:, 3], n)
        par_r, node_r, row_r = np.tile(par, a), np.tile(node, a), np.tile(row, a)
        t_r = np.tile(t, a)
        # once the person holds still, waiting longer changes nothing: of the waits that depart then, only
        # the first is kept
        t_s = self.sep.t_static
        keep = (wait <= 1) | (t_r + (wait - 1) * cfg.wait_step_s < t_s)
        if not keep.all():
            alt, opt, fc, wait, par_r, node_r, row_r, t_r = (
                x[keep] for x in (alt, opt, fc, wait, par_r, node_r, row_r, t_r)
            )
            u_r = np.tile(u, a)[keep]
        else:
            u_r = np.tile(u, a)
        b, L, same = self._options(row_r, opt)
        u0 = np.where(wait != 0, 0.0, np.minimum(u_r, fc))  # from rest after a wait or a stop
        t_dep = t_r + np.maximum(wait, 0.0) * cfg.wait_step_s
        return self.moves(par_r, node_r, b, L, same, t_dep, u0, fc, alt, row_r)

    def _alternative_kinds(self) -> list[tuple[int, int, float, int]]:
        """(kind, option, cruise speed, wait steps) of each alternative of a failed move, in order."""
        cfg = self.config
        kinds = [(1, k, self.f, 0) for k in range(1, self.view.n_options)]
        if self.sep.forecast is not None:
            slow = [fs for fs in cfg.slow_speed_fractions if fs < self.f]
            kinds += [(2, 0, fs, 0) for fs in slow]
            if slow:  # stop, then creep (slower than creeping on at the parent's speed)
                kinds.append((4, 0, min(slow), -1))
            K, _ = _wait_grid(cfg)
            kinds += [(3, 0, self.f, k) for k in range(1, K + 1)]
        return kinds

    # -- checking (vectorised)
    def check(self, batch: np.ndarray) -> np.ndarray:
        """Check a batch of moves; stores the configuration of every move that passes. Returns (M,) bool."""
        if self.compiled:
            return self._check_fast(batch)
        view = self.view
        par = self.parent[batch]
        cv = self.node[batch]
        b = self.branch[batch]
        q_par = self.q[par]
        target = view.align(view.ik[cv, b], q_par)
        pre = self.qset[batch]
        if pre.any():  # a speculative chain: its configurations were aligned one after the other
            target[pre] = self.q[batch[pre]]
        ok = np.ones(batch.size, dtype=bool)
        # static scene: moves the roadmap checked (same branch, edge bit, the same move) need nothing more
        same = self.same[batch].copy()
        pn = self.node[par]
        pb = self.branch[par]
        chk = np.flatnonzero(same)
        if chk.size:
            ref = view.ik[pn[chk], pb[chk]]
            ref_t = view.align(view.ik[cv[chk], b[chk]], ref)
            moved = np.abs((ref_t - ref) - (target[chk] - q_par[chk])).max(axis=1) > 1e-9
            same[chk[moved]] = False
        todo = np.flatnonzero(~same)
        if todo.size:
            ok[todo] = (
                view.static_check(pn[todo], pb[todo], cv[todo], b[todo], q_par[todo], target[todo]) == 1
            )
        if self.sep.forecast is not None:
            live = np.flatnonzero(ok)
            if live.size:
                ok[live] = self._check_forecast(
                    batch[live], par[live], cv[live], b[live], q_par[live], target[live]
                )
        good = batch[ok]
        self.q[good] = target[ok]
        self.status[batch] = np.where(ok, 1, 2)
        return ok

    def _check_fast(self, batch: np.ndarray) -> np.ndarray:
        """:meth:`check` with the compiled set-up (:func:`app.planning._kernels.check_prepare`) and the
        compiled move check called directly: the same checks in the same order, the same result."""
        view = self.view
        sep = self.sep
        target, same, q_par, pts, cen, rad, fl, hold, end, waits, rows, par, stored = _kernels.check_prepare(
            batch, self._k_state, view.k_ik, view.k_limits, view.k_tables, self._start_k,
            -2 if self.goal is None else self.goal, self.hold_s > 0,
        )  # fmt: skip
        M = batch.size
        target_all = target
        ok = np.ones(M, dtype=bool)
        if not same.all():
            todo = np.flatnonzero(~same)
            pt, st = par[todo], batch[todo]
            res = view.static_check(
                self.node[pt], self.branch[pt], self.node[st], self.branch[st], q_par[todo], target[todo],
                same_move=stored[todo],
            )  # fmt: skip
            ok[todo] = res == 1
        if sep.forecast is not None:
            geo = sep.kernel
            assert geo is not None  # a compiled run's separation is compiled too
            dep = fl[0]
            # waits: the parent must be able to stand still until the departure (checked once per parent)
            waits &= ok
            if waits.any():
                waiting = np.flatnonzero(waits)
                wp = par[waiting]
                wt = np.unique(wp[np.isnan(self.wait_ok[wp])])
                if wt.size:
                    self._check_waits(wt)
                ok[waiting] = dep[waiting] < self.wait_ok[wp] - _EPS_T
            live = None if ok.all() else np.flatnonzero(ok)
            if live is None or live.size:
                if live is not None:
                    q_par, target, pts, cen, rad, hold, end, rows = (
                        q_par[live], target[live], pts[live], cen[live], rad[live], hold[live], end[live],
                        rows[live],
                    )  # fmt: skip
                    fl = np.ascontiguousarray(fl[:, live])
                # the fields of Moves, packed (built as a plain tuple: this runs once per batch)
                moves = (q_par, target, pts, cen, rad, rows, *fl, end, hold)
                res, n_samples, n_exact = _kernels.moves_separation_ok(
                    moves, view.k_tables, view.k_motion, float(self.hold_s), sep.k_requirement,
                    sep.k_forecast, geo.robot, geo.person,
                )  # fmt: skip
                sep.samples += n_samples
                sep.exact_samples += n_exact
                if live is None:
                    ok = res
                else:
                    ok[live] = res
        _kernels.check_store(batch, ok, target_all, self.q, self.status)
        return ok

    def _check_waits(self, todo: np.ndarray) -> None:
        """Until when standing still at each of the checked states ``todo`` is safe (``wait_ok``)."""
        cfg = self.config
        K, sub = _wait_grid(cfg)
        n_w = K * sub
        sep = self.sep
        geo = sep.kernel
        if self.compiled and geo is not None:  # the samples and their requirement compiled
            view = self.view
            qs, t_all, req, cen, rad, ts = _kernels.wait_samples(
                todo, self._k_state, view.k_tables, self._start_k, n_w, cfg.wait_step_s / sub,
                sep.k_requirement, sep.k_forecast,
            )  # fmt: skip
            ok, exact = _kernels.sample_separation_ok(
                qs,
                t_all,
                req,
                cen,
                rad,
                True,
                _NO_IDS,
                0,
                sep.k_forecast,
                geo.robot,
                geo.person,
                sep.k_requirement[1],
            )
            sep.samples += t_all.size
            sep.exact_samples += exact
            _kernels.wait_finish(todo, ok, ts, self.wait_ok)
            return
        ts = self.t[todo][:, None] + (cfg.wait_step_s / sub) * np.arange(1, n_w + 1)
        rep = np.repeat(np.arange(todo.size), n_w)
        _, cen_w, rad_w = self._parent_geometry(todo)
        res_w = self.sep.check(
            self.q[todo][rep], ts.reshape(-1), np.zeros(rep.size), np.zeros(rep.size), cen_w[rep], rad_w[rep]
        )
        res_w = res_w.reshape(todo.size, -1)
        first_bad = ts[np.arange(todo.size), np.argmin(res_w, axis=1)]
        self.wait_ok[todo] = np.where(res_w.all(axis=1), np.inf, first_bad)

    def _parent_geometry(self, par: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        view = self.view
        pn = self.node[par]
        pb = self.branch[par]
        on = pn >= 0
        if on.all():
            return view.pts_all[pn, pb], view.cen_all[pn, pb], view.rad_all[pn, pb]
        pn, pb = pn.clip(0), pb.clip(0)
        pts = np.where(on[:, None, None], view.pts_all[pn, pb], self.start_pts[None])
        cen = np.where(on[:, None, None], view.cen_all[pn, pb], self.start_cen[None])
        rad = np.where(on[:, None], view.rad_all[pn, pb], self.start_rad[None])
        return pts, cen, rad

    def _check_forecast(
        self,
        idx: np.ndarray,
        par: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        q_par: np.ndarray,
        target: np.ndarray,
    ) -> np.ndarray:
        """Moves against the forecast, with the waits before them, in one vectorised check (the NumPy
        reference of :meth:`_check_fast`: a run is compiled whenever its planner's checks are)."""
        view = self.view
        cfg = self.config
        sep = self.sep
        ok = np.ones(idx.size, dtype=bool)
        # waits: the parent must be able to stand still until the departure (checked once per parent)
        dep = self.dep[idx]
        waiting = np.flatnonzero(dep > self.t[par] + _EPS_T)
        todo = np.zeros(0, dtype=np.int64)
        parts: list[tuple[np.ndarray, ...]] = []
        if waiting.size:
            wp = par[waiting]
            todo = np.unique(wp[np.isnan(self.wait_ok[wp])])
            if todo.size:
                K, sub = _wait_grid(cfg)
                n_w = K * sub
                ts = self.t[todo][:, None] + (cfg.wait_step_s / sub) * np.arange(1, n_w + 1)
                rep = np.repeat(np.arange(todo.size), n_w)
                _, cen_w, rad_w = self._parent_geometry(todo)
                parts.append(
                    (
                        self.q[todo][rep],
                        ts.reshape(-1),
                        np.zeros(rep.size),
                        np.zeros(rep.size),
                        cen_w[rep],
                        rad_w[rep],
                    )
                )
        n_wait = parts[0][0].shape[0] if parts else 0
        pts, cen, rad = self._parent_geometry(par)
        hold = cv == self.goal if self.goal is not None else np.full(idx.size, self.hold_s > 0)
        sel, owner, *samples = view.move_samples(
            sep,
            q_par,
            pts,
            cen,
            rad,
            cv,
            b,
            target,
            dep,
            self.h[idx],
            self.u0[idx],
            self.L[idx],
            self.end[idx],
            self.fc[idx],
            hold,
            self.hold_s,
        )
        parts.append(tuple(samples))
        # groups: every wait sample on its own (the first unsafe instant matters), then each move's samples
        groups = [np.arange(n_wait)] if n_wait else []
        groups.append(owner + n_wait)
        if len(parts) > 1:
            res = sep.check(*(np.concatenate(x) for x in zip(*parts, strict=True)), np.concatenate(groups))
        else:
            res = sep.check(*parts[0], groups[0])
        if todo.size:
            res_w = res[:n_wait].reshape(todo.size, -1)
            t_w = parts[0][1].reshape(todo.size, -1)
            first_bad = t_w[np.arange(todo.size), np.argmin(res_w, axis=1)]
            self.wait_ok[todo] = np.where(res_w.all(axis=1), np.inf, first_bad)
        if waiting.size:
            ok[waiting] = dep[waiting] < self.wait_ok[par[waiting]] - _EPS_T
        if sel.size:
            ok[sel] &= np.bincount(owner, weights=~res[n_wait:], minlength=sel.size) == 0
        return ok

    def reconstruct(self, sid: int) -> Plan:
        chain = []
        s = sid
        while s >= 0:
            chain.append(s)
            s = int(self.parent[s])
        chain.reverse()
        if len(chain) > 1:
            a, c = chain[0], chain[1]
            if self.t[c] <= self.t[a] + _EPS_T and np.allclose(self.q[a], self.q[c], atol=1e-12):
                chain = chain[1:]  # the start is a roadmap node: one waypoint, labelled with the node
        times, qs, nodes = [], [], []
        for i, s in enumerate(chain):
            if i > 0:
                par = chain[i - 1]
                if self.dep[s] > self.t[par] + _EPS_T:  # waited at the parent
                    times.append(float(self.dep[s]))
                    qs.append(self.q[par])
                    nodes.append(int(self.node[par]))
            times.append(float(self.t[s]))
            qs.append(self.q[s])
            nodes.append(int(self.node[s]))
        return Plan(times=np.array(times), q=np.array(qs), nodes=np.array(nodes))
