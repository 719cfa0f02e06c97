"""Shortcuts of the search's path (part of :class:`app.planning.search.planner.Planner`): runs of waypoints
replaced greedily by straight joint moves that keep the forecast clearance, then re-timed."""

from __future__ import annotations

import numpy as np

from app.planning.search.profiles import (
    _profile_arrays,
    _profile_py,
)
from app.planning.search.separation import _Separation
from app.planning.trajectory import Plan


class _Shortcuts:
    """The shortcut pass of :class:`~app.planning.search.planner.Planner`."""

    # ------------------------------------------------------------------------------------------ shortcut
    def _shortcut(self, waypoints: Plan, sep: _Separation, *, hold_s: float) -> Plan | None:
        """The search's path with runs of waypoints replaced by single straight joint moves, re-timed.

        Roadmap paths follow straight TCP segments between samples, so in joint space they zig-zag and the
        spline through them has to slow down at every reversal. From each kept waypoint (the start first)
        the farthest later waypoint is taken that one straight joint move reaches (a) free of the static
        scene and of self-collision (:meth:`_static_free`) and (b) keeping the forecast clearance over time,
        checked as the search checks its moves (:meth:`_moves_ok`: the path-speed profile from the path
        speed reached there, braking to rest into the goal, with the goal hold). The move straight from the
        start to the goal is checked first (on a free way the only check); after that, all candidates of a
        waypoint are checked in one vectorised call, together with the search's own move to the next
        waypoint (re-timed, at the cruise speed or one of ``slow_speed_fractions``), which is kept where no
        shortcut passes. If even that fails at its new time, the whole shortcut is given up. After
        ``shortcut_rounds`` such calls one more call checks the move straight to the goal and, as the
        alternative, the rest of the search's moves re-timed one after the other (the last one also slower),
        so the cost stays bounded: at most ``shortcut_rounds + 1`` vectorised forecast checks and
        ``shortcut_rounds + 1`` static ones.

        Waits stay as they are: only the part after the last wait is shortened (its moves depart from rest
        at the wait's end, as the search timed them); the part before keeps the search's times.

        Returns:
            The shortened plan (times from the profile), or None when nothing was shortened or a move failed.
            It is only a candidate: the caller fits and verifies it (:meth:`_finish`) like any plan and
            falls back to ``waypoints``.
        """
        cfg = self.config
        times, q, nodes = waypoints.times, waypoints.q, waypoints.nodes
        still = np.flatnonzero(np.all(np.abs(np.diff(q, axis=0)) <= 1e-12, axis=1))  # waits
        s0 = int(still[-1]) + 1 if still.size else 0
        qs = q[s0:]
        n = qs.shape[0]
        if n < 3:
            return None
        pts, cen, rad = self._points_and_spheres(qs)
        f, A = cfg.speed_fraction, self._A
        speeds = np.array([f, *sorted((x for x in cfg.slow_speed_fractions if x < f), reverse=True)])

        def attempt(
            ia: np.ndarray, js: np.ndarray, fc: np.ndarray, t_dep: np.ndarray, u: np.ndarray
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """Moves qs[ia] -> qs[js] departing at t_dep with path speed u at cruise speeds fc: (ok, h, exit
            speed). The static scene is checked for shortcuts only (a move to the next waypoint is the
            search's own)."""
            L = self._metric(qs[js] - qs[ia])
            end = js == n - 1
            u0 = np.minimum(u, fc)
            h, u1, _ = _profile_arrays(u0, L, fc, A, end)
            h = np.where(L > 1e-12, np.maximum(h, cfg.min_edge_s), h)
            ok = np.ones(js.size, dtype=bool)
            cut = np.flatnonzero(js > ia + 1)
            if cut.size:
                ok[cut] = self._static_free(qs[ia[cut]], qs[js[cut]])
            live = np.flatnonzero(ok)
            if live.size and sep.forecast is not None:
                al, jl = ia[live], js[live]
                ok[live] = self._moves_ok(
                    sep,
                    qs[al],
                    pts[al],
                    cen[al],
                    rad[al],
                    np.zeros(live.size, dtype=np.int64),
                    np.zeros(live.size, dtype=np.int64),
                    qs[jl],
                    t_dep[live],
                    h[live],
                    u0[live],
                    L[live],
                    end[live],
                    fc[live],
                    end[live],
                    hold_s,
                    target_geometry=(pts[jl], cen[jl], rad[jl]),
                )
            return ok, h, u1

        keep, t_new = [0], [float(times[s0])]
        i, t, u = 0, float(times[s0]), 0.0
        rounds = 0
        while i < n - 1 and rounds < cfg.shortcut_rounds:
            j, top = -1, n
            if rounds == 0 and i + 2 <= n - 1:  # straight to the goal: on a free way the only check
                ok, h, u1 = attempt(
                    np.array([i]), np.array([n - 1]), speeds[:1], np.array([t]), np.array([u])
                )
                rounds += 1
                if ok[0]:
                    j, hj, uj = n - 1, float(h[0]), float(u1[0])
                top = n - 1
            if j < 0:
                if rounds >= cfg.shortcut_rounds:
                    break
                # every shortcut from here (the farthest that passes wins) and, in the same check, the
                # search's own move to the next waypoint at each speed (the fastest that passes is the
                # fallback)
                cuts = np.arange(i + 2, top)
                js = np.concatenate([cuts, np.full(speeds.size, i + 1)])
                m = js.size
                fc = np.concatenate([np.full(cuts.size, f), speeds])
                ok, h, u1 = attempt(np.full(m, i), js, fc, np.full(m, t), np.full(m, u))
                rounds += 1
                good = np.flatnonzero(ok)
                if good.size == 0:
                    return None
                passed_cuts = good[good < cuts.size]
                k = int(passed_cuts[-1]) if passed_cuts.size else int(good[0])
                j, hj, uj = int(js[k]), float(h[k]), float(u1[k])
            i, t, u = j, t + hj, uj
            keep.append(j)
            t_new.append(t)
        if keep[-1] == len(keep) - 1:
            return None  # nothing shortened (nor would the rest be)
        if i < n - 1:
            # the rounds are used up: straight to the goal, or else the rest of the search's moves re-timed
            # at the cruise speed one after the other (the last, into the goal, also slower), in one call
            rest = np.arange(i, n - 1)
            dep, u_in = np.empty(rest.size), np.empty(rest.size)
            t_k, u_k = t, u
            for k, a in enumerate(rest.tolist()):
                L = float(self._metric(qs[a + 1] - qs[a]))
                h_k, u_next, _ = _profile_py(u_k, L, f, A, a + 1 == n - 1)
                dep[k], u_in[k] = t_k, u_k
                t_k, u_k = t_k + (max(h_k, cfg.min_edge_s) if L > 1e-12 else h_k), u_next
            d = int(rest.size > 1)  # the move straight to the goal first, when it is a shortcut
            slow = speeds[1:]
            m = rest.size
            ia = np.concatenate([np.full(d, i), rest, np.full(slow.size, n - 2)])
            js = np.concatenate([np.full(d, n - 1), rest + 1, np.full(slow.size, n - 1)])
            ok, h, _ = attempt(
                ia,
                js,
                np.concatenate([np.full(d + m, f), slow]),
                np.concatenate([np.full(d, t), dep, np.full(slow.size, dep[-1])]),
                np.concatenate([np.full(d, u), u_in, np.full(slow.size, u_in[-1])]),
            )
            chain = ok[d : d + m].copy()
            h_chain = h[d : d + m].copy()
            last = np.flatnonzero(ok[d + m :])
            if not chain[-1] and last.size:  # the goal reached more slowly
                chain[-1], h_chain[-1] = True, h[d + m + int(last[0])]
            if d and ok[0]:
                keep.append(n - 1)
                t_new.append(t + float(h[0]))
            elif chain.all():
                keep.extend((rest + 1).tolist())
                t_new.extend((dep + h_chain).tolist())
            else:
                return None
        idx = np.concatenate([np.arange(s0), s0 + np.asarray(keep)])
        return Plan(
            times=np.concatenate([times[:s0], t_new]),
            q=q[idx],
            nodes=nodes[idx],
        )
