"""Pass/fail of robot samples and whole moves against a forecast person (:class:`_Separation`): the
time-sampled check of the search's moves and of the verification, with its broad phase."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from app.planning import _kernels
from app.planning.search.config import (
    RobotModel,
)
from app.planning.search.profiles import (
    _NO_IDS,
)
from app.safety.ssm import SSMParams, forecast_clearance
from app.safety.stopping import UR5E_STOP, StoppingModel

if TYPE_CHECKING:
    from app.prediction.forecast import HumanForecast


class _Separation:
    """Pass/fail of robot samples (and whole moves) against a forecast person.

    Two stages, the first conservative: (0/1) a sphere per robot capsule (for a whole move one that contains
    the capsule during the move, see :meth:`Planner._moves_ok`; for a sample one known without forward
    kinematics) against a box that contains the whole person over the time window; (2) for the samples still
    close, the exact minimum surface distance robot-person
    (:meth:`app.planning.collision.CollisionModel.distance_to_human_paired`) against the pose interpolated
    at the sample's time. The boxes are precomputed once per query at the forecast's own samples (a pose
    between two samples is a blend of them, so it lies in the union of their boxes; beyond the horizon the
    last pose is held), with a sparse table for unions over longer windows.
    """

    def __init__(
        self,
        model: RobotModel,
        forecast: HumanForecast | None,
        ssm: SSMParams,
        *,
        extra_m: float,
        offsets: tuple[float, ...] = (0.0,),
        floor_m: float | None = None,
        subsets: bool = False,
        cap_ends: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        robot_r: np.ndarray | None = None,
        kernel: _kernels.KernelGeometry | None = None,
        ssm_extra: tuple[float, np.ndarray] | None = None,
        stopping: StoppingModel = UR5E_STOP,
    ) -> None:
        self.model = model
        self.forecast = forecast
        self.ssm = ssm
        #: The robot's stopping model: ``S_s`` of the clearance (:func:`app.safety.ssm.forecast_clearance`).
        self.stopping = stopping
        self.extra_m = extra_m
        #: SSM-aware search: ``(dv, extra)``, the governor's extra clearance (m) at speeds ``i * dv``
        #: (:meth:`app.safety.governor.GovernorModel.extra_clearance`), or None.
        self.ssm_extra = ssm_extra
        self.offsets = offsets
        self.floor_m = floor_m
        self.samples = 0
        self.exact_samples = 0
        self.t_static = math.inf  # from then on the person holds still and the margin is constant (s)
        self._kernel: _kernels.KernelGeometry | None = None
        if forecast is None:
            return
        m_end = float(forecast.margins[-1])
        cap = max(forecast.max_margin_m, float(forecast.margins.max()))
        grow = max(cap - m_end, 0.0) / forecast.growth_mps if forecast.growth_mps > 0 else 0.0
        self.t_static = forecast.horizon_end + grow - min(offsets)
        joints = forecast.joints  # (H, J, 3)
        r_max = float(np.max(model.human_capsules(joints[:1])[2]))
        lo = joints.min(axis=1) - r_max  # (H, 3): every capsule of the pose lies inside
        # the margin rides along as a 4th column of the upper table (unions take its maximum)
        hi = np.concatenate([joints.max(axis=1) + r_max, forecast.margins[:, None]], axis=1)
        # sparse table of unions over index ranges [i, i + 2^k)
        self._lo_tab, self._hi_tab = [lo], [hi]
        k = 1
        while (1 << k) <= lo.shape[0]:
            plo, phi = self._lo_tab[-1], self._hi_tab[-1]
            half = 1 << (k - 1)
            self._lo_tab.append(np.minimum(plo[:-half], plo[half:]))
            self._hi_tab.append(np.maximum(phi[:-half], phi[half:]))
            k += 1
        self._times = forecast.times
        self._H = forecast.times.shape[0]
        self._joints = joints
        self._djoints = np.diff(joints, axis=0)
        self._dtimes = np.diff(forecast.times)
        self._margin_arr = forecast.margins
        self._cap = max(forecast.max_margin_m, float(forecast.margins.max()))
        # boxes around two consecutive samples (a sample's own box when there is only one)
        self._lo_pair = self._lo_tab[1] if len(self._lo_tab) > 1 else lo
        self._hi_pair = self._hi_tab[1] if len(self._hi_tab) > 1 else hi
        self._n_pair = self._lo_pair.shape[0]
        # the compiled check (``kernel``: CollisionModel.kernel_geometry()) and its forecast arrays
        self._kernel = kernel
        if kernel is not None:
            H, J = joints.shape[0], joints.shape[1]
            # the sparse table as (levels, H, .) arrays (level k is valid on its first H - 2^k + 1 rows)
            n_lev = len(self._lo_tab)
            lo_tab, hi_tab = np.zeros((n_lev, H, 3)), np.zeros((n_lev, H, 4))
            for k, (a, b) in enumerate(zip(self._lo_tab, self._hi_tab, strict=True)):
                lo_tab[k, : a.shape[0]] = a
                hi_tab[k, : b.shape[0]] = b
            self._k_forecast = _kernels.pack(
                _kernels.PersonForecast(
                    times=_kernels.as_f64(self._times),
                    joints=_kernels.as_f64(joints),
                    djoints=_kernels.as_f64(self._djoints if H > 1 else np.zeros((1, J, 3))),
                    dtimes=_kernels.as_f64(self._dtimes if H > 1 else np.ones(1)),
                    lo_pair=_kernels.as_f64(self._lo_pair),
                    hi_pair=_kernels.as_f64(self._hi_pair),
                    margins=_kernels.as_f64(self._margin_arr),
                    lo_tab=lo_tab,
                    hi_tab=hi_tab,
                )
            )
            params = np.array(
                [
                    forecast.growth_mps,
                    self._cap,
                    ssm.t_reaction_s,
                    ssm.intrusion_m,
                    ssm.z_robot_m,
                    ssm.z_human_m,
                    extra_m,
                    math.inf if floor_m is None else floor_m,
                    stopping.decel_mps2,
                    stopping.slowest_joint_decel_radps2,
                    stopping.delay_s,
                    *(() if ssm_extra is None else (ssm_extra[0], *np.asarray(ssm_extra[1]).tolist())),
                ],
                dtype=np.float64,
            )
            self._k_offsets = np.array(offsets, dtype=np.float64)
            weights = np.array(stopping.joint_weights, dtype=np.float64)
            self._k_requirement = _kernels.pack(_kernels.Requirement(self._k_offsets, params, weights))
        # per person capsule boxes (for the exact stage to skip capsules far from the robot), sparse table
        # the exact stage's shortcuts need the collision model's segments and capsule subsets
        self._subsets = subsets and cap_ends is not None and robot_r is not None
        if self._subsets:
            assert cap_ends is not None and robot_r is not None
            self._cap_ends, self._robot_r = cap_ends, robot_r
        if self._subsets:
            ha, hb, hr = model.human_capsules(joints)
            clo = np.minimum(ha, hb) - np.asarray(hr)[None, :, None]  # (H, M, 3)
            chi = np.maximum(ha, hb) + np.asarray(hr)[None, :, None]
            self._clo_tab, self._chi_tab = [clo], [chi]
            k = 1
            while (1 << k) <= clo.shape[0]:
                plo, phi = self._clo_tab[-1], self._chi_tab[-1]
                half = 1 << (k - 1)
                self._clo_tab.append(np.minimum(plo[:-half], plo[half:]))
                self._chi_tab.append(np.maximum(phi[:-half], phi[half:]))
                k += 1

    @property
    def kernel(self) -> _kernels.KernelGeometry | None:
        """The compiled robot and person geometry (:meth:`CollisionModel.kernel_geometry`) when the check is
        compiled; None with a NumPy model or without a forecast."""
        return self._kernel

    @property
    def k_requirement(self) -> tuple[Any, ...]:
        """The required clearance's parameters as the compiled checks take them
        (:class:`app.planning._kernels.Requirement`, packed). Only with a forecast and a :attr:`kernel`."""
        return self._compiled("_k_requirement")

    @property
    def k_forecast(self) -> tuple[Any, ...]:
        """The forecast as the compiled checks take it (:class:`app.planning._kernels.PersonForecast`,
        packed). Only with a forecast and a :attr:`kernel`."""
        return self._compiled("_k_forecast")

    def _compiled(self, name: str) -> tuple[Any, ...]:
        value = getattr(self, name, None)
        if value is None:
            raise AttributeError(
                f"_Separation.{name[1:]} exists only for a compiled check with a forecast: test "
                "`forecast is not None and kernel is not None` first"
            )
        return value

    def _boxes(self, t0: np.ndarray, t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boxes that contain the person over each window [t0, t1] (t0 <= t1): lower corners (n, 3) and
        upper corners with the largest forecast margin at the samples of the window appended (n, 4)."""
        times = self._times
        H = self._H
        i0 = np.minimum(np.maximum(np.searchsorted(times, t0, side="right") - 1, 0), H - 1)
        i1 = np.maximum(np.minimum(np.searchsorted(times, t1, side="left"), H - 1), i0)
        k = np.floor(np.log2(i1 - i0 + 1)).astype(np.int64)
        lo = np.empty((t0.shape[0], 3))
        hi = np.empty((t0.shape[0], 4))
        uk = np.unique(k)
        for kk in uk.tolist():
            sel = slice(None) if uk.size == 1 else np.flatnonzero(k == kk)
            a, b = i0[sel], i1[sel] - (1 << kk) + 1
            lo[sel] = np.minimum(self._lo_tab[kk][a], self._lo_tab[kk][b])
            hi[sel] = np.maximum(self._hi_tab[kk][a], self._hi_tab[kk][b])
        return lo, hi

    def _margins(self, t: np.ndarray) -> np.ndarray:
        """The forecast's margins at times ``t`` (as :meth:`HumanForecast.poses_at`, without the poses)."""
        fc = self.forecast
        assert fc is not None
        m = np.interp(t, self._times, self._margin_arr)
        if fc.growth_mps > 0.0:
            m = np.minimum(m + fc.growth_mps * np.maximum(t - self._times[-1], 0.0), self._cap)
        return m

    def _clearance(self, v: np.ndarray, w: np.ndarray, margin: np.ndarray) -> np.ndarray:
        """The separation (m) asked of the robot moving at ``v`` (its fastest point, m/s) and ``w`` (its
        fastest joint, rad/s) from a forecast pose of ``margin``."""
        req = forecast_clearance(v, margin, self.ssm, w_top_radps=w, stopping=self.stopping) + self.extra_m
        if self.ssm_extra is not None:
            dv, table = self.ssm_extra
            grid = np.arange(table.shape[0]) * dv
            req = req + np.interp(np.maximum(v, 0.0), grid, table)
        return req if self.floor_m is None else np.minimum(req, self.floor_m)

    def _required(self, v: np.ndarray, w: np.ndarray, t: np.ndarray) -> np.ndarray:
        return self._clearance(v, w, self._margins(t))

    def _poses(self, t: np.ndarray) -> np.ndarray:
        """Poses (n, J, 3) at times ``t`` (n,): :meth:`HumanForecast.poses_at`'s interpolation."""
        if self._H == 1:
            return np.broadcast_to(self._joints, (t.shape[0], *self._joints.shape[1:]))
        times = self._times
        tc = np.minimum(np.maximum(t, times[0]), times[-1])
        i0 = np.minimum(np.searchsorted(times, tc, side="right"), self._H - 1) - 1
        w = (tc - times[i0]) / self._dtimes[i0]
        return self._joints[i0] + w[:, None, None] * self._djoints[i0]

    def near_moves(
        self, cen: np.ndarray, rad: np.ndarray, t0: np.ndarray, t1: np.ndarray, v: np.ndarray, w: np.ndarray
    ) -> np.ndarray:
        """Stage 0: (M,) bool, False where a move certainly keeps the separation.

        ``cen`` (M, L, 3) / ``rad`` (M, L): spheres that contain each robot capsule during the whole move,
        which lasts from ``t0`` to ``t1`` with its fastest point at most at ``v`` (m/s) and its fastest
        joint at most at ``w`` (rad/s)."""
        M = cen.shape[0]
        if self.forecast is None or M == 0:
            return np.zeros(M, dtype=bool)
        lo_off, hi_off = min(self.offsets), max(self.offsets)
        lo, hi = self._boxes(t0 + lo_off, t1 + hi_off)
        # the largest requirement over the window: its largest margin (at a forecast sample inside it, at
        # either end, or grown beyond the horizon at its end)
        m_hi = np.maximum(hi[:, 3], np.maximum(self._margins(t0 + lo_off), self._margins(t1 + hi_off)))
        hi = hi[:, :3]
        req = self._clearance(v, w, m_hi)
        g = np.maximum(np.maximum(lo[:, None] - cen, cen - hi[:, None]), 0.0)  # (M, L, 3)
        gap = np.sqrt(np.einsum("mlk,mlk->ml", g, g)) - rad
        return (gap < req[:, None]).any(axis=1)

    def check(
        self,
        q: np.ndarray,
        t: np.ndarray,
        v: np.ndarray,
        w: np.ndarray,
        cen: np.ndarray | None = None,
        rad: np.ndarray | None = None,
        groups: np.ndarray | None = None,
    ) -> np.ndarray:
        """Boolean (S,): robot ``q[k]`` (6,) at time ``t[k]``, its fastest point moving at ``v[k]`` m/s and
        its fastest joint at ``w[k]`` rad/s, keeps the separation.

        ``cen`` (S, L, 3) / ``rad`` (S, L): spheres that contain the robot capsules at each sample, if known.
        ``groups`` (S,) int: samples of one group (a move) are only of interest together: once one of them
        certainly fails, the others of its group are reported as failing without being computed.
        """
        S = q.shape[0]
        if self.forecast is None or S == 0:
            return np.ones(S, dtype=bool)
        if self._kernel is not None:
            return self._check_compiled(q, t, v, w, cen, rad, groups)
        n_off = len(self.offsets)
        if n_off > 1:
            t = (t[None, :] + np.asarray(self.offsets)[:, None]).reshape(-1)
            q = np.broadcast_to(q, (n_off, S, 6)).reshape(-1, 6)
            if groups is not None:
                groups = np.tile(groups, n_off)
            v = np.broadcast_to(v, (n_off, S)).reshape(-1)
            w = np.broadcast_to(w, (n_off, S)).reshape(-1)
            if cen is not None and rad is not None:
                cen = np.broadcast_to(cen, (n_off, *cen.shape)).reshape(-1, *cen.shape[1:])
                rad = np.broadcast_to(rad, (n_off, *rad.shape)).reshape(-1, rad.shape[1])
        elif self.offsets[0] != 0.0:
            t = t + self.offsets[0]
        req = self._required(v, w, t)
        n = q.shape[0]
        self.samples += n
        ok = np.ones(n, dtype=bool)
        if cen is not None and rad is not None:
            i = np.minimum(np.maximum(np.searchsorted(self._times, t, side="right") - 1, 0), self._n_pair - 1)
            lo, hi = self._lo_pair[i][:, None], self._hi_pair[i][:, None, :3]
            g = np.maximum(np.maximum(lo - cen, cen - hi), 0.0)  # (n, L, 3)
            gap = np.sqrt(np.einsum("nlk,nlk->nl", g, g)) - rad
            near = np.flatnonzero((gap < req[:, None]).any(axis=1))
        else:
            near = np.arange(n)
        if near.size:
            tn, rn = t[near], req[near]
            poses = self._poses(tn)
            if self._subsets and cen is not None and rad is not None:
                # only the robot capsules near the person's box at some sample, and only the person
                # capsules whose box over the samples' time window comes near those robot capsules
                close = gap[near] < rn[:, None]  # (n', L)
                links = np.flatnonzero(close.any(axis=0))
                cn, rdn = cen[near][:, links].reshape(-1, 3), rad[near][:, links].reshape(-1, 1)
                r_lo = (cn - rdn).min(axis=0) - rn.max()
                r_hi = (cn + rdn).max(axis=0) + rn.max()
                c_lo, c_hi = self._capsule_boxes(float(tn.min()), float(tn.max()))
                caps = np.flatnonzero(np.all((c_lo <= r_hi) & (c_hi >= r_lo), axis=1))
                a_c, d_c = self.model.robot_segments(q[near])
                if groups is not None and links.size and caps.size:
                    # a sample certainly too close fails its whole move: no exact distances for the rest
                    # (looked for at every third sample: a move that fails usually does over several)
                    some = np.arange(0, near.size, 3)
                    dead = np.zeros(near.size, dtype=bool)
                    dead[some] = (
                        self._upper_bound(a_c[..., some], d_c[..., some], poses[some], links, caps) < rn[some]
                    )
                    if dead.any():
                        ok[near[dead]] = False
                        alive = ~np.isin(groups[near], groups[near[dead]])
                        near, tn, rn, poses = near[alive], tn[alive], rn[alive], poses[alive]
                        a_c, d_c = a_c[..., alive], d_c[..., alive]
                self.exact_samples += near.size
                d = self.model.distance_to_human_paired(
                    q[near], poses, segments=(a_c, d_c), links=links, capsules=caps
                )
            else:
                self.exact_samples += near.size
                d = self.model.distance_to_human_paired(q[near], poses)
            ok[near] = d >= rn
        return ok.reshape(n_off, S).all(axis=0) if n_off > 1 else ok

    def _check_compiled(
        self,
        q: np.ndarray,
        t: np.ndarray,
        v: np.ndarray,
        w: np.ndarray,
        cen: np.ndarray | None,
        rad: np.ndarray | None,
        groups: np.ndarray | None,
    ) -> np.ndarray:
        """:meth:`check` in one compiled pass (:func:`app.planning._kernels.sample_separation_ok`): the same
        broad phase and exact distances, with the exact stage stopping at the first capsule pair that is too
        close and skipping the rest of a group once one of its samples failed."""
        S = q.shape[0]
        n_off = len(self.offsets)
        t_all = np.asarray(t, dtype=np.float64)[None, :] + self._k_offsets[:, None]
        v_all = np.broadcast_to(np.asarray(v, dtype=np.float64), (n_off, S)).reshape(-1)
        w_all = np.broadcast_to(np.asarray(w, dtype=np.float64), (n_off, S)).reshape(-1)
        req = self._required(v_all, w_all, t_all.reshape(-1)).reshape(n_off, S)
        use_spheres = cen is not None and rad is not None
        if use_spheres:
            cen_k, rad_k = _kernels.as_f64(cen), _kernels.as_f64(rad)
        else:
            cen_k, rad_k = np.zeros((1, 1, 3)), np.zeros((1, 1))
        if groups is None:
            groups_k, n_groups = _NO_IDS, 0
        else:
            groups_k = _kernels.as_i64(groups)
            n_groups = int(groups_k.max()) + 1
        geo = self._kernel
        assert geo is not None
        ok, exact = _kernels.sample_separation_ok(
            _kernels.as_f64(q),
            t_all,
            _kernels.as_f64(req),
            cen_k,
            rad_k,
            use_spheres,
            groups_k,
            n_groups,
            self._k_forecast,
            geo.robot,
            geo.person,
            self.k_requirement[1],
        )
        self.samples += n_off * S
        self.exact_samples += exact
        return ok

    def _upper_bound(
        self, a_c: np.ndarray, d_c: np.ndarray, poses: np.ndarray, links: np.ndarray, caps: np.ndarray
    ) -> np.ndarray:
        """An upper bound (n,) of the surface distance between the robot capsules ``links`` (segments
        ``a_c``, ``d_c`` (L, 3, n)) and the person capsules ``caps`` in ``poses`` (n, J, 3): the distance
        between a point on a robot capsule's axis (either end) and a joint on a person capsule's axis, less
        both radii, is never below the capsules' distance."""
        ia, ib, hr = self._cap_ends
        r_joint = np.full(poses.shape[1], -np.inf)
        np.maximum.at(r_joint, ia[caps], hr[caps])
        np.maximum.at(r_joint, ib[caps], hr[caps])
        joints = np.flatnonzero(np.isfinite(r_joint))
        a, d = a_c[links], d_c[links]
        pts = np.concatenate([a, a + d])  # (2L', 3, n): both ends of each axis
        jt = poses[:, joints].transpose(2, 1, 0)  # (3, J', n)
        sq = np.zeros((pts.shape[0], joints.size, pts.shape[2]))
        for k in range(3):
            diff = pts[:, k, None, :] - jt[k][None]
            diff *= diff
            sq += diff
        dist = np.sqrt(sq, out=sq)
        dist -= np.tile(self._robot_r[links], 2)[:, None, None] + r_joint[joints][None, :, None]
        return dist.reshape(-1, dist.shape[2]).min(axis=0)

    def _capsule_boxes(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """Boxes (M, 3) x 2 that contain each person capsule over the window [t0, t1]."""
        times, H = self._times, self._H
        i0 = min(max(int(np.searchsorted(times, t0, side="right")) - 1, 0), H - 1)
        i1 = max(min(int(np.searchsorted(times, t1, side="left")), H - 1), i0)
        k = (i1 - i0 + 1).bit_length() - 1
        a, b = i0, i1 - (1 << k) + 1
        return (
            np.minimum(self._clo_tab[k][a], self._clo_tab[k][b]),
            np.maximum(self._chi_tab[k][a], self._chi_tab[k][b]),
        )
