"""``hrc cell ...``: commands about the cell (robot backends and human sources)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

cell_app = typer.Typer(help="The cell: robot backends and human sources.", no_args_is_help=True)


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
