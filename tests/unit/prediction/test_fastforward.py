from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from app.prediction import _kernels
from app.prediction.fastforward import FastGraphMixer, compile_fast
from app.prediction.graphmixer import GraphMixer, GraphMixerConfig
from app.prediction.predictor import DEFAULT_WEIGHTS, load_graphmixer
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS

torch.set_num_threads(1)
TOL_M = 1e-5


def _histories(t_in: int, n: int, seed: int) -> np.ndarray:
    """``n`` observed histories (n, t_in, J, 3) at 30 Hz: people around 1 m high anywhere in a 4 m square,
    any heading, walking at up to 2 m/s with swinging joints; the last one has all joints at one point
    (a degenerate facing) and the one before stands still (``n >= 3``)."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, t_in, NUM_JOINTS, 3))
    steps = np.arange(t_in)[:, None, None] / 30.0
    for i in range(n):
        yaw = rng.uniform(-np.pi, np.pi)
        body = rng.normal(scale=0.25, size=(NUM_JOINTS, 3))
        body[JOINT_INDEX["l_hip"]] = [0.0, 0.12, -0.1]
        body[JOINT_INDEX["r_hip"]] = [0.0, -0.12, -0.1]
        body[JOINT_INDEX["l_shoulder"]] = [0.0, 0.2, 0.45]
        body[JOINT_INDEX["r_shoulder"]] = [0.0, -0.2, 0.45]
        c, s = np.cos(yaw), np.sin(yaw)
        body = body @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        centre = np.array([*rng.uniform(-2.0, 2.0, size=2), 1.0])
        speed = rng.uniform(0.0, 2.0)
        heading = rng.uniform(-np.pi, np.pi)
        v = speed * np.array([np.cos(heading), np.sin(heading), 0.0])
        swing = rng.normal(scale=0.3, size=(1, NUM_JOINTS, 3)) * np.sin(2 * np.pi * 1.5 * steps)
        out[i] = centre + body + steps * v + swing
    out[-2] = out[-2, :1]  # standing still
    out[-1] = np.array([0.5, -1.0, 1.0])  # every joint at one point: no facing, the identity frame
    return out


def _torch(model: GraphMixer, x: np.ndarray, *, double: bool = False) -> np.ndarray:
    with torch.inference_mode():
        if double:
            return copy.deepcopy(model).double()(torch.from_numpy(x)).numpy()
        return model(torch.from_numpy(x.astype(np.float32))).numpy()


def _fast(model: GraphMixer, x: np.ndarray) -> np.ndarray:
    f = compile_fast(model)
    return np.stack([f(h) for h in x])


def _randomise(model: GraphMixer, seed: int) -> GraphMixer:
    """Perturb every parameter (LayerNorm scales and shifts, adjacency offsets, the zero-initialised head and
    skip), so that every folded term of the compiled pass matters."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.add_(torch.randn(p.shape, generator=g) * (0.2 if "norm" in name else 0.1))
    return model.eval()


def test_the_shipped_network_matches_torch() -> None:
    model = load_graphmixer(DEFAULT_WEIGHTS).model
    x = _histories(model.cfg.t_in, 12, seed=1)
    got = _fast(model, x)
    assert got.shape == (12, model.cfg.horizon, NUM_JOINTS, 3) and got.dtype == np.float64
    np.testing.assert_allclose(got, _torch(model, x), rtol=0, atol=TOL_M)
    np.testing.assert_allclose(got, _torch(model, x, double=True), rtol=0, atol=TOL_M)
    # the forecasts are far from trivial: the comparison above is not between two near-constant outputs
    assert np.abs(got - x[:, -1:]).max() > 0.2


@pytest.mark.parametrize(
    "cfg",
    [
        GraphMixerConfig(
            channels=20, blocks=2, t_in=6, horizon=12, embed_dim=4, se_reduction=2, pose_input=False,
            linear_skip=False,
        ),
        GraphMixerConfig(channels=4, blocks=1, t_in=4, horizon=5, embed_dim=3),  # lift: weights first
        GraphMixerConfig(channels=8, blocks=0, t_in=3, horizon=7, embed_dim=2),
    ],
    ids=["c20-b2-t6-velocities-only", "c4-b1-t4", "c8-b0-t3"],
)  # fmt: skip
def test_other_configurations_match_torch(cfg: GraphMixerConfig) -> None:
    torch.manual_seed(0)
    model = _randomise(GraphMixer(cfg), seed=2)
    x = _histories(cfg.t_in, 8, seed=3)
    got = _fast(model, x)
    np.testing.assert_allclose(got, _torch(model, x), rtol=0, atol=TOL_M)
    np.testing.assert_allclose(got, _torch(model, x, double=True), rtol=0, atol=TOL_M)
    assert np.abs(got - x[:, -1:]).max() > 0.2


def test_a_changed_weight_shows_in_the_comparison() -> None:
    """The compiled pass holds its own copy of the weights; a change to the torch module after compiling
    makes the two disagree by far more than the tolerance (the comparison can fail)."""
    torch.manual_seed(0)
    model = _randomise(GraphMixer(GraphMixerConfig(channels=8, blocks=1, embed_dim=4)), seed=4)
    x = _histories(10, 4, seed=5)
    fast = compile_fast(model)
    before = np.stack([fast(h) for h in x])
    np.testing.assert_allclose(before, _torch(model, x), rtol=0, atol=TOL_M)
    for name, change in [
        ("blocks.0.norm_s.bias", 0.3),
        ("blocks.0.temporal.offset", 0.5),
        ("head.bias", 0.05),
    ]:
        changed = copy.deepcopy(model)
        with torch.no_grad():
            changed.get_parameter(name).add_(change)
        assert np.abs(before - _torch(changed, x)).max() > 100 * TOL_M, name
        np.testing.assert_allclose(_fast(changed, x), _torch(changed, x), rtol=0, atol=TOL_M)


def test_input_shape_is_checked() -> None:
    fast = FastGraphMixer(GraphMixer(GraphMixerConfig(channels=8, blocks=1, embed_dim=4)))
    with pytest.raises(ValueError, match=r"\(10, 19, 3\)"):
        fast(np.zeros((9, NUM_JOINTS, 3)))
    with pytest.raises(ValueError, match="one person"):
        fast(np.zeros((1, 10, NUM_JOINTS, 3)))


def test_vectorised_exp_matches_numpy() -> None:
    x = np.concatenate([np.linspace(-87.0, 88.0, 20001), [0.0, -1e-8, 1e-8]]).astype(np.float32)
    out = np.empty_like(x)
    _kernels.vexp(x, out, np.empty(x.size, dtype=np.int32))
    ref = np.exp(x.astype(np.float64))
    assert np.max(np.abs(out / ref - 1.0)) < 5e-7
    # beyond the clamp: exp(-87) and exp(88), finite, never 0 or inf
    far = np.array([-1e4, -100.0, 100.0, 1e4], dtype=np.float32)
    _kernels.vexp(far, far, np.empty(4, dtype=np.int32))
    np.testing.assert_allclose(far, np.exp([-87.0, -87.0, 88.0, 88.0]), rtol=5e-7)


def test_blas_threads_are_restored_after_a_call() -> None:
    threadpoolctl = pytest.importorskip("threadpoolctl")
    model = GraphMixer(GraphMixerConfig(channels=8, blocks=1, embed_dim=4))
    fast = compile_fast(model)
    x = _histories(10, 3, seed=6)[0]
    fast(x)  # the first call compiles (or loads) the kernel and finds the BLAS libraries
    with threadpoolctl.threadpool_limits(2, user_api="blas"):
        before = [lib["num_threads"] for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas"]
        saved = fast._blas.limit()
        during = [lib["num_threads"] for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas"]
        fast._blas.restore(saved)
        fast(x)
        after = [lib["num_threads"] for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas"]
    if not before or all(n == 1 for n in before):
        pytest.skip("BLAS runs on one thread here whatever is asked")
    assert all(n == 1 for n in during)
    assert after == before
