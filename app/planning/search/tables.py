"""The planner's precomputed tables and static checks (part of :class:`app.planning.search.planner.Planner`):
capsule points and spheres per node and branch, the per-edge move tables, the static scene check with its
memo, and the heuristic (static time-to-go)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from app.planning import _kernels
from app.planning.roadmap import NUM_BRANCHES
from app.planning.search.config import (
    _TWO_PI,
)

if TYPE_CHECKING:
    from scipy.sparse import csr_matrix


class _StaticTables:
    """Set-up tables, static checks and the heuristic of :class:`~app.planning.search.planner.Planner`."""

    # ------------------------------------------------------------------------------------------ set-up
    def _points_and_spheres(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Capsule end points (B, 2L, 3) of configurations (B, 6), and a bounding sphere per capsule:
        centres (B, L, 3) and radii (B, L)."""
        a, b, r = self.collision.robot_capsules(np.asarray(q, dtype=np.float64).reshape(-1, 6))
        pts = np.concatenate([a, b], axis=1)
        return pts, 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=-1) + r

    def _lever_model(self) -> tuple[np.ndarray, np.ndarray]:
        """Per joint, a bound (6,) on any robot point's distance from its axis (m), and per capsule the last
        joint that moves it (L,) (1..6). For the UR5e capsule model both come from the geometry; for any other
        model every joint moves every capsule with ``lever_arm_m``."""
        from app.planning.collision import ROBOT_LINKS
        from app.planning.roadmap import _LINK_LAST_JOINT, lever_arms

        cell = getattr(self.collision, "cell", None)
        if cell is not None and self._n_caps == len(ROBOT_LINKS):
            return lever_arms(cell), np.array([_LINK_LAST_JOINT[n] for n in ROBOT_LINKS])
        return np.full(6, self.config.lever_arm_m), np.full(self._n_caps, 6)

    def _build_edge_tables(self) -> None:
        """Per CSR entry e = (u -> v) and parent branch b: v's branches nearest first (E, 8, R), the straight
        move lengths (E, 8, R) and whether the roadmap's static edge check covers the move (E, 8, R)."""
        rm = self.roadmap
        E = rm.indices.shape[0]
        R = self._R
        src = np.repeat(np.arange(rm.num_nodes), np.diff(rm.indptr))
        self._ord_tab = np.zeros((E, NUM_BRANCHES, R), dtype=np.int8)
        self._L_tab = np.full((E, NUM_BRANCHES, R), np.inf)
        self._same_tab = np.zeros((E, NUM_BRANCHES, R), dtype=bool)
        bidx = np.arange(NUM_BRANCHES)
        for c0 in range(0, E, 2048):
            c1 = min(E, c0 + 2048)
            u, v = src[c0:c1], rm.indices[c0:c1]
            qu = self._ik[u]  # (c, 8, 6) parent branches
            aligned = self._align(self._ik[v][:, None, :, :], qu[:, :, None, :])  # (c, 8p, 8s, 6)
            L = self._metric(aligned - qu[:, :, None, :])
            L = np.where(self._valid[v][:, None, :], L, np.inf)
            order = np.argsort(L, axis=2, kind="stable")[:, :, :R]
            self._ord_tab[c0:c1] = order
            self._L_tab[c0:c1] = np.take_along_axis(L, order, axis=2)
            bits = ((rm.edge_branches[c0:c1, None].astype(np.int64) >> bidx) & 1).astype(bool)  # (c, 8)
            same = order == bidx[None, :, None]
            same &= np.take_along_axis(bits[:, None, :].repeat(NUM_BRANCHES, 1), order, axis=2)
            same &= self._valid[u][:, :, None]
            self._same_tab[c0:c1] = same
        self._L_tab.setflags(write=False)
        # the same tables with one row per (CSR entry, parent branch): row = e * 8 + b
        self._ord_flat = self._ord_tab.reshape(E * NUM_BRANCHES, R).astype(np.int64)
        self._L_flat = self._L_tab.reshape(E * NUM_BRANCHES, R)
        self._same_flat = self._same_tab.reshape(E * NUM_BRANCHES, R)
        self._indptr = rm.indptr
        self._indices = rm.indices
        self._src_state = (src[:, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)).reshape(-1)

    def _static_box_bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """World-axis bounds (B, 3) x 2 of the static boxes and the (link, box) pairs that count, if known."""
        boxes = getattr(self.collision, "static_boxes", None)
        pairs = getattr(self.collision, "static_pairs", None)
        if boxes is None or pairs is None or len(boxes) == 0:
            return None
        lo, hi = [], []
        for box in boxes:
            c, hs, yaw = np.asarray(box.center), np.asarray(box.size) / 2.0, float(box.yaw)
            ext = np.array(
                [
                    abs(math.cos(yaw)) * hs[0] + abs(math.sin(yaw)) * hs[1],
                    abs(math.sin(yaw)) * hs[0] + abs(math.cos(yaw)) * hs[1],
                    hs[2],
                ]
            )
            lo.append(c - ext)
            hi.append(c + ext)
        return np.array(lo), np.array(hi), np.asarray(pairs, dtype=bool)

    # ------------------------------------------------------------------------------------------ helpers
    def _align(self, q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
        """2 pi-shift every joint of ``q`` (..., 6) next to ``q_ref`` (broadcastable), within the limits."""
        if self._k_align is not None and q.ndim == 2 and q.shape == q_ref.shape:
            return _kernels.align_rows(_kernels.as_f64(q), _kernels.as_f64(q_ref), *self._k_align)
        nearest = q + _TWO_PI * np.rint((q_ref - q) * (1.0 / _TWO_PI))
        nearest = np.where(nearest > self.q_max, nearest - _TWO_PI, nearest)
        nearest = np.where(nearest < self.q_min, nearest + _TWO_PI, nearest)
        bad = (nearest > self.q_max) | (nearest < self.q_min)
        return np.where(bad, q, nearest)

    def _metric(self, dq: np.ndarray) -> np.ndarray:
        """Straight-move length (...,) in seconds at full joint speed: max_j |dq_j| / qd_max_j."""
        return np.max(np.abs(dq) * self._inv_qd, axis=-1)

    def _within_limits(self, q: np.ndarray) -> np.ndarray:
        return np.all((q >= self.q_min - 1e-9) & (q <= self.q_max + 1e-9), axis=-1)

    def _static_bad(self, q: np.ndarray, segments: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Configurations (n, 6) in collision with the static scene or themselves, or beyond the limits.

        ``segments``: the robot's segments for ``q`` (:meth:`CollisionModel.robot_segments`), if known."""
        bad = ~self._within_limits(q)
        sb = self._static_boxes
        kw = {} if segments is None else {"segments": segments}
        if sb is None:
            need = np.arange(q.shape[0])
        else:
            blo, bhi, pairs = sb
            if segments is None:
                a, b, r = self.collision.robot_capsules(q)
            else:
                a, r = segments[0].transpose(2, 0, 1), self._robot_r
                b = a + segments[1].transpose(2, 0, 1)
            lo = np.minimum(a, b) - r[:, None]  # (n, L, 3)
            hi = np.maximum(a, b) + r[:, None]
            g = np.maximum(
                np.maximum(blo[None, None] - hi[:, :, None], lo[:, :, None] - bhi[None, None]), 0.0
            )
            gap = np.sqrt(np.einsum("nlbk,nlbk->nlb", g, g))
            near = (gap <= self.config.static_margin_m + 1e-9) & pairs[None]
            need = np.flatnonzero(near.any(axis=(1, 2)))
        if need.size:
            sub = {} if segments is None else {"segments": (segments[0][..., need], segments[1][..., need])}
            bad[need] |= self.collision.in_static_collision(
                q[need], margin_m=self.config.static_margin_m, **sub
            )
        bad |= self.collision.self_collision(q, **kw)
        return bad

    def _static_free(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """Whether the straight joint moves qa[k] -> qb[k] ((M, 6) each) are free of the static scene and
        of self-collision at configurations at most ``check_step_rad`` apart (both ends included)."""
        M = qa.shape[0]
        if M == 0:
            return np.ones(0, dtype=bool)
        n = np.maximum(np.ceil(np.max(np.abs(qb - qa), axis=1) / self.config.check_step_rad), 1).astype(
            np.int64
        )
        idx = np.repeat(np.arange(M), n + 1)
        start = np.cumsum(n + 1) - (n + 1)
        frac = (np.arange(idx.shape[0]) - start[idx]) / n[idx]
        q = qa[idx] + frac[:, None] * (qb - qa)[idx]
        bad = self._static_bad(q)
        return np.bincount(idx, weights=bad, minlength=M) == 0

    def _static_cached(
        self,
        u: np.ndarray,
        bu: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        q_par: np.ndarray,
        target: np.ndarray,
        *,
        same_move: np.ndarray | None = None,
    ) -> np.ndarray:
        """Static check (1 free, -1 blocked) of moves q_par -> target that the roadmap did not check, from
        node ``u`` at branch ``bu`` (-1: the start) to node ``cv`` at branch ``b``; memoised per
        (node, branch, node, branch) when the move is the one between the stored branch configurations
        (``same_move`` (M,) where the caller knows it).

        The memo belongs to the planner (never the roadmap) and only ever gains entries that are pure
        functions of the roadmap, so concurrent queries may share it.
        """
        out = np.zeros(u.shape[0], dtype=np.int8)
        keys: list[tuple[int, int, int, int] | None] = [None] * u.shape[0]
        if same_move is not None:
            on = np.flatnonzero(same_move)
            same_move = np.ones(on.size, dtype=bool)
        else:
            on = np.flatnonzero(u >= 0)
            if on.size:
                ref = self._ik[u[on], bu[on]]
                ref_t = self._align(self._ik[cv[on], b[on]], ref)
                same_move = np.abs((ref_t - ref) - (target[on] - q_par[on])).max(axis=1) <= 1e-9
        if on.size:
            for i in on[same_move].tolist():
                key = (int(u[i]), int(bu[i]), int(cv[i]), int(b[i]))
                keys[i] = key
                hit = self._static_memo.get(key)
                if hit is not None:
                    out[i] = hit
        todo = np.flatnonzero(out == 0)
        if todo.size:
            res = np.where(self._static_free(q_par[todo], target[todo]), 1, -1).astype(np.int8)
            out[todo] = res
            for i, val in zip(todo.tolist(), res.tolist(), strict=True):
                if keys[i] is not None:
                    self._static_memo[keys[i]] = val
        return out

    def _heuristic_table(self, goal: int) -> np.ndarray:
        """h (N, 8): time lower bound (s) from every node branch to the goal at cruise speed.

        The larger of two admissible bounds: the straight joint-space move to the goal's nearest branch, and
        the static time-to-go over the search's own moves (:meth:`_static_to_go`, a backward Dijkstra from
        the goal's branches). A branch from which no move sequence reaches the goal gets +inf (pruned).
        """
        tab = self._h_cache.get(goal)
        if tab is None:
            straight = self._heuristic(self._ik.reshape(-1, 6), goal)
            tab = np.maximum(straight, self._static_to_go(goal)).reshape(-1, NUM_BRANCHES)
            tab.setflags(write=False)
            self._h_cache[goal] = tab
            self._next_cache[goal] = self._next_rows(tab)
            self._next_cache_k[goal] = np.asarray(self._next_cache[goal], dtype=np.int64)
        return tab

    def _next_rows(self, h: np.ndarray) -> list[int]:
        """Per node branch (index ``node * 8 + branch``), the option-table row of the move a search would
        try first that is best by ``L / cruise + h`` (the next step of the static shortest path through the
        nearest-branch moves), or -1: the speculative chain (:meth:`_Run.speculate`) follows it."""
        rows = np.arange(self._L_flat.shape[0])
        src = self._src_state
        cost = (
            self._L_flat[:, 0] / self.config.speed_fraction
            + h.reshape(-1)[self._indices[rows // NUM_BRANCHES] * NUM_BRANCHES + self._ord_flat[:, 0]]
        )
        order = np.lexsort((cost, src))
        first = order[np.r_[True, src[order][1:] != src[order][:-1]]]
        first = first[np.isfinite(cost[first])]
        out = np.full(self.roadmap.num_nodes * NUM_BRANCHES, -1, dtype=np.int64)
        out[src[first]] = first
        return out.tolist()

    def _reverse_move_graph(self) -> csr_matrix:
        """The search's moves (node, branch) -> (node, branch) as a sparse matrix of the *reversed* graph:
        entry [dst, src] = the move's length (s at full joint speed, :attr:`_L_tab`) / cruise speed."""
        rm = self.roadmap
        E, R = self._L_tab.shape[0], self._R
        S = rm.num_nodes * NUM_BRANCHES
        src_node = np.repeat(np.arange(rm.num_nodes), np.diff(rm.indptr))
        src = (src_node[:, None, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)[None, :, None]).repeat(R, 2)
        dst = rm.indices[:, None, None] * NUM_BRANCHES + self._ord_tab.astype(np.int64)
        # a hair shorter than the timed moves: round-off never makes the bound exceed a path's duration
        cost = self._L_tab * ((1.0 - 1e-12) / self.config.speed_fraction)
        keep = np.isfinite(cost) & self._valid[src_node][:, :, None]
        assert src.shape == dst.shape == cost.shape == (E, NUM_BRANCHES, R)
        from scipy.sparse import csr_matrix  # scipy is only loaded with a planner

        return csr_matrix((cost[keep], (dst[keep], src[keep])), shape=(S, S))

    def _to_goal_neighbours(self, goal: int) -> np.ndarray:
        """(N, 8) static time (s, cruise speed, as :meth:`_static_to_go`) from every node branch to a node
        branch that has a move into ``goal`` (0 there; +inf where none can be reached)."""
        rm = self.roadmap
        entries = np.flatnonzero(rm.indices == goal)
        src = np.searchsorted(rm.indptr, entries, side="right") - 1
        states = (src[:, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)).reshape(-1)
        rows = (entries[:, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)).reshape(-1)
        states = states[np.isfinite(self._L_flat[rows, 0]) & self._valid.reshape(-1)[states]]
        if states.size == 0:
            return np.full((rm.num_nodes, NUM_BRANCHES), np.inf)
        from scipy.sparse.csgraph import dijkstra

        d = dijkstra(self._rev_graph, directed=True, indices=states, min_only=True)
        return np.asarray(d).reshape(-1, NUM_BRANCHES)

    def _static_to_go(self, goal: int) -> np.ndarray:
        """Static time-to-go (N * 8,) in s from every node branch to any valid branch of ``goal`` over the
        moves the search can take (nearest ``max_branch_tries`` branches per edge), each timed at the cruise
        speed without acceleration: a lower bound of any search path's duration (its moves last at least
        their length / cruise speed), +inf where the goal cannot be reached."""
        sources = goal * NUM_BRANCHES + np.flatnonzero(self._valid[goal])
        if sources.size == 0:
            return np.full(self.roadmap.num_nodes * NUM_BRANCHES, np.inf)
        from scipy.sparse.csgraph import dijkstra

        return dijkstra(self._rev_graph, directed=True, indices=sources, min_only=True)

    def _heuristic(self, q: np.ndarray, goal: int) -> np.ndarray:
        G = self._ik[goal][self._valid[goal]]
        inv = self._inv_qd / self.config.speed_fraction
        out = np.full(q.shape[0], np.inf)
        for g in G:  # at most 8 branches
            d = q - g
            d = np.abs(d - _TWO_PI * np.rint(d * (1.0 / _TWO_PI)))
            np.minimum(out, np.max(d * inv, axis=-1), out=out)
        return out
