from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from app.prediction.baselines import constant_velocity, zero_velocity
from app.prediction.fastforward import FastGraphMixer
from app.prediction.forecast import HumanForecast
from app.prediction.graphmixer import GraphMixer, GraphMixerConfig, save_checkpoint
from app.prediction.predictor import (
    DEFAULT_WEIGHTS,
    MotionPredictor,
    PredictorInputError,
    load_default_predictor,
    quantiles_path,
)
from app.prediction.reference import cap_speed_reference
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS, HumanFrame

torch.set_num_threads(1)
FPS = 30.0
DT = 1.0 / FPS


def _pose(t: float) -> np.ndarray:
    """A person walking along +x at 1 m/s, facing +x, with a swinging right hand."""
    rng = np.random.default_rng(0)
    base = rng.normal(scale=0.2, size=(NUM_JOINTS, 3)) + np.array([0.0, 0.0, 1.0])
    base[JOINT_INDEX["l_hip"]] = [0.0, 0.1, 0.9]
    base[JOINT_INDEX["r_hip"]] = [0.0, -0.1, 0.9]
    pose = base + np.array([1.0 * t, 0.0, 0.0])
    pose[JOINT_INDEX["r_hand"]] += [0.0, 0.0, 0.1 * np.sin(3.0 * t)]
    return pose


def _frame(t: float, **kw) -> HumanFrame:
    return HumanFrame(t=t, joints=kw.pop("joints", _pose(t)), **kw)


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory) -> Path:
    """An untrained small Graph-Mixer (random head) and a quantile file next to it."""
    torch.manual_seed(0)
    model = GraphMixer(GraphMixerConfig(channels=8, blocks=1, embed_dim=4))
    with torch.no_grad():
        model.head.weight.weight.normal_(std=0.05)
    path = tmp_path_factory.mktemp("w") / "tiny.pt"
    save_checkpoint(path, model)
    steps = np.arange(31) / FPS
    kinds = {
        "graphmixer": {"p95": (0.3 * steps).tolist()},
        "constant_velocity": {"p95": (0.5 * steps).tolist()},
        "zero_velocity": {"p95": (0.4 * steps).tolist()},
    }
    quantiles_path(path).write_text(json.dumps({"fps": FPS, "horizon": 30, "kinds": kinds}))
    return path


def _feed(p: MotionPredictor, times) -> HumanForecast:
    f = None
    for t in times:
        f = p.update(_frame(float(t)))
    assert f is not None
    return f


def test_baselines_known_answers() -> None:
    hist = np.stack([_pose(k * DT) for k in range(10)])[None]
    cv = constant_velocity(hist, 30)
    # the pelvis moves at 1 m/s: after 30 frames it is 1 m further
    np.testing.assert_allclose(cv[0, -1, 0] - hist[0, -1, 0], [1.0, 0.0, 0.0], atol=1e-9)
    zv = zero_velocity(hist, 5)
    assert zv.shape == (1, 5, NUM_JOINTS, 3)
    np.testing.assert_allclose(zv[0, 3], hist[0, -1])
    np.testing.assert_allclose(constant_velocity(hist[:, :1], 4), zero_velocity(hist[:, :1], 4))
    with pytest.raises(ValueError, match="history"):
        constant_velocity(np.zeros((10, NUM_JOINTS, 3)), 3)


def test_forecast_layout_and_warm_up(tiny_weights: Path) -> None:
    p = MotionPredictor(weights=tiny_weights)
    assert p.effective_kind == "graphmixer"
    f = p.update(_frame(1.0))
    assert p.last_source == "zero_velocity"
    assert f.joints.shape == (31, NUM_JOINTS, 3) and f.t0 == 1.0
    np.testing.assert_allclose(np.diff(f.times), DT)
    f = p.update(_frame(1.0 + DT))
    assert p.last_source == "constant_velocity"
    np.testing.assert_allclose(f.joints[-1, 0] - f.joints[0, 0], [1.0, 0.0, 0.0], atol=1e-6)
    f = _feed(p, 1.0 + DT * np.arange(2, 10))
    assert p.last_source == "graphmixer"
    np.testing.assert_allclose(f.joints[0], _pose(1.0 + 9 * DT))
    # margins come from the p95 quantiles of the predictor that made the forecast, and grow
    np.testing.assert_allclose(f.margins, 0.3 * np.arange(31) / FPS)
    assert p.counters["fallback_forecasts"] == 9  # frames 1 to 9 of the warm-up


def test_graphmixer_window_matches_predict_batch(tiny_weights: Path) -> None:
    p = MotionPredictor(weights=tiny_weights, max_speed_mps=1e3)  # no cap: compare the raw network
    f = _feed(p, 2.0 + DT * np.arange(12))
    hist = np.stack([_pose(2.0 + DT * k) for k in range(2, 12)])[None]
    np.testing.assert_allclose(f.joints[1:], p.predict_batch(hist)[0], atol=1e-5)
    # several people at once
    many = np.concatenate([hist, hist + np.array([0.5, 0.0, 0.0])])
    out = p.predict_batch(many)
    assert out.shape == (2, 30, NUM_JOINTS, 3)
    np.testing.assert_allclose(out[1], out[0] + [0.5, 0.0, 0.0], atol=1e-5)
    # the batch runs eagerly, one person through the compiled pass: same numbers
    np.testing.assert_allclose(out[0], p.predict_batch(hist)[0], atol=1e-5)
    eager = MotionPredictor(weights=tiny_weights, jit=False).predict_batch(hist)
    np.testing.assert_allclose(eager, p.predict_batch(hist), atol=1e-5)
    with pytest.raises(ValueError, match="non-finite"):
        p.predict_batch(np.full((1, 10, NUM_JOINTS, 3), np.nan))


def test_single_person_forecasts_run_through_the_compiled_pass_then_onnx_then_torch(
    tiny_weights: Path, monkeypatch: pytest.MonkeyPatch, caplog
) -> None:
    import builtins

    hist = np.stack([_pose(2.0 + DT * k) for k in range(10)])[None]
    hist = hist + np.random.default_rng(3).normal(0.0, 0.02, size=hist.shape)
    eager = MotionPredictor(weights=tiny_weights, jit=False)
    assert eager.single_person_backend == "torch"
    expected = eager.predict_batch(hist)
    fast = MotionPredictor(weights=tiny_weights)
    assert fast.single_person_backend == "numba"
    np.testing.assert_allclose(fast.predict_batch(hist), expected, atol=1e-5)
    # a compiled pass that fails its check against torch at build is not used: ONNX Runtime answers
    pytest.importorskip("onnxruntime")
    monkeypatch.setattr("app.prediction.predictor._COPIES", {})
    real_call = FastGraphMixer.__call__
    monkeypatch.setattr(FastGraphMixer, "__call__", lambda self, x: real_call(self, x) + 1e-3)
    with caplog.at_level(logging.WARNING, logger="app.prediction.predictor"):
        checked = MotionPredictor(weights=tiny_weights)
        assert checked.single_person_backend == "onnxruntime"
    assert "differs from the torch one" in caplog.text
    np.testing.assert_allclose(checked.predict_batch(hist), expected, atol=1e-5)
    # without onnxruntime either, the traced torch network answers, with the same numbers
    real_import = builtins.__import__

    def no_onnxruntime(name: str, *args, **kwargs):
        if name == "onnxruntime":
            raise ImportError("no onnxruntime here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_onnxruntime)
    monkeypatch.setattr("app.prediction.predictor._COPIES", {})
    slow = MotionPredictor(weights=tiny_weights)
    assert slow.single_person_backend == "torch-traced"
    np.testing.assert_allclose(slow.predict_batch(hist), expected, atol=1e-5)
    assert slow._onnx_session() is None


def test_jittered_timestamps_are_resampled(tiny_weights: Path) -> None:
    p = MotionPredictor(kind="constant_velocity")
    rng = np.random.default_rng(1)
    times = 0.5 + DT * np.arange(15) + rng.uniform(-0.004, 0.004, size=15)
    _feed(p, times)
    win = p.window()
    grid = times[-1] - DT * np.arange(9, -1, -1)
    expected = np.stack([_pose(t) for t in grid])
    # the pose is linear in time except for the small hand swing
    np.testing.assert_allclose(win[:, 0], expected[:, 0], atol=1e-9)


def test_missing_weights_fall_back_with_warning(tmp_path: Path, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="app.prediction.predictor"):
        p = MotionPredictor(weights=tmp_path / "nope.pt")
    assert p.effective_kind == "constant_velocity"
    assert any("not found" in r.message for r in caplog.records)
    f = _feed(p, DT * np.arange(12))
    assert p.last_source == "constant_velocity" and np.all(np.isfinite(f.joints))


def test_mismatched_weights_fall_back(tiny_weights: Path, tmp_path: Path, caplog) -> None:
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00" * 64)
    with caplog.at_level(logging.WARNING):
        assert MotionPredictor(weights=junk).effective_kind == "constant_velocity"
        # weights made for 10 observed frames do not fit a 12-frame history
        assert MotionPredictor(weights=tiny_weights, history=12).effective_kind == "constant_velocity"
    assert len([r for r in caplog.records if "falling back" in r.message]) == 2


def test_margins_without_quantiles_grow_at_human_speed(tmp_path: Path) -> None:
    p = MotionPredictor(
        kind="zero_velocity", weights=tmp_path / "none.pt", quantiles=tmp_path / "none.json", growth_mps=1.6
    )
    f = _feed(p, [0.0])
    np.testing.assert_allclose(f.margins, np.minimum(1.6 * np.arange(31) / FPS, 1.0))


def test_nan_and_inf_joints_are_repaired(tiny_weights: Path) -> None:
    p = MotionPredictor(weights=tiny_weights)
    _feed(p, DT * np.arange(10))
    t = 10 * DT
    bad = _pose(t)
    bad[JOINT_INDEX["l_wrist"]] = np.nan
    bad[JOINT_INDEX["head"], 2] = np.inf
    f = p.update(HumanFrame(t=t, joints=bad))
    assert np.all(np.isfinite(f.joints)) and np.all(np.isfinite(f.margins))
    # filled from the previous frame, moved with the body (1 m/s along x)
    expected = _pose(9 * DT)[JOINT_INDEX["l_wrist"]] + [DT, 0.0, 0.0]
    np.testing.assert_allclose(f.joints[0, JOINT_INDEX["l_wrist"]], expected, atol=1e-3)
    assert p.counters["repaired_joints"] == 2
    assert p.last_source == "graphmixer"


def test_low_confidence_joints_are_repaired(tiny_weights: Path) -> None:
    p = MotionPredictor(weights=tiny_weights, min_confidence=0.5)
    _feed(p, DT * np.arange(10))
    t = 10 * DT
    wild = _pose(t)
    wild[JOINT_INDEX["r_hand"]] = [50.0, 50.0, 50.0]  # a tracker glitch with low confidence
    conf = np.ones(NUM_JOINTS)
    conf[JOINT_INDEX["r_hand"]] = 0.1
    f = p.update(HumanFrame(t=t, joints=wild, confidence=conf))
    assert np.linalg.norm(f.joints[0, JOINT_INDEX["r_hand"]] - _pose(t)[JOINT_INDEX["r_hand"]]) < 0.05
    assert np.all(np.isfinite(f.joints))


def test_missing_joints_without_history_use_ancestors() -> None:
    p = MotionPredictor(kind="constant_velocity")
    pose = _pose(0.0)
    conf = np.ones(NUM_JOINTS)
    conf[[JOINT_INDEX["l_elbow"], JOINT_INDEX["l_wrist"]]] = 0.0
    f = p.update(HumanFrame(t=0.0, joints=pose, confidence=conf))
    np.testing.assert_allclose(f.joints[0, JOINT_INDEX["l_wrist"]], pose[JOINT_INDEX["l_shoulder"]])


def test_frame_without_valid_joints(tiny_weights: Path) -> None:
    p = MotionPredictor(weights=tiny_weights)
    nan_frame = HumanFrame(t=0.0, joints=np.full((NUM_JOINTS, 3), np.nan))
    with pytest.raises(PredictorInputError, match="no valid joint"):
        p.update(nan_frame)
    _feed(p, DT * np.arange(1, 11))
    f = p.update(HumanFrame(t=11 * DT, joints=np.full((NUM_JOINTS, 3), np.nan)))
    assert p.counters["dropped_frames"] == 2
    assert f.t0 == pytest.approx(10 * DT) and np.all(np.isfinite(f.joints))


def test_time_gap_resets_history(tiny_weights: Path) -> None:
    p = MotionPredictor(weights=tiny_weights)
    _feed(p, DT * np.arange(10))
    assert p.last_source == "graphmixer"
    f = p.update(_frame(2.0))  # 1.7 s later
    assert p.counters["gap_resets"] == 1 and p.history_len == 1
    assert p.last_source == "zero_velocity" and np.all(np.isfinite(f.joints))
    _feed(p, 2.0 + DT * np.arange(1, 5))
    assert p.last_source == "constant_velocity"
    _feed(p, 2.0 + DT * np.arange(5, 10))
    assert p.last_source == "graphmixer"


def test_time_going_backwards_resets_history(tiny_weights: Path) -> None:
    p = MotionPredictor(weights=tiny_weights)
    _feed(p, 5.0 + DT * np.arange(10))
    f = p.update(_frame(1.0))
    assert p.counters["time_resets"] == 1 and p.history_len == 1
    assert f.t0 == 1.0 and p.last_source == "zero_velocity"
    # a repeated timestamp replaces the frame instead of dividing by zero
    f = p.update(_frame(1.0))
    f = p.update(_frame(1.0 + DT))
    assert p.counters["duplicates"] == 1 and np.all(np.isfinite(f.joints))


def test_predicted_speed_is_capped() -> None:
    p = MotionPredictor(kind="constant_velocity", max_speed_mps=2.0)
    p.update(_frame(0.0))
    jump = _pose(DT) + np.array([1.0, 0.0, 0.0])  # 30 m/s for one frame
    f = p.update(HumanFrame(t=DT, joints=jump))
    travel = np.linalg.norm(f.joints[-1] - f.joints[0], axis=-1)
    assert travel.max() <= 2.0 + 1e-9


def test_compiled_speed_cap_equals_the_numpy_reference() -> None:
    p = MotionPredictor(kind="constant_velocity", max_speed_mps=2.0)
    rng = np.random.default_rng(3)
    for scale in (0.01, 0.1, 1.0, 10.0):  # none, some and all of the joints capped
        last = rng.normal(size=(NUM_JOINTS, 3))
        future = last[None] + rng.normal(scale=scale, size=(30, NUM_JOINTS, 3))
        future[3, 4] = last[4]  # a joint that does not move
        got = p._cap_speed(last, future)
        want = cap_speed_reference(last, future, dt_s=p.dt_s, max_speed_mps=p.max_speed_mps)
        assert got.shape == (31, NUM_JOINTS, 3)
        np.testing.assert_array_equal(got, want)


def test_frames_on_the_grid_are_taken_as_they_are(tiny_weights: Path) -> None:
    """The window of frames at the nominal rate is the frames themselves; a frame off the grid by more than
    the tolerance is resampled."""
    p = MotionPredictor(weights=tiny_weights)
    times = 2.0 + DT * np.arange(12)
    _feed(p, times)
    want = np.stack([_pose(t) for t in times[-10:]])
    np.testing.assert_array_equal(p.window(), want)
    p.reset()
    jittered = times.copy()
    jittered[-3] += 0.25 * DT
    _feed(p, jittered)
    w = p.window()
    np.testing.assert_allclose(w[..., 0], want[..., 0], atol=1e-9)  # x is linear in time: resampled exactly
    assert not np.array_equal(w[-3], _pose(jittered[-3]))


def test_unknown_kind_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown predictor kind"):
        MotionPredictor(kind="oracle")  # type: ignore[arg-type]


@pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="shipped weights not built yet")
def test_shipped_weights_load_and_are_small() -> None:
    p = load_default_predictor()
    assert p.effective_kind == "graphmixer"
    assert DEFAULT_WEIGHTS.stat().st_size < 5e6
    m = p.margins_for("graphmixer")
    assert m[0] == 0.0 and m[-1] > m[3] > 0.0
    f = _feed(p, DT * np.arange(10))
    assert p.last_source == "graphmixer" and np.all(np.isfinite(f.joints))


@pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="shipped weights not built yet")
def test_shipped_weights_beat_constant_velocity_on_cmu_test(cmu_dir: Path) -> None:
    from app.prediction.data import load_clip_dir
    from app.prediction.evaluate import evaluate_clips

    p = load_default_predictor()
    fns = {k: (lambda obs, H, k=k: p.predict_batch(obs, kind=k)) for k in ("graphmixer", "constant_velocity")}
    res = evaluate_clips(load_clip_dir(cmu_dir, split="test"), fns, stride=3)
    gm, cv = res["graphmixer"]["mpjpe_mm"], res["constant_velocity"]["mpjpe_mm"]
    assert gm["400"] <= 0.7 * cv["400"]
    assert gm["1000"] <= 0.8 * cv["1000"]
