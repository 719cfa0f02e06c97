"""The Graph-Mixer's forward pass for one person without torch: the per-frame forecast, 2x ONNX's speed.

For one person the network (about 60k parameters, 8 million multiply-adds) spends most of its time in torch
or ONNX Runtime on the overhead of a few hundred small operators. :class:`FastGraphMixer` prepares once what
does not depend on the input and runs the whole pass in one compiled call (:func:`app.prediction._kernels.
forward`): the matrix products through BLAS, every step between them as fused numba loops over (T, J, C)
float32 activations. What the preparation folds:

* each LayerNorm only normalises: its scale and shift go into the weights, the embedding and the bias of
  the graph convolution after it. The shift becomes a constant bias because every row of an adjacency sums
  to ``1 + rowsum(fixed + offset)`` (the data-dependent softmax rows sum to one); the last LayerNorm passes
  through ``time_out`` (a map over frames) into the head the same way, with one shift per future frame;
* the embedding's 1/sqrt(d) scale goes into its weights; the fixed and learnable adjacencies are summed;
* the head runs before ``time_out`` (both are linear once the head's adjacency is known: one maps frames,
  the other joints and channels), on 9 observed frames instead of 30 future ones;
* the skip extrapolation and the way back to the world frame: ``skip @ diff(local) @ R = skip @ diff(x)``
  and ``local[-1] @ R + origin = x[-1]``.

The :class:`~app.prediction.graphmixer.GraphMixer` stays the only definition of the network and the
reference: the two agree to float32 rounding (about 3e-7 m on poses of a metre; the predictor checks 1e-5 m
when it builds this pass). BLAS is held to one thread during a call: a second thread only adds wake-ups on
products this small, and on a loaded machine it makes the slow calls much slower.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from app.prediction.skeleton import JOINT_INDEX

if TYPE_CHECKING:
    from torch import nn

    from app.prediction.graphmixer import AdaptiveGraphConv, GraphMixer

log = logging.getLogger(__name__)

_PELVIS = JOINT_INDEX["pelvis"]
_L_HIP, _R_HIP = JOINT_INDEX["l_hip"], JOINT_INDEX["r_hip"]
_L_SHOULDER, _R_SHOULDER = JOINT_INDEX["l_shoulder"], JOINT_INDEX["r_shoulder"]


def _f64(t) -> np.ndarray:
    """A torch tensor (or array-like) as a float64 numpy array (the preparation runs in float64)."""
    if hasattr(t, "detach"):
        t = t.detach().cpu().double().numpy()
    return np.array(t, dtype=np.float64)


@dataclass(frozen=True)
class _Affine:
    """Scale (C,) and shift ((C,), or (F, C) per frame) applied to a graph convolution's input.

    The identity where there is no LayerNorm before the convolution.
    """

    scale: np.ndarray
    shift: np.ndarray

    @classmethod
    def of(cls, norm: nn.LayerNorm | None, channels: int) -> _Affine:
        if norm is None:
            return cls(np.ones(channels), np.zeros(channels))
        return cls(_f64(norm.weight), _f64(norm.bias))


@dataclass(frozen=True)
class _GraphConv:
    """An :class:`~app.prediction.graphmixer.AdaptiveGraphConv` with the affine map before it folded in.

    Attributes:
        time: Mixes frames (N = T), else joints (N = J).
        mix_first: Joints only: mix the joints before the weight product (cheaper where C' > C).
        base: ``fixed + offset`` (K, N, N).
        w_embed: Embedding weights (C, 2*K*d); the e1 half carries the 1/sqrt(d) scale.
        b_embed: Embedding bias (2*K*d,), scaled alike.
        weight: (C, K*C') with columns (k, c'), or (K*C, C') with rows (k, c) where ``mix_first``.
        bias: The conv's bias plus what the folded shift adds: (T, C') along time; (J, C') along the
            joints, or (F, J, C') for a shift per frame.
        K: Adjacencies.
        d: Embedding size.
        c_out: Output channels C'.
    """

    time: bool
    mix_first: bool
    base: np.ndarray
    w_embed: np.ndarray
    b_embed: np.ndarray
    weight: np.ndarray
    bias: np.ndarray
    K: int
    d: int
    c_out: int

    @classmethod
    def build(cls, conv: AdaptiveGraphConv, affine: _Affine) -> _GraphConv:
        """Prepare ``conv(affine(x))`` (float32 arrays, computed in float64)."""
        K, d, c_out = conv.K, conv.embed_dim, conv.c_out
        c_in = conv.weight.in_features
        time = conv.axis == "time"
        if time and affine.shift.ndim != 1:
            raise ValueError("a shift per frame cannot be folded into a graph convolution along time")
        base = _f64(conv.fixed) + _f64(conv.offset)  # (K, N, N)
        scale = np.ones(2 * K * d)
        scale[: K * d] = 1.0 / math.sqrt(d)  # the embedding read as (N, 2, K, d): e1 first
        we, be = _f64(conv.embed.weight), _f64(conv.embed.bias)  # (2Kd, C), (2Kd,)
        # the pooled input is affine(mean of x): its shift is the shift's mean over the pooled axis
        shift_mean = affine.shift if affine.shift.ndim == 1 else affine.shift.mean(axis=0)
        w_embed = (we * affine.scale).T * scale
        b_embed = (be + we @ shift_mean) * scale
        w_raw = _f64(conv.weight.weight).reshape(K, c_out, c_in)  # W_k (C', C)
        w = w_raw * affine.scale
        shift_w = affine.shift @ w_raw.transpose(0, 2, 1)  # (K, C') or (K, F, C'): W_k shift
        rows = 1.0 + base.sum(axis=2)  # (K, N): row sums of fixed + offset + softmax
        if shift_w.ndim == 2:
            bias = _f64(conv.bias) + np.einsum("kn,ko->no", rows, shift_w)  # (N, C')
        else:
            bias = _f64(conv.bias) + np.einsum("kn,kfo->fno", rows, shift_w)  # (F, J, C')
        mix_first = not time and c_out > c_in
        if mix_first:
            weight = w.transpose(0, 2, 1).reshape(K * c_in, c_out)
        else:
            weight = w.transpose(2, 0, 1).reshape(c_in, K * c_out)

        def arr(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(a, dtype=np.float32)

        return cls(
            time=time,
            mix_first=mix_first,
            base=arr(base),
            w_embed=arr(w_embed),
            b_embed=arr(b_embed),
            weight=arr(weight),
            bias=arr(bias),
            K=K,
            d=d,
            c_out=c_out,
        )


class _BlasThreads:
    """Runs BLAS on one thread for the duration of a call (threadpoolctl; a no-op without it)."""

    def __init__(self) -> None:
        try:
            from threadpoolctl import ThreadpoolController

            self._libs = list(ThreadpoolController().select(user_api="blas").lib_controllers)
        except Exception as exc:  # threadpoolctl missing or a library it cannot drive
            log.debug("BLAS threads not limited for the Graph-Mixer (%s)", exc)
            self._libs = []

    def limit(self) -> list[tuple[object, int]]:
        """Set every BLAS library to one thread; returns what :meth:`restore` needs."""
        saved = []
        for lib in self._libs:
            n = lib.get_num_threads()
            if n is not None and n != 1:
                lib.set_num_threads(1)
                saved.append((lib, n))
        return saved

    @staticmethod
    def restore(saved: list[tuple[object, int]]) -> None:
        for lib, n in saved:
            lib.set_num_threads(n)


class FastGraphMixer:
    """The forward pass of a :class:`~app.prediction.graphmixer.GraphMixer` for one person, without torch.

    Call it with the observed poses of one person (T, J, 3) in the world frame (metres, on the model's
    frame grid); it returns the future poses (H, J, 3) in the world frame (float64). The activations are
    float32, like the torch module's. It holds its own prepared copies of the weights: later changes to the
    torch module are not seen. The first call compiles the kernel (or loads it from numba's cache).

    Args:
        model: The torch network (read once).
    """

    def __init__(self, model: GraphMixer) -> None:
        cfg = model.cfg
        self.cfg = cfg
        T, J, H, C = cfg.t_in, cfg.n_joints, cfg.horizon, cfg.channels
        tf = T - 1
        f32 = np.dtype(np.float32)

        def arr(a) -> np.ndarray:
            return np.ascontiguousarray(_f64(a), dtype=f32)

        def stack(arrays: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
            """(B, ...) from the blocks' arrays; (0, ...) of ``shape`` without blocks."""
            return np.ascontiguousarray(np.stack(arrays) if arrays else np.zeros((0, *shape)), dtype=f32)

        c_in = 6 if cfg.pose_input else 3
        lift = _GraphConv.build(model.lift, _Affine.of(None, c_in))
        temporal = [_GraphConv.build(b.temporal, _Affine.of(b.norm_t, C)) for b in model.blocks]
        spatial = [_GraphConv.build(b.spatial, _Affine.of(b.norm_s, C)) for b in model.blocks]
        # norm_out's scale and shift pass through time_out (a map over frames) into the head:
        # time_out(xhat * g + b) = (time_w @ xhat) * g + [rowsum(time_w) b + time_b] (one shift per frame)
        time_w = _f64(model.time_out.weight)  # (H, T-1)
        shift = time_w.sum(axis=1)[:, None] * _f64(model.norm_out.bias) + _f64(model.time_out.bias)[:, None]
        head = _GraphConv.build(model.head, _Affine(_f64(model.norm_out.weight), shift))
        # the world-frame extrapolation (linear skip) plus the last pose: out += M @ x, M (H, T)
        M = np.zeros((H, T))
        M[:, -1] = 1.0
        if model.skip is not None:
            S = _f64(model.skip)  # (H, T-1), on velocities divided by fps: on frame differences
            M[:, 1:] += S
            M[:, :-1] -= S
        # the LayerNorm after the lift and after each block is the next block's norm_t (norm_out at the end)
        eps = [float(model.blocks[0].norm_t.eps) if len(model.blocks) else float(model.norm_out.eps)]
        for i, b in enumerate(model.blocks):
            nxt = model.blocks[i + 1].norm_t if i + 1 < len(model.blocks) else model.norm_out
            eps += [float(b.norm_s.eps), float(nxt.eps)]
        blocks = list(model.blocks)
        Kt = temporal[0].K if temporal else 2
        Ks = spatial[0].K if spatial else 3
        Q = 2 * cfg.embed_dim
        hidden = blocks[0].se.fc1.out_features if blocks else 1
        self.params: tuple[np.ndarray, ...] = (
            lift.w_embed,
            lift.b_embed,
            lift.base,
            lift.weight,
            lift.bias,
            stack([t.w_embed for t in temporal], (C, Kt * Q)),
            stack([t.b_embed for t in temporal], (Kt * Q,)),
            stack([t.base for t in temporal], (Kt, tf, tf)),
            stack([t.weight for t in temporal], (C, Kt * C)),
            stack([t.bias for t in temporal], (tf, C)),
            stack([arr(b.se.fc1.weight.T) for b in blocks], (C, hidden)),
            stack([arr(b.se.fc1.bias) for b in blocks], (hidden,)),
            stack([arr(b.se.fc2.weight.T) for b in blocks], (hidden, C)),
            stack([arr(b.se.fc2.bias) for b in blocks], (C,)),
            stack([s.w_embed for s in spatial], (C, Ks * Q)),
            stack([s.b_embed for s in spatial], (Ks * Q,)),
            stack([s.base for s in spatial], (Ks, J, J)),
            stack([s.weight for s in spatial], (C, Ks * C)),
            stack([s.bias for s in spatial], (J, C)),
            np.asarray(eps, dtype=f32),
            arr(time_w),
            head.w_embed,
            head.b_embed,
            head.base,
            head.weight,
            head.bias,
            M,
        )
        self._ints = np.array(
            [
                cfg.embed_dim,
                int(lift.mix_first),
                int(cfg.pose_input),
                _PELVIS,
                _L_HIP,
                _R_HIP,
                _L_SHOULDER,
                _R_SHOULDER,
            ],
            dtype=np.int64,
        )
        self._fps = float(cfg.fps)
        from app.prediction._kernels import forward

        self._kernel = forward
        self._blas: _BlasThreads | None = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Future poses (H, J, 3) in the world frame (m, float64) for observed poses ``x`` (T, J, 3).

        Raises:
            ValueError: ``x`` is not (T, J, 3).
        """
        cfg = self.cfg
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.shape != (cfg.t_in, cfg.n_joints, 3):
            raise ValueError(
                f"the Graph-Mixer expects one person's poses ({cfg.t_in}, {cfg.n_joints}, 3), got {x.shape}"
            )
        if self._blas is None:  # after the first call: numba has loaded the BLAS it calls by then
            out = self._kernel(x, self.params, self._ints, self._fps)
            self._blas = _BlasThreads()
            return out
        saved = self._blas.limit()
        try:
            return self._kernel(x, self.params, self._ints, self._fps)
        finally:
            self._blas.restore(saved)


def compile_fast(model: GraphMixer) -> FastGraphMixer:
    """The torch-free forward pass of ``model`` for one person: ``f(x (T, J, 3)) -> (H, J, 3)``, world, m.

    Args:
        model: A Graph-Mixer (it has no dropout or batch statistics: train or eval mode give the same).
    """
    return FastGraphMixer(model)
