"""``hrc cell ...``: commands about the cell (robot backends and human sources)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

cell_app = typer.Typer(
    help="The cell: robot backends and human sources.", no_args_is_help=True, rich_markup_mode=None
)


@cell_app.command("demo")
def demo(
    seconds: Annotated[float, typer.Option("--seconds", min=0.5, help="How long to run (s).")] = 10.0,
    source: Annotated[str, typer.Option("--source", help="Human source: sim or replay.")] = "sim",
    clip: Annotated[
        Path | None, typer.Option("--clip", help="Clip to replay (.npz: the CMU format or a recording).")
    ] = None,
    seed: Annotated[int, typer.Option("--seed", help="Participant seed of the simulated operator.")] = 0,
    rate_hz: Annotated[float, typer.Option("--rate", min=10.0, max=1000.0, help="Servo rate (Hz).")] = 125.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
) -> None:
    """Run the simulated robot and a human source together on the wall clock; print the frame rate and the
    validation counters."""
    from app.cell.demo import run_demo

    if source not in ("sim", "replay"):
        raise typer.BadParameter(f"--source must be 'sim' or 'replay', got {source!r}")
    if source == "replay" and clip is None:
        raise typer.BadParameter("--source replay needs --clip PATH")
    if clip is not None and not clip.is_file():
        raise typer.BadParameter(f"clip {clip} does not exist")
    report = run_demo(
        seconds=seconds,
        source=source,  # type: ignore[arg-type]
        clip=clip,
        seed=seed,
        rate_hz=rate_hz,
        progress=None if as_json else typer.echo,
    )
    if as_json:
        typer.echo(json.dumps(report))
        return
    v = report["validation"]
    loop = report["control_loop"]
    typer.echo(
        f"\n{report['source']}: {report['frames']} frames in {report['seconds']:.1f} s = "
        f"{report['frame_rate_hz']:.1f} Hz"
    )
    rejected = {k.removeprefix("rejected_"): n for k, n in v.items() if k.startswith("rejected_") and n}
    typer.echo(f"validation: accepted {v['accepted']}, rejected {v['rejected']} {rejected or ''}".rstrip())
    typer.echo(f"stale-stream events: {report['stale_events']}")
    typer.echo(
        f"control loop: {loop['ticks']} ticks at {loop['rate_hz']:g} Hz, {loop['overruns']} overruns "
        f"({loop['missed_ticks']} missed)"
    )
    r = report["robot"]
    typer.echo(
        f"robot: {r['moves']} moves, {r['blocks_placed']} blocks placed, "
        f"max tracking error {r['max_tracking_error_rad']:.4f} rad"
    )
    if "operator" in report:
        o = report["operator"]
        typer.echo(f"operator: {o['fetches']} fetches, {o['reaches_across']} reaches across; {o['params']}")


@cell_app.command("check")
def check(
    clips: Annotated[
        list[Path] | None,
        typer.Option(
            "--clip",
            help="A recording of the person at work in this cell's world frame (.npz: a tracker recording "
            "or the CMU format; repeat for more); default: simulated participants.",
        ),
    ] = None,
    place: Annotated[
        bool, typer.Option("--place", help="Place each clip in the operator's area (recorded elsewhere).")
    ] = False,
    participants: Annotated[
        int, typer.Option("--participants", min=1, help="Simulated participants (without --clip).")
    ] = 3,
    seed: Annotated[int, typer.Option("--seed", help="Participant seed of the first one.")] = 1,
    duration: Annotated[
        float, typer.Option("--duration", min=1.0, help="Seconds recorded per simulated participant.")
    ] = 60.0,
    speed: Annotated[
        float, typer.Option("--speed", min=0.001, help="Speed (m/s) to ask of the robot at each task pose.")
    ] = 0.1,
    suggest: Annotated[
        bool,
        typer.Option(
            "--suggest",
            help="Also find, for each drop station, the nearest place away from the person's work spot where "
            "the robot may move at --speed in at least --target-free of the frames.",
        ),
    ] = False,
    target_free: Annotated[
        float,
        typer.Option(
            "--target-free", min=0.01, max=1.0, help="Share of the frames a suggested station must be free."
        ),
    ] = 0.75,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
) -> None:
    """Check the cell's layout under the safety model: at each task pose, how close the person at work comes
    and how often the speed governor lets the robot move there at --speed (see app/control/layout.py);
    with --suggest, where to move the drop stations that the person's work blocks."""
    import numpy as np

    from app.cell.human import load_replay_clip, place_clip
    from app.cell.recording import simulated_operator_sequences
    from app.commands import fail, load_settings, load_workcell_or_fail
    from app.control.engine import EngineOptions, governor_model, supervisor_config
    from app.control.layout import DEFAULT_MAX_SHIFT_M, check_layout, suggest_stations
    from app.control.stack import PlanningStack

    settings, options = load_settings(), EngineOptions()
    cell = load_workcell_or_fail(settings)
    fps = 1.0 / settings.frame_period_s
    if clips:
        recordings, label = [], ", ".join(str(c) for c in clips)
        for path in clips:
            if not path.is_file():
                fail(f"--clip: clip {path} does not exist")
            try:
                clip = load_replay_clip(path, fps=fps)
            except ValueError as exc:
                fail(f"--clip: {exc}")
            recordings.append(place_clip(clip.joints, cell) if place else np.asarray(clip.joints))
    else:
        recordings = simulated_operator_sequences(
            cell, participants=participants, duration_s=duration, seed=seed, fps=fps
        )
        label = f"{participants} simulated participants from seed {seed}, {duration:g} s each"
    stack = PlanningStack.for_cell(cell, t_reaction_s=settings.reaction_time_s(options.servo_period_s))
    governor = governor_model(settings, stack.ssm, supervisor_config(settings, "proactive", options), options)
    moves = ()
    try:
        report = check_layout(stack, governor, recordings, fps=fps, speed_mps=speed)
        if suggest:
            moves = suggest_stations(
                stack, governor, recordings, fps=fps, speed_mps=speed, target_free=target_free
            )
    except ValueError as exc:
        fail(f"--clip: {exc}")
    if as_json:
        doc = {"cell": cell.name, "person": label, **report.to_json()}
        if suggest:
            doc["target_free"] = target_free
            doc["suggestions"] = {m.name: m.to_json() for m in moves}
        typer.echo(json.dumps(doc))
        return
    typer.echo(f"cell {cell.name!r} against {label} ({report.frames} frames)")
    typer.echo(
        f"the governor lets a part move at {speed:g} m/s only beyond {report.zone_m:.2f} m of a person "
        "standing still"
    )
    typer.echo(f"{'pose':<18}{'separation p5/p50 (m)':>24}{'allowed speed p50 (m/s)':>26}{'free':>8}")
    for p in report.poses:
        sep = f"{p.separation_m[0]:.2f} / {p.separation_m[1]:.2f}"
        typer.echo(f"{p.name:<18}{sep:>24}{p.allowed_speed_mps[1]:>26.3f}{p.free:>8.0%}")
    for p in report.blocked():
        typer.echo(
            f"warning: at {p.name} the robot may move at {speed:g} m/s in only {p.free:.0%} of the frames: "
            "the person works within the governor's zone of it"
        )
    for m in moves:
        if m.suggested_xyz is None:
            typer.echo(
                f"{m.name}: no place within {DEFAULT_MAX_SHIFT_M:g} m away from the work spot is free "
                f"{target_free:.0%} of the time"
            )
        elif m.shift_m == 0.0:
            typer.echo(f"{m.name}: free {m.free:.0%} of the time where it is")
        else:
            xyz = ", ".join(f"{v:.3f}" for v in m.suggested_xyz)
            typer.echo(
                f"{m.name}: move it {m.shift_m:.3f} m to xyz = [{xyz}] (free {m.suggested_free:.0%} of the "
                f"time there, {m.free:.0%} now; {m.reach_change_m:+.3f} m from the pickup)"
            )
