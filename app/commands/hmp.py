"""``hrc hmp``: train and evaluate the human motion predictor (registered in :mod:`app.cli`).

It lives above the predictor's package so that it may record simulated operators for it.

Heavy modules (torch, the data loaders) are imported inside the command bodies so ``hrc --help`` stays fast.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Annotated

import typer

hmp_app = typer.Typer(
    name="hmp",
    help="Human motion prediction: train the Graph-Mixer, evaluate it against the baselines.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
)


#: The data sources of a cross-source evaluation (``--leave-out``): the CMU clips (trained on their train
#: split, evaluated on their test split) and the simulated operators of the configured cell (trained on
#: participant seeds from ``--sim-train-seed``, by default 2000 on; evaluated on ``--sim-seed``, by default 1
#: on).
SOURCES: tuple[str, ...] = ("cmu", "sim")

#: Where ``hrc hmp train --leave-out SOURCE`` writes its weights by default and ``hrc hmp eval --leave-out
#: SOURCE`` reads them.
LEAVE_OUT_DIR = Path("var") / "hmp_leave_out"


def _leave_out_weights(source: str) -> Path:
    return LEAVE_OUT_DIR / f"{source}.pt"


def _check_source(source: str) -> None:
    if source not in SOURCES:
        raise _fail(f"unknown source {source!r} for --leave-out; choose one of {', '.join(SOURCES)}")


def _fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


@hmp_app.command("train")
def train_cmd(
    clips: Annotated[
        Path | None,
        typer.Option(help="Clip folder (npz); default: the shared CMU clips (their train split)."),
    ] = None,
    extra_clips: Annotated[
        list[Path] | None,
        typer.Option("--extra-clips", help="More clip folders to train on (all their clips)."),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Weights file to write; default: the shipped asset.")
    ] = None,
    checkpoint_dir: Annotated[
        Path | None, typer.Option(help="Resumable checkpoints; default: var/hmp_checkpoints.")
    ] = None,
    val_clips: Annotated[
        str | None,
        typer.Option(help="Comma-separated clip names held out for validation (default: one per action)."),
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    steps: Annotated[int, typer.Option(help="Maximum optimiser steps.")] = 20000,
    batch: Annotated[int, typer.Option(help="Windows per step.")] = 32,
    lr: Annotated[float, typer.Option(help="Peak learning rate.")] = 2e-3,
    max_minutes: Annotated[float, typer.Option(help="Wall-time budget (0: none).")] = 14.0,
    patience: Annotated[int, typer.Option(help="Validations without improvement before stopping.")] = 10,
    eval_every: Annotated[int, typer.Option(help="Steps between validations and checkpoints.")] = 250,
    threads: Annotated[int, typer.Option(help="Torch CPU threads.")] = 1,
    channels: Annotated[int, typer.Option(help="Hidden channels of the network.")] = 48,
    blocks: Annotated[int, typer.Option(help="Mixer blocks.")] = 3,
    resume: Annotated[bool, typer.Option(help="Continue from the last checkpoint.")] = False,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    leave_out: Annotated[
        str | None,
        typer.Option(
            "--leave-out",
            help="Train on every source but this one (cmu, sim: the CMU train split, simulated operators) "
            "for a cross-source evaluation with `hrc hmp eval --leave-out SOURCE`; default --out: "
            "var/hmp_leave_out/SOURCE.pt.",
        ),
    ] = None,
    sim_train_operators: Annotated[
        int, typer.Option(min=1, help="Simulated operators to train on (2 more validate).")
    ] = 12,
    sim_train_seed: Annotated[
        int, typer.Option(help="Seed of the first simulated operator trained on (not 1000-1999).")
    ] = 2000,
    sim_train_duration: Annotated[
        float, typer.Option(min=2.0, help="Seconds recorded per simulated operator.")
    ] = 60.0,
) -> None:
    """Train the Graph-Mixer on every source (the CMU train split, simulated operators of the configured
    cell) and your own clips; write weights, quantiles, model card.

    With ``--leave-out SOURCE`` it trains on every source of :data:`SOURCES` but ``SOURCE`` instead."""
    from app.prediction.data import (
        DEFAULT_VAL_CLIPS,
        ClipError,
        check_disjoint,
        load_clip_dir,
        require_cmu_dir,
        split_clips,
    )
    from app.prediction.graphmixer import GraphMixerConfig
    from app.prediction.predictor import DEFAULT_WEIGHTS
    from app.prediction.train import TrainConfig, train

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if leave_out is not None:
        _check_source(leave_out)
    if leave_out != "sim":
        last = sim_train_seed + sim_train_operators + 1
        if sim_train_seed <= 1999 and last >= 1000:
            raise _fail("--sim-train-seed: seeds 1000-1999 are the tuning seeds; train on others (2000 on)")
    train_clips, val, test, notes, sources = [], [], [], [], []
    try:
        if leave_out != "cmu":
            base_dir = require_cmu_dir(clips)
            base = load_clip_dir(base_dir, split="train" if (base_dir / "train").is_dir() else None)
            test = load_clip_dir(base_dir, split="test") if (base_dir / "test").is_dir() else []
            names = tuple(n.strip() for n in val_clips.split(",")) if val_clips else DEFAULT_VAL_CLIPS
            train_clips, val = split_clips(base, names)
            if not val:
                raise ClipError(
                    f"none of the validation clips {', '.join(names)} is in {base_dir}; pass --val-clips"
                )
            sources.append("cmu")
            notes.append(f"Clip folder: {base_dir.name}")
        if leave_out != "sim":
            label, sim_clips = _sim_operator_clips(
                sim_train_operators + 2, sim_train_seed, sim_train_duration, split="sim_train"
            )
            train_clips = [*train_clips, *sim_clips[:-2]]
            val = [*val, *(dataclasses.replace(c, split="sim_val") for c in sim_clips[-2:])]
            sources.append("sim")
            notes.append(f"{label} (the last two validate)")
        # clips of other folders keyed by their folder too: names repeat across folders
        extra = [
            dataclasses.replace(c, split=(d / c.split).as_posix())
            for d in (extra_clips or [])
            for c in load_clip_dir(d)
        ]
        if extra:
            sources.append("extra")
        check_disjoint(train=[*train_clips, *extra], validation=val, test=test)
    except ClipError as exc:
        raise _fail(str(exc)) from exc
    cfg = TrainConfig(
        seed=seed,
        steps=steps,
        batch=batch,
        lr=lr,
        max_minutes=max_minutes or None,
        patience=patience,
        eval_every=eval_every,
        threads=threads,
        model=GraphMixerConfig(channels=channels, blocks=blocks),
    )
    if extra:
        notes.append(f"extra clips: {', '.join(c.label for c in extra)}")
    if leave_out is not None:
        notes.insert(0, f"Cross-source run: source {leave_out!r} left out of training")
    default_out = DEFAULT_WEIGHTS if leave_out is None else _leave_out_weights(leave_out)
    default_ckpt = Path("var") / "hmp_checkpoints" / (f"leave_out_{leave_out}" if leave_out else "")
    result = train(
        [*train_clips, *extra],
        val,
        cfg,
        out=out or default_out,
        checkpoint_dir=checkpoint_dir or default_ckpt,
        test_clips=test,
        resume=resume,
        progress=progress,
        data_note="; ".join(notes),
        sources=sources,
        left_out=leave_out,
    )
    typer.echo(
        f"wrote {result.weights} ({result.steps} steps, kept step {result.best_step}, "
        f"validation MPJPE {result.val_mpjpe_mm:.1f} mm, stopped by {result.stopped}, "
        f"{result.minutes:.1f} min)"
    )
    typer.echo(f"model card: {result.card}; error quantiles: {result.quantiles}")


def _sim_operator_clips(count: int, seed: int, duration_s: float, *, split: str = "sim") -> tuple[str, list]:
    """Simulated operators of the configured cell at work (participant seeds ``seed`` .. ``seed + count -
    1``) as clips of the ``split`` split, and a line that says what they are."""
    from app.cell.recording import simulated_operator_sequences
    from app.config import Settings
    from app.prediction.data import Clip

    cell = Settings().load_workcell()
    sequences = simulated_operator_sequences(cell, participants=count, duration_s=duration_s, seed=seed)
    clips = [
        Clip(name=f"sim_operator_{seed + i}", positions=seq, action="work", split=split)
        for i, seq in enumerate(sequences)
    ]
    last = seed + count - 1
    label = f"simulated operators of cell {cell.name!r}: seeds {seed}..{last}, {duration_s:g} s each"
    if seed <= 1999 and last >= 1000:
        label += " (includes tuning seeds 1000-1999: not a held-out evaluation)"
    return label, clips


def _margin_prior(predictor, weights: Path | None, *, coverage: float):
    """The arbiter's prior margins for the preferred candidate: its stored error quantile at the coverage
    target (the quantile file next to the weights), or ``(None, None)`` (the arbiter's flat prior)."""
    from app.prediction.arbitration import prior_margins
    from app.prediction.predictor import DEFAULT_WEIGHTS, load_quantiles, quantiles_path

    kind = "graphmixer" if predictor.model is not None else "constant_velocity"
    path = quantiles_path(weights or DEFAULT_WEIGHTS)
    if not path.is_file():
        return None, None
    try:
        data = load_quantiles(path)
        prior = prior_margins(data, kind, coverage=coverage, fps=predictor.fps, horizon=predictor.horizon)
    except (KeyError, ValueError, OSError) as exc:
        raise _fail(f"cannot use the error quantiles {path} as the margins' prior: {exc}") from exc
    return prior, f"{path.name} ({kind})"


@hmp_app.command("eval")
def eval_cmd(
    clips: Annotated[
        Path | None, typer.Option(help="Clip folder (npz); default: the shared CMU clips.")
    ] = None,
    split: Annotated[str, typer.Option(help="Sub-folder / split to evaluate ('' for all clips).")] = "test",
    weights: Annotated[
        Path | None, typer.Option(help="Graph-Mixer weights; default: the shipped ones.")
    ] = None,
    stride: Annotated[int, typer.Option(help="Stride between evaluation windows.")] = 1,
    sim_operators: Annotated[
        int,
        typer.Option(
            min=0,
            help="Evaluate on this many simulated operators of the configured cell instead of clips (a "
            "held-out source: seeds 1000-1999 are the tuning seeds, report on others).",
        ),
    ] = 0,
    sim_seed: Annotated[int, typer.Option(help="Seed of the first simulated operator.")] = 1,
    sim_duration: Annotated[
        float, typer.Option(min=2.0, help="Seconds recorded per simulated operator.")
    ] = 60.0,
    leave_out: Annotated[
        str | None,
        typer.Option(
            "--leave-out",
            help="Cross-source evaluation: evaluate weights trained without this source (cmu, sim; by "
            "`hrc hmp train --leave-out SOURCE`, default var/hmp_leave_out/SOURCE.pt) on its held-out "
            "data (cmu: the CMU test split; sim: --sim-operators, default 10, from --sim-seed).",
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    card: Annotated[
        Path | None,
        typer.Option(
            help="Also write the results as a section of this model card (e.g. "
            "app/assets/hmp_graphmixer.md), replacing the section of the same data if it is there.",
        ),
    ] = None,
) -> None:
    """MPJPE (mm) at 80..1000 ms of the Graph-Mixer and both baselines on clips (default: CMU test split) or
    on simulated operators (``--sim-operators N``), and of the arbitrated forecast with its margins'
    coverage and mean margin, overall and per clip (``forecast.per_clip``), with the clip and horizon where
    it is worst against the better baseline (``forecast.worst_clip``)."""
    import torch

    from app.prediction.data import ClipError, load_clip_dir, require_cmu_dir
    from app.prediction.evaluate import HORIZONS_MS, evaluate_arbitrated, evaluate_clips
    from app.prediction.predictor import MotionPredictor

    torch.set_num_threads(1)
    trained_on = None
    if leave_out is not None:
        from app.prediction.predictor import WeightsError, load_graphmixer

        _check_source(leave_out)
        weights = weights or _leave_out_weights(leave_out)
        try:
            info = load_graphmixer(weights).meta.get("info") or {}
        except WeightsError as exc:
            raise _fail(f"{exc} (train them with `hrc hmp train --leave-out {leave_out}`)") from exc
        if info.get("left_out") != leave_out:
            raise _fail(
                f"{weights} was not trained with --leave-out {leave_out} (left out: {info.get('left_out')}, "
                f"sources: {info.get('sources', 'not recorded')}); it may have seen {leave_out!r}"
            )
        trained_on = info.get("sources")
        if leave_out == "sim":
            sim_operators = sim_operators or 10
        elif sim_operators > 0:
            raise _fail("--leave-out cmu evaluates on the CMU clips; drop --sim-operators")
    try:
        if sim_operators > 0:
            directory, clip_set = _sim_operator_clips(sim_operators, sim_seed, sim_duration)
            split = ""
        else:
            directory = require_cmu_dir(clips)
            clip_set = load_clip_dir(directory, split=split or None)
    except ClipError as exc:
        raise _fail(str(exc)) from exc
    if weights is not None:  # a path given is used or refused, never replaced by a baseline
        from app.prediction.predictor import WeightsError, load_graphmixer

        try:
            load_graphmixer(weights)
        except WeightsError as exc:
            raise _fail(str(exc)) from exc
    predictor = MotionPredictor(kind="graphmixer", weights=weights)
    predictors = {
        "constant_velocity": lambda obs, H: predictor.predict_batch(obs, kind="constant_velocity")[:, :H],
        "zero_velocity": lambda obs, H: predictor.predict_batch(obs, kind="zero_velocity")[:, :H],
    }
    if predictor.model is not None:
        predictors = {"graphmixer": lambda obs, H: predictor.predict_batch(obs, kind="graphmixer")[:, :H]} | (
            predictors
        )
    try:
        results = evaluate_clips(
            clip_set,
            predictors,
            t_in=predictor.history,
            horizon=predictor.horizon,
            fps=predictor.fps,
            stride=stride,
        )
    except ValueError as exc:
        raise _fail(str(exc)) from exc
    # the runtime's forecast: the candidates above arbitrated online, replayed frame by frame; the margins
    # start from the coverage-target error quantile stored with the weights (measured on clips the network
    # was not trained on, never on these)
    prior, prior_source = _margin_prior(predictor, weights, coverage=0.95)
    forecast = evaluate_arbitrated(
        clip_set,
        predictors,
        t_in=predictor.history,
        horizon=predictor.horizon,
        fps=predictor.fps,
        coverage=0.95,
        prior_m=prior,
    )
    forecast["margin_prior"] = prior_source
    report = {
        "clips": str(directory) + (f" ({split})" if split else ""),
        "windows": next(iter(results.values()))["windows"],
        "weights": str(weights or "shipped") if predictor.model is not None else None,
        "mpjpe_mm": {k: v["mpjpe_mm"] for k, v in results.items()},
        "forecast": forecast,
    }
    if leave_out is not None:
        report["left_out"] = leave_out
        report["trained_on"] = trained_on
    if card is not None:
        from app.prediction.evaluate import report_markdown, write_card_section

        if not card.parent.is_dir():
            raise _fail(f"--card: folder {card.parent} does not exist")
        if sim_operators:
            key = f"simulated operators from seed {sim_seed}, {sim_operators} x {sim_duration:g} s"
        else:
            key = f"{Path(str(directory)).name} ({split or 'all'})"
        key += f", {leave_out} left out of training" if leave_out else ""
        write_card_section(card, key, report_markdown(report))
    if as_json:
        typer.echo(json.dumps(report))
        return
    typer.echo(f"{report['clips']}: {report['windows']} windows; MPJPE in mm")
    typer.echo(f"{'predictor':<18}" + "".join(f"{ms:>8}" for ms in HORIZONS_MS))
    for kind, row in report["mpjpe_mm"].items():
        typer.echo(f"{kind:<18}" + "".join(f"{row[str(ms)]:>8.1f}" for ms in HORIZONS_MS))
    typer.echo(f"{'forecast':<18}" + "".join(f"{forecast['mpjpe_mm'][str(ms)]:>8.1f}" for ms in HORIZONS_MS))
    typer.echo(
        f"{'  coverage':<18}" + "".join(f"{forecast['coverage'][str(ms)]:>8.3f}" for ms in HORIZONS_MS)
    )
    typer.echo(
        f"{'  margin (mm)':<18}" + "".join(f"{forecast['margin_mm'][str(ms)]:>8.1f}" for ms in HORIZONS_MS)
    )
    if forecast.get("worst_clip"):
        from app.prediction.evaluate import worst_clip_text

        typer.echo(f"worst clip, forecast / better baseline: {worst_clip_text(forecast['worst_clip'])}")
    if predictor.model is None:
        typer.echo("(no usable Graph-Mixer weights: baselines only)")


@hmp_app.command("calibrate")
def calibrate_cmd(
    out: Annotated[Path, typer.Option(help="Quantile file to write (JSON).")],
    clips: Annotated[
        Path | None,
        typer.Option(
            help="Recorded motion of this cell (npz clips, e.g. tracker recordings); default: none."
        ),
    ] = None,
    sim_participants: Annotated[
        int, typer.Option(min=0, help="Simulated operators to record instead (when no --clips).")
    ] = 6,
    duration: Annotated[
        float, typer.Option(min=10.0, help="Seconds recorded per simulated operator.")
    ] = 120.0,
    seed: Annotated[int, typer.Option(help="Seed of the first simulated operator.")] = 1000,
    stride: Annotated[int, typer.Option(min=1, help="Frames between calibration windows.")] = 3,
    weights: Annotated[
        Path | None, typer.Option(help="Graph-Mixer weights to calibrate; default: the shipped ones.")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON summary.")] = False,
) -> None:
    """Forecast error quantiles on this cell's own motion (for HRC_HMP_QUANTILES): the margins the planner
    keeps around the forecast person, measured where the predictor runs instead of on the CMU clips."""
    import torch

    from app.cell.recording import simulated_operator_sequences
    from app.config import Settings
    from app.prediction.calibrate import calibrate_quantiles, write_quantiles
    from app.prediction.data import ClipError, load_clip_dir
    from app.prediction.predictor import MotionPredictor

    torch.set_num_threads(1)
    predictor = MotionPredictor(kind="graphmixer", weights=weights)
    if predictor.model is None:
        raise _fail(f"no usable Graph-Mixer weights at {weights or 'the shipped path'}")
    if clips is not None:
        try:
            sequences = [c.positions for c in load_clip_dir(clips)]
        except ClipError as exc:
            raise _fail(str(exc)) from exc
        source = f"clips {clips}"
    else:
        if sim_participants < 1:
            raise _fail("give --clips DIR or --sim-participants N >= 1")
        cell = Settings().load_workcell()
        sequences = simulated_operator_sequences(
            cell, participants=sim_participants, duration_s=duration, seed=seed, fps=predictor.fps
        )
        source = (
            f"simulated operators of cell {cell.name!r}: participant seeds"
            f" {seed}..{seed + sim_participants - 1}, {duration:g} s each"
        )
    try:
        result = calibrate_quantiles(sequences, predictor, stride=stride)
    except ValueError as exc:
        raise _fail(str(exc)) from exc
    path = write_quantiles(out, result, fps=predictor.fps, horizon=predictor.horizon, source=source)
    summary = {
        "out": str(path),
        "source": source,
        "windows": result["windows"],
        "p50_at_1s_m": {k: round(v["p50"][-1], 4) for k, v in result["kinds"].items()},
        "p95_at_1s_m": {k: round(v["p95"][-1], 4) for k, v in result["kinds"].items()},
        "mpjpe_mm": {k: v["mpjpe_mm"] for k, v in result["kinds"].items()},
    }
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo(f"wrote {path} ({result['windows']} windows of {source})")
    for k in result["kinds"]:
        typer.echo(
            f"  {k:<18} p50 at 1 s {summary['p50_at_1s_m'][k]:.3f} m, p95 {summary['p95_at_1s_m'][k]:.3f} m"
        )


@hmp_app.command("record-sim")
def record_sim_cmd(
    out: Annotated[Path, typer.Option(help="Folder to write the clips into (npz, canonical joints, 30 Hz).")],
    participants: Annotated[int, typer.Option(min=1, help="Simulated operators, one clip each.")] = 20,
    duration: Annotated[float, typer.Option(min=2.0, help="Seconds per clip.")] = 120.0,
    seed: Annotated[int, typer.Option(help="Seed of the first simulated operator.")] = 2000,
) -> None:
    """Record simulated operators at work as clips (for ``hrc hmp train --extra-clips``), the way a lab
    records its own operators with the tracker to tune the predictor to its cell."""
    import numpy as np

    from app.cell.recording import simulated_operator_sequences
    from app.config import Settings
    from app.prediction.skeleton import JOINTS

    cell = Settings().load_workcell()
    out.mkdir(parents=True, exist_ok=True)
    sequences = simulated_operator_sequences(cell, participants=participants, duration_s=duration, seed=seed)
    for i, seq in enumerate(sequences):
        np.savez_compressed(
            out / f"sim_operator_{seed + i}.npz",
            positions=seq.astype(np.float32),
            fps=np.float64(30.0),
            joint_names=np.array(JOINTS),
        )
    typer.echo(f"wrote {len(sequences)} clips of {duration:g} s to {out}")
