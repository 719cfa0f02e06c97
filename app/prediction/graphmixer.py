"""Graph-Mixer motion predictor (torch).

After "Adaptive Spatial-Temporal Graph-Mixer for Human Motion Prediction".

Pipeline for observed poses ``x`` (B, T, J, 3) in the world frame (metres, z up, 30 Hz):

1. **Person-centred frame**: subtract the pelvis position of the last observed frame and rotate about z so
   that the person faces +x (facing from the hip and shoulder lines of the last frame: left = +y). The
   forecast is mapped back at the end, so the network never sees absolute positions or headings (this is
   what lets a model trained on a few minutes of motion capture generalise to any place and heading in the
   work cell).
2. **Input**: the T-1 frame-to-frame differences (as velocities, m/s) and, optionally, the centred poses of
   the same frames (metres), per joint: (B, T-1, J, 3 or 6).
3. **Lift**: a spatial graph convolution 3 (6) -> C channels.
4. **Mixer blocks**: ``h = x + SE(TemporalGC(LN(x)))``; ``x = h + Mish(SpatialGC(LN(h)))``. The temporal
   graph convolution mixes frames (self and neighbour-frame adjacencies); the spatial one mixes joints (self,
   skeleton inbound = from the parent, outbound = from the children). Every adjacency is
   ``A_k = fixed_k + learnable offset_k + softmax(E1(x) E2(x)^T / sqrt(d))`` (the last term depends on the
   data).
5. **Head**: a linear map over time T-1 -> H, a spatial graph convolution C -> 3 giving each future frame's
   displacement from the last observed pose, which is added to it; then back to the world frame. Optionally
   (``linear_skip``, on by default; not in the paper) a learned linear extrapolation of the observed
   differences is added to the displacements, so that the short horizons do not have to be learned through the
   whole network.

Training loss: MPJPE (mean Euclidean joint error over the H future frames).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional

from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS, PARENTS

#: Checkpoint format tag; a file without it is refused.
CHECKPOINT_FORMAT = "hrc-hmp-graphmixer/1"

#: Scale applied to frame differences (a frame difference times fps is a velocity in m/s).
_FPS = 30.0


@dataclass(frozen=True)
class GraphMixerConfig:
    """Architecture settings (stored in every checkpoint; a mismatch refuses to load).

    Attributes:
        n_joints: Joints per pose (canonical skeleton).
        t_in: Observed frames (the network sees ``t_in - 1`` differences).
        horizon: Predicted frames after the last observed one.
        channels: Hidden channels C.
        blocks: Mixer blocks.
        embed_dim: Size d of the embeddings of the data-dependent adjacency term.
        se_reduction: Squeeze-and-excitation reduction ratio.
        pose_input: Also feed the centred poses next to the differences (6 input channels instead of 3).
        linear_skip: Add a learned linear extrapolation of the observed differences (weights over time, shared
            by all joints and axes, zero at the start) to the network's displacements; an addition to the
            published architecture that makes the short horizons train quickly.
        fps: Frame rate the model was trained at (Hz).
    """

    n_joints: int = NUM_JOINTS
    t_in: int = 10
    horizon: int = 30
    channels: int = 48
    blocks: int = 3
    embed_dim: int = 8
    se_reduction: int = 4
    pose_input: bool = True
    linear_skip: bool = True
    fps: float = _FPS

    def to_dict(self) -> dict:
        return asdict(self)


def skeleton_adjacencies() -> np.ndarray:
    """Fixed spatial adjacencies (3, J, J): self, inbound (from the parent), outbound (from the children).

    Row ``n`` holds the weights of the joints that joint ``n`` receives from; non-empty rows sum to one.
    """
    J = NUM_JOINTS
    A = np.zeros((3, J, J))
    A[0] = np.eye(J)
    for child in range(J):
        parent = int(PARENTS[child])
        if parent >= 0:
            A[1, child, parent] = 1.0
            A[2, parent, child] = 1.0
    deg = A[2].sum(axis=1, keepdims=True)
    A[2] = np.divide(A[2], deg, out=np.zeros_like(A[2]), where=deg > 0)
    return A


def temporal_adjacencies(T: int) -> np.ndarray:
    """Fixed temporal adjacencies (2, T, T): self, and the neighbouring frames (rows sum to one)."""
    A = np.zeros((2, T, T))
    A[0] = np.eye(T)
    for t in range(T):
        for s in (t - 1, t + 1):
            if 0 <= s < T:
                A[1, t, s] = 1.0
    A[1] /= A[1].sum(axis=1, keepdims=True)
    return A


class AdaptiveGraphConv(nn.Module):
    """Graph convolution along one axis of (B, T, J, C) with K adaptive adjacencies.

    ``out = sum_k A_k(x) · x · W_k + b`` where ``A_k(x) = fixed_k + offset_k + softmax(E1_k(x) E2_k(x)^T)``
    and the embeddings are computed from ``x`` averaged over the other axis.

    Args:
        fixed: Fixed adjacencies (K, N, N) along the mixed axis.
        c_in: Input channels.
        c_out: Output channels.
        axis: ``"time"`` mixes frames (N = T), ``"joints"`` mixes joints (N = J).
        embed_dim: Size of the embeddings of the data-dependent term.
    """

    def __init__(self, fixed: np.ndarray, c_in: int, c_out: int, *, axis: str, embed_dim: int) -> None:
        super().__init__()
        if axis not in ("time", "joints"):
            raise ValueError(f"axis must be 'time' or 'joints', got {axis!r}")
        K, N, _ = fixed.shape
        self.axis = axis
        self.K = K
        self.c_out = c_out
        self.embed_dim = embed_dim
        self.register_buffer("fixed", torch.as_tensor(fixed, dtype=torch.float32))
        self.offset = nn.Parameter(torch.zeros(K, N, N))
        self.embed = nn.Linear(c_in, 2 * K * embed_dim)
        self.weight = nn.Linear(c_in, K * c_out, bias=False)
        self.bias = nn.Parameter(torch.zeros(c_out))
        nn.init.normal_(self.embed.weight, std=0.02)
        nn.init.zeros_(self.embed.bias)
        nn.init.normal_(self.weight.weight, std=1.0 / math.sqrt(c_in * K))

    def adjacency(self, x: torch.Tensor) -> torch.Tensor:
        """Adjacencies (B, K, N, N) for input ``x`` (B, T, J, C)."""
        pooled = x.mean(dim=2) if self.axis == "time" else x.mean(dim=1)  # (B, N, C)
        B, N, _ = pooled.shape
        e = self.embed(pooled).view(B, N, 2, self.K, self.embed_dim)
        e1 = e[:, :, 0].transpose(1, 2)  # (B, K, N, d)
        e2 = e[:, :, 1].transpose(1, 2)
        data = torch.softmax(e1 @ e2.transpose(-1, -2) / math.sqrt(self.embed_dim), dim=-1)
        return self.fixed + self.offset + data

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, T, J, _ = x.shape
        A = self.adjacency(x)
        xw = self.weight(x).view(B, T, J, self.K, self.c_out)
        if self.axis == "time":
            out = torch.einsum("bkts,bsjkc->btjc", A, xw)
        else:
            out = torch.einsum("bknm,btmkc->btnc", A, xw)
        return out + self.bias


class SqueezeExcite(nn.Module):
    """Channel squeeze-and-excitation over (B, T, J, C)."""

    def __init__(self, channels: int, reduction: int) -> None:
        super().__init__()
        hidden = max(channels // reduction, 4)
        self.fc1 = nn.Linear(channels, hidden)
        self.fc2 = nn.Linear(hidden, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = x.mean(dim=(1, 2))
        s = torch.sigmoid(self.fc2(functional.relu(self.fc1(s))))
        return x * s[:, None, None, :]


class MixerBlock(nn.Module):
    """LayerNorm, temporal mixing, squeeze-and-excitation, residual; LayerNorm, spatial mixing, Mish."""

    def __init__(self, cfg: GraphMixerConfig, t_feat: int) -> None:
        super().__init__()
        C = cfg.channels
        self.norm_t = nn.LayerNorm(C)
        self.temporal = AdaptiveGraphConv(
            temporal_adjacencies(t_feat), C, C, axis="time", embed_dim=cfg.embed_dim
        )
        self.se = SqueezeExcite(C, cfg.se_reduction)
        self.norm_s = nn.LayerNorm(C)
        self.spatial = AdaptiveGraphConv(skeleton_adjacencies(), C, C, axis="joints", embed_dim=cfg.embed_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = x + self.se(self.temporal(self.norm_t(x)))
        return h + functional.mish(self.spatial(self.norm_s(h)))


def person_frame(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Origin (B, 3) and rotation R (B, 3, 3) of the person-centred frame of poses ``x`` (B, T, J, 3).

    ``p_local = R @ (p_world - origin)``: the origin is the last frame's pelvis; R turns about z so that the
    person faces +x. A degenerate facing (left direction shorter than 1 mm) gives the identity rotation.
    """
    last = x[:, -1]
    origin = last[:, JOINT_INDEX["pelvis"]]
    left = (
        last[:, JOINT_INDEX["l_hip"]]
        - last[:, JOINT_INDEX["r_hip"]]
        + last[:, JOINT_INDEX["l_shoulder"]]
        - last[:, JOINT_INDEX["r_shoulder"]]
    )
    # forward = left x up = (left_y, -left_x, 0)
    fx, fy = left[:, 1], -left[:, 0]
    norm = torch.sqrt(fx * fx + fy * fy)
    ok = norm > 1e-3
    safe = torch.where(ok, norm, torch.ones_like(norm))
    c = torch.where(ok, fx / safe, torch.ones_like(fx))
    s = torch.where(ok, fy / safe, torch.zeros_like(fy))
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    # rotation by -yaw: maps the forward direction (c, s) onto +x
    R = torch.stack(
        [torch.stack([c, s, zero], -1), torch.stack([-s, c, zero], -1), torch.stack([zero, zero, one], -1)],
        dim=-2,
    )
    return origin, R


class GraphMixer(nn.Module):
    """The Graph-Mixer predictor: observed poses (B, T, J, 3) -> future poses (B, H, J, 3), world frame."""

    def __init__(self, cfg: GraphMixerConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or GraphMixerConfig()
        if cfg.t_in < 2:
            raise ValueError(f"GraphMixer needs t_in >= 2 observed frames, got {cfg.t_in}")
        t_feat = cfg.t_in - 1
        c_in = 6 if cfg.pose_input else 3
        A_s = skeleton_adjacencies()
        self.lift = AdaptiveGraphConv(A_s, c_in, cfg.channels, axis="joints", embed_dim=cfg.embed_dim)
        self.blocks = nn.ModuleList([MixerBlock(cfg, t_feat) for _ in range(cfg.blocks)])
        self.norm_out = nn.LayerNorm(cfg.channels)
        self.time_out = nn.Linear(t_feat, cfg.horizon)
        self.head = AdaptiveGraphConv(A_s, cfg.channels, 3, axis="joints", embed_dim=cfg.embed_dim)
        # start from the zero-velocity forecast
        nn.init.zeros_(self.head.weight.weight)
        nn.init.zeros_(self.head.bias)
        self.skip = nn.Parameter(torch.zeros(cfg.horizon, t_feat)) if cfg.linear_skip else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Future poses (B, H, J, 3) in the world frame for observed poses ``x`` (B, T, J, 3)."""
        _, T, J, _ = x.shape
        cfg = self.cfg
        if cfg.t_in != T or cfg.n_joints != J:
            raise ValueError(
                f"GraphMixer expects (B, {cfg.t_in}, {cfg.n_joints}, 3) inputs, got {tuple(x.shape)}"
            )
        origin, R = person_frame(x)
        local = torch.einsum("bij,btnj->btni", R, x - origin[:, None, None, :])
        vel = (local[:, 1:] - local[:, :-1]) * cfg.fps
        feat = torch.cat([vel, local[:, 1:]], dim=-1) if cfg.pose_input else vel
        h = self.lift(feat)
        for block in self.blocks:
            h = block(h)
        h = self.norm_out(h)
        h = self.time_out(h.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)  # (B, H, J, C)
        disp = self.head(h)  # (B, H, J, 3) displacement from the last pose, local frame
        if self.skip is not None:
            disp = disp + torch.einsum("ht,btjc->bhjc", self.skip, vel) / cfg.fps
        future_local = local[:, -1:] + disp
        return torch.einsum("bji,btnj->btni", R, future_local) + origin[:, None, None, :]


def save_checkpoint(path: str | Path, model: GraphMixer, **meta: object) -> None:
    """Write ``model`` as a checkpoint that :func:`app.prediction.predictor.load_graphmixer` reads.

    ``meta`` entries (plain Python values: quantiles, metrics, settings) are stored next to the weights.
    """
    ckpt = {
        "format": CHECKPOINT_FORMAT,
        "config": model.cfg.to_dict(),
        "state_dict": {k: v.detach().contiguous() for k, v in model.state_dict().items()},
        **meta,
    }
    torch.save(ckpt, Path(path))


def mpjpe(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean per-joint position error (metres) over all leading dims of (..., J, 3)."""
    return torch.linalg.vector_norm(pred - target, dim=-1).mean()


def count_parameters(model: nn.Module) -> int:
    """Number of parameters (trainable or frozen)."""
    return sum(p.numel() for p in model.parameters())
