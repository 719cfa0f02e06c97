"""Online arbitration between forecasts and adaptive conformal margins (app.prediction.arbitration)."""

from __future__ import annotations

import numpy as np
import pytest

from app.prediction.arbitration import COLD_START_SCALE, FAR_ALPHA_FACTOR, ForecastArbiter
from app.prediction.reference import ReferenceForecastArbiter
from app.prediction.skeleton import NUM_JOINTS

H, DT = 10, 1 / 30


def _walk(v: np.ndarray, n: int, rng: np.random.Generator, noise: float = 0.0) -> np.ndarray:
    """A person moving at constant velocity ``v`` (3,): n poses (n, J, 3)."""
    base = rng.normal(0.0, 0.2, size=(NUM_JOINTS, 3))
    t = np.arange(n) * DT
    return base[None] + t[:, None, None] * v + rng.normal(0.0, noise, size=(n, NUM_JOINTS, 3))


def _run(arbiter: ForecastArbiter, poses: np.ndarray, candidates: dict) -> list:
    outs = []
    for i in range(1, poses.shape[0]):
        t = i * DT
        arbiter.score(t, poses[i])
        futures = {name: fn(poses[i - 1], poses[i]) for name, fn in candidates.items()}
        outs.append(arbiter.combine(t, futures))
    return outs


def _cv(prev: np.ndarray, last: np.ndarray) -> np.ndarray:
    return last[None] + np.arange(H + 1)[:, None, None] * (last - prev)[None]


def _hold(prev: np.ndarray, last: np.ndarray) -> np.ndarray:
    return np.repeat(last[None], H + 1, axis=0)


def test_the_arbiter_picks_what_has_been_right_lately_per_horizon() -> None:
    rng = np.random.default_rng(0)
    walking = _walk(np.array([1.0, 0.0, 0.0]), 120, rng)
    arbiter = ForecastArbiter(["network", "constant_velocity"], horizon=H, dt_s=DT, min_scores=5)
    # a "network" that is wrong by 0.3 m on this person, constant velocity that is exact
    candidates = {"network": lambda p, q: _cv(p, q) + 0.3, "constant_velocity": _cv}
    outs = _run(arbiter, walking, candidates)
    assert outs[0].chosen[1:] == ("network",) * H  # nothing scored yet: the preferred one
    assert outs[-1].chosen[1:] == ("constant_velocity",) * H
    np.testing.assert_allclose(outs[-1].joints[1:], _cv(walking[-2], walking[-1])[1:])


def test_the_arbitrated_forecast_converges_to_the_baseline_that_fits_the_motion() -> None:
    rng = np.random.default_rng(11)
    ramp = np.arange(H + 1)[:, None, None] / H

    def network(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # right on average, off by up to 10 cm
        return _cv(p, q) + ramp * rng.normal(0.0, 0.1, size=(H + 1, NUM_JOINTS, 3))

    candidates = {"network": network, "constant_velocity": _cv, "zero_velocity": _hold}
    # pure constant-velocity motion: constant velocity at every step
    walking = _walk(np.array([0.8, 0.3, 0.0]), 150, rng)
    outs = _run(ForecastArbiter(list(candidates), horizon=H, dt_s=DT), walking, candidates)
    assert outs[-1].chosen[1:] == ("constant_velocity",) * H
    np.testing.assert_allclose(outs[-1].joints, _cv(walking[-2], walking[-1]), atol=1e-12)
    # a still person seen with tracking noise: zero velocity (constant velocity extrapolates the noise)
    still = _walk(np.zeros(3), 150, rng, noise=0.005)
    outs = _run(ForecastArbiter(list(candidates), horizon=H, dt_s=DT), still, candidates)
    assert outs[-1].chosen[1:] == ("zero_velocity",) * H
    np.testing.assert_allclose(outs[-1].joints, _hold(still[-2], still[-1]), atol=1e-12)


def test_adaptive_margins_cover_the_target_and_follow_the_motion() -> None:
    rng = np.random.default_rng(1)
    still = _walk(np.zeros(3), 400, rng, noise=0.01)
    arbiter = ForecastArbiter(["hold"], horizon=H, dt_s=DT, coverage=0.9, gamma=0.02, floor_m=0.005)
    outs = _run(arbiter, still, {"hold": _hold})
    coverage = arbiter.coverage()[1:]
    target = 1.0 - arbiter.alpha_k[1:]  # 0.9 at step 0, higher at the far steps (FAR_ALPHA_FACTOR)
    assert np.all(np.abs(coverage - target) < 0.05)  # the fraction of joints inside tracks the target
    calm = outs[-1].margins[H]
    # the person starts walking: holding the pose gets it wrong, the margins widen
    moving = _walk(np.array([1.0, 0.0, 0.0]), 200, rng, noise=0.01) + still[-1].mean(axis=0)
    outs = _run(arbiter, moving, {"hold": _hold})
    assert outs[-1].margins[H] > 5 * calm
    assert outs[-1].margins[H] == pytest.approx(H * DT * 1.0, rel=0.3)  # ~ how far one walks in H steps


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="at least one candidate"):
        ForecastArbiter([], horizon=H, dt_s=DT)
    with pytest.raises(ValueError, match="coverage"):
        ForecastArbiter(["a"], horizon=H, dt_s=DT, coverage=1.0)
    arbiter = ForecastArbiter(["a", "b"], horizon=H, dt_s=DT)
    with pytest.raises(ValueError, match="no forecast from"):
        arbiter.combine(0.0, {"a": np.zeros((H + 1, NUM_JOINTS, 3))})


def test_the_predictor_hands_on_the_arbitrated_forecast_when_asked() -> None:
    from app.prediction.predictor import MotionPredictor
    from app.prediction.skeleton import HumanFrame

    rng = np.random.default_rng(3)
    walking = _walk(np.array([0.0, 0.5, 0.0]), 90, rng, noise=0.005)
    plain = MotionPredictor(kind="graphmixer", tracking_margin_m=0.02)
    arbitrated = MotionPredictor(kind="graphmixer", tracking_margin_m=0.02, arbitrate=True, coverage=0.9)
    assert plain.arbiter is None and arbitrated.arbiter is not None
    # the arbiter starts from the stored quantile at its cold-start level (p99 for a 90-99 % target)
    p95 = plain.margins_for("graphmixer")
    assert np.all(arbitrated.arbiter.prior_m[1:] >= p95[1:] - 1e-9)
    assert arbitrated.arbiter.prior_m[-1] > p95[-1]
    assert arbitrated.arbiter.candidates[-2:] == ("constant_velocity", "zero_velocity")
    for i, pose in enumerate(walking):
        fc = arbitrated.update(HumanFrame(i / 30, pose))
        plain.update(HumanFrame(i / 30, pose))
    assert arbitrated.last_source == "arbitrated"
    # the steps and, between them, the samples whose margins are calibrated there
    H_p = arbitrated.horizon
    assert fc.joints.shape == (2 * H_p + 1, NUM_JOINTS, 3) and np.all(np.isfinite(fc.joints))
    np.testing.assert_allclose(fc.times, fc.t0 + np.arange(2 * H_p + 1) * arbitrated.dt_s / 2)
    np.testing.assert_allclose(fc.joints[1::2], 0.5 * (fc.joints[:-1:2] + fc.joints[2::2]))
    assert np.all(fc.margins >= 0.02) and fc.max_margin_m >= fc.margins.max()
    # on a person walking straight, constant velocity has been right: the far steps take it
    steps = fc.joints[0::2]
    chosen = arbitrated.arbiter.combine(fc.t0, dict.fromkeys(arbitrated.arbiter.candidates, steps)).chosen
    assert chosen[-1] == "constant_velocity"
    arbitrated.reset()
    assert arbitrated.history_len == 0 and arbitrated.arbiter.scored.sum() == 0


def _noisy_stream(rng: np.random.Generator, n: int, sigma: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A still person and a candidate whose every joint is off by isotropic Gaussian noise of ``sigma`` per
    axis: the joint error is Maxwell distributed (known quantiles)."""
    poses = np.repeat(rng.normal(0.0, 0.2, size=(1, NUM_JOINTS, 3)), n, axis=0)
    noise = rng.normal(0.0, sigma, size=(n, H + 1, NUM_JOINTS, 3))
    noise[:, 0] = 0.0
    return poses, {"noisy": poses[:, None] + noise}


def _maxwell_quantile(q: float, sigma: float) -> float:
    """Quantile of |x| for x ~ N(0, sigma^2 I_3) (numerically, from a large sample)."""
    x = np.random.default_rng(99).normal(0.0, sigma, size=(400_000, 3))
    return float(np.quantile(np.linalg.norm(x, axis=1), q))


def _replay(arbiter: ForecastArbiter, poses: np.ndarray, futures: dict[str, np.ndarray]) -> list:
    outs = []
    for i in range(poses.shape[0]):
        arbiter.score(i * DT, poses[i])
        outs.append(arbiter.combine(i * DT, {k: v[i] for k, v in futures.items()}))
    return outs


def test_coverage_on_a_stream_with_a_known_error_distribution_is_the_target() -> None:
    rng = np.random.default_rng(5)
    sigma = 0.05
    poses, futures = _noisy_stream(rng, 1500, sigma)
    arbiter = ForecastArbiter(
        ["noisy"], horizon=H, dt_s=DT, coverage=0.95, floor_m=0.001, far_alpha_factor=1.0
    )
    outs = _replay(arbiter, poses, futures)
    assert np.all(np.abs(arbiter.coverage()[1:] - 0.95) < 0.015)
    # and the margin is the distribution's own 95 % quantile
    assert outs[-1].margins[1:] == pytest.approx(np.full(H, _maxwell_quantile(0.95, sigma)), rel=0.1)


def test_by_default_the_far_steps_aim_higher_and_each_step_tracks_its_own_target() -> None:
    rng = np.random.default_rng(5)
    poses, futures = _noisy_stream(rng, 1500, 0.05)
    arbiter = ForecastArbiter(["noisy"], horizon=H, dt_s=DT, coverage=0.95, floor_m=0.001)
    _replay(arbiter, poses, futures)
    target = 1.0 - arbiter.alpha_k
    assert target[0] == pytest.approx(0.95)
    assert target[H] == pytest.approx(1.0 - 0.05 * FAR_ALPHA_FACTOR)
    assert np.all(np.diff(target) > 0)
    assert np.all(np.abs(arbiter.coverage()[1:] - target[1:]) < 0.015)


def test_between_the_steps_the_margins_are_calibrated_where_the_frames_noise_averages_out() -> None:
    # a still person seen through independent tracking noise, forecast exactly: a step's error is one frame's
    # noise (Maxwell, sigma), the error halfway between two steps the mean of two frames' (sigma / sqrt 2)
    rng = np.random.default_rng(8)
    sigma = 0.03
    truth = rng.normal(0.0, 0.2, size=(NUM_JOINTS, 3))
    frames = truth[None] + rng.normal(0.0, sigma, size=(1500, NUM_JOINTS, 3))
    exact = np.repeat(truth[None], H + 1, axis=0)
    arbiter = ForecastArbiter(
        ["exact"], horizon=H, dt_s=DT, coverage=0.95, floor_m=0.001, far_alpha_factor=1.0
    )
    outs = []
    for i, frame in enumerate(frames):
        arbiter.score(i * DT, frame)
        outs.append(arbiter.combine(i * DT, {"exact": exact}))
    assert np.all(np.abs(arbiter.coverage()[1:] - 0.95) < 0.015)
    assert np.all(np.abs(arbiter.coverage(halves=True) - 0.95) < 0.015)
    q95 = _maxwell_quantile(0.95, sigma)
    assert outs[-1].margins[1:] == pytest.approx(np.full(H, q95), rel=0.1)
    assert outs[-1].half_margins == pytest.approx(np.full(H, q95 / np.sqrt(2.0)), rel=0.1)
    # without: the steps' margins hold between them, where they cover more than the target
    plain = ForecastArbiter(
        ["exact"], horizon=H, dt_s=DT, coverage=0.95, floor_m=0.001, far_alpha_factor=1.0, half_steps=False
    )
    for i, frame in enumerate(frames):
        plain.score(i * DT, frame)
        out = plain.combine(i * DT, {"exact": exact})
    assert out.half_margins is None and np.all(np.isnan(plain.coverage(halves=True)))


def test_two_scores_at_one_point_are_stored_one_after_the_other() -> None:
    from app.prediction.arbitration import _Ledger

    rng = np.random.default_rng(13)
    alpha_k = np.full(4, 0.05)
    ks, err, miss = np.array([2, 1, 2]), rng.random((3, NUM_JOINTS)), np.array([1.0, 0.5, 0.0])
    together, apart = _Ledger(alpha_k, 8), _Ledger(alpha_k, 8)
    rows = together.record(ks, err, miss, 0.1)
    one_by_one = [apart.record(ks[i : i + 1], err[i : i + 1], miss[i : i + 1], 0.1) for i in range(3)]
    np.testing.assert_array_equal(rows, np.concatenate(one_by_one))
    assert rows.tolist() == [0, 0, 1]  # the second score at point 2 goes to the next ring row
    for name in ("err", "count", "head", "alpha_t", "covered", "scored"):
        np.testing.assert_array_equal(getattr(together, name), getattr(apart, name))
    # at point 2 the level moves twice: down to 0 (clipped) after the miss, then up by 0.1 * 0.05
    assert together.count[2] == 2 and together.alpha_t[2] == pytest.approx(0.005)


def test_the_half_step_grid_inserts_the_halfway_samples() -> None:
    from app.prediction.forecast import half_step_grid

    times = np.array([1.0, 1.1, 1.3])
    joints = np.stack([np.full((NUM_JOINTS, 3), v) for v in (0.0, 1.0, 3.0)])
    t, j, m = half_step_grid(times, joints, np.array([0.02, 0.1, 0.3]), np.array([0.05, 0.15]))
    np.testing.assert_allclose(t, [1.0, 1.05, 1.1, 1.2, 1.3])
    np.testing.assert_allclose(j[:, 0, 0], [0.0, 0.5, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(m, [0.02, 0.05, 0.1, 0.15, 0.3])
    with pytest.raises(ValueError, match="do not fit"):
        half_step_grid(times, joints, np.array([0.02, 0.1, 0.3]), np.array([0.05]))


def test_the_margin_quantile_is_numpys() -> None:
    rng = np.random.default_rng(6)
    poses, futures = _noisy_stream(rng, 60, 0.03)
    arbiter = ForecastArbiter(["noisy"], horizon=H, dt_s=DT, window=20, warmup=0, floor_m=0.0)
    _replay(arbiter, poses, futures)
    k = 4
    steps = arbiter._steps
    errs = steps.err[k, : steps.count[k]].ravel()
    expected = np.quantile(errs, 1.0 - steps.alpha_t[k])
    assert arbiter.margins()[k] == pytest.approx(expected, rel=1e-9)


def test_the_prior_holds_until_scores_exist_and_bounds_the_warm_up() -> None:
    rng = np.random.default_rng(7)
    sigma = 0.05
    q95 = _maxwell_quantile(0.95, sigma)
    prior = np.linspace(0.0, 2.0 * q95, H + 1)  # too wide at the far steps, too narrow at the near ones
    poses, futures = _noisy_stream(rng, 300, sigma)
    arbiter = ForecastArbiter(
        ["noisy"],
        horizon=H,
        dt_s=DT,
        floor_m=0.001,
        prior_m=prior,
        warmup=60,
        rescale_prior=False,
        cold_start_scale=0.0,
    )
    outs = _replay(arbiter, poses, futures)
    np.testing.assert_allclose(outs[0].margins[1:], prior[1:])  # nothing scored yet: the prior
    during = outs[40].margins  # every step scored >= 10 and < 60 times: at least the prior
    assert np.all(during[1:] >= prior[1:] - 1e-12)
    after = outs[-1].margins  # past the warm-up: the scores alone
    assert after[H] == pytest.approx(q95, rel=0.2) and after[H] < 0.7 * prior[H]

    # a flat prior far too narrow for this stream: the first forecasts are not covered; the stored one is
    def early_coverage(prior_m: np.ndarray) -> float:
        a = ForecastArbiter(
            ["noisy"],
            horizon=H,
            dt_s=DT,
            floor_m=0.001,
            prior_m=prior_m,
            rescale_prior=False,
            cold_start_scale=0.0,
            min_scores=10,
        )
        _replay(a, poses[:30], futures)
        return float(a.coverage()[H])

    assert early_coverage(np.full(H + 1, 0.2 * q95)) < 0.2
    assert early_coverage(np.full(H + 1, q95)) > 0.85


def test_the_prior_widens_with_what_the_fresh_steps_show() -> None:
    rng = np.random.default_rng(8)
    sigma = 0.05
    q95 = _maxwell_quantile(0.95, sigma)
    poses, futures = _noisy_stream(rng, 16, sigma)
    prior = np.full(H + 1, 0.25 * q95)  # 4x too narrow
    kwargs = {"horizon": H, "dt_s": DT, "floor_m": 0.001, "prior_m": prior, "far_alpha_factor": 1.0}
    kwargs["cold_start_scale"] = 0.0  # the stored prior alone before any score
    kwargs["min_scores"] = 10  # after 16 frames, steps up to 5 scored enough
    plain = _replay(ForecastArbiter(["noisy"], rescale_prior=False, **kwargs), poses, futures)[-1]
    rescaled = _replay(ForecastArbiter(["noisy"], **kwargs), poses, futures)[-5:]
    # after 16 frames the near steps are scored, the far ones not yet: the far margins are the prior, widened
    # to the near steps' quantile of errors over their motion scales times the far steps' motion scale (here
    # about the same at every step: the candidate's noise, which makes each frame's margin vary with it)
    assert plain.margins[H] == pytest.approx(prior[H])
    assert np.mean([out.margins[H] for out in rescaled]) == pytest.approx(q95, rel=0.3)


def test_a_new_person_who_moves_fast_gets_wide_margins_before_any_score() -> None:
    rng = np.random.default_rng(12)
    narrow = np.full(H + 1, 0.05)  # a stored prior from people who hardly moved
    kwargs = {"horizon": H, "dt_s": DT, "prior_m": narrow, "floor_m": 0.001}
    candidates = {"network": _hold, "constant_velocity": _cv}
    running = _walk(np.array([3.0, 0.0, 0.0]), 3, rng)
    first = _run(ForecastArbiter(["network", "constant_velocity"], **kwargs), running, candidates)[0]
    # constant velocity says the person may be 3 m/s x t away: the prior is COLD_START_SCALE times that (plus
    # the floor)
    t = DT * np.arange(H + 1)
    np.testing.assert_allclose(first.margins[1:], (COLD_START_SCALE * (0.05 + 3.0 * t))[1:], rtol=1e-6)
    assert first.margins[0] == pytest.approx(0.001)
    # a still person gets COLD_START_SCALE times the motion scale's floor where that is wider than the stored
    # prior; with no cold-start scale: the stored prior
    still = _run(
        ForecastArbiter(["network", "constant_velocity"], **kwargs), _walk(np.zeros(3), 3, rng), candidates
    )
    np.testing.assert_allclose(still[0].margins[1:], max(0.05, COLD_START_SCALE * 0.05), rtol=1e-6)
    off = ForecastArbiter(["network", "constant_velocity"], cold_start_scale=0.0, **kwargs)
    np.testing.assert_allclose(_run(off, running, candidates)[0].margins[1:], 0.05)
    with pytest.raises(ValueError, match="cold_start_scale"):
        ForecastArbiter(["a"], horizon=H, dt_s=DT, cold_start_scale=-1.0)


def test_prior_margins_take_the_cold_start_level_of_the_stored_quantiles() -> None:
    from app.prediction.arbitration import prior_margins

    stored = {"p50": [0.0, 0.1, 0.2], "p95": [0.0, 0.3, 0.6], "p99": [0.0, 0.5, 1.0], "max_p95": [0, 9, 9]}
    doc = {"fps": 10.0, "kinds": {"net": stored, "none": {"max_p95": [0.0]}}}
    # 95 % target: the p99 row (a new person), on a grid twice as fine, held beyond the stored steps
    np.testing.assert_allclose(
        prior_margins(doc, "net", coverage=0.95, fps=20.0, horizon=6), [0.0, 0.25, 0.5, 0.75, 1.0, 1.0, 1.0]
    )
    np.testing.assert_allclose(prior_margins(doc, "net", coverage=0.5, fps=10.0, horizon=2), [0.0, 0.3, 0.6])
    with pytest.raises(ValueError, match="no stored error quantile"):
        prior_margins(doc, "none", coverage=0.95, fps=10.0, horizon=2)
    with pytest.raises(ValueError, match="no stored error quantiles of 'other'"):
        prior_margins(doc, "other", coverage=0.95, fps=10.0, horizon=2)


def test_the_far_steps_follow_the_near_steps_only_on_clear_evidence() -> None:
    rng = np.random.default_rng(9)
    still = _walk(np.zeros(3), 16, rng)
    # near steps scored, far steps not yet: "hold" has been exact, the preferred "network" off by 0.3 m
    candidates = {"network": lambda p, q: _hold(p, q) + 0.3, "hold": _hold}
    kwargs = {"horizon": H, "dt_s": DT, "min_scores": 10}  # after 16 frames, steps up to 5 scored enough
    plain = _run(ForecastArbiter(["network", "hold"], transfer_ratio=0.0, **kwargs), still, candidates)[-1]
    transfer = _run(ForecastArbiter(["network", "hold"], **kwargs), still, candidates)[-1]  # default 0.5
    assert plain.chosen[1] == "hold" and plain.chosen[H] == "network"
    assert transfer.chosen[1:] == ("hold",) * H
    # a candidate only slightly better at the near steps does not take the far ones
    close = {"network": lambda p, q: _hold(p, q) + 0.01, "hold": lambda p, q: _hold(p, q) + 0.008}
    out = _run(ForecastArbiter(["network", "hold"], transfer_ratio=0.5, **kwargs), still, close)[-1]
    assert out.chosen[1] == "hold" and out.chosen[H] == "network"


def test_the_compiled_arbiter_gives_the_numpy_reference_numbers() -> None:
    pytest.importorskip("numba")
    rng = np.random.default_rng(11)
    poses, futures = _noisy_stream(rng, 200, 0.04)
    other = poses[:, None] + rng.normal(0.0, 0.04, size=futures["noisy"].shape)
    other[:, 0] = poses
    futures = {"noisy": futures["noisy"], "other": other}
    kwargs = {"horizon": H, "dt_s": DT, "window": 30, "min_scores": 5, "floor_m": 0.0}
    compiled = ForecastArbiter(["noisy", "other"], **kwargs)
    reference = ReferenceForecastArbiter(["noisy", "other"], **kwargs)
    for a, b in zip(_replay(compiled, poses, futures), _replay(reference, poses, futures), strict=True):
        np.testing.assert_allclose(a.margins, b.margins, rtol=1e-12, atol=0)
        np.testing.assert_allclose(a.half_margins, b.half_margins, rtol=1e-12, atol=0)
        np.testing.assert_array_equal(a.joints, b.joints)
        assert a.chosen == b.chosen
    np.testing.assert_allclose(compiled._cand_err, reference._cand_err, rtol=1e-12)
    np.testing.assert_allclose(compiled._steps.alpha_t, reference._steps.alpha_t, rtol=1e-12)
    np.testing.assert_array_equal(compiled.covered, reference.covered)


def test_the_compiled_quantile_is_numpys_at_every_level() -> None:
    pytest.importorskip("numba")
    from app.prediction._aci_kernels import step_quantiles

    rng = np.random.default_rng(12)
    err = rng.gamma(2.0, 0.05, size=(6, 7, 5))
    err[2, :3] = 0.1  # ties
    count = np.array([7, 3, 7, 1, 0, 5])
    level = np.array([0.95, 0.5, 0.999, 0.3, 0.9, 1.0])
    for levels in (level, np.array([0.0, 0.1, 0.05, 0.7, 0.2, 0.45])):
        exact = step_quantiles(err, count, levels, np.full(6, np.inf))
        for k in range(6):
            if count[k] == 0:
                assert exact[k] == np.inf
            else:
                expected = np.quantile(err[k, : count[k]].ravel(), levels[k])
                assert exact[k] == pytest.approx(expected, rel=1e-12)
        # a hint (last frame's quantiles) only saves work: too low, too high or right, the same numbers
        for factor in (0.3, 1.0, 1.1, 5.0):
            hinted = step_quantiles(err, count, levels, np.where(np.isfinite(exact), factor * exact, np.inf))
            np.testing.assert_array_equal(hinted, exact)


def test_the_runtime_arbiter_starts_with_the_first_full_history_as_the_evaluation_does() -> None:
    """Until the history spans the network's input the predictor hands on its fallback (constant velocity
    from the last two frames) without the arbiter, which scores and learns only from the forecasts made from
    a full history, as :func:`app.prediction.evaluate.evaluate_arbitrated` replays them. Two noisy frames
    extrapolated over a second are far off even for a person standing still; scored, they held the 1-s
    margin at half a metre and more for the window's 3 s, and the planner found no plan near the person
    meanwhile (every proactive trial began with seconds of waiting for a plan)."""
    from app.cell.operator_sim import SimulatedOperator
    from app.config import load_workcell
    from app.prediction.predictor import MotionPredictor

    operator = SimulatedOperator(load_workcell(), seed=3)  # at work, still from 2 s to 3.3 s
    p = MotionPredictor(kind="graphmixer", tracking_margin_m=0.02, arbitrate=True)
    assert p.arbiter is not None
    for i in range(p.history - 1):
        p.update(operator.frame_at(i / 30))
        assert p.last_source == ("zero_velocity" if i == 0 else "constant_velocity")
        assert not np.isfinite(p.arbiter._t0).any()  # nothing stored to be scored
    p.update(operator.frame_at((p.history - 1) / 30))
    assert p.last_source == "arbitrated" and np.isfinite(p.arbiter._t0).sum() == 1
    far = {i: p.update(operator.frame_at(i / 30)).margins[-1] for i in range(p.history, 100)}
    # once the far step's warm-up is over, the 1-s margin is the still person's (0.55 m with the stand-ins)
    assert max(far[i] for i in range(75, 100)) < 0.1
