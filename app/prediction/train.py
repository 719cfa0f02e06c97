"""Training of the Graph-Mixer predictor (``hrc hmp train``): seeded, with checkpoints and early stopping.

The result is one weights file (``.pt``: format tag, model config, state dict, validation error quantiles and
metrics), its error-quantile JSON (``<stem>.quantiles.json``, for every predictor kind, read by
:class:`~app.prediction.predictor.MotionPredictor`) and a model card (``<stem>.md``) next to it.
"""

from __future__ import annotations

import json
import logging
import math
import platform
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from app.prediction.data import Augmentation, Clip, WindowSampler, check_disjoint, windows
from app.prediction.evaluate import HORIZONS_MS, evaluate_windows
from app.prediction.graphmixer import GraphMixerConfig
from app.prediction.predictor import quantiles_path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Training settings.

    Attributes:
        seed: Seeds torch, the window sampler and the augmentation.
        steps: Maximum optimiser steps.
        batch: Windows per step.
        lr: Peak learning rate (AdamW; linear warm-up, cosine decay to 5 %).
        weight_decay: AdamW weight decay.
        warmup: Warm-up steps.
        eval_every: Steps between validations (and checkpoints).
        patience: Validations without improvement before stopping early.
        max_minutes: Wall-time budget; training stops (keeping the best model) when it runs out.
        threads: Torch CPU threads.
        val_stride: Stride of the validation windows.
        augmentation: Random augmentation of the training windows.
        model: Network settings.
    """

    seed: int = 0
    steps: int = 20000
    batch: int = 32
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup: int = 200
    eval_every: int = 250
    patience: int = 10
    max_minutes: float | None = 14.0
    threads: int = 1
    val_stride: int = 2
    augmentation: Augmentation = field(default_factory=Augmentation)
    model: GraphMixerConfig = field(default_factory=GraphMixerConfig)

    def to_dict(self) -> dict:
        d = asdict(self)
        for key in ("speed", "slow_speed", "pause_frames"):
            d["augmentation"][key] = list(getattr(self.augmentation, key))
        return d


@dataclass(frozen=True)
class TrainResult:
    """Outcome of a training run.

    Attributes:
        weights: The written weights file.
        card: The written model card.
        quantiles: The written error-quantile JSON.
        steps: Optimiser steps taken.
        best_step: Step of the kept (best validation) model.
        val_mpjpe_mm: Validation MPJPE (mm) over the whole horizon of the kept model.
        stopped: Why training ended: ``"steps"``, ``"early_stopping"`` or ``"time_budget"``.
        metrics: ``{"validation": {...}, "test": {...}?}`` as from :func:`evaluate_windows`.
        minutes: Wall time.
    """

    weights: Path
    card: Path
    quantiles: Path
    steps: int
    best_step: int
    val_mpjpe_mm: float
    stopped: str
    metrics: dict
    minutes: float


def _lr_at(step: int, cfg: TrainConfig) -> float:
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    frac = min((step - cfg.warmup) / max(cfg.steps - cfg.warmup, 1), 1.0)
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * frac)))


def _model_fn(model):
    import torch

    def predict(obs: np.ndarray, H: int) -> np.ndarray:
        out = []
        with torch.inference_mode():
            for s in range(0, obs.shape[0], 512):
                x = torch.from_numpy(obs[s : s + 512].astype(np.float32))
                out.append(model(x).numpy().astype(np.float64))
        return np.concatenate(out, axis=0)[:, :H]

    return predict


def _val_loss_mm(model, val: np.ndarray, t_in: int) -> float:
    pred = _model_fn(model)(val[:, :t_in], val.shape[1] - t_in)
    return float(np.linalg.norm(pred - val[:, t_in:], axis=-1).mean() * 1000.0)


def train(
    train_clips: Sequence[Clip],
    val_clips: Sequence[Clip],
    cfg: TrainConfig,
    *,
    out: str | Path,
    checkpoint_dir: str | Path | None = None,
    test_clips: Sequence[Clip] | None = None,
    resume: bool = False,
    progress: bool = True,
    data_note: str = "",
    sources: Sequence[str] = (),
    left_out: str | None = None,
) -> TrainResult:
    """Train a Graph-Mixer and write weights, error quantiles and model card.

    Args:
        train_clips: Clips to draw (augmented) training windows from.
        val_clips: Clips for early stopping and the shipped error quantiles (not augmented).
        cfg: Settings.
        out: Weights file to write (``.pt``); the card and quantiles go next to it.
        checkpoint_dir: Where ``last.pt`` (resumable) and ``best.pt`` go; default ``<out dir>/checkpoints``.
        test_clips: Optional held-out clips, evaluated once at the end for the model card.

    Raises:
        ClipError: a clip (by split and name) is in two of the sets.
        resume: Continue from ``checkpoint_dir/last.pt`` if it exists.
        progress: Show a tqdm progress bar.
        data_note: Free text about the data for the model card.
        sources: The data sources trained on (``cmu``, ``sim``, ...), recorded with the weights.
        left_out: The source left out of training (``hrc hmp train --leave-out``), recorded with the weights
            so that ``hrc hmp eval --leave-out`` can check it.
    """
    import torch
    from tqdm import tqdm

    from app.prediction.graphmixer import GraphMixer, count_parameters, mpjpe, save_checkpoint

    check_disjoint(train=train_clips, validation=val_clips, test=test_clips or [])
    t_start = time.monotonic()
    out = Path(out)
    ckpt_dir = Path(checkpoint_dir) if checkpoint_dir is not None else out.parent / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    mcfg = cfg.model
    length = mcfg.t_in + mcfg.horizon
    sampler = WindowSampler(train_clips, length, augmentation=cfg.augmentation, seed=cfg.seed)
    noise_rng = np.random.default_rng(cfg.seed + 1)
    val = windows(val_clips, length, stride=cfg.val_stride)
    if val.shape[0] == 0:
        raise ValueError(
            f"the validation clips give no window of {length} frames; add longer validation clips"
        )

    model = GraphMixer(mcfg)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    step = 0
    best_mm = float("inf")
    best_step = 0
    best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    bad_evals = 0
    last_path = ckpt_dir / "last.pt"
    if resume and last_path.is_file():
        state = torch.load(last_path, map_location="cpu", weights_only=False)
        if state.get("config") != cfg.to_dict():
            raise ValueError(
                f"{last_path} was written with other settings; remove it or train without --resume"
            )
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        step, best_mm, best_step, bad_evals = (
            state["step"],
            state["best_mm"],
            state["best_step"],
            state["bad_evals"],
        )
        best_state = state["best_state"]
        sampler.rng.bit_generator.state = state["sampler_rng"]
        noise_rng.bit_generator.state = state["noise_rng"]
        torch.set_rng_state(state["torch_rng"])
        log.info("resumed from %s at step %d", last_path, step)

    stopped = "steps"
    bar = tqdm(total=cfg.steps, initial=step, disable=not progress, desc="hmp train", unit="step")
    running = None
    model.train()
    while step < cfg.steps:
        batch = sampler.sample(cfg.batch)
        obs = batch[:, : mcfg.t_in]
        if cfg.augmentation.noise_m > 0:
            obs = obs + noise_rng.normal(0.0, cfg.augmentation.noise_m, size=obs.shape)
        x = torch.from_numpy(obs.astype(np.float32))
        y = torch.from_numpy(batch[:, mcfg.t_in :].astype(np.float32))
        for g in opt.param_groups:
            g["lr"] = _lr_at(step, cfg)
        loss = mpjpe(model(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        step += 1
        lv = float(loss.detach()) * 1000.0
        running = lv if running is None else 0.98 * running + 0.02 * lv
        bar.update(1)
        if step % cfg.eval_every == 0 or step == cfg.steps:
            model.eval()
            val_mm = _val_loss_mm(model, val, mcfg.t_in)
            model.train()
            if val_mm < best_mm - 0.05:
                best_mm, best_step, bad_evals = val_mm, step, 0
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
                torch.save({"step": step, "val_mm": val_mm, "state_dict": best_state}, ckpt_dir / "best.pt")
            else:
                bad_evals += 1
            torch.save(
                {
                    "config": cfg.to_dict(),
                    "model": model.state_dict(),
                    "optimizer": opt.state_dict(),
                    "step": step,
                    "best_mm": best_mm,
                    "best_step": best_step,
                    "bad_evals": bad_evals,
                    "best_state": best_state,
                    "sampler_rng": sampler.rng.bit_generator.state,
                    "noise_rng": noise_rng.bit_generator.state,
                    "torch_rng": torch.get_rng_state(),
                },
                last_path,
            )
            bar.set_postfix(train_mm=f"{running:.1f}", val_mm=f"{val_mm:.1f}", best=f"{best_mm:.1f}")
            log.info("step %d: train %.1f mm, validation %.1f mm (best %.1f)", step, running, val_mm, best_mm)
            if bad_evals >= cfg.patience:
                stopped = "early_stopping"
                break
        if cfg.max_minutes is not None and time.monotonic() - t_start > 60.0 * cfg.max_minutes:
            stopped = "time_budget"
            break
    bar.close()
    if best_mm == float("inf"):  # stopped before the first validation
        model.eval()
        best_mm, best_step = _val_loss_mm(model, val, mcfg.t_in), step
        best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}

    model.load_state_dict(best_state)
    model.eval()
    from app.prediction.baselines import constant_velocity, zero_velocity

    predictors = {
        "graphmixer": _model_fn(model),
        "constant_velocity": constant_velocity,
        "zero_velocity": zero_velocity,
    }
    val_full = windows(val_clips, length, stride=1)
    metrics = {
        "validation": evaluate_windows(
            val_full, predictors, t_in=mcfg.t_in, fps=mcfg.fps, with_quantiles=True
        )
    }
    metrics["validation"]["windows"] = int(val_full.shape[0])
    if test_clips:
        test = windows(test_clips, length, stride=1)
        if test.shape[0] > 0:
            metrics["test"] = evaluate_windows(test, predictors, t_in=mcfg.t_in, fps=mcfg.fps)
            metrics["test"]["windows"] = int(test.shape[0])
    quantiles = {k: metrics["validation"][k].pop("quantiles_m") for k in predictors}
    minutes = (time.monotonic() - t_start) / 60.0
    info = {
        "trained_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "steps": step,
        "best_step": best_step,
        "stopped": stopped,
        "minutes": round(minutes, 2),
        "params": count_parameters(model),
        "train_clips": [c.label for c in train_clips],
        "val_clips": [c.label for c in val_clips],
        "test_clips": [c.label for c in test_clips] if test_clips else [],
        "train_frames": int(sum(c.frames for c in train_clips)),
        "val_frames": int(sum(c.frames for c in val_clips)),
        "torch": str(torch.__version__),
        "python": platform.python_version(),
        "data_note": data_note,
        "sources": list(sources),
        "left_out": left_out,
    }
    save_checkpoint(
        out,
        model,
        quantiles=quantiles["graphmixer"],
        metrics=metrics,
        train_config=cfg.to_dict(),
        info=info,
    )
    qpath = quantiles_path(out)
    qpath.write_text(
        json.dumps(
            {
                "fps": mcfg.fps,
                "horizon": mcfg.horizon,
                "source": f"validation clips ({metrics['validation']['windows']} windows): "
                + ", ".join(info["val_clips"]),
                "unit": "m",
                "kinds": quantiles,
            },
            indent=1,
        )
    )
    card = out.with_suffix(".md")
    card.write_text(model_card(cfg, info, metrics, quantiles, weights_name=out.name))
    return TrainResult(
        weights=out,
        card=card,
        quantiles=qpath,
        steps=step,
        best_step=best_step,
        val_mpjpe_mm=best_mm,
        stopped=stopped,
        metrics=metrics,
        minutes=minutes,
    )


def _table(results: dict, kinds: Sequence[str]) -> str:
    head = "| predictor | " + " | ".join(f"{ms} ms" for ms in HORIZONS_MS) + " |"
    sep = "|---|" + "---:|" * len(HORIZONS_MS)
    rows = [
        f"| {k} | " + " | ".join(f"{results[k]['mpjpe_mm'][str(ms)]:.1f}" for ms in HORIZONS_MS) + " |"
        for k in kinds
        if k in results
    ]
    return "\n".join([head, sep, *rows])


def _ratios(results: dict) -> str:
    gm, cv = results["graphmixer"]["mpjpe_mm"], results["constant_velocity"]["mpjpe_mm"]
    r400 = gm["400"] / cv["400"]
    r1000 = gm["1000"] / cv["1000"]
    met400 = "met" if r400 <= 0.7 else "not met"
    met1000 = "met" if r1000 <= 0.8 else "not met"
    return (
        f"Graph-Mixer / constant velocity: {r400:.2f} at 400 ms (aim <= 0.70: {met400}),"
        f" {r1000:.2f} at 1000 ms (aim <= 0.80: {met1000})."
    )


def model_card(
    cfg: TrainConfig, info: dict, metrics: dict, quantiles: dict, *, weights_name: str, extra: str = ""
) -> str:
    """The model card (Markdown) written next to the weights."""
    kinds = ("graphmixer", "constant_velocity", "zero_velocity")
    m = cfg.model
    lines = [
        f"# Model card: `{weights_name}` (Graph-Mixer human motion predictor)",
        "",
        f"Forecasts the canonical {m.n_joints}-joint skeleton {m.horizon} frames",
        f"({m.horizon / m.fps:.2f} s at {m.fps:g} Hz) ahead from the last {m.t_in} observed frames,",
        "for the proactive planner.",
        'Architecture after "Adaptive Spatial-Temporal Graph-Mixer for Human Motion Prediction"',
        "(see `app/prediction/graphmixer.py`); trained from scratch by `hrc hmp train`.",
        "",
        "## Inputs and frames",
        "",
        f"- Input: {m.t_in} poses (world frame, metres, z up, {m.fps:g} Hz). The network works in a",
        "  person-centred frame: the last observed pelvis is the origin and the frame is turned about z so",
        "  that the person faces +x (from the hip and shoulder lines). The network sees frame-to-frame",
        "  differences (as m/s) and the centred poses; it predicts displacements from the last pose, which",
        "  are mapped back to the world frame.",
        f"- Output: {m.horizon} future poses. Uncertainty: per-horizon quantiles of the per-joint error on",
        "  the validation clips, in the `.quantiles.json` next to the weights (the predictor's margins;",
        "  default p95).",
        "",
        "## Data",
        "",
        f"- Training clips ({len(info['train_clips'])}, {info['train_frames']} frames): "
        + ", ".join(info["train_clips"]),
        f"- Validation clips ({len(info['val_clips'])}, {info['val_frames']} frames; early stopping and"
        " error quantiles): " + ", ".join(info["val_clips"]),
        f"- Test clips (never used in training): {', '.join(info['test_clips']) or 'none'}",
        "- CMU clips are converted with `from_cmu38` (orientation fix: the shared clips' bodies are",
        "  mirrored and turned 90 degrees against their root trajectories; see",
        "  `app/prediction/adapters.py`).",
    ]
    if info.get("data_note"):
        lines.append(f"- {info['data_note']}")
    aug = cfg.augmentation
    lines += [
        "",
        "## Settings",
        "",
        f"- Model: {json.dumps(m.to_dict())}; {info['params']} parameters.",
        f"- Optimiser: AdamW, lr {cfg.lr} (warm-up {cfg.warmup} steps, cosine decay), weight decay "
        f"{cfg.weight_decay}, batch {cfg.batch}, gradient clipping 1.0, loss MPJPE, seed {cfg.seed}.",
        f"- Augmentation: rotation about z {'uniform' if aug.rotate else 'off'}, horizontal translation "
        f"+-{aug.translate_m} m, mirroring p={aug.mirror_p}, speed x{aug.speed[0]}..x{aug.speed[1]} "
        f"(resampled), input noise {aug.noise_m} m; work-cell motion: slow work p={aug.slow_p} "
        f"(speed x{aug.slow_speed[0]}..x{aug.slow_speed[1]}), pauses p={aug.pause_p} "
        f"({aug.pause_frames[0]}-{aug.pause_frames[1]} frames at rest).",
        f"- Run: {info['steps']} steps in {info['minutes']} min on {cfg.threads} CPU thread(s) (stopped "
        f"by {info['stopped']}); kept the model of step {info['best_step']}; torch {info['torch']}.",
        "",
        "## Metrics (MPJPE in mm, world frame, all joints; every window, stride 1)",
        "",
        f"Validation ({metrics['validation']['windows']} windows):",
        "",
        _table(metrics["validation"], kinds),
        "",
        _ratios(metrics["validation"]),
    ]
    if "test" in metrics:
        lines += [
            "",
            f"Test clips ({metrics['test']['windows']} windows):",
            "",
            _table(metrics["test"], kinds),
            "",
            _ratios(metrics["test"]),
        ]
    q = quantiles["graphmixer"]
    steps = [k for k in (3, 6, 12, 18, 24, 30) if k <= m.horizon]
    lines += [
        "",
        "## Error quantiles (Graph-Mixer, per-joint error on validation, m)",
        "",
        "| quantile | " + " | ".join(f"{round(k / m.fps * 1000)} ms" for k in steps) + " |",
        "|---|" + "---:|" * len(steps),
        *(
            f"| {name} | " + " | ".join(f"{q[name][k]:.3f}" for k in steps) + " |"
            for name in ("p50", "p90", "p95", "p99", "max_p95")
        ),
        "",
        "## Limits",
        "",
        f"- Trained on {info['train_frames'] / m.fps / 60:.1f} minutes of motion; motion unlike the",
        "  training clips (e.g. industrial pick-and-place, if it is not in them) may be forecast worse than",
        "  the validation numbers say. The margins are measured on held-out clips of the same kind.",
        "- The forecast is deterministic; the margins, not the poses, carry the uncertainty.",
    ]
    if extra:
        lines += ["", extra]
    return "\n".join(lines) + "\n"
