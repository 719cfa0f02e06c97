"""The move check against the forecast (part of :class:`app.planning.search.planner.Planner`): the broad
phase over whole moves, the NumPy and compiled checks and the samples of a move."""

from __future__ import annotations

import math

import numpy as np

from app.planning import _kernels
from app.planning.roadmap import NUM_BRANCHES
from app.planning.search.profiles import (
    _per_move,
    _profile_arrays,
    _profile_samples,
)
from app.planning.search.separation import _Separation


class _MoveChecks:
    """The move checks of :class:`~app.planning.search.planner.Planner`."""

    def _moves_ok(
        self,
        sep: _Separation,
        q_a: np.ndarray,
        pts_a: np.ndarray,
        cen_a: np.ndarray,
        rad_a: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        target: np.ndarray,
        t_dep: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        f: np.ndarray,
        hold: np.ndarray,
        hold_s: float,
        *,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Check moves (and the hold at their end where ``hold``) against the forecast; boolean (M,).
        The arguments are those of :meth:`_move_samples`."""
        M = q_a.shape[0]
        result = np.ones(M, dtype=bool)
        if sep.forecast is None or M == 0:
            return result
        if sep.kernel is not None:
            return self._moves_ok_compiled(
                sep,
                q_a,
                pts_a,
                cen_a,
                rad_a,
                cv,
                b,
                target,
                t_dep,
                h,
                u0,
                L,
                end_rest,
                f,
                hold,
                hold_s,
                target_geometry=target_geometry,
            )
        sel, owner, q, t, v, w, cen, rad = self._move_samples(
            sep,
            q_a,
            pts_a,
            cen_a,
            rad_a,
            cv,
            b,
            target,
            t_dep,
            h,
            u0,
            L,
            end_rest,
            f,
            hold,
            hold_s,
            target_geometry=target_geometry,
        )
        if sel.size:
            ok_s = sep.check(q, t, v, w, cen, rad, owner)
            result[sel] = np.bincount(owner, weights=~ok_s, minlength=sel.size) == 0
        return result

    def _move_prep(
        self,
        q_a: np.ndarray,
        pts_a: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        target: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        f: np.ndarray,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> tuple[np.ndarray, ...]:
        """Per move (arguments as in :meth:`_move_samples`): the joint step ``dq`` (M, 6), how far the
        joints can carry each capsule ``travel`` (M, L), the target's spheres ``cen_b`` (M, L, 3) / ``rad_b``
        (M, L), the profile's duration and peak speed, its clock (profile seconds per real second),
        ``kv`` (m/s per unit of path speed) and ``kw`` (the fastest joint's rad/s per unit of path speed)."""
        M = q_a.shape[0]
        dq = target - q_a
        cum = np.concatenate([np.zeros((M, 1)), np.cumsum(np.abs(dq) * self._lever, axis=1)], axis=1)
        travel = cum[:, self._moved_by]  # (M, L): how far joints 1..J(l) can carry capsule l
        if target_geometry is None:
            pts_b, cen_b, rad_b = self._pts_all[cv, b], self._cen_all[cv, b], self._rad_all[cv, b]
        else:
            pts_b, cen_b, rad_b = target_geometry
        chord = np.max(np.linalg.norm(pts_b - pts_a, axis=-1), axis=-1)
        dur, _, peak = _profile_arrays(u0, L, f, self._A, end_rest)
        moving = L > 1e-12
        clock = np.where(h > 0, dur / np.maximum(h, 1e-12), 1.0)  # profile seconds per real second
        # m/s per unit of path speed
        kv = np.where(moving, self.config.speed_factor * chord * clock / np.maximum(L, 1e-12), 0.0)
        # the joints move along dq in proportion to the path: the fastest one at max|dq| per unit of it
        kw = np.where(moving, self.config.stopping.braking_speed(dq) * clock / np.maximum(L, 1e-12), 0.0)
        return dq, travel, cen_b, rad_b, dur, peak, clock, kv, kw

    def _moves_ok_compiled(
        self,
        sep: _Separation,
        q_a: np.ndarray,
        pts_a: np.ndarray,
        cen_a: np.ndarray,
        rad_a: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        target: np.ndarray,
        t_dep: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        f: np.ndarray,
        hold: np.ndarray,
        hold_s: float,
        *,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """:meth:`_moves_ok` in one compiled pass (:func:`app.planning._kernels.moves_separation_ok`): the
        same stage 0, samples and exact distances (and the same :meth:`_move_prep`); a move stops at its
        first sample that fails."""
        f64, M = _kernels.as_f64, q_a.shape[0]
        if target_geometry is None:
            tables = self._k_tables
            rows = _kernels.as_i64(np.asarray(cv) * NUM_BRANCHES + np.asarray(b))
        else:
            tables = _kernels.pack(_kernels.CapsuleBounds(*(f64(x) for x in target_geometry)))
            rows = np.arange(M, dtype=np.int64)
        moves = _kernels.pack(
            _kernels.Moves(
                q_a=f64(q_a),
                target=f64(target),
                pts_a=f64(pts_a),
                cen_a=f64(cen_a),
                rad_a=f64(rad_a),
                rows=rows,
                t_dep=_per_move(t_dep, M),
                h=f64(h),
                u0=f64(u0),
                L=f64(L),
                f=_per_move(f, M),
                end_rest=_per_move(end_rest, M, np.bool_),
                hold=_per_move(hold, M, np.bool_),
            )
        )
        geo = sep.kernel
        assert geo is not None
        ok, n_samples, n_exact = _kernels.moves_separation_ok(
            moves,
            tables,
            self._k_motion,
            float(hold_s),
            sep.k_requirement,
            sep.k_forecast,
            geo.robot,
            geo.person,
        )
        sep.samples += n_samples
        sep.exact_samples += n_exact
        return ok

    def _move_samples(
        self,
        sep: _Separation,
        q_a: np.ndarray,
        pts_a: np.ndarray,
        cen_a: np.ndarray,
        rad_a: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        target: np.ndarray,
        t_dep: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        f: np.ndarray,
        hold: np.ndarray,
        hold_s: float,
        *,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, ...]:
        """The samples of the moves (and the holds at their end where ``hold``) that stage 0 cannot pass.

        Returns ``(sel (M',), owner (S,), q (S, 6), t (S,), v (S,), w (S,), cen (S, L, 3), rad (S, L))``: the
        moves that need samples and, per sample, its move (index into ``sel``), configuration, time, robot
        speed (m/s), fastest joint speed (rad/s) and the spheres that contain the robot's capsules. A move
        passes when all its samples pass.

        Per move: the start configuration ``q_a`` with its capsule points/spheres, the target roadmap node
        ``cv`` at branch ``b`` (configuration ``target``), departure, duration, entry speed (``<= f``),
        length, whether it ends at rest and its cruise speed ``f``. ``target_geometry``: the target's capsule
        points (M, 2L, 3), sphere centres (M, L, 3) and radii (M, L) when it is not a roadmap configuration
        (``cv``, ``b`` are then not used).

        The robot speed of a sample (for ``S_r + S_s``) is the largest speed the path-speed profile reaches
        between the previous sample and this one, turned into m/s with the move's largest chord (the
        furthest any capsule point travels between the two configurations) per unit of path, times
        ``speed_factor`` (arcs are longer than chords); its fastest joint's speed (for ``T_s``) is the
        same profile speed times the largest joint step per unit of path (a straight joint move: exact);
        the hold after a move is at rest.
        """
        M = q_a.shape[0]
        cfg = self.config
        A = self._A
        dq, travel, cen_b, rad_b, dur, peak, clock, kv, kw = self._move_prep(
            q_a, pts_a, cv, b, target, h, u0, L, end_rest, f, target_geometry
        )
        # stage 0: moves far from the person over their whole time window pass without samples; a capsule
        # point is within frac * T of its start and (1 - frac) * T of its end, so within
        # T / 2 + (rho_a + rho_b) / 2 of the middle of the two sphere centres
        near = sep.near_moves(
            0.5 * (cen_a + cen_b),
            0.5 * (rad_a + rad_b + travel),
            t_dep,
            t_dep + h + np.where(hold, hold_s, 0.0),
            kv * peak,
            kw * peak,
        )
        sel = np.flatnonzero(near)
        if sel.size < M:
            q_a, cen_a, rad_a, cen_b, rad_b, t_dep, h, u0, L, end_rest, f, hold, dq, travel = (
                x[sel]
                for x in (q_a, cen_a, rad_a, cen_b, rad_b, t_dep, h, u0, L, end_rest, f, hold, dq, travel)
            )
            dur, clock, kv, kw = dur[sel], clock[sel], kv[sel], kw[sel]
        M = sel.size
        # samples: the move every sample_dt_s (its end included), then the hold
        n = np.maximum(np.ceil(h / cfg.sample_dt_s - 1e-9), 1).astype(np.int64)
        n_hold_1 = max(math.ceil(hold_s / cfg.sample_dt_s - 1e-9), 0)
        tot = n + np.where(hold, n_hold_1, 0)
        owner = np.repeat(np.arange(M), tot)
        i = np.arange(owner.shape[0]) - np.repeat(np.cumsum(tot) - tot, tot) + 1
        n_o, h_o = n[owner], h[owner]
        in_move = i <= n_o
        tau = np.where(in_move, i / n_o, 1.0) * h_o
        c_o = clock[owner]
        frac, speed = _profile_samples(
            tau * c_o,
            np.where(in_move, i - 1, n_o) / n_o * h_o * c_o,
            u0[owner],
            L[owner],
            dur[owner],
            f[owner],
            A,
            end_rest[owner],
        )
        frac = np.where(in_move, frac, 1.0)
        q = q_a[owner] + frac[:, None] * dq[owner]
        t = t_dep[owner] + tau + np.where(in_move, 0.0, (i - n_o) * (hold_s / max(n_hold_1, 1)))
        v = np.where(in_move, kv[owner] * speed, 0.0)
        w = np.where(in_move, kw[owner] * speed, 0.0)
        # capsule l lies within its start sphere grown by frac * T_l and its end sphere grown by
        # (1 - frac) * T_l; take the smaller sphere
        fo = frac[:, None]
        tr = travel[owner]
        ra = rad_a[owner] + fo * tr
        rb = rad_b[owner] + (1.0 - fo) * tr
        use_a = ra <= rb
        cen = np.where(use_a[..., None], cen_a[owner], cen_b[owner])
        rad = np.where(use_a, ra, rb)
        return sel, owner, q, t, v, w, cen, rad
