"""Forecast margins calibrated on the motion of the cell where the predictor runs.

The shipped error quantiles (``app/assets/hmp_graphmixer.quantiles.json``) were measured on the CMU
validation clips: people walking, turning and reaching at full speed. A person standing at an assembly
table moves far less, so those margins overstate the forecast's error there, and every plan keeps that much
more room than it needs (the reactive baseline keeps only the tracking margin). Calibration measures the
per-horizon error quantiles on recorded motion of the cell itself (tracker recordings of its operators, or
the simulated operator) and writes them in the same file format; point ``HRC_HMP_QUANTILES`` at the result.

The quantiles are measured exactly as for the shipped file (:func:`app.prediction.evaluate.error_quantiles`:
every window of ``history + horizon`` consecutive frames, every joint), so the margin stays a statement
about this predictor's error on this kind of motion.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.prediction.evaluate import evaluate_windows
from app.prediction.skeleton import NUM_JOINTS

if TYPE_CHECKING:
    from app.prediction.predictor import MotionPredictor

__all__ = ["calibrate_quantiles", "write_quantiles"]

#: Windows are evaluated in batches of this many (bounded memory).
_BATCH = 512


def _windows(sequences: Sequence[np.ndarray], length: int, stride: int) -> np.ndarray:
    out = []
    for seq in sequences:
        seq = np.asarray(seq, dtype=np.float64)
        if seq.ndim != 3 or seq.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"a sequence must have shape (T, {NUM_JOINTS}, 3), got {seq.shape}")
        if not np.all(np.isfinite(seq)):
            raise ValueError("a calibration sequence has non-finite coordinates")
        starts = np.arange(0, seq.shape[0] - length + 1, stride)
        if starts.size:
            out.append(np.stack([seq[s : s + length] for s in starts]))
    if not out:
        raise ValueError(f"no calibration window: every sequence is shorter than {length} frames")
    return np.concatenate(out)


def calibrate_quantiles(
    sequences: Sequence[np.ndarray], predictor: MotionPredictor, *, stride: int = 2
) -> dict[str, Any]:
    """Error quantiles of ``predictor`` (and of both baselines) on ``sequences`` ((T, J, 3) each, on the
    predictor's frame grid), as the ``kinds`` and ``windows`` of a quantile file."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    t_in, H = predictor.history, predictor.horizon
    data = _windows(sequences, t_in + H, stride)
    kinds = ["constant_velocity", "zero_velocity"]
    if predictor.model is not None:
        kinds.insert(0, "graphmixer")
    # predictions in bounded batches, then one evaluation of every kind on the windows themselves
    preds = {
        k: np.concatenate(
            [
                predictor.predict_batch(data[i : i + _BATCH, :t_in], kind=k)[:, :H]
                for i in range(0, data.shape[0], _BATCH)
            ]
        )
        for k in kinds
    }
    results = evaluate_windows(
        data,
        {k: (lambda _obs, _h, p=p: p) for k, p in preds.items()},
        t_in=t_in,
        fps=predictor.fps,
        with_quantiles=True,
    )
    out = {k: {**r["quantiles_m"], "mpjpe_mm": r["mpjpe_mm"]} for k, r in results.items()}
    return {"kinds": out, "windows": int(data.shape[0])}


def write_quantiles(
    path: str | Path, result: dict[str, Any], *, fps: float, horizon: int, source: str
) -> Path:
    """Write a calibration result as a quantile file that :class:`MotionPredictor` reads."""
    path = Path(path)
    kinds = {k: {q: v for q, v in entry.items() if q != "mpjpe_mm"} for k, entry in result["kinds"].items()}
    doc = {
        "fps": float(fps),
        "horizon": int(horizon),
        "source": source,
        "unit": "m",
        "windows": result["windows"],
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "kinds": kinds,
        "mpjpe_mm": {k: entry["mpjpe_mm"] for k, entry in result["kinds"].items()},
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path
