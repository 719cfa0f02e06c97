"""Human motion prediction: canonical skeleton, adapters, predictors (Graph-Mixer, baselines), training, eval.

The public names below are imported lazily, so importing this package (e.g. from the command line) stays
cheap; torch is only imported when a Graph-Mixer is loaded or trained.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, str] = {
    "JOINTS": "app.prediction.skeleton",
    "NUM_JOINTS": "app.prediction.skeleton",
    "HumanFrame": "app.prediction.skeleton",
    "HumanForecast": "app.prediction.forecast",
    "Predictor": "app.prediction.forecast",
    "from_zed34": "app.prediction.adapters",
    "from_zed38": "app.prediction.adapters",
    "from_cmu38": "app.prediction.adapters",
    "ZED34_NAMES": "app.prediction.adapters",
    "ZED38_NAMES": "app.prediction.adapters",
    "MotionPredictor": "app.prediction.predictor",
    "load_default_predictor": "app.prediction.predictor",
    "PredictorInputError": "app.prediction.predictor",
    "WeightsError": "app.prediction.predictor",
    "constant_velocity": "app.prediction.baselines",
    "zero_velocity": "app.prediction.baselines",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'app.prediction' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
