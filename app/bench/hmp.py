"""``hrc bench hmp``: forecast latency (one person, one CPU thread) and MPJPE on the CMU test split.

Prints ``infer_ms`` {p50, p95} (Graph-Mixer, one person, including the numpy/torch conversion), ``update_ms``
(the whole ``MotionPredictor.update``: repair, resampling, network, forecast object), ``mpjpe_mm``
{graphmixer, constant_velocity, zero_velocity} each {"80": ..., "1000": ...} on every window of the CMU test
split (``null`` with a ``note`` if the clips are not on this machine), ``params``, the aims' ratios, and
``reference_workload_ms`` (a fixed numpy workload timed the same way: its p95/p50 ratio shows how much of the
forecast's p95 is the machine's own timing noise).
"""

from __future__ import annotations

import time

import numpy as np


def _percentiles(samples_s: list[float]) -> dict[str, float]:
    a = np.asarray(samples_s) * 1000.0
    return {"p50": round(float(np.percentile(a, 50)), 4), "p95": round(float(np.percentile(a, 95)), 4)}


def run(*, quick: bool = False, progress: bool = True) -> dict:
    """Measure; returns the JSON-able result."""
    import torch

    from app.prediction.data import ClipError, load_clip_dir, require_cmu_dir
    from app.prediction.evaluate import evaluate_clips
    from app.prediction.graphmixer import count_parameters
    from app.prediction.predictor import DEFAULT_WEIGHTS, MotionPredictor
    from app.prediction.skeleton import NUM_JOINTS, HumanFrame

    torch.set_num_threads(1)
    predictor = MotionPredictor(kind="graphmixer")
    result: dict = {"weights": DEFAULT_WEIGHTS.name, "kind": predictor.effective_kind, "threads": 1}
    repeats = 100 if quick else 1000
    rng = np.random.default_rng(0)
    base = rng.normal(scale=0.3, size=(NUM_JOINTS, 3)) + np.array([0.0, 0.0, 1.0])
    history = (base[None] + np.linspace(0.0, 0.3, predictor.history)[:, None, None] * [1.0, 0.2, 0.0])[None]
    kind = predictor.effective_kind
    for _ in range(20):
        predictor.predict_batch(history, kind=kind)
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        predictor.predict_batch(history, kind=kind)
        samples.append(time.perf_counter() - t)
    result["infer_ms"] = _percentiles(samples)
    samples = []
    for k in range(repeats + predictor.history):
        frame = HumanFrame(t=k / predictor.fps, joints=base + np.array([0.03 * k, 0.0, 0.0]))
        t = time.perf_counter()
        predictor.update(frame)
        if k >= predictor.history:
            samples.append(time.perf_counter() - t)
    result["update_ms"] = _percentiles(samples)
    result["params"] = count_parameters(predictor.model) if predictor.model is not None else 0
    # the same number of repetitions of a fixed numpy workload: how noisy this machine's timing is right now
    a = rng.random((160, 160))
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(8):
            a @ a
        samples.append(time.perf_counter() - t)
    result["reference_workload_ms"] = _percentiles(samples)

    try:
        clips = load_clip_dir(require_cmu_dir(None), split="test")
    except ClipError as exc:
        result["mpjpe_mm"] = None
        result["note"] = str(exc)
        return result
    kinds = (
        ["graphmixer", "constant_velocity", "zero_velocity"]
        if predictor.model is not None
        else [
            "constant_velocity",
            "zero_velocity",
        ]
    )
    fns = {k: (lambda obs, H, k=k: predictor.predict_batch(obs, kind=k)[:, :H]) for k in kinds}
    res = evaluate_clips(clips, fns, t_in=predictor.history, horizon=predictor.horizon, fps=predictor.fps)
    result["mpjpe_mm"] = {k: {ms: round(v, 2) for ms, v in res[k]["mpjpe_mm"].items()} for k in kinds}
    result["test_windows"] = next(iter(res.values()))["windows"]
    if predictor.model is not None:
        gm, cv = result["mpjpe_mm"]["graphmixer"], result["mpjpe_mm"]["constant_velocity"]
        result["ratio_to_constant_velocity"] = {
            "400": round(gm["400"] / cv["400"], 3),
            "1000": round(gm["1000"] / cv["1000"], 3),
        }
    return result
