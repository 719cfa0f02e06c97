"""Online arbitration between forecasts and adaptive conformal margins (app.prediction.arbitration)."""

from __future__ import annotations

import numpy as np
import pytest

from app.prediction.arbitration import ForecastArbiter
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


def test_adaptive_margins_cover_the_target_and_follow_the_motion() -> None:
    rng = np.random.default_rng(1)
    still = _walk(np.zeros(3), 400, rng, noise=0.01)
    arbiter = ForecastArbiter(["hold"], horizon=H, dt_s=DT, coverage=0.9, gamma=0.02, floor_m=0.005)
    outs = _run(arbiter, still, {"hold": _hold})
    coverage = arbiter.coverage()[1:]
    assert np.all(np.abs(coverage - 0.9) < 0.05)  # the fraction of joints inside tracks the target
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
    assert arbitrated.arbiter.candidates[-2:] == ("constant_velocity", "zero_velocity")
    for i, pose in enumerate(walking):
        fc = arbitrated.update(HumanFrame(i / 30, pose))
        plain.update(HumanFrame(i / 30, pose))
    assert arbitrated.last_source == "arbitrated"
    assert fc.joints.shape == (arbitrated.horizon + 1, NUM_JOINTS, 3) and np.all(np.isfinite(fc.joints))
    assert np.all(fc.margins >= 0.02) and fc.max_margin_m >= fc.margins.max()
    # on a person walking straight, constant velocity has been right: the far steps take it
    assert (
        arbitrated.arbiter.combine(fc.t0, {name: fc.joints for name in arbitrated.arbiter.candidates}).chosen[
            -1
        ]
        == "constant_velocity"
    )
    arbitrated.reset()
    assert arbitrated.history_len == 0 and arbitrated.arbiter.scored.sum() == 0
