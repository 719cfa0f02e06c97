"""The arbitrated forecast per clip against the better baseline (``per_clip``, ``worst_clip`` of
:func:`app.prediction.evaluate.evaluate_arbitrated`)."""

from __future__ import annotations

import numpy as np
import pytest

from app.prediction.data import Clip
from app.prediction.evaluate import evaluate_arbitrated, evaluate_clips, report_markdown
from app.prediction.skeleton import NUM_JOINTS

FPS, T_IN, H = 10.0, 2, 3
HORIZONS = (100, 200, 300)  # steps 1, 2 and 3
FRAMES = 10  # forecasts from frames 1..6 (the last observed one), 3.5 on average


def _hold(obs: np.ndarray, h: int) -> np.ndarray:
    return np.repeat(obs[:, -1:], h, axis=1)


def _cv(obs: np.ndarray, h: int) -> np.ndarray:
    v = obs[:, -1] - obs[:, -2]
    return obs[:, -1][:, None] + np.arange(1, h + 1)[None, :, None, None] * v[:, None]


def _clip(name: str, x: np.ndarray) -> Clip:
    """A body of fixed shape whose every joint moves by ``x`` (FRAMES,) along the x axis."""
    body = np.random.default_rng(0).normal(0.0, 0.3, size=(NUM_JOINTS, 3))
    pos = np.repeat(body[None], x.size, axis=0)
    pos[..., 0] += x[:, None]
    return Clip(name=name, positions=pos, split="test")


def _accelerating(name: str, start_frame: int) -> Clip:
    """Constant acceleration a = 2 m/s^2 from rest at frame ``-start_frame``: x = (t + start_frame dt)^2."""
    t = (np.arange(FRAMES) + start_frame) / FPS
    return _clip(name, t**2)


def test_the_worst_clip_is_the_one_the_forecast_gets_most_wrong_against_the_better_baseline() -> None:
    """The preferred candidate (the network's stand-in, here holding the pose) is taken at every step (no
    step is ever scored enough to switch), so the forecast is zero velocity and the ratios have closed forms.

    Under constant acceleration a, a forecast from frame i (t = i dt) is off by a dt^2 (i k + k^2 / 2) at
    step k when it holds the pose, and by a dt^2 k (k + 1) / 2 at constant velocity from the last two frames
    at every i: with i = m on average over the clip's forecasts, the forecast over the better baseline
    (constant velocity) is (2 m + k) / (k + 1). From rest at frame 0, m = 3.5: 4, 3 and 2.5; from rest ten
    frames before, m = 13.5: 14, 29 / 3 and 7.5. A person jittering by +-d on the spot is off by 2d, 0 and
    2d holding the pose and by 4d, 4d and 8d at constant velocity: the forecast is the better baseline, 1
    (0 against 0 at step 2)."""
    clips = [
        _accelerating("from_rest", 0),
        _accelerating("late", 10),
        _clip("jitter", 0.01 * (-1.0) ** np.arange(FRAMES)),
    ]
    predictors = {"network": _hold, "constant_velocity": _cv, "zero_velocity": _hold}
    out = evaluate_arbitrated(
        clips,
        predictors,
        t_in=T_IN,
        horizon=H,
        fps=FPS,
        horizons_ms=HORIZONS,
        arbiter_options={"min_scores": 10**6},
    )
    assert out["chosen"] == {"network": 1.0, "constant_velocity": 0.0, "zero_velocity": 0.0}
    per_clip = {c["clip"]: c for c in out["per_clip"]}
    assert list(per_clip) == ["test/from_rest", "test/late", "test/jitter"]
    assert all(c["forecasts"] == FRAMES - T_IN - H + 1 for c in per_clip.values())
    assert per_clip["test/from_rest"]["ratio"] == {"100": 4.0, "200": 3.0, "300": 2.5}
    assert per_clip["test/late"]["ratio"] == {"100": 14.0, "200": round(29 / 3, 3), "300": 7.5}
    assert per_clip["test/jitter"]["ratio"] == {"100": 1.0, "200": 1.0, "300": 1.0}
    # a dt^2 = 0.02 m: holding the pose is off by 20 (13.5 + 0.5) mm at step 1 of the late clip
    late = per_clip["test/late"]
    assert late["mpjpe_mm"]["100"] == pytest.approx(280.0)
    cv_mm = {"100": 20.0, "200": 60.0, "300": 120.0}  # a dt^2 k (k + 1) / 2
    assert late["baselines_mm"]["constant_velocity"] == pytest.approx(cv_mm)
    assert late["baselines_mm"]["zero_velocity"] == late["mpjpe_mm"]
    assert per_clip["test/jitter"]["baselines_mm"]["zero_velocity"] == pytest.approx(
        {"100": 20.0, "200": 0.0, "300": 20.0}
    )
    assert out["worst_clip"] == {
        "clip": "test/late",
        "horizon_ms": 100,
        "ratio": 14.0,
        "arbitrated_mm": 280.0,
        "best_baseline": "constant_velocity",
        "best_baseline_mm": 20.0,
        "coverage": late["coverage"]["100"],
        "forecasts": 6,
    }
    # the clips' coverages make up the whole set's
    for ms in map(str, HORIZONS):
        mean = np.mean([c["coverage"][ms] for c in per_clip.values()])
        assert out["coverage"][ms] == pytest.approx(mean, abs=1e-4)


def test_the_baselines_per_clip_are_those_of_every_window_of_the_clip() -> None:
    """Arbitrated as at run time (the candidates taken by their recent errors), a clip's baselines are the
    same windows' as :func:`evaluate_clips` on that clip alone (every window, the first one included), the
    ratios the arbitrated MPJPE over the better of them, and the worst clip the highest ratio of all."""
    rng = np.random.default_rng(4)
    clips = [
        _clip("noisy_walk", 1.2 * np.arange(40) / FPS + rng.normal(0.0, 0.01, 40)),
        _clip("sway", 0.2 * np.sin(np.arange(40) / 3.0)),
    ]
    predictors = {"constant_velocity": _cv, "zero_velocity": _hold}
    out = evaluate_arbitrated(clips, predictors, t_in=T_IN, horizon=H, fps=FPS, horizons_ms=HORIZONS)
    ratios = []
    for clip, entry in zip(clips, out["per_clip"], strict=True):
        alone = evaluate_clips([clip], predictors, t_in=T_IN, horizon=H, fps=FPS, horizons_ms=HORIZONS)
        assert entry["forecasts"] == alone["zero_velocity"]["windows"] == 40 - T_IN - H + 1
        for ms in map(str, HORIZONS):
            cv, zv = (alone[n]["mpjpe_mm"][ms] for n in ("constant_velocity", "zero_velocity"))
            assert entry["baselines_mm"]["constant_velocity"][ms] == pytest.approx(cv, abs=0.05)
            assert entry["baselines_mm"]["zero_velocity"][ms] == pytest.approx(zv, abs=0.05)
            # (the MPJPE reported to 0.1 mm, the ratio to 0.001)
            tol = 0.0005 + 0.05 / min(cv, zv) + 1e-9
            assert entry["ratio"][ms] == pytest.approx(entry["mpjpe_mm"][ms] / min(cv, zv), abs=tol)
            ratios.append((entry["ratio"][ms], entry["clip"], int(ms)))
    worst = out["worst_clip"]
    assert (worst["ratio"], worst["clip"], worst["horizon_ms"]) == max(ratios)
    # the set's MPJPE is the clips' weighted by their forecasts
    n = np.array([c["forecasts"] for c in out["per_clip"]])
    for ms in map(str, HORIZONS):
        mm = np.array([c["mpjpe_mm"][ms] for c in out["per_clip"]])
        assert out["mpjpe_mm"][ms] == pytest.approx(float(mm @ n / n.sum()), abs=0.1)
    # no baseline among the candidates: nothing to measure against
    alone = evaluate_arbitrated(clips, {"network": _cv}, t_in=T_IN, horizon=H, fps=FPS, horizons_ms=HORIZONS)
    assert alone["worst_clip"] is None and all(c["ratio"] == {} for c in alone["per_clip"])


def test_the_model_card_section_names_the_worst_clip() -> None:
    cols = {"80": 10.0, "1000": 100.0}
    report = {
        "clips": "/data/cmu_mocap (test)",
        "windows": 10,
        "mpjpe_mm": {"constant_velocity": cols, "zero_velocity": cols},
        "forecast": {
            "mpjpe_mm": cols,
            "coverage": {"80": 0.95, "1000": 0.94},
            "coverage_target": 0.95,
            "margin_mm": cols,
            "forecasts": 10,
            "chosen": {"constant_velocity": 1.0},
            "worst_clip": {
                "clip": "test/jumping_1",
                "horizon_ms": 1000,
                "ratio": 1.234,
                "arbitrated_mm": 123.4,
                "best_baseline": "zero_velocity",
                "best_baseline_mm": 100.0,
                "coverage": 0.9312,
                "forecasts": 483,
            },
        },
    }
    text = report_markdown(report, horizons_ms=(80, 1000))
    assert text.endswith(
        "Worst clip (the forecast over the better baseline): test/jumping_1 at 1000 ms, 1.234x (123.4 mm "
        "against zero_velocity 100.0 mm; coverage 0.931, 483 forecasts)."
    )
