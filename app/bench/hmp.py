"""``hrc bench hmp``: forecast latency (one person, one CPU thread; and the forecast of 1, 2 and 4 people per
frame, before and after the decision, ``people_forecast_ms``) and MPJPE on the CMU test split.

Prints ``infer_ms`` {p50, p95} (Graph-Mixer, one person, the per-frame call ``predict_batch`` on (1, T, J, 3)
through the path the predictor uses, named by ``single_person_backend``: ``numba``, ``onnxruntime``,
``torch-traced`` or ``torch``), ``infer_ms_by_backend`` (the network alone timed through each path that is
available here, ``torch`` being eager ``predict_batch``; interleaved, so that all see the same machine
load), ``update_ms``
(the whole ``MotionPredictor.update``: repair, resampling, network, forecast object), ``update_arbitrated_ms``
(the same with ``arbitrate=True``: network, both baselines, arbitration and adaptive margins), ``mpjpe_mm``
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


def _by_backend(predictor, history: np.ndarray, repeats: int) -> dict[str, dict[str, float]]:
    """The one-person forecast timed through each path available here (the predictor's own fallbacks)."""
    from app.prediction.predictor import MotionPredictor

    paths = {"numba": predictor._fast_forward(), "onnxruntime": predictor._onnx_session()}
    paths["torch-traced"] = predictor._single_person_net()
    x = history[0]
    x32 = np.ascontiguousarray(history, dtype=np.float32)
    calls = {}
    if paths["numba"] is not None:
        calls["numba"] = lambda f=paths["numba"]: f(x)
    if paths["onnxruntime"] is not None:
        calls["onnxruntime"] = lambda s=paths["onnxruntime"]: s.run(None, {"x": x32})[0].astype(np.float64)
    if paths["torch-traced"] is not predictor.model:
        import torch

        def traced(net=paths["torch-traced"]) -> np.ndarray:
            with torch.inference_mode():
                return net(torch.from_numpy(x32)).numpy().astype(np.float64)

        calls["torch-traced"] = traced
    eager = MotionPredictor(kind="graphmixer", jit=False)  # the shipped weights, like ``predictor``
    calls["torch"] = lambda: eager.predict_batch(history)
    samples: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(10):
        for call in calls.values():
            call()
    for _ in range(repeats):
        for name, call in calls.items():
            t = time.perf_counter()
            call()
            samples[name].append(time.perf_counter() - t)
    return {name: _percentiles(s) for name, s in samples.items()}


def _people_ms(bodies: int, base: np.ndarray, repeats: int) -> dict[str, dict[str, float]]:
    """Per frame, the forecast of ``bodies`` people walking side by side 0.8 m apart (arbitrated, as the
    engine forecasts each person, body 0 the one expected to fetch): before the decision
    (:meth:`~app.control.people.People.forecast`) and after it
    (:meth:`~app.control.people.People.catch_up`)."""
    from app.control.people import People
    from app.prediction.predictor import MotionPredictor
    from app.prediction.skeleton import HumanFrame

    people = People(MotionPredictor(kind="graphmixer", arbitrate=True))
    warm = 40 + 10
    before: list[float] = []
    after: list[float] = []
    for k in range(repeats + warm):
        t = k / 30.0
        frame = HumanFrame.stack(
            t,
            [HumanFrame(t, base + np.array([0.03 * k, 0.8 * b, 0.0]), body_ids=(b,)) for b in range(bodies)],
        )
        t_start = time.perf_counter()
        people.forecast(people.update(frame), margin_m=0.02, first=0)
        t_decided = time.perf_counter()
        people.catch_up()
        if k >= warm:
            before.append(t_decided - t_start)
            after.append(time.perf_counter() - t_decided)
    return {"before_decision": _percentiles(before), "after_decision": _percentiles(after)}


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
    result["single_person_backend"] = predictor.single_person_backend
    for _ in range(20):
        predictor.predict_batch(history, kind=kind)
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        predictor.predict_batch(history, kind=kind)
        samples.append(time.perf_counter() - t)
    result["infer_ms"] = _percentiles(samples)
    if predictor.model is not None:
        result["infer_ms_by_backend"] = _by_backend(predictor, history, repeats)
    samples = []
    for k in range(repeats + predictor.history):
        frame = HumanFrame(t=k / predictor.fps, joints=base + np.array([0.03 * k, 0.0, 0.0]))
        t = time.perf_counter()
        predictor.update(frame)
        if k >= predictor.history:
            samples.append(time.perf_counter() - t)
    result["update_ms"] = _percentiles(samples)
    # the same with the arbiter on: the network, both baselines, the arbitration and the adaptive margins
    arbitrated = MotionPredictor(kind="graphmixer", arbitrate=True)
    samples = []
    for k in range(repeats + arbitrated.horizon + arbitrated.history):
        frame = HumanFrame(t=k / arbitrated.fps, joints=base + np.array([0.03 * k, 0.0, 0.0]))
        t = time.perf_counter()
        arbitrated.update(frame)
        if k >= arbitrated.history + arbitrated.horizon:  # every step scored: the full per-frame work
            samples.append(time.perf_counter() - t)
    result["update_arbitrated_ms"] = _percentiles(samples)
    # every person in the cell: the engine's forecast of 1, 2 and 4 tracked bodies per frame (one arbitrated
    # predictor per person, the forecasts stacked), as :class:`app.control.people.People` runs it
    result["people_forecast_ms"] = {str(n): _people_ms(n, base, repeats) for n in (1, 2, 4)}
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
