"""The compiled kernels (app.planning._kernels) against the NumPy reference implementations.

Distances agree to 1e-9 m wherever the segment axes are apart; where they touch, the NumPy reference's
expansion in dot products is off by up to a few 1e-8 m and the kernel is checked against the exact answer
instead. The planner with compiled checks must return exactly what it returns with the NumPy checks.
"""

from __future__ import annotations

import heapq
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from app.config import load_workcell
from app.planning import _kernels
from app.planning.collision import (
    HUMAN_CAPSULES,
    ROBOT_LINKS,
    CollisionModel,
    segment_distance,
)
from app.planning.kinematics import UR5e
from app.planning.reference import ReferenceCollisionModel, ReferenceUR5e, segment_distance_reference
from app.planning.roadmap import RoadmapConfig, load_or_build_roadmap
from app.planning.scenarios import reference_queries
from app.planning.search import Planner
from app.planning.trajectory import Trajectory
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import NUM_JOINTS, HumanFrame

TOL = 1e-9


@pytest.fixture(scope="module")
def cell():  # type: ignore[no-untyped-def]
    return load_workcell()


@pytest.fixture(scope="module")
def models(cell):  # type: ignore[no-untyped-def]
    return CollisionModel(cell), ReferenceCollisionModel(cell)


def _poses(rng: np.random.Generator, n: int, spread: float = 0.35) -> np.ndarray:
    """Person-sized clouds of joints in front of the robot, (n, J, 3)."""
    centre = np.array([0.55, 0.25, 0.45]) + rng.uniform(-0.3, 0.3, (n, 1, 3))
    return centre + spread * rng.normal(size=(n, NUM_JOINTS, 3))


def _all_close(got: tuple[np.ndarray, ...], ref: tuple[np.ndarray, ...], atol: float = 1e-12) -> None:
    """Each array of ``got`` equals its counterpart in ``ref`` (as many of them) to ``atol``."""
    assert len(got) == len(ref)
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=atol)


# ------------------------------------------------------------------------------------------ segments


@pytest.mark.parametrize("n", [1, 500])
def test_segment_distances_match_the_numpy_reference(n: int) -> None:
    rng = np.random.default_rng(n)
    p1, q1, p2, q2 = (rng.uniform(-1.0, 1.0, (n, 3)) for _ in range(4))
    kind = rng.integers(0, 5, n)
    q1[kind == 1] = p1[kind == 1]  # a point
    q2[kind == 2] = p2[kind == 2]
    par = kind == 3  # parallel, offset and shifted along
    q2[par] = p2[par] + rng.uniform(-1.5, 1.5, (par.sum(), 1)) * (q1[par] - p1[par])
    col = kind == 4  # collinear, overlapping or not
    p2[col] = p1[col] + rng.uniform(-2.0, 2.0, (col.sum(), 1)) * (q1[col] - p1[col])
    q2[col] = p2[col] + rng.uniform(-1.5, 1.5, (col.sum(), 1)) * (q1[col] - p1[col])
    got = segment_distance(p1, q1, p2, q2)
    ref = segment_distance_reference(p1, q1, p2, q2)
    assert got.shape == (n,)
    apart = ref > 1e-6
    np.testing.assert_allclose(got[apart], ref[apart], rtol=0.0, atol=TOL)
    np.testing.assert_allclose(got[~apart], ref[~apart], rtol=0.0, atol=1e-7)


def test_touching_parallel_and_degenerate_segments_have_their_exact_distance() -> None:
    o = np.zeros(3)
    x, y, z = np.eye(3)
    cases = [
        # crossing axes: exactly 0 (NumPy's expansion only gets within ~1e-8)
        ((-x, x, -y + 0.3 * z * 0, y), 0.0),
        ((o, x, 0.5 * x - y, 0.5 * x + y), 0.0),
        # touching at an end
        ((o, x, x, x + y), 0.0),
        # parallel, 0.3 apart, overlapping
        ((o, x, 0.3 * y + 0.2 * x, 0.3 * y + 2.0 * x), 0.3),
        # collinear, a gap of 0.5
        ((o, x, 1.5 * x, 3.0 * x), 0.5),
        # a point and a segment, two points
        ((0.5 * x + 0.4 * z, 0.5 * x + 0.4 * z, o, x), 0.4),
        ((o, o, 0.3 * y, 0.3 * y), 0.3),
        ((y, y, y, y), 0.0),
    ]
    for (p1, q1, p2, q2), expected in cases:
        got = float(segment_distance(p1, q1, p2, q2))
        assert abs(got - expected) <= 1e-12, (p1, q1, p2, q2, got)
        assert abs(float(segment_distance_reference(p1, q1, p2, q2)) - got) <= 1e-7
        # the same pair swapped and reversed
        assert abs(float(segment_distance(q2, p2, q1, p1)) - expected) <= 1e-12


def test_segment_distance_broadcasts_like_the_reference() -> None:
    rng = np.random.default_rng(3)
    p1, q1 = rng.normal(size=(2, 4, 1, 3))
    p2, q2 = rng.normal(size=(2, 1, 5, 3))
    got = segment_distance(p1, q1, p2, q2)
    assert got.shape == (4, 5)
    np.testing.assert_allclose(got, segment_distance_reference(p1, q1, p2, q2), rtol=0.0, atol=TOL)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        segment_distance(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 2)))


# ------------------------------------------------------------------------------------------ kinematics


@pytest.mark.parametrize("n", [1, 7, 64])
def test_compiled_chain_equals_the_numpy_chain(cell, n: int) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(n)
    q = rng.uniform(-2 * np.pi, 2 * np.pi, (n, 6))
    kin, ref = UR5e.from_workcell(cell), ReferenceUR5e.from_workcell(cell)
    _all_close(kin._chain(q), ref._chain(q))
    np.testing.assert_allclose(kin.fk(q), ref.fk(q), rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(kin.fk_tcp(q), ref.fk_tcp(q), rtol=0.0, atol=1e-12)
    _all_close(kin.link_origins_and_axes(q), ref.link_origins_and_axes(q))


@pytest.mark.parametrize("n", [1, 40])
def test_compiled_capsules_equal_the_numpy_capsules(models, n: int) -> None:  # type: ignore[no-untyped-def]
    fast, ref = models
    rng = np.random.default_rng(10 + n)
    q = rng.uniform(-np.pi, np.pi, (n, 6))
    segs = fast.robot_segments(q)
    assert [a.shape for a in segs] == [(len(ROBOT_LINKS), 3, n)] * 2
    _all_close(segs, ref.robot_segments(q))
    _all_close(fast.robot_capsules(q), ref.robot_capsules(q))


# ------------------------------------------------------------------------------------------ robot-person


@pytest.mark.parametrize("n", [1, 37])
def test_robot_person_distances_match_the_reference(models, n: int) -> None:  # type: ignore[no-untyped-def]
    fast, ref = models
    rng = np.random.default_rng(20 + n)
    q = rng.uniform(-np.pi, np.pi, (n, 6))
    joints = _poses(rng, n)
    got = fast.distance_to_human_paired(q, joints)
    assert got.shape == (n,)
    np.testing.assert_allclose(got, ref.distance_to_human_paired(q, joints), rtol=0.0, atol=TOL)
    cross = fast.distance_to_human(q, joints[: max(1, n // 3)])
    np.testing.assert_allclose(cross, ref.distance_to_human(q, joints[: max(1, n // 3)]), rtol=0.0, atol=TOL)
    np.testing.assert_allclose(np.diag(fast.distance_to_human(q, joints)), got, rtol=0.0, atol=1e-12)
    # capsule subsets, and the segments passed in
    links, caps = np.array([2, 4, 8]), np.array([0, 5, 11, len(HUMAN_CAPSULES) - 1])
    segs = fast.robot_segments(q)
    sub = fast.distance_to_human_paired(q, joints, segments=segs, links=links, capsules=caps)
    ref_sub = ref.distance_to_human_paired(q, joints, links=links, capsules=caps)
    np.testing.assert_allclose(sub, ref_sub, rtol=0.0, atol=TOL)
    assert np.all(sub >= got - 1e-12)
    assert np.all(np.isinf(fast.distance_to_human_paired(q, joints, links=np.array([], dtype=int))))


def test_penetrating_and_nan_inputs(models) -> None:  # type: ignore[no-untyped-def]
    fast, ref = models
    q = np.zeros((2, 6))
    tcp = fast.robot_capsules(q)[1][:, -1]  # (2, 3): the TCP
    joints = np.repeat(tcp[:, None, :], NUM_JOINTS, axis=1)  # a person collapsed onto the TCP
    joints[:, :, 2] += np.linspace(-0.02, 0.02, NUM_JOINTS)
    got = fast.distance_to_human_paired(q, joints)
    assert np.all(got < -0.05)  # deep overlap: minus both radii
    np.testing.assert_allclose(got, ref.distance_to_human_paired(q, joints), rtol=0.0, atol=1e-7)
    joints[1, 3] = np.nan
    assert np.isnan(fast.distance_to_human_paired(q, joints)[1])
    assert np.isnan(fast.distance_to_human(q, joints)[:, 1]).all()


def test_self_and_pair_distances_match_the_reference(models) -> None:  # type: ignore[no-untyped-def]
    fast, ref = models
    rng = np.random.default_rng(30)
    q = rng.uniform(-np.pi, np.pi, (25, 6))
    np.testing.assert_allclose(fast.self_distances(q), ref.self_distances(q), rtol=0.0, atol=TOL)
    np.testing.assert_array_equal(fast.self_collision(q), ref.self_collision(q))
    joints = _poses(rng, 3)
    got = fast.pair_distances(q[0], joints)
    assert got.shape == (3, len(ROBOT_LINKS), len(HUMAN_CAPSULES))
    np.testing.assert_allclose(got, ref.pair_distances(q[0], joints), rtol=0.0, atol=TOL)
    np.testing.assert_allclose(
        got.min(axis=(1, 2)), ref.distance_to_human(q[:1], joints)[0], rtol=0.0, atol=TOL
    )
    with pytest.raises(ValueError, match=r"\(6,\)"):
        fast.pair_distances(q[:2], joints)


def test_each_kernel_compiles_for_one_signature(models) -> None:  # type: ignore[no-untyped-def]
    fast, _ = models
    rng = np.random.default_rng(4)
    q = rng.uniform(-1.0, 1.0, (5, 6))
    joints = _poses(rng, 5)
    ro_q, ro_joints = q.copy(), joints.copy()
    ro_q.setflags(write=False)
    ro_joints.setflags(write=False)
    for qq, jj in ((q, joints), (ro_q, ro_joints), (q[:, ::1].T.copy().T, np.asfortranarray(joints))):
        fast.distance_to_human_paired(qq, jj)
        fast.distance_to_human(qq, jj[:2])
        fast.self_distances(qq)
    for kernel in (
        _kernels.robot_segments,
        _kernels.paired_min_distance,
        _kernels.cross_min_distance,
        _kernels.self_distances,
    ):
        assert len(kernel.signatures) == 1, kernel


def test_without_a_cache_location_the_kernels_compile_in_memory() -> None:
    code = textwrap.dedent(
        """
        import logging
        import numba.core.caching as caching
        impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
        impl._locator_classes = []  # no writable cache location: a read-only install and home
        logging.basicConfig(level=logging.WARNING)
        import numpy as np
        from app.planning import _kernels
        d = _kernels.segment_distances(np.zeros((1, 3)), np.ones((1, 3)), np.array([[1.0, 0, 0]]),
                                       np.array([[1.0, 0, 1]]))
        print(round(float(d[0]), 12))
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(round(np.sqrt(0.5), 12))
    assert "compile in memory" in out.stderr


# ------------------------------------------------------------------------------------------ the planner


@pytest.fixture(scope="module")
def planners(cell, models, tmp_path_factory):  # type: ignore[no-untyped-def]
    fast, ref = models
    cfg = RoadmapConfig(num_nodes=120, k_neighbors=8)
    rm = load_or_build_roadmap(cell, config=cfg, cache_dir=tmp_path_factory.mktemp("rm"), collision=fast)
    return rm, Planner(rm, fast), Planner(rm, ref)


def test_the_planner_uses_the_compiled_checks_only_with_a_compiled_model(planners) -> None:  # type: ignore[no-untyped-def]
    _, fast, ref = planners
    assert fast._kernel_geometry is not None
    assert ref._kernel_geometry is None


def test_sample_checks_match_the_numpy_check(cell, planners) -> None:  # type: ignore[no-untyped-def]
    rm, fast, ref = planners
    rng = np.random.default_rng(5)
    queries = reference_queries(cell, rm, n=3, seed=2)
    verdicts = []
    for qr in queries:
        for offsets in ((0.0,), (0.0, 0.25)):
            s_fast = fast._separation(qr.forecast, extra_m=0.02, offsets=offsets)
            s_ref = ref._separation(qr.forecast, extra_m=0.02, offsets=offsets)
            nodes = rng.integers(0, rm.num_nodes, 300)
            br = rng.integers(0, 8, 300)
            q = rm.ik[nodes, br]
            t = qr.t_start + rng.uniform(-0.2, 2.0, 300)
            v = rng.uniform(0.0, 1.0, 300)
            w = rng.uniform(0.0, 2.0, 300)
            cen, rad = fast._cen_all[nodes, br], fast._rad_all[nodes, br]
            np.testing.assert_array_equal(s_fast.check(q, t, v, w), s_ref.check(q, t, v, w))
            got = s_fast.check(q, t, v, w, cen, rad)
            np.testing.assert_array_equal(got, s_ref.check(q, t, v, w, cen, rad))
            verdicts.append(got)
            # with groups only the verdict of a whole group counts
            groups = np.repeat(np.arange(60), 5)
            a = s_fast.check(q, t, v, w, cen, rad, groups)
            b = s_ref.check(q, t, v, w, cen, rad, groups)
            np.testing.assert_array_equal(
                np.bincount(groups, weights=~a) == 0, np.bincount(groups, weights=~b) == 0
            )
    both = np.concatenate(verdicts)
    assert 0 < both.sum() < both.size  # passes and failures were exercised


def test_move_checks_and_verification_match_the_numpy_checks(cell, planners) -> None:  # type: ignore[no-untyped-def]
    rm, fast, ref = planners
    rng = np.random.default_rng(6)
    qr = reference_queries(cell, rm, n=1, seed=3)[0]
    for hold in (False, True):
        s_fast = fast._separation(qr.forecast, extra_m=0.02)
        s_ref = ref._separation(qr.forecast, extra_m=0.02)
        n = 200
        u, bu = rng.integers(0, rm.num_nodes, n), rng.integers(0, 8, n)
        cv, b = rng.integers(0, rm.num_nodes, n), rng.integers(0, 8, n)
        q_a = rm.ik[u, bu]
        target = fast._align(rm.ik[cv, b], q_a)
        L = fast._metric(target - q_a)
        f = rng.choice([0.2, 0.6, 1.0], n)
        u0 = rng.uniform(0.0, 1.0, n) * f
        end = rng.random(n) < 0.5
        h = np.maximum(L / f, 0.05) * rng.uniform(1.0, 1.5, n)
        t_dep = qr.t_start + rng.uniform(0.0, 1.5, n)
        args = (q_a, fast._pts_all[u, bu], fast._cen_all[u, bu], fast._rad_all[u, bu], cv, b, target, t_dep)
        rest = (h, u0, L, end, f, np.full(n, hold), 0.3)
        got = fast._moves_ok(s_fast, *args, *rest)
        want = ref._moves_ok(s_ref, *args, *rest)
        np.testing.assert_array_equal(got, want)
        assert 0 < got.sum() < n  # both kinds of answer were exercised
    # the trajectory verification (first_violation) on the plans of a few queries
    found = []
    for qr in reference_queries(cell, rm, n=3, seed=4):
        res = ref.plan(q_start=qr.q_start, t_start=qr.t_start, goal=qr.goal, forecast=None)
        if not res.ok:
            continue
        traj = res.trajectory
        for fc in (qr.forecast, _shifted(qr.forecast, rng)):
            got = fast.first_violation(traj, fc, t_from=traj.t_start, t_to=traj.t_end + 0.3)
            assert got == ref.first_violation(traj, fc, t_from=traj.t_start, t_to=traj.t_end + 0.3)
            found.append(got is None)
            # a view of the trajectory in another timing (the supervisor's speed-scaled plan in execution)
            view = _SlowView(traj, t_ref=traj.t_start - 0.2, tau_ref=traj.t_start + 0.1, scale=0.6)
            got = fast.first_violation(view, fc, t_from=view.t_ref, t_to=view.t_end + 0.3)
            assert got == ref.first_violation(view, fc, t_from=view.t_ref, t_to=view.t_end + 0.3)
            found.append(got is None)
    assert any(found) and not all(found)  # trajectories with and without a violation


def test_a_slow_view_is_checked_against_the_static_scene_at_its_paths_own_spacing(cell, planners) -> None:  # type: ignore[no-untyped-def]
    """The static scene does not depend on the timing: a view of a path at a quarter of its speed (as the
    SSM-aware timing makes one) is checked at the path's own spacing, and fails where the path does, at the
    view's wall time, no later than the dense check of every wall sample finds it."""
    _, fast, ref = planners
    q0 = np.asarray(cell.robot.home_q, dtype=float)
    q1 = q0.copy()
    q1[1] = 0.3  # the shoulder lowers the arm into the table
    t = np.linspace(0.0, 2.0, 5)
    s = 0.5 - 0.5 * np.cos(np.pi * t / 2.0)
    qd = (0.25 * np.pi) * np.sin(np.pi * t / 2.0)[:, None] * (q1 - q0)
    traj = Trajectory(t, q0 + s[:, None] * (q1 - q0), qd)
    far = HumanForecast.hold(
        HumanFrame(0.0, np.full((NUM_JOINTS, 3), 6.0) + np.linspace(0.0, 1e-3, NUM_JOINTS)[:, None])
    )
    at_full = fast._verify(traj, far, 0.0, traj.t_end, static=True)
    assert at_full is not None and 0.5 < at_full < traj.t_end
    view = _SlowView(traj, t_ref=0.0, tau_ref=0.0, scale=0.25)
    got = fast._verify(view, far, 0.0, view.t_end, static=True)
    dense = ref._verify(view, far, 0.0, view.t_end, static=True)
    assert got == pytest.approx(at_full / 0.25, abs=0.05)
    assert dense is not None and got <= dense + 1e-9 and dense - got <= 0.05


class _SlowView:
    """A trajectory run at ``scale`` of its speed from wall time ``t_ref`` at its time ``tau_ref`` (the
    interface of :class:`app.control.trajectory_views.ScaledView` that the planner's check uses)."""

    def __init__(self, traj: Trajectory, *, t_ref: float, tau_ref: float, scale: float) -> None:
        self.base_trajectory, self.t_ref, self.tau_ref, self.scale = traj, t_ref, tau_ref, scale
        self.t_start = t_ref
        self.t_end = t_ref + (traj.t_end - tau_ref) / scale

    def path_times(self, t: np.ndarray) -> np.ndarray:
        return self.tau_ref + self.scale * np.maximum(np.asarray(t, dtype=np.float64) - self.t_ref, 0.0)

    def q(self, t: np.ndarray) -> np.ndarray:
        return self.base_trajectory.q(self.path_times(t))

    def sample(self, dt_s: float, *, t_from: float, t_to: float) -> np.ndarray:
        n = max(math.ceil((t_to - t_from) / dt_s - 1e-9), 1)
        return np.linspace(t_from, t_to, n + 1)


def _shifted(fc: HumanForecast, rng: np.random.Generator) -> HumanForecast:
    """The forecast person moved toward the robot (so that trajectories do violate it)."""
    return HumanForecast(
        t0=fc.t0,
        times=fc.times,
        joints=fc.joints - np.array([0.0, 0.35, 0.0]) + 0.01 * rng.normal(size=fc.joints.shape),
        margins=fc.margins,
        growth_mps=fc.growth_mps,
        max_margin_m=fc.max_margin_m,
    )


def test_plans_are_the_same_with_and_without_the_compiled_checks(cell, planners) -> None:  # type: ignore[no-untyped-def]
    rm, fast, ref = planners
    for qr in reference_queries(cell, rm, n=6, seed=9):
        for workers in (1, 16):
            kw = dict(
                q_start=qr.q_start, t_start=qr.t_start, goal=qr.goal, forecast=qr.forecast, workers=workers
            )
            a, b = fast.plan(**kw), ref.plan(**kw)
            assert (a.ok, a.reason, a.expanded) == (b.ok, b.reason, b.expanded)
            if a.ok:
                np.testing.assert_array_equal(a.plan.times, b.plan.times)
                np.testing.assert_array_equal(a.plan.q, b.plan.q)
        e_a = fast.emergency(q_start=qr.q_start, t_start=qr.t_start, forecast=qr.forecast, horizon_s=0.2)
        e_b = ref.emergency(q_start=qr.q_start, t_start=qr.t_start, forecast=qr.forecast, horizon_s=0.2)
        assert (e_a.ok, e_a.reason, e_a.expanded) == (e_b.ok, e_b.reason, e_b.expanded)
        if e_a.ok:
            np.testing.assert_array_equal(e_a.plan.times, e_b.plan.times)
            np.testing.assert_array_equal(e_a.plan.q, e_b.plan.q)


def _same_search(a, b) -> None:  # type: ignore[no-untyped-def]
    """The raw searches (waypoints before the fit) are the same, bit for bit."""
    (wa, na, ra), (wb, nb, rb) = a, b
    assert (na, ra) == (nb, rb)
    assert (wa is None) == (wb is None)
    if wa is not None:
        np.testing.assert_array_equal(wa.times, wb.times)
        np.testing.assert_array_equal(wa.q, wb.q)
        np.testing.assert_array_equal(wa.nodes, wb.nodes)


def test_the_compiled_search_bookkeeping_expands_exactly_like_the_numpy_search(cell, planners) -> None:  # type: ignore[no-untyped-def]
    """The compiled generation, open list, lookahead and batch set-up (:class:`_Run` with ``compiled``)
    against the NumPy/heapq search: the same waypoints, expansions and reasons for the sequential,
    batched and static searches and the emergency horizon, person or not."""
    rm, fast, ref = planners
    compiled_runs = []
    search_compiled = fast._search_compiled

    def counting(run, *args, **kwargs):  # type: ignore[no-untyped-def]
        compiled_runs.append(run.compiled)
        return search_compiled(run, *args, **kwargs)

    fast._search_compiled = counting
    ref._search_compiled = counting
    checked = 0
    for qr in reference_queries(cell, rm, n=8, seed=11):
        for forecast in (qr.forecast, None):
            for workers in (1, 4, 32):
                goal = rm.resolve(qr.goal)
                kw = dict(goal=goal, stop_time=None, hold_s=fast.config.goal_hold_s, workers=workers)
                out = []
                for pl in (fast, ref):
                    sep = pl._separation(forecast, extra_m=pl.config.corridor_margin_m)
                    out.append(pl._search(qr.q_start, qr.t_start, sep, **kw, deadline=None))
                _same_search(*out)
                checked += out[0][0] is not None
        stop = dict(goal=None, stop_time=qr.t_start + 0.3, hold_s=0.2, workers=8, deadline=None)
        out = []
        for pl in (fast, ref):
            sep = pl._separation(qr.forecast, extra_m=pl.config.corridor_margin_m)
            out.append(pl._search(qr.q_start, qr.t_start, sep, **stop))
        _same_search(*out)
    del fast._search_compiled, ref._search_compiled
    assert checked >= 10  # most of them found a path
    assert len(compiled_runs) == 8 * 2 * 3 + 8 and all(compiled_runs)  # only the compiled planner's runs


def test_the_compiled_open_list_pops_in_heapq_order() -> None:
    rng = np.random.default_rng(12)
    n = 3000
    keys = rng.integers(0, 40, n) * 0.125  # many equal keys, equal times among them: ties go to the id
    ts = rng.integers(0, 8, n) * 0.25
    ids = rng.permutation(n).astype(np.int64)
    heap, hs = np.zeros(n, dtype=np.int64), np.zeros(2, dtype=np.int64)
    E_key, E_negt, E_id = np.zeros(n), np.zeros(n), np.zeros(n, dtype=np.int64)
    ref: list[tuple[float, float, int]] = []
    for lo in range(0, n, 500):  # pushes and pops interleaved
        hi = lo + 500
        _kernels.heap_add(ids[lo:hi], keys[lo:hi], ts[lo:hi], heap, hs, E_key, E_negt, E_id)
        for k in range(lo, hi):
            heapq.heappush(ref, (float(keys[k]), float(-ts[k]), int(ids[k])))
        for _ in range(200):
            e = _kernels._heap_pop(heap, hs, E_key, E_negt, E_id)
            assert (E_key[e], E_negt[e], E_id[e]) == heapq.heappop(ref)
    while ref:
        e = _kernels._heap_pop(heap, hs, E_key, E_negt, E_id)
        assert (E_key[e], E_negt[e], E_id[e]) == heapq.heappop(ref)
    assert hs[0] == 0


def test_the_record_layout_matches_the_kernels(planners) -> None:  # type: ignore[no-untyped-def]
    from app.planning.search.search_state import _Run

    k = _kernels
    assert _Run._FLOAT.index("t") == k.REC_T and _Run._FLOAT.index("wait_ok") == k.REC_WAIT_OK
    assert [_Run._FLOAT.index(x) for x in ("u", "u0", "dep", "fc", "L", "h", "peak")] == [
        k.REC_U, k.REC_U0, k.REC_DEP, k.REC_FC, k.REC_L, k.REC_H, k.REC_PEAK,
    ]  # fmt: skip
    assert [_Run._INT.index(x) for x in ("node", "branch", "parent", "row", "spec_child")] == [
        k.REC_NODE, k.REC_BRANCH, k.REC_PARENT, k.REC_ROW, k.REC_SPEC_CHILD,
    ]  # fmt: skip
    assert [_Run._BOOL.index(x) for x in ("end", "same", "accepted", "qset")] == [
        k.REC_END, k.REC_SAME, k.REC_ACCEPTED, k.REC_QSET,
    ]  # fmt: skip


def test_compiled_align_equals_the_numpy_align(planners) -> None:  # type: ignore[no-untyped-def]
    _, fast, ref = planners
    rng = np.random.default_rng(8)
    q = rng.uniform(-7.0, 7.0, (500, 6))
    q_ref = rng.uniform(-7.0, 7.0, (500, 6))
    q[:4] = [np.pi, -np.pi, 3 * np.pi, -2.5 * np.pi, 2 * np.pi, 0.0]  # half-way ties and the limits
    q_ref[:4] = 0.0
    np.testing.assert_array_equal(fast._align(q, q_ref), ref._align(q, q_ref))
    assert fast._k_align is not None and ref._k_align is None


@pytest.mark.parametrize("offsets", [(0.0,), (-0.05, 0.0, 0.1, 0.2)])
def test_compiled_wait_checks_equal_the_numpy_wait_checks(cell, planners, offsets) -> None:  # type: ignore[no-untyped-def]
    from app.planning.search.search_state import _Run

    rm, fast, _ = planners
    rng = np.random.default_rng(13)
    qr = reference_queries(cell, rm, n=1, seed=3)[0]
    goal = rm.resolve(qr.goal)
    sep = fast._separation(qr.forecast, extra_m=0.02, offsets=offsets)
    run = _Run(
        fast.view, fast.config, qr.q_start, qr.t_start, sep, goal=goal, stop_time=None, hold_s=0.3,
        h_tab=fast._heuristic_table(goal), t_last=math.inf,
    )  # fmt: skip
    m = 60
    run._grow(m + 1)
    ids = np.arange(1, m + 1)
    run.n += m
    nodes = rng.integers(0, rm.num_nodes, m)
    nodes = nodes[rm.valid[nodes].any(axis=1)]
    ids = ids[: nodes.size]
    branches = np.argmax(rm.valid[nodes], axis=1)
    run.node[ids], run.branch[ids], run.q[ids] = nodes, branches, rm.ik[nodes, branches]
    run.t[ids] = qr.t_start + rng.uniform(0.0, 2.5, ids.size)
    todo = np.r_[0, ids]
    assert run.compiled
    run._check_waits(todo)
    got = run.wait_ok[todo].copy()
    run.wait_ok[todo] = np.nan
    run.compiled = False
    run._check_waits(todo)
    np.testing.assert_array_equal(got, run.wait_ok[todo])
    assert np.isinf(got).any() and np.isfinite(got).any()  # both outcomes are exercised
    # the requirement of each wait sample, compiled, is NumPy's to the bit
    _, t_all, req, *_ = _kernels.wait_samples(
        todo, run._k_state, fast.view.k_tables, run._start_k, 6, 0.05, sep.k_requirement, sep.k_forecast
    )
    at_rest = np.zeros(t_all.size)
    np.testing.assert_array_equal(req.reshape(-1), sep._required(at_rest, at_rest, t_all.reshape(-1)))
