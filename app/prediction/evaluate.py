"""Evaluation of motion predictors on clips: MPJPE per horizon and per-horizon error quantiles.

Protocol: every window of ``t_in`` observed + ``horizon`` future frames of every clip (stride 1 unless told
otherwise), in the world frame. The error at a horizon in milliseconds that falls between two frames (80 ms is
frame 2.4 at 30 Hz) is measured between the prediction and the ground truth, both linearly interpolated in
time at that instant (index 0 being the last observed pose, where both coincide).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from app.prediction.data import Clip, windows

#: Horizons (ms) reported by ``hrc hmp eval`` and ``hrc bench hmp``.
HORIZONS_MS: tuple[int, ...] = (80, 160, 320, 400, 560, 720, 880, 1000)

#: Quantiles of the per-joint error stored with the weights ("p95" is the default margin).
QUANTILES: tuple[int, ...] = (50, 90, 95, 99)

#: The baselines a forecast is measured against (the better of the two, per clip and horizon).
BASELINES: tuple[str, ...] = ("constant_velocity", "zero_velocity")

PredictFn = Callable[[np.ndarray], np.ndarray]


def interpolate_horizon(seq: np.ndarray, t_s: float, fps: float) -> np.ndarray:
    """Poses (N, J, 3) at ``t_s`` after the last observation from ``seq`` (N, H + 1, J, 3) (index 0 = t 0)."""
    x = t_s * fps
    H = seq.shape[1] - 1
    if not 0.0 <= x <= H + 1e-9:
        raise ValueError(
            f"horizon {t_s * 1000:.0f} ms is outside the forecast (0 .. {H / fps * 1000:.0f} ms)"
        )
    k0 = min(int(np.floor(x + 1e-9)), H - 1) if H > 0 else 0
    w = x - k0
    if H == 0:
        return seq[:, 0]
    return seq[:, k0] * (1.0 - w) + seq[:, k0 + 1] * w


def mpjpe_at_horizons(
    last_obs: np.ndarray,
    pred: np.ndarray,
    target: np.ndarray,
    *,
    fps: float,
    horizons_ms: Sequence[int] = HORIZONS_MS,
) -> dict[str, float]:
    """MPJPE in millimetres at each horizon.

    Args:
        last_obs: Last observed poses (N, J, 3).
        pred: Predicted future poses (N, H, J, 3), frame k at ``k / fps`` after the last observation.
        target: True future poses (N, H, J, 3).
        fps: Frame rate (Hz).
        horizons_ms: Horizons to report (ms).

    Returns:
        ``{"80": mm, ...}`` keyed by the horizon in ms as a string.
    """
    if pred.shape != target.shape or pred.ndim != 4 or last_obs.shape != pred[:, 0].shape:
        raise ValueError(
            f"shape mismatch: last_obs {last_obs.shape}, pred {pred.shape}, target {target.shape}"
        )
    p = np.concatenate([last_obs[:, None], pred], axis=1)
    g = np.concatenate([last_obs[:, None], target], axis=1)
    out: dict[str, float] = {}
    for ms in horizons_ms:
        a = interpolate_horizon(p, ms / 1000.0, fps)
        b = interpolate_horizon(g, ms / 1000.0, fps)
        out[str(ms)] = float(np.linalg.norm(a - b, axis=-1).mean() * 1000.0)
    return out


def error_quantiles(pred: np.ndarray, target: np.ndarray) -> dict[str, list[float]]:
    """Per-horizon-step quantiles (m) of the per-joint error, with a leading 0 for the observed pose.

    Args:
        pred: Predicted future poses (N, H, J, 3).
        target: True future poses (N, H, J, 3).

    Returns:
        ``{"p50": [H + 1 values], "p90": ..., "p95": ..., "p99": ..., "max_p95": ...}``; ``max_p95`` is the
        95th percentile over windows of the largest joint error of the pose.
    """
    err = np.linalg.norm(pred - target, axis=-1)  # (N, H, J)
    out: dict[str, list[float]] = {}
    for q in QUANTILES:
        per_step = np.percentile(err.transpose(1, 0, 2).reshape(err.shape[1], -1), q, axis=1)
        out[f"p{q}"] = [0.0, *(float(v) for v in per_step)]
    out["max_p95"] = [0.0, *(float(v) for v in np.percentile(err.max(axis=2), 95, axis=0))]
    return out


def evaluate_windows(
    data: np.ndarray,
    predictors: Mapping[str, Callable[[np.ndarray, int], np.ndarray]],
    *,
    t_in: int,
    fps: float,
    horizons_ms: Sequence[int] = HORIZONS_MS,
    with_quantiles: bool = False,
) -> dict[str, dict]:
    """Evaluate predictors on windows (N, t_in + H, J, 3).

    Args:
        data: Windows of consecutive frames (world frame, metres).
        predictors: ``name -> fn(obs (N, t_in, J, 3), H) -> pred (N, H, J, 3)``.
        t_in: Observed frames per window.
        fps: Frame rate (Hz).
        horizons_ms: Horizons to report.
        with_quantiles: Also return the per-step error quantiles of each predictor.

    Returns:
        ``{name: {"mpjpe_mm": {"80": ...}, "quantiles_m": {...}?}}``.
    """
    if data.ndim != 4 or data.shape[1] <= t_in:
        raise ValueError(f"windows must be (N, t_in + H, J, 3) with H >= 1, got {data.shape} for t_in={t_in}")
    if data.shape[0] == 0:
        raise ValueError("no evaluation windows: the clips are shorter than t_in + horizon frames")
    obs, fut = data[:, :t_in], data[:, t_in:]
    H = fut.shape[1]
    results: dict[str, dict] = {}
    for name, fn in predictors.items():
        pred = np.asarray(fn(obs, H), dtype=np.float64)
        entry: dict = {"mpjpe_mm": mpjpe_at_horizons(obs[:, -1], pred, fut, fps=fps, horizons_ms=horizons_ms)}
        if with_quantiles:
            entry["quantiles_m"] = error_quantiles(pred, fut)
        results[name] = entry
    return results


def evaluate_clips(
    clips: Sequence[Clip],
    predictors: Mapping[str, Callable[[np.ndarray, int], np.ndarray]],
    *,
    t_in: int = 10,
    horizon: int = 30,
    fps: float = 30.0,
    stride: int = 1,
    horizons_ms: Sequence[int] = HORIZONS_MS,
    with_quantiles: bool = False,
) -> dict[str, dict]:
    """:func:`evaluate_windows` on every window of ``clips``; also reports the ``windows`` count."""
    data = windows(clips, t_in + horizon, stride=stride)
    results = evaluate_windows(
        data, predictors, t_in=t_in, fps=fps, horizons_ms=horizons_ms, with_quantiles=with_quantiles
    )
    for entry in results.values():
        entry["windows"] = int(data.shape[0])
    return results


def baseline_ratio(forecast_mm: float, baseline_mm: float) -> float:
    """A forecast's error over a baseline's: 1 where both are exact (0 mm), infinite where only the baseline
    is (reported as None)."""
    if baseline_mm > 0.0:
        return forecast_mm / baseline_mm
    return 1.0 if forecast_mm == 0.0 else float("inf")


def evaluate_arbitrated(
    clips: Sequence[Clip],
    predictors: Mapping[str, Callable[[np.ndarray, int], np.ndarray]],
    *,
    t_in: int = 10,
    horizon: int = 30,
    fps: float = 30.0,
    coverage: float = 0.95,
    horizons_ms: Sequence[int] = HORIZONS_MS,
    prior_m: np.ndarray | None = None,
    arbiter_options: Mapping[str, Any] | None = None,
    batch: int = 512,
) -> dict[str, object]:
    """The arbitrated runtime forecast (:class:`app.prediction.arbitration.ForecastArbiter` over
    ``predictors``, the preferred one first), replayed frame by frame through each clip as the runtime would
    run it: at every frame from the ``t_in``-th on, each candidate forecasts from the last ``t_in`` frames,
    the arbiter scores the forecasts made before against this frame and combines the new ones. Each clip is
    a new person (the arbiter starts over, from ``prior_m``). The candidates' forecasts do not depend on the
    arbiter, so they are computed per clip in batches of ``batch`` windows first.

    ``prior_m``: the arbiter's prior margin per step (default: its own); ``arbiter_options``: other keyword
    arguments of the arbiter (``gamma``, ``warmup``, ...).

    Returns ``{"mpjpe_mm": {ms: ...}, "coverage": {ms: ...}, "coverage_target": ..., "margin_mm": {ms:
    ...}, "forecasts": n, "chosen": {candidate: share of the steps}, "per_clip": [...], "worst_clip":
    {...}}``: the MPJPE of the combined forecast, the fraction of joints inside its margin and the mean
    margin, per horizon (margins interpolated like the poses, on the grid of half steps where the arbiter
    calibrates them there).

    ``per_clip`` has, for each clip evaluated, ``{"clip": label, "forecasts": n, "mpjpe_mm": {ms: ...},
    "baselines_mm": {baseline: {ms: ...}}, "ratio": {ms: ...}, "coverage": {ms: ...}}``: the combined
    forecast's MPJPE, that of each baseline of :data:`BASELINES` among ``predictors`` over the same forecasts
    (from the clip's first), the combined forecast's over the better baseline's (:func:`baseline_ratio`) and
    its coverage, per horizon. ``worst_clip`` is the clip and horizon of the highest ratio, ``{"clip",
    "horizon_ms", "ratio", "arbitrated_mm", "best_baseline", "best_baseline_mm", "coverage", "forecasts"}``
    (the clip's coverage at that horizon and its number of forecasts), or None where no baseline is among
    the candidates.
    """
    from app.prediction.arbitration import ForecastArbiter

    names = list(predictors)
    err_sum = np.zeros(len(horizons_ms))
    cov_sum = np.zeros(len(horizons_ms))
    margin_sum = np.zeros(len(horizons_ms))
    count = 0
    chosen_counts = dict.fromkeys(names, 0)
    options = dict(arbiter_options or {})
    if prior_m is not None:
        options["prior_m"] = prior_m
    baselines = [n for n in BASELINES if n in predictors]
    per_clip: list[dict[str, Any]] = []
    worst: dict[str, Any] | None = None
    worst_ratio = -np.inf
    for clip in clips:
        pos = np.asarray(clip.positions, dtype=np.float64)
        if pos.shape[0] < t_in + horizon:
            continue
        arbiter = ForecastArbiter(names, horizon=horizon, dt_s=1.0 / fps, coverage=coverage, **options)
        ends = np.arange(t_in - 1, pos.shape[0] - horizon)
        hist = np.stack([pos[i - t_in + 1 : i + 1] for i in ends])
        futures = {
            n: np.concatenate(
                [
                    np.concatenate([hist[s : s + batch, -1:], fn(hist[s : s + batch], horizon)], axis=1)
                    for s in range(0, hist.shape[0], batch)
                ]
            )
            for n, fn in predictors.items()
        }
        combined = np.empty((ends.size, horizon + 1, *pos.shape[1:]))
        # the margins on the grid of half steps (the runtime's forecast carries the margins calibrated
        # halfway between the steps, where the arbiter has them; else the steps' margins interpolated)
        margins = np.empty((ends.size, 2 * horizon + 1))
        for j_end, i in enumerate(ends):
            t = i / fps
            arbiter.score(t, pos[i])
            out = arbiter.combine(t, {n: f[j_end] for n, f in futures.items()})
            combined[j_end] = out.joints
            margins[j_end, 0::2] = out.margins
            half = out.half_margins
            margins[j_end, 1::2] = 0.5 * (out.margins[:-1] + out.margins[1:]) if half is None else half
            for name in out.chosen[1:]:
                chosen_counts[name] += 1
        truth = np.stack([pos[i : i + horizon + 1] for i in ends])
        clip_mm: dict[str, float] = {}
        clip_cov: dict[str, float] = {}
        base_mm: dict[str, dict[str, float]] = {n: {} for n in baselines}
        for j, ms in enumerate(horizons_ms):
            p = interpolate_horizon(combined, ms / 1000.0, fps)
            g = interpolate_horizon(truth, ms / 1000.0, fps)
            m = interpolate_horizon(margins[..., None, None], ms / 1000.0, 2.0 * fps)[:, 0, 0]
            d = np.linalg.norm(p - g, axis=-1)  # (forecasts, J)
            err_sum[j] += float(d.mean(axis=1).sum())
            cov_sum[j] += float(np.mean(d <= m[:, None], axis=1).sum())
            margin_sum[j] += float(m.sum())
            clip_mm[str(ms)] = 1000.0 * float(d.mean())
            clip_cov[str(ms)] = float(np.mean(d <= m[:, None]))
            for n in baselines:
                b = interpolate_horizon(futures[n], ms / 1000.0, fps)
                base_mm[n][str(ms)] = 1000.0 * float(np.linalg.norm(b - g, axis=-1).mean())
        count += int(ends.size)
        ratios: dict[str, float | None] = {}
        for key, mm in clip_mm.items() if baselines else ():
            best = min(baselines, key=lambda n, key=key: base_mm[n][key])
            ratio = baseline_ratio(mm, base_mm[best][key])
            ratios[key] = None if np.isinf(ratio) else round(ratio, 3)
            if ratio > worst_ratio:
                worst_ratio = ratio
                worst = {
                    "clip": clip.label,
                    "horizon_ms": int(key),
                    "ratio": ratios[key],
                    "arbitrated_mm": round(mm, 1),
                    "best_baseline": best,
                    "best_baseline_mm": round(base_mm[best][key], 1),
                    "coverage": round(clip_cov[key], 4),
                    "forecasts": int(ends.size),
                }
        per_clip.append(
            {
                "clip": clip.label,
                "forecasts": int(ends.size),
                "mpjpe_mm": {k: round(v, 1) for k, v in clip_mm.items()},
                "baselines_mm": {n: {k: round(v, 1) for k, v in base_mm[n].items()} for n in baselines},
                "ratio": ratios,
                "coverage": {k: round(v, 4) for k, v in clip_cov.items()},
            }
        )
    if count == 0:
        raise ValueError(f"no clip is longer than {t_in + horizon} frames")
    n_steps = sum(chosen_counts.values())
    return {
        "mpjpe_mm": {
            str(ms): round(1000.0 * e / count, 1) for ms, e in zip(horizons_ms, err_sum, strict=True)
        },
        "coverage": {str(ms): round(c / count, 4) for ms, c in zip(horizons_ms, cov_sum, strict=True)},
        "coverage_target": coverage,
        "margin_mm": {
            str(ms): round(1000.0 * m / count, 1) for ms, m in zip(horizons_ms, margin_sum, strict=True)
        },
        "forecasts": count,
        "chosen": {n: round(c / max(n_steps, 1), 3) for n, c in chosen_counts.items()},
        "per_clip": per_clip,
        "worst_clip": worst,
    }


def report_markdown(report: Mapping[str, Any], *, horizons_ms: Sequence[int] = HORIZONS_MS) -> str:
    """A report of ``hrc hmp eval --json`` as a model-card section: what was evaluated, then one table of
    MPJPE (mm) per predictor and for the arbitrated forecast, the forecast over the better baseline, its
    margins' coverage and mean margin, per horizon; then the share of the steps taken from each candidate
    and the clip and horizon where the forecast is worst against the better baseline."""
    forecast = report["forecast"]
    data = str(report["clips"]).rsplit("/", 1)[-1]  # a clip folder by its name: the card is read elsewhere
    lines = [f"Data: {data}; {report['windows']} windows, {forecast['forecasts']} forecasts."]
    if report.get("left_out"):
        lines.append(
            f"Weights trained without {report['left_out']!r} (on "
            f"{', '.join(report.get('trained_on') or [])}): {report['weights']}."
        )
    elif report.get("weights"):
        lines.append(f"Weights: {report['weights']}.")
    cols = [str(ms) for ms in horizons_ms]
    table = ["| | " + " | ".join(f"{ms} ms" for ms in cols) + " |", "|---|" + "---:|" * len(cols)]

    def row(name: str, values: Sequence[float], fmt: str) -> None:
        table.append(f"| {name} | " + " | ".join(format(v, fmt) for v in values) + " |")

    for name, mpjpe in report["mpjpe_mm"].items():
        row(name, [mpjpe[c] for c in cols], ".1f")
    row("forecast", [forecast["mpjpe_mm"][c] for c in cols], ".1f")
    cv, zv = report["mpjpe_mm"]["constant_velocity"], report["mpjpe_mm"]["zero_velocity"]
    row(
        "forecast / min(constant, zero velocity)",
        [forecast["mpjpe_mm"][c] / min(cv[c], zv[c]) for c in cols],
        ".3f",
    )
    row(f"coverage (target {forecast['coverage_target']:g})", [forecast["coverage"][c] for c in cols], ".3f")
    row("mean margin (mm)", [forecast["margin_mm"][c] for c in cols], ".1f")
    chosen = ", ".join(f"{k} {v:.1%}" for k, v in forecast.get("chosen", {}).items())
    tail = [f"Steps taken from each candidate: {chosen}."]
    if forecast.get("worst_clip"):
        worst = worst_clip_text(forecast["worst_clip"])
        tail.append(f"Worst clip (the forecast over the better baseline): {worst}.")
    return "\n".join([*lines, "", *table, "", *tail])


def worst_clip_text(worst: Mapping[str, Any]) -> str:
    """``worst_clip`` of :func:`evaluate_arbitrated` in one line."""
    ratio = "inf" if worst["ratio"] is None else f"{worst['ratio']:.3f}"
    return (
        f"{worst['clip']} at {worst['horizon_ms']} ms, {ratio}x ({worst['arbitrated_mm']:.1f} mm against "
        f"{worst['best_baseline']} {worst['best_baseline_mm']:.1f} mm; coverage {worst['coverage']:.3f}, "
        f"{worst['forecasts']} forecasts)"
    )


def write_card_section(card: Path, key: str, body: str) -> None:
    """Put ``body`` into the model card ``card`` between the markers of section ``key`` (replacing what
    was there; appended at the end the first time), so that a card is regenerated by running the
    evaluations again."""
    start, end = f"<!-- hrc hmp eval: {key} -->", f"<!-- end: {key} -->"
    text = card.read_text() if card.is_file() else ""
    block = f"{start}\n{body}\n{end}"
    if start in text and end in text:
        head, rest = text.split(start, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + block + "\n"
    card.write_text(text)
