"""The compiled one-person forward pass of the Graph-Mixer (numba), used by :mod:`app.prediction.fastforward`.

:func:`forward` runs the whole network in one call: the matrix products through BLAS (``np.dot``), every
step between them (adaptive adjacencies, frame mixing, squeeze-and-excitation, residual updates,
LayerNorms, Mish) as fused loops over the (T, J, C) activations. The weights come prepared by
:class:`app.prediction.fastforward.FastGraphMixer` (LayerNorm scales and shifts folded into the layers after
them, adjacencies' fixed parts summed), in float32; the reference is the torch module
(:class:`app.prediction.graphmixer.GraphMixer`), which the tests compare against.

Compiled with ``fastmath`` reassociation and contraction only (sums are vectorised, so the results agree
with torch to float32 rounding, not bit for bit; inf and NaN keep their meaning) and NumPy's error model
(division by zero gives inf). ``cache=True`` keeps the machine code next to this file (numba compiles in
memory, with a warning, where that folder is read-only).
"""

from __future__ import annotations

import math

import numpy as np

from app.jit import jit

__all__ = ["cap_speed", "forward", "vexp"]

_OPTS = {"error_model": "numpy", "fastmath": {"reassoc", "contract"}}
_EXACT = {"error_model": "numpy"}  # no fastmath: the NumPy reference's numbers

_F = np.float32
_ZERO, _HALF, _ONE, _TWO = _F(0.0), _F(0.5), _F(1.0), _F(2.0)
# exp(v) = 2^n e^r, n = round(v / ln 2), |r| <= ln(2)/2; e^r by its Taylor polynomial of degree 6 (relative
# error below 3e-7); 2^n assembled from its float32 bits. The clamp keeps 2^n a normal number.
_LOG2E = _F(1.4426950408889634)
_LN2_HI, _LN2_LO = _F(0.693359375), _F(-2.12194440e-4)
_EXP_LO, _EXP_HI = _F(-87.0), _F(88.0)
_C1, _C2, _C3, _C4, _C5, _C6 = (_F(1.0 / math.factorial(k)) for k in range(1, 7))
#: Beyond this ``e^v`` Mish's ratio n / (n + 2) is 1 in float32; the cap keeps n = e (e + 2) finite.
_MISH_E_CAP = _F(1e18)


@jit(**_OPTS)
def vexp(x: np.ndarray, out: np.ndarray, bits: np.ndarray) -> None:
    """``out = exp(x)`` for flat float32 arrays (vectorised; ``bits`` is int32 scratch of the same size).

    Inputs below -87 give exp(-87) (about 1.6e-38), above 88 give exp(88); ``out`` may be ``x``.
    """
    scale = bits.view(np.float32)
    for i in range(x.size):
        v = min(max(x[i], _EXP_LO), _EXP_HI)
        n = np.floor(v * _LOG2E + _HALF)
        bits[i] = (np.int32(n) + np.int32(127)) << np.int32(23)
        r = v - n * _LN2_HI - n * _LN2_LO
        out[i] = _ONE + r * (_C1 + r * (_C2 + r * (_C3 + r * (_C4 + r * (_C5 + r * _C6)))))
    for i in range(x.size):
        out[i] *= scale[i]


@jit(**_OPTS)
def _adjacency(pooled, w_embed, b_embed, base, d, k_first, A):
    """``A_k[n, m] = base[k, n, m] + softmax_m(e1_k[n] . e2_k[m])`` with ``e = pooled @ w_embed + b_embed``
    read as (N, 2, K, d) (the 1/sqrt(d) scale is in the weights), written ``A[n, m, k]`` (N, N, K) or, with
    ``k_first``, ``A[n, k, m]`` (N, K, N)."""
    K, N, _ = base.shape
    e = np.dot(pooled, w_embed)  # (N, 2*K*d)
    e2 = np.empty((K * d, N), dtype=np.float32)  # the e2 half, transposed
    for n in range(N):
        for q in range(2 * K * d):
            e[n, q] += b_embed[q]
    for q in range(K * d):
        for m in range(N):
            e2[q, m] = e[m, K * d + q]
    s = np.empty((K, N, N), dtype=np.float32)
    for k in range(K):
        for n in range(N):
            row = s[k, n]
            row[:] = _ZERO
            for i in range(d):
                a = e[n, k * d + i]
                for m in range(N):
                    row[m] += a * e2[k * d + i, m]
            top = row.max()
            for m in range(N):
                row[m] -= top
    flat = s.reshape(K * N * N)
    vexp(flat, flat, np.empty(K * N * N, dtype=np.int32))
    for k in range(K):
        for n in range(N):
            row = s[k, n]
            inv = _ONE / row.sum()
            if k_first:
                for m in range(N):
                    A[n, k, m] = row[m] * inv + base[k, n, m]
            else:
                for m in range(N):
                    A[n, m, k] = row[m] * inv + base[k, n, m]


@jit(**_OPTS)
def _norm_pools(h, eps, xhat, pool_t, pool_j):
    """``xhat = LN(h)`` (no scale or shift) for (T, J, C); its means over joints (T, C) and frames (J, C)."""
    T, J, C = h.shape
    inv_c = _ONE / _F(C)
    pool_t[:] = _ZERO
    pool_j[:] = _ZERO
    for t in range(T):
        for j in range(J):
            mean = _ZERO
            for c in range(C):
                mean += h[t, j, c]
            mean *= inv_c
            var = _ZERO
            for c in range(C):
                dv = h[t, j, c] - mean
                var += dv * dv
            inv = _ONE / np.sqrt(var * inv_c + eps)
            for c in range(C):
                v = (h[t, j, c] - mean) * inv
                xhat[t, j, c] = v
                pool_t[t, c] += v
                pool_j[j, c] += v
    pool_t *= _ONE / _F(J)
    pool_j *= _ONE / _F(T)


@jit(**_OPTS)
def _mix_joints(A, xw, out):
    """``out[t] = A (N, N*K) @ xw[t]`` for ``xw`` (T, N*K, C'): mixing along the joints, one product per
    frame."""
    N = A.shape[0]
    Ar = A.reshape(N, A.shape[1] * A.shape[2])
    for t in range(xw.shape[0]):
        np.dot(Ar, xw[t], out[t])


@jit(**_OPTS)
def forward(x, p, ints, fps):
    """Future poses (H, J, 3) in the world frame (float64) for one person's observed poses ``x`` (T, J, 3).

    Args:
        x: Observed poses (T, J, 3), world frame, m (float64).
        p: The prepared weights (:attr:`app.prediction.fastforward.FastGraphMixer.params`).
        ints: ``(embed_dim, lift_mix_first, pose_input, pelvis, l_hip, r_hip, l_shoulder, r_shoulder)``.
        fps: Frame rate (Hz): frame differences times ``fps`` are the velocities the network sees.
    """
    (
        l_wemb, l_bemb, l_base, l_weight, l_bias,
        t_wemb, t_bemb, t_base, t_weight, t_bias,
        se_w1, se_b1, se_w2, se_b2,
        s_wemb, s_bemb, s_base, s_weight, s_bias,
        eps, time_w, h_wemb, h_bemb, h_base, h_weight, h_bias, extrapolate,
    ) = p  # fmt: skip
    d, mix_first, pose_input = ints[0], ints[1] != 0, ints[2] != 0
    T, J, _ = x.shape
    Tf = T - 1
    H = time_w.shape[0]
    C = l_bias.shape[1]
    B = t_wemb.shape[0]
    # ---- person-centred frame: p_local = R (p_world - origin), R turns the facing onto +x
    fx = x[T - 1, ints[4], 1] - x[T - 1, ints[5], 1] + x[T - 1, ints[6], 1] - x[T - 1, ints[7], 1]
    fy = -(x[T - 1, ints[4], 0] - x[T - 1, ints[5], 0] + x[T - 1, ints[6], 0] - x[T - 1, ints[7], 0])
    norm = math.sqrt(fx * fx + fy * fy)
    c, s = 1.0, 0.0
    if norm > 1e-3:
        c, s = fx / norm, fy / norm
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    origin = x[T - 1, ints[3]]
    local = np.empty((T, J, 3))
    for t in range(T):
        for j in range(J):
            for a in range(3):
                local[t, j, a] = (
                    R[a, 0] * (x[t, j, 0] - origin[0])
                    + R[a, 1] * (x[t, j, 1] - origin[1])
                    + R[a, 2] * (x[t, j, 2] - origin[2])
                )
    c_in = 6 if pose_input else 3
    feat = np.empty((Tf, J, c_in), dtype=np.float32)
    for t in range(Tf):
        for j in range(J):
            for a in range(3):
                feat[t, j, a] = (local[t + 1, j, a] - local[t, j, a]) * fps
                if pose_input:
                    feat[t, j, 3 + a] = local[t + 1, j, a]
    # ---- lift: a graph convolution along the joints, c_in -> C (bias added before the first LayerNorm)
    K = l_base.shape[0]
    pooled = np.zeros((J, c_in), dtype=np.float32)
    for t in range(Tf):
        pooled += feat[t]
    pooled *= _ONE / _F(Tf)
    h = np.empty((Tf, J, C), dtype=np.float32)
    if mix_first:  # joints first: mixed[t] = A (J*K, J) @ feat[t], rows (n, k); then the weights
        A = np.empty((J, K, J), dtype=np.float32)
        _adjacency(pooled, l_wemb, l_bemb, l_base, d, True, A)
        Ak = A.reshape(J * K, J)
        mixed = np.empty((Tf, J * K, c_in), dtype=np.float32)
        for t in range(Tf):
            np.dot(Ak, feat[t], mixed[t])
        np.dot(mixed.reshape(Tf * J, K * c_in), l_weight, h.reshape(Tf * J, C))
    else:
        A = np.empty((J, J, K), dtype=np.float32)
        _adjacency(pooled, l_wemb, l_bemb, l_base, d, False, A)
        xw = np.dot(feat.reshape(Tf * J, c_in), l_weight)  # (T*J, K*C): rows (t, m), columns (k, c)
        _mix_joints(A, xw.reshape(Tf, J * K, C), h)
    for t in range(Tf):
        h[t] += l_bias
    xhat = np.empty_like(h)
    pool_t = np.empty((Tf, C), dtype=np.float32)
    pool_j = np.empty((J, C), dtype=np.float32)
    _norm_pools(h, eps[0], xhat, pool_t, pool_j)
    # ---- mixer blocks
    g = np.empty_like(h)
    ev = np.empty(Tf * J * C, dtype=np.float32)
    bits = np.empty(Tf * J * C, dtype=np.int32)
    col = np.empty(C, dtype=np.float32)
    gate = np.empty(C, dtype=np.float32)
    for b in range(B):
        # temporal graph convolution: g[t, j] = bias[t] + sum_{s,k} A_k[t, s] (xhat W_k)[s, j]
        Kt = t_base.shape[1]
        At = np.empty((Tf, Tf, Kt), dtype=np.float32)
        _adjacency(pool_t, t_wemb[b], t_bemb[b], t_base[b], d, False, At)
        xw = np.dot(xhat.reshape(Tf * J, C), t_weight[b]).reshape(Tf, J, Kt * C)
        col[:] = _ZERO
        for t in range(Tf):
            for j in range(J):
                out = g[t, j]
                out[:] = t_bias[b, t]
                for s_ in range(Tf):
                    for k in range(Kt):
                        a = At[t, s_, k]
                        for q in range(C):
                            out[q] += a * xw[s_, j, k * C + q]
                col += out
        # squeeze-and-excitation gate on the channel means
        hid = se_b1[b].copy()
        inv_rows = _ONE / _F(Tf * J)
        for q in range(C):
            mq = col[q] * inv_rows
            for i in range(hid.size):
                hid[i] += mq * se_w1[b, q, i]
        for q in range(C):
            z = se_b2[b, q]
            for i in range(hid.size):
                z += max(hid[i], _ZERO) * se_w2[b, i, q]
            gate[q] = _ONE / (_ONE + np.exp(-z))
        for t in range(Tf):
            for j in range(J):
                for q in range(C):
                    h[t, j, q] += g[t, j, q] * gate[q]
        _norm_pools(h, eps[1 + 2 * b], xhat, pool_t, pool_j)
        # spatial graph convolution, then Mish: h += mish(A (xhat W) + bias)
        Ks = s_base.shape[1]
        As = np.empty((J, J, Ks), dtype=np.float32)
        _adjacency(pool_j, s_wemb[b], s_bemb[b], s_base[b], d, False, As)
        xw = np.dot(xhat.reshape(Tf * J, C), s_weight[b])
        _mix_joints(As, xw.reshape(Tf, J * Ks, C), g)
        for t in range(Tf):
            g[t] += s_bias[b]
        gf = g.reshape(Tf * J * C)
        vexp(gf, ev, bits)
        hf = h.reshape(Tf * J * C)
        for i in range(gf.size):
            e = min(ev[i], _MISH_E_CAP)
            n = e * (e + _TWO)
            hf[i] += gf[i] * (n / (n + _TWO))  # mish(v) = v tanh(softplus(v)) = v n / (n + 2)
        _norm_pools(h, eps[2 + 2 * b], xhat, pool_t, pool_j)
    # ---- time_out, then the head. Both are linear once the head's adjacency is known, and time_out maps
    # frames while the head maps joints and channels, so the head runs first, on the T-1 observed frames:
    # disp = time_w @ [A (xhat W)]. The head's input, z = time_w @ xhat (the last LayerNorm's scale and
    # shift are in the head), is only needed as its mean over the future frames, for the adjacency.
    Kh = h_base.shape[0]
    c_out = h_bias.shape[2]
    tw_mean = np.zeros(Tf, dtype=np.float32)
    for t in range(H):
        tw_mean += time_w[t]
    tw_mean *= _ONE / _F(H)
    pooled = np.zeros((J, C), dtype=np.float32)
    for t in range(Tf):
        pooled += tw_mean[t] * xhat[t]
    Ah = np.empty((J, J, Kh), dtype=np.float32)
    _adjacency(pooled, h_wemb, h_bemb, h_base, d, False, Ah)
    xw = np.dot(xhat.reshape(Tf * J, C), h_weight).reshape(Tf, J * Kh, c_out)
    mixed = np.empty((Tf, J, c_out), dtype=np.float32)
    _mix_joints(Ah, xw, mixed)
    disp = np.dot(time_w, mixed.reshape(Tf, J * c_out)).reshape(H, J, c_out)
    disp += h_bias
    # ---- back to the world frame: disp R + the extrapolation from x (linear skip and last pose)
    res = np.dot(extrapolate, x.reshape(T, J * 3)).reshape(H, J, 3)
    for t in range(H):
        for j in range(J):
            for a in range(3):
                res[t, j, a] += disp[t, j, 0] * R[0, a] + disp[t, j, 1] * R[1, a] + disp[t, j, 2] * R[2, a]
    return res


@jit(**_EXACT)
def cap_speed(last: np.ndarray, future: np.ndarray, dt: float, vmax: float) -> np.ndarray:
    """The forecast's joints (H + 1, J, 3): ``last`` (J, 3) then ``future`` (H, J, 3) with each joint's
    displacement from ``last`` capped at ``vmax * dt * (h + 1)`` (m) at step ``h``. The numbers of
    :func:`app.prediction.reference.cap_speed_reference` (same operations, same order)."""
    H, J = future.shape[0], future.shape[1]
    out = np.empty((H + 1, J, 3))
    out[0] = last
    for h in range(H):
        limit = vmax * (dt * (h + 1.0))
        for j in range(J):
            d0 = future[h, j, 0] - last[j, 0]
            d1 = future[h, j, 1] - last[j, 1]
            d2 = future[h, j, 2] - last[j, 2]
            dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            s = limit / max(dist, 1e-12) if dist > limit else 1.0
            out[h + 1, j, 0] = last[j, 0] + d0 * s
            out[h + 1, j, 1] = last[j, 1] + d1 * s
            out[h + 1, j, 2] = last[j, 2] + d2 * s
    return out
