from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from app.prediction.graphmixer import (
    GraphMixer,
    GraphMixerConfig,
    count_parameters,
    mpjpe,
    person_frame,
    save_checkpoint,
    skeleton_adjacencies,
    temporal_adjacencies,
)
from app.prediction.predictor import WeightsError, load_graphmixer
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS

torch.set_num_threads(1)
SMALL = GraphMixerConfig(channels=16, blocks=2, embed_dim=4)


def _randomise_head(model: GraphMixer, seed: int = 0) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        model.head.weight.weight.copy_(torch.randn(model.head.weight.weight.shape, generator=g) * 0.3)


def _standing(T: int = 10, seed: int = 0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    base = rng.normal(scale=0.3, size=(NUM_JOINTS, 3))
    base[JOINT_INDEX["l_hip"]] = [0.0, 0.1, 0.9]
    base[JOINT_INDEX["r_hip"]] = [0.0, -0.1, 0.9]
    motion = np.linspace(0, 1, T)[:, None, None] * rng.normal(scale=0.2, size=(1, NUM_JOINTS, 3))
    return torch.tensor(base[None] + motion, dtype=torch.float32)[None]


def test_fixed_adjacencies() -> None:
    A = skeleton_adjacencies()
    assert A.shape == (3, NUM_JOINTS, NUM_JOINTS)
    np.testing.assert_allclose(A[0], np.eye(NUM_JOINTS))
    # inbound: every joint but the root receives from exactly its parent
    assert (
        A[1].sum(axis=1)[JOINT_INDEX["pelvis"]] == 0
        and A[1][JOINT_INDEX["l_elbow"], JOINT_INDEX["l_shoulder"]] == 1
    )
    rows = A[2].sum(axis=1)
    np.testing.assert_allclose(rows[rows > 0], 1.0)
    assert A[2][JOINT_INDEX["chest"], JOINT_INDEX["neck"]] == pytest.approx(1 / 3)
    At = temporal_adjacencies(5)
    np.testing.assert_allclose(At[1].sum(axis=1), 1.0)
    assert At[1][0, 1] == 1.0 and At[1][2, 1] == 0.5 and At[1][2, 3] == 0.5


def test_adjacency_is_fixed_plus_offset_plus_softmax_term() -> None:
    model = GraphMixer(SMALL)
    conv = model.blocks[0].spatial
    with torch.no_grad():
        conv.offset.fill_(0.25)
    x = torch.randn(2, SMALL.t_in - 1, NUM_JOINTS, SMALL.channels)
    A = conv.adjacency(x)
    data = A - conv.fixed - conv.offset
    assert A.shape == (2, 3, NUM_JOINTS, NUM_JOINTS)
    torch.testing.assert_close(data.sum(-1), torch.ones(2, 3, NUM_JOINTS))
    assert (data > 0).all()


def test_zero_initialised_head_gives_zero_velocity() -> None:
    model = GraphMixer(SMALL).eval()
    x = _standing()
    y = model(x)
    assert y.shape == (1, SMALL.horizon, NUM_JOINTS, 3)
    torch.testing.assert_close(y, x[:, -1:].expand_as(y), atol=1e-5, rtol=0)


def test_forecast_is_equivariant_to_yaw_and_translation() -> None:
    model = GraphMixer(SMALL).eval()
    _randomise_head(model)
    x = _standing(seed=1)
    yaw = 1.1
    c, s = np.cos(yaw), np.sin(yaw)
    R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
    shift = torch.tensor([1.5, -0.7, 0.2])
    with torch.no_grad():
        y = model(x)
        y_moved = model(x @ R.T + shift)
    assert (y - x[:, -1:]).abs().max() > 1e-3  # the head does something
    torch.testing.assert_close(y_moved, y @ R.T + shift, atol=2e-4, rtol=0)


def test_person_frame_faces_plus_x() -> None:
    x = _standing(seed=2)
    # rotate the person so that it faces +y: left must then point to -x
    yaw = np.pi / 2
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
    origin, Rl = person_frame(x @ R.T)
    last = (x @ R.T)[0, -1]
    local = (last - origin[0]) @ Rl[0].T
    left = local[JOINT_INDEX["l_hip"]] - local[JOINT_INDEX["r_hip"]] + local[JOINT_INDEX["l_shoulder"]]
    left = left - local[JOINT_INDEX["r_shoulder"]]
    assert left[1] > 0 and abs(float(left[0])) < 1e-5
    assert yaw > 0
    # degenerate facing (all joints on one point) gives the identity
    origin, Rd = person_frame(torch.zeros(1, 10, NUM_JOINTS, 3))
    torch.testing.assert_close(Rd[0], torch.eye(3))


def test_gradients_reach_offsets_and_embeddings() -> None:
    model = GraphMixer(SMALL)
    _randomise_head(model)
    x = _standing(seed=3)
    loss = mpjpe(model(x), x[:, -1:].expand(1, SMALL.horizon, NUM_JOINTS, 3) + 0.1)
    loss.backward()
    conv = model.blocks[0].temporal
    assert conv.offset.grad is not None and conv.offset.grad.abs().sum() > 0
    assert conv.embed.weight.grad is not None and conv.embed.weight.grad.abs().sum() > 0


def test_default_model_is_small() -> None:
    n = count_parameters(GraphMixer(GraphMixerConfig()))
    assert n * 4 < 5e6


def test_input_shape_is_checked() -> None:
    with pytest.raises(ValueError, match="expects"):
        GraphMixer(SMALL)(torch.zeros(1, 5, NUM_JOINTS, 3))


def test_checkpoint_round_trip_and_mismatch(tmp_path) -> None:
    model = GraphMixer(SMALL).eval()
    _randomise_head(model)
    path = tmp_path / "w.pt"
    save_checkpoint(path, model, quantiles={"p95": [0.0] * 31})
    loaded = load_graphmixer(path)
    x = _standing(seed=4)
    torch.testing.assert_close(loaded.model(x), model(x))
    assert loaded.meta["quantiles"]["p95"][0] == 0.0
    # a state dict of another size does not load
    bad = GraphMixer(GraphMixerConfig(channels=8, blocks=1, embed_dim=4))
    state = torch.load(path, weights_only=True)
    state["state_dict"] = bad.state_dict()
    torch.save(state, tmp_path / "bad.pt")
    with pytest.raises(WeightsError, match="do not match"):
        load_graphmixer(tmp_path / "bad.pt")
    torch.save({"weights": nn.Linear(2, 2).state_dict()}, tmp_path / "other.pt")
    with pytest.raises(WeightsError, match="format"):
        load_graphmixer(tmp_path / "other.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsError, match="cannot read"):
        load_graphmixer(tmp_path / "junk.pt")
    with pytest.raises(WeightsError, match="not found"):
        load_graphmixer(tmp_path / "missing.pt")
