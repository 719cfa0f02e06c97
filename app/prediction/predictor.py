"""The motion predictor the runtime calls every frame: bounded history in, :class:`HumanForecast` out.

:class:`MotionPredictor` keeps the last frames of one person, repairs bad input and forecasts ``horizon``
frames (default 30 = 1 s at 30 Hz) from the last ``history`` frames (default 10), resampled onto a uniform
30 Hz grid that ends at the newest frame. Index 0 of the forecast is that newest (repaired) pose.

Bad input never yields a NaN forecast:

* joints with NaN/infinite coordinates or confidence below ``min_confidence`` are filled from the previous
  frame, moved by the mean displacement of the valid joints (or, with no previous frame, placed on their
  nearest valid ancestor in the skeleton); a frame with no valid joint is dropped;
* a gap longer than ``max_gap_s`` or a timestamp that goes backwards resets the history;
* until the history spans ``history`` frames the forecast falls back to constant velocity (two frames or more)
  or zero velocity (one frame), with their stored margins, also when the forecast is arbitrated: the arbiter
  scores and learns only from forecasts made from a full history (as ``hrc hmp eval`` replays them), not
  from these stand-ins, which are far off at the far steps (two noisy frames extrapolated over a second);
  predicted displacements are capped at ``max_speed_mps``.

Margins: each forecast carries per-step margins ``tracking_margin_m + q(t)``, where ``q`` is a per-horizon
quantile (default p95) of the per-joint error of the predictor that made the forecast, measured on validation
clips and shipped with the weights (``app/assets/hmp_graphmixer.quantiles.json``). Without that file the
margin grows at ``growth_mps`` (the ISO/TS 15066 human speed bound) from zero.

Inference: a single person's forecast (the per-frame call) runs through the compiled forward pass of
:mod:`app.prediction.fastforward` (BLAS products and fused numba loops, no torch; built once at first use and
checked against torch on probe inputs; about 2x less time per frame than ONNX Runtime and 3.5x less than
the traced torch network, whose per-operator overhead dominates such a small network). Where that path is
unavailable or fails its check, ONNX Runtime (the network exported once, checked alike), else a traced,
frozen torch copy; :attr:`MotionPredictor.single_person_backend` says which. Batches run eagerly in torch.
All run on the caller's thread with one thread each (BLAS is held to one thread during the compiled pass);
the runtime should also call ``torch.set_num_threads(1)`` once.
"""

from __future__ import annotations

import copy
import functools
import json
import logging
import math
import threading
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from app.prediction.baselines import constant_velocity, zero_velocity
from app.prediction.forecast import HumanForecast, Predictor, half_step_grid
from app.prediction.skeleton import MIN_JOINT_CONFIDENCE, NUM_JOINTS, PARENTS, HumanFrame

if TYPE_CHECKING:
    from app.prediction.arbitration import ForecastArbiter
    from app.prediction.graphmixer import GraphMixer

log = logging.getLogger(__name__)

#: Frames this close to the grid (s) are taken as they are by :meth:`MotionPredictor.window`.
_GRID_TOL_S = 1e-6

Kind = Literal["graphmixer", "constant_velocity", "zero_velocity"]
KINDS: tuple[str, ...] = ("graphmixer", "constant_velocity", "zero_velocity")

ASSETS_DIR = Path(__file__).resolve().parents[1] / "assets"
#: The shipped Graph-Mixer weights.
DEFAULT_WEIGHTS = ASSETS_DIR / "hmp_graphmixer.pt"


class WeightsError(RuntimeError):
    """A weights file is missing, unreadable or does not match the model; the message says which."""


class PredictorInputError(ValueError):
    """A frame cannot be used at all (no valid joint and nothing to repair it from)."""


@functools.cache
def _cap_speed_kernel() -> Callable[..., np.ndarray]:
    """The compiled speed cap, imported on first use (numba loads in about a second)."""
    from app.prediction._kernels import cap_speed

    return cap_speed


def quantiles_path(weights: str | Path) -> Path:
    """The error-quantile JSON that belongs to a weights file (``<stem>.quantiles.json`` next to it)."""
    weights = Path(weights)
    return weights.with_name(weights.stem + ".quantiles.json")


@dataclass(frozen=True)
class LoadedModel:
    """A Graph-Mixer with its checkpoint metadata."""

    model: GraphMixer
    path: Path
    meta: dict


_MODEL_CACHE: dict[tuple[str, float], LoadedModel] = {}
_MODEL_LOCK = threading.Lock()


def load_graphmixer(path: str | Path | None = None) -> LoadedModel:
    """Load (and cache, per path and modification time) a Graph-Mixer checkpoint.

    Raises:
        WeightsError: the file is missing, unreadable, of another format, or its tensors do not fit.
    """
    import torch

    from app.prediction.graphmixer import CHECKPOINT_FORMAT, GraphMixer, GraphMixerConfig

    path = Path(path) if path is not None else DEFAULT_WEIGHTS
    if not path.is_file():
        raise WeightsError(f"Graph-Mixer weights not found at {path}; train them with `hrc hmp train`")
    key = (str(path.resolve()), path.stat().st_mtime)
    with _MODEL_LOCK:
        if key in _MODEL_CACHE:
            return _MODEL_CACHE[key]
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt files
        # torch's messages run to many lines (and suggest loading untrusted pickles): the cause in brief
        raise WeightsError(
            f"cannot read Graph-Mixer weights {path}: the file is corrupt or not a torch checkpoint "
            f"({type(exc).__name__})"
        ) from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise WeightsError(f"{path} is not a Graph-Mixer checkpoint of format {CHECKPOINT_FORMAT!r}")
    try:
        cfg = GraphMixerConfig(**ckpt["config"])
        model = GraphMixer(cfg)
        model.load_state_dict(ckpt["state_dict"], strict=True)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise WeightsError(f"Graph-Mixer weights {path} do not match the model: {exc}") from exc
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    meta = {k: v for k, v in ckpt.items() if k != "state_dict"}
    loaded = LoadedModel(model=model, path=path, meta=meta)
    with _MODEL_LOCK:
        _MODEL_CACHE[key] = loaded
    return loaded


def load_quantiles(path: str | Path) -> dict[str, dict]:
    """Error quantiles from a ``*.quantiles.json`` file: ``{"fps", "kinds": {kind: {"p95": [...], ...}}}``."""
    data = json.loads(Path(path).read_text())
    if "kinds" not in data or "fps" not in data:
        raise ValueError(f"{path} is not an error-quantile file (needs 'fps' and 'kinds')")
    return data


def _tree_fill(joints: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Place each invalid joint on its nearest valid ancestor (or the mean of valid joints for the root)."""
    out = joints.copy()
    centre = joints[valid].mean(axis=0)
    for j in range(NUM_JOINTS):  # parents come before children in JOINTS
        if valid[j]:
            continue
        p = int(PARENTS[j])
        out[j] = out[p] if p >= 0 else centre
    return out


class MotionPredictor(Predictor):
    """Forecasts one person's motion from a bounded history of frames.

    Args:
        kind: ``"graphmixer"`` (the shipped network), ``"constant_velocity"`` or ``"zero_velocity"``.
        history: Observed frames the forecast is made from (on the ``fps`` grid).
        horizon: Predicted frames after the newest observation.
        fps: Rate of the forecast's samples and of the history grid (Hz).
        weights: Graph-Mixer checkpoint; default: the shipped one. If it is missing or does not match, the
            predictor logs a warning and uses constant velocity.
        quantiles: Error-quantile JSON; default: the one next to ``weights`` (or next to the shipped weights).
        margin_quantile: Which stored quantile becomes the margin (``"p50"``, ``"p90"``, ``"p95"``, ``"p99"``,
            ``"max_p95"``).
        tracking_margin_m: Margin added at every step, index 0 included (tracking error), m.
        growth_mps: Margin growth beyond the horizon (and the fallback margin slope), m/s.
        max_margin_m: Cap of the grown margin, m.
        min_confidence: Joints with lower confidence are repaired.
        max_gap_s: A longer gap between frames resets the history (default 4 frame periods).
        max_speed_mps: Cap of a predicted joint's displacement per second from the newest pose.
        jit: Run single-person forecasts through a compiled copy of the network (same numbers within
            1e-5, less overhead): the numba forward pass of :mod:`app.prediction.fastforward`, else ONNX
            Runtime if installed, else a traced, frozen torch module; batches run eagerly.
        arbitrate: Hand on the forecast arbitrated online between the network and both baselines, with
            adaptive conformal margins (:class:`app.prediction.arbitration.ForecastArbiter`) instead of the
            network's forecast with its stored quantile margins.
        coverage: The arbitrated forecast's target coverage (fraction of joints inside the margin).
    """

    def __init__(
        self,
        *,
        kind: Kind = "graphmixer",
        history: int = 10,
        horizon: int = 30,
        fps: float = 30.0,
        weights: str | Path | None = None,
        quantiles: str | Path | None = None,
        margin_quantile: str = "p95",
        tracking_margin_m: float = 0.0,
        growth_mps: float = 1.6,
        max_margin_m: float = 1.0,
        min_confidence: float = MIN_JOINT_CONFIDENCE,
        max_gap_s: float | None = None,
        max_speed_mps: float = 3.0,
        jit: bool = True,
        arbitrate: bool = False,
        coverage: float = 0.95,
    ) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown predictor kind {kind!r}; choose one of {', '.join(KINDS)}")
        if history < 2 or horizon < 1 or fps <= 0:
            raise ValueError(f"need history >= 2, horizon >= 1, fps > 0; got {history}, {horizon}, {fps}")
        self.kind: str = kind
        self.history = history
        self.horizon = horizon
        self.fps = float(fps)
        self.dt_s = 1.0 / self.fps
        self.tracking_margin_m = tracking_margin_m
        self.growth_mps = growth_mps
        self.max_margin_m = max_margin_m
        self.min_confidence = min_confidence
        self.max_gap_s = 4.0 * self.dt_s if max_gap_s is None else max_gap_s
        self.max_speed_mps = max_speed_mps
        self._steps_s = self.dt_s * np.arange(horizon + 1)
        self.margin_quantile = margin_quantile
        self._frames: deque[tuple[float, np.ndarray]] = deque(maxlen=4 * history)
        self.counters: dict[str, int] = {
            "frames": 0,
            "repaired_joints": 0,
            "dropped_frames": 0,
            "gap_resets": 0,
            "time_resets": 0,
            "duplicates": 0,
            "fallback_forecasts": 0,
        }
        self.last_source: str = "zero_velocity"
        self.model: GraphMixer | None = None
        self.jit = jit
        self._traced = None
        self._onnx = None
        self._fast = None
        self.model_meta: dict = {}
        self.effective_kind: str = kind
        #: Why the predictor runs constant velocity instead of the network it was asked for (None: it runs
        #: what was asked).
        self.fallback_reason: str | None = None
        weights_path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
        self.weights_path: Path | None = weights_path if kind == "graphmixer" else None
        if kind == "graphmixer":
            try:
                loaded = load_graphmixer(weights_path)
            except WeightsError as exc:
                log.warning("%s; falling back to the constant-velocity predictor", exc)
                self.effective_kind = "constant_velocity"
                self.fallback_reason = str(exc)
            else:
                cfg = loaded.model.cfg
                if cfg.t_in != history or cfg.horizon != horizon or abs(cfg.fps - self.fps) > 1e-6:
                    log.warning(
                        "Graph-Mixer weights %s are for %d frames in, %d out at %.1f Hz, not %d/%d at %.1f"
                        " Hz; falling back to the constant-velocity predictor",
                        weights_path,
                        cfg.t_in,
                        cfg.horizon,
                        cfg.fps,
                        history,
                        horizon,
                        self.fps,
                    )
                    self.effective_kind = "constant_velocity"
                    self.fallback_reason = (
                        f"Graph-Mixer weights {weights_path} are for {cfg.t_in} frames in, {cfg.horizon} out "
                        f"at {cfg.fps:.1f} Hz, not {history}/{horizon} at {self.fps:.1f} Hz"
                    )
                else:
                    self.model = loaded.model
                    self.model_meta = loaded.meta
        self._quantile_data: dict[str, Any] | None = None
        self._margins = self._load_margins(quantiles, weights_path)
        self.arbiter: ForecastArbiter | None = None
        if arbitrate:
            from app.prediction.arbitration import ForecastArbiter

            names = ("constant_velocity", "zero_velocity")
            if self.model is not None and self.effective_kind == "graphmixer":
                names = ("graphmixer", *names)
            self.arbiter = ForecastArbiter(
                names,
                horizon=self.horizon,
                dt_s=self.dt_s,
                coverage=coverage,
                floor_m=max(self.tracking_margin_m, 1e-3),
                prior_m=self._arbiter_prior(names[0], coverage),
            )

    # ---------------------------------------------------------------- margins
    def _arbiter_prior(self, kind: str, coverage: float) -> np.ndarray:
        """The arbiter's prior margins: the stored error quantile at its cold-start level for ``coverage``
        (:func:`app.prediction.arbitration.prior_margins`) plus the tracking margin; else the stored
        margins."""
        from app.prediction.arbitration import prior_margins

        if self._quantile_data is None:
            return self._margins[kind]
        try:
            prior = prior_margins(
                self._quantile_data, kind, coverage=coverage, fps=self.fps, horizon=self.horizon
            )
        except ValueError:
            return self._margins[kind]
        return prior + self.tracking_margin_m

    def _load_margins(self, quantiles: str | Path | None, weights_path: Path) -> dict[str, np.ndarray]:
        times = np.arange(self.horizon + 1) * self.dt_s
        candidates = [Path(quantiles)] if quantiles is not None else [quantiles_path(weights_path)]
        if quantiles is None and weights_path != DEFAULT_WEIGHTS:
            candidates.append(quantiles_path(DEFAULT_WEIGHTS))
        data = None
        for c in candidates:
            if c.is_file():
                try:
                    data = load_quantiles(c)
                    self._quantile_data = data
                    break
                except (ValueError, OSError) as exc:
                    log.warning("ignoring error-quantile file %s: %s", c, exc)
        margins: dict[str, np.ndarray] = {}
        for kind in KINDS:
            q = None
            if data is not None:
                entry = data["kinds"].get(kind, {})
                if self.margin_quantile in entry:
                    values = np.asarray(entry[self.margin_quantile], dtype=np.float64)
                    src_t = np.arange(values.shape[0]) / float(data["fps"])
                    q = np.interp(times, src_t, values)
                    beyond = np.maximum(times - src_t[-1], 0.0)
                    q = q + self.growth_mps * beyond
            if q is None:
                q = self.growth_mps * times
            margins[kind] = np.minimum(
                q + self.tracking_margin_m, max(self.max_margin_m, self.tracking_margin_m)
            )
        if data is None:
            log.warning(
                "no forecast error quantiles found (%s); margins grow at %.2f m/s instead",
                ", ".join(str(c) for c in candidates),
                self.growth_mps,
            )
        return margins

    def margins_for(self, kind: str) -> np.ndarray:
        """Margins (H + 1,) in metres used with forecasts of ``kind``."""
        return self._margins[kind].copy()

    @property
    def arbitrated(self) -> bool:
        """The forecast is arbitrated online with the baselines (:attr:`arbiter`)."""
        return self.arbiter is not None

    # ---------------------------------------------------------------- history
    def reset(self) -> None:
        """Forget the history (e.g. when the tracked person changes), and what the arbiter learned."""
        self._frames.clear()
        if self.arbiter is not None:
            self.arbiter.reset()

    def spawn(self) -> MotionPredictor:
        """This predictor for another person: the network, its compiled forms and the margins shared; the
        history, the counters and the arbiter's record its own."""
        twin = copy.copy(self)
        twin._frames = deque(maxlen=self._frames.maxlen)
        twin.counters = dict.fromkeys(self.counters, 0)
        twin.arbiter = None if self.arbiter is None else copy.deepcopy(self.arbiter)
        twin.reset()
        return twin

    @property
    def history_len(self) -> int:
        """Frames currently held."""
        return len(self._frames)

    def _repair(self, frame: HumanFrame) -> np.ndarray | None:
        joints = np.asarray(frame.joints, dtype=np.float64)
        conf = np.asarray(frame.confidence, dtype=np.float64)
        valid = np.all(np.isfinite(joints), axis=1) & np.isfinite(conf) & (conf >= self.min_confidence)
        n_bad = int(NUM_JOINTS - valid.sum())
        if n_bad == 0:
            return joints
        if n_bad == NUM_JOINTS:
            return None
        self.counters["repaired_joints"] += n_bad
        if self._frames:
            prev = self._frames[-1][1]
            shift = (joints[valid] - prev[valid]).mean(axis=0)
            out = joints.copy()
            out[~valid] = prev[~valid] + shift
            return out
        return _tree_fill(np.where(valid[:, None], joints, 0.0), valid)

    def observe(self, frame: HumanFrame) -> bool:
        """Add a frame to the history (repairing it); returns False if the frame was dropped."""
        t = float(frame.t)
        if not math.isfinite(t):
            self.counters["dropped_frames"] += 1
            log.debug("dropped a frame with a non-finite timestamp")
            return False
        if self._frames:
            t_last = self._frames[-1][0]
            if t < t_last:
                self.counters["time_resets"] += 1
                log.info("frame time went backwards (%.3f s < %.3f s): history reset", t, t_last)
                self._frames.clear()
            elif t == t_last:
                self.counters["duplicates"] += 1
                self._frames.pop()
            elif t - t_last > self.max_gap_s:
                self.counters["gap_resets"] += 1
                log.info("gap of %.3f s between frames: history reset", t - t_last)
                self._frames.clear()
        joints = self._repair(frame)
        if joints is None:
            self.counters["dropped_frames"] += 1
            if not self._frames:
                raise PredictorInputError(
                    f"frame at t={t:.3f} s has no valid joint (all non-finite or below confidence "
                    f"{self.min_confidence}) and there is no history to repair it from"
                )
            return False
        self._frames.append((t, joints))
        self.counters["frames"] += 1
        if self.arbiter is not None:
            self.arbiter.score(t, joints)
        return True

    def window(self) -> np.ndarray | None:
        """The history resampled on the ``fps`` grid ending at the newest frame: (history, J, 3).

        None if the frames held do not span it yet.
        """
        if not self._frames:
            return None
        n, H = len(self._frames), self.history
        if n >= H:  # a tracker at its nominal rate: the newest frames lie on the grid, nothing to resample
            recent = [self._frames[i] for i in range(n - H, n)]
            if all(abs(recent[i + 1][0] - recent[i][0] - self.dt_s) <= _GRID_TOL_S for i in range(H - 1)):
                return np.stack([f[1] for f in recent])
        times = np.fromiter((f[0] for f in self._frames), dtype=np.float64, count=len(self._frames))
        t_grid = times[-1] - self.dt_s * np.arange(self.history - 1, -1, -1)
        if times[0] > t_grid[0] + 0.25 * self.dt_s:
            return None
        poses = np.stack([f[1] for f in self._frames])
        idx = np.clip(np.searchsorted(times, t_grid, side="right"), 1, len(times) - 1)
        if len(times) == 1:
            return np.repeat(poses, self.history, axis=0)
        t0, t1 = times[idx - 1], times[idx]
        w = np.clip((t_grid - t0) / (t1 - t0), 0.0, 1.0)[:, None, None]
        return poses[idx - 1] * (1.0 - w) + poses[idx] * w

    # ---------------------------------------------------------------- forecasting
    def update(self, frame: HumanFrame) -> HumanForecast:
        """Observe ``frame`` and forecast from the history (never NaN).

        Raises:
            PredictorInputError: the very first frame (or the first after a reset) has no valid joint.
        """
        self.observe(frame)
        return self.forecast()

    def forecast(self) -> HumanForecast:
        """Forecast from the current history (index 0 = newest held pose): one sample per step of the
        horizon, and, when arbitrated, one more halfway between each two with the margin the arbiter
        calibrates there (:func:`app.prediction.forecast.half_step_grid`).

        Raises:
            PredictorInputError: the history is empty.
        """
        if not self._frames:
            raise PredictorInputError("no frame observed yet; call update(frame) first")
        t_last, last = self._frames[-1]
        kind = self.effective_kind
        win = self.window() if self.arbiter is not None or kind == "graphmixer" else None
        if self.arbiter is not None and win is not None:
            return self._arbitrated(win)
        future = None
        if kind == "graphmixer" and win is not None:
            future = self.predict_batch(win[None], kind="graphmixer")[0]
            source = "graphmixer"
            if not np.all(np.isfinite(future)):
                log.warning("Graph-Mixer returned non-finite values; using constant velocity for this frame")
                future = None
        if future is None:
            if kind != "zero_velocity" and len(self._frames) >= 2:
                t_prev, prev = self._frames[-2]
                step = (last - prev) * (self.dt_s / (t_last - t_prev))
                future = constant_velocity(np.stack([last - step, last])[None], self.horizon)[0]
                source = "constant_velocity"
            else:
                future = zero_velocity(last[None, None], self.horizon)[0]
                source = "zero_velocity"
            if source != self.kind:
                self.counters["fallback_forecasts"] += 1
        joints = self._cap_speed(last, future)
        self.last_source = source
        times = t_last + self._steps_s
        return HumanForecast(
            t0=t_last,
            times=times,
            joints=joints,
            margins=self._margins[source],
            growth_mps=self.growth_mps,
            max_margin_m=self.max_margin_m,
        )

    def _arbitrated(self, win: np.ndarray) -> HumanForecast:
        """The forecast of the arbiter over the network (when loaded) and both baselines, from the full
        history ``win`` (:meth:`window`)."""
        assert self.arbiter is not None
        t_last, last = self._frames[-1]
        t_prev, prev = self._frames[-2]
        step = (last - prev) * (self.dt_s / (t_last - t_prev))
        cv = constant_velocity(np.stack([last - step, last])[None], self.horizon)[0]
        futures = {"constant_velocity": cv, "zero_velocity": zero_velocity(last[None, None], self.horizon)[0]}
        if "graphmixer" in self.arbiter.candidates:
            net = self.predict_batch(win[None], kind="graphmixer")[0]
            futures["graphmixer"] = net if np.all(np.isfinite(net)) else cv
        out = self.arbiter.combine(t_last, {k: self._cap_speed(last, v) for k, v in futures.items()})
        self.last_source = "arbitrated"
        times, joints, margins = t_last + self._steps_s, out.joints, out.margins
        if out.half_margins is not None:  # the margins calibrated halfway between the steps too
            times, joints, margins = half_step_grid(times, joints, margins, out.half_margins)
        return HumanForecast(
            t0=t_last,
            times=times,
            joints=joints,
            margins=margins,
            growth_mps=self.growth_mps,
            max_margin_m=max(self.max_margin_m, float(margins.max())),
        )

    def _cap_speed(self, last: np.ndarray, future: np.ndarray) -> np.ndarray:
        """The forecast's joints (H + 1, J, 3): ``last``, then ``future`` with every joint's displacement
        from ``last`` capped at ``max_speed_mps`` times the step's time (compiled:
        :func:`app.prediction._kernels.cap_speed`; the tests compare it with the NumPy reference
        :func:`app.prediction.reference.cap_speed_reference`)."""
        return _cap_speed_kernel()(
            np.ascontiguousarray(last, dtype=np.float64),
            np.ascontiguousarray(future, dtype=np.float64),
            float(self.dt_s),
            float(self.max_speed_mps),
        )

    def predict_batch(self, history: np.ndarray, *, kind: str | None = None) -> np.ndarray:
        """Forecasts for several people at once: uniform histories (P, T, J, 3) -> futures (P, H, J, 3).

        The histories must be clean (finite) and on the ``fps`` grid; for the Graph-Mixer T must equal
        ``history``. ``kind`` defaults to the predictor's effective kind.

        Raises:
            ValueError: wrong shape or non-finite input.
            WeightsError: the Graph-Mixer was asked for but no weights are loaded.
        """
        history = np.asarray(history, dtype=np.float64)
        if history.ndim != 4 or history.shape[2:] != (NUM_JOINTS, 3):
            raise ValueError(f"predict_batch expects (P, T, {NUM_JOINTS}, 3), got {history.shape}")
        if not np.all(np.isfinite(history)):
            raise ValueError("predict_batch got non-finite coordinates; use update() for raw tracker frames")
        kind = kind or self.effective_kind
        if kind == "zero_velocity":
            return zero_velocity(history, self.horizon)
        if kind == "constant_velocity":
            return constant_velocity(history, self.horizon)
        if kind != "graphmixer":
            raise ValueError(f"unknown predictor kind {kind!r}")
        if self.model is None:
            raise WeightsError("no Graph-Mixer weights loaded")
        if history.shape[1] != self.history:
            raise ValueError(f"the Graph-Mixer needs {self.history} observed frames, got {history.shape[1]}")
        if history.shape[0] == 1 and self.jit:
            fast = self._fast_forward()
            if fast is not None:
                return fast(history[0])[None]
        import torch

        x32 = np.ascontiguousarray(history, dtype=np.float32)
        if x32.shape[0] == 1 and self.jit:
            session = self._onnx_session()
            if session is not None:
                return session.run(None, {"x": x32})[0].astype(np.float64)
        with torch.inference_mode():
            x = torch.from_numpy(x32)
            net = self._single_person_net() if x.shape[0] == 1 else self.model
            return net(x).numpy().astype(np.float64)

    @property
    def single_person_backend(self) -> str:
        """What a single person's Graph-Mixer forecast runs through (built on first use): ``"numba"`` (the
        compiled forward pass of :mod:`app.prediction.fastforward`), ``"onnxruntime"``, ``"torch-traced"`` or
        ``"torch"`` (``jit=False``, or every compiled path failed its check); ``"none"`` without weights."""
        if self.model is None:
            return "none"
        if not self.jit:
            return "torch"
        if self._fast_forward() is not None:
            return "numba"
        if self._onnx_session() is not None:
            return "onnxruntime"
        return "torch-traced" if self._single_person_net() is not self.model else "torch"

    def _fast_forward(self):
        """The compiled one-person forward pass, or None (numba missing, or it failed its check)."""
        if self._fast is None and self.model is not None:
            self._fast = _fast_single(self.model, self.history) or False
        return self._fast or None

    def _onnx_session(self):
        """The ONNX Runtime session for one person, or None (not installed, or the export failed)."""
        if self._onnx is None and self.model is not None:
            self._onnx = _onnx_single(self.model, self.history) or False
        return self._onnx or None

    def _single_person_net(self):
        """The network traced and frozen for one person (less Python overhead); eager if that fails."""
        if self._traced is None and self.jit and self.model is not None:
            self._traced = _trace_single(self.model, self.history)
        return self._traced if self._traced is not None else self.model


def _probe_histories(t_in: int) -> np.ndarray:
    """Inputs (2, t_in, J, 3) on which a compiled copy of the network must match torch: a ramp, and a person
    walking at 1 m/s through the cell with seeded joint noise."""
    ramp = np.zeros((t_in, NUM_JOINTS, 3))
    ramp[:, :, 0] = np.linspace(0.0, 0.1, t_in)[:, None]
    ramp[:, :, 1] = np.linspace(-0.2, 0.3, NUM_JOINTS)[None, :]
    rng = np.random.default_rng(7)
    base = rng.normal(scale=0.25, size=(NUM_JOINTS, 3)) + np.array([0.8, -0.4, 1.0])
    steps = np.arange(t_in)[:, None, None] / 30.0
    walk = base[None] + steps * np.array([0.6, 0.8, 0.0]) + rng.normal(scale=0.01, size=(t_in, NUM_JOINTS, 3))
    return np.stack([ramp, walk])


_COPIES: dict[str, weakref.WeakKeyDictionary] = {}


def _checked_copy(kind: str, model: GraphMixer, build: Callable[[], Any], fallback: str) -> Any:
    """A faster copy of ``model`` made once per model and ``kind`` by ``build()``, which checks it against
    the torch network and raises when it differs; None when it fails (logged with ``fallback``, what runs
    instead: the copies are an optimisation, torch stays the reference)."""
    with _MODEL_LOCK:
        cache = _COPIES.setdefault(kind, weakref.WeakKeyDictionary())
        if model in cache:
            return cache[model]
    try:
        copy = build()
    except Exception as exc:
        log.warning("could not run the Graph-Mixer through %s (%s); %s", kind, exc, fallback)
        copy = None
    with _MODEL_LOCK:
        cache[model] = copy
    return copy


def _trace_single(model: GraphMixer, t_in: int):
    """The network traced and frozen for one person, checked against the eager one; None if that fails."""
    import warnings

    import torch

    def build():
        example = torch.from_numpy(_probe_histories(t_in)[:1].astype(np.float32))
        with warnings.catch_warnings(), torch.inference_mode():
            warnings.simplefilter("ignore")
            traced = torch.jit.freeze(torch.jit.trace(model, example))
            if not torch.allclose(traced(example), model(example), atol=1e-5):
                raise RuntimeError("traced network differs from the eager one")
        return traced

    return _checked_copy("torch tracing", model, build, "running it eagerly")


def _fast_single(model: GraphMixer, t_in: int):
    """The compiled one-person forward pass of ``model`` (a :class:`~app.prediction.fastforward.
    FastGraphMixer`), checked against the torch network on probe inputs (1e-5 m); None when numba is missing
    or anything fails."""

    def build():
        import torch

        from app.prediction.fastforward import FastGraphMixer

        probes = _probe_histories(t_in)
        with torch.inference_mode():
            expected = model(torch.from_numpy(probes.astype(np.float32))).numpy()
        fast = FastGraphMixer(model)
        got = np.stack([fast(p) for p in probes])  # the first call compiles (or loads numba's cache)
        err = float(np.max(np.abs(got - expected)))
        if not err <= 1e-5:
            raise RuntimeError(f"the compiled network differs from the torch one by {err:.2e} m")
        return fast

    return _checked_copy("its compiled forward pass", model, build, "using ONNX/torch")


def _onnx_single(model: GraphMixer, t_in: int):
    """An ONNX Runtime session of ``model`` for one person (input ``x`` (1, t_in, J, 3) float32), checked
    against the torch network on a probe input; None when onnxruntime is missing or anything fails."""
    try:
        import onnxruntime as ort
    except ImportError:
        log.info("onnxruntime is not installed; forecasts run through torch")
        return None

    def build():
        import io
        import warnings

        import torch

        example = torch.from_numpy(_probe_histories(t_in)[:1].astype(np.float32))
        buf = io.BytesIO()
        with warnings.catch_warnings(), torch.inference_mode():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                model, (example,), buf, dynamo=False, input_names=["x"], output_names=["y"], opset_version=17
            )
            expected = model(example).numpy()
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        session = ort.InferenceSession(buf.getvalue(), options, providers=["CPUExecutionProvider"])
        got = session.run(None, {"x": example.numpy()})[0]
        if got.shape != expected.shape or not np.allclose(got, expected, atol=1e-5):
            raise RuntimeError("the ONNX network differs from the torch one")
        return session

    return _checked_copy("ONNX Runtime", model, build, "using torch")


def load_default_predictor(
    kind: Kind = "graphmixer", *, weights: str | Path | None = None
) -> MotionPredictor:
    """The app's predictor: the shipped Graph-Mixer (constant velocity with a warning if its weights are
    missing or do not match), or a baseline."""
    return MotionPredictor(kind=kind, weights=weights)
