"""The ``hrc`` command line.

Every sub-command imports what it needs inside its body, so ``hrc --help`` stays fast and a missing
optional piece only affects the command that uses it.
"""

from __future__ import annotations

import importlib
import json
import pkgutil
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.commands import fail, load_workcell_or_fail
from app.commands.cell import cell_app
from app.commands.hmp import hmp_app

if TYPE_CHECKING:
    from app.config import Settings
    from app.study.repository import StudyRepository

app = typer.Typer(
    name="hrc",
    # errors and help as plain text: a rich panel folds or cuts a message (a long path) to the terminal's
    # width; a usage error is one "Error: ..." line that a narrow terminal wraps, never truncates
    rich_markup_mode=None,
    help="Proactive human-aware motion planning for a UR5e working beside a person.",
    no_args_is_help=True,
    add_completion=False,
)


@app.callback()
def _root() -> None:
    """Proactive human-aware motion planning for a UR5e working beside a person."""
    _check_environment()


def _check_environment() -> None:
    """Warn about every ``HRC_`` variable that is no setting (naming the nearest one), or stop (exit 2) with
    ``HRC_STRICT_SETTINGS=true``."""
    import os

    from app.config import strict_settings, unknown_environment_settings

    try:
        strict = strict_settings(os.environ)
    except ValueError as exc:
        fail(str(exc))
    problems = unknown_environment_settings(os.environ)
    for message in problems:
        typer.echo(f"{'error' if strict else 'warning'}: {message}", err=True)
    if problems and strict:
        raise typer.Exit(2)


def _bench_names() -> list[str]:
    import app.bench as bench_pkg

    return sorted(m.name for m in pkgutil.iter_modules(bench_pkg.__path__) if not m.name.startswith("_"))


@app.command()
def bench(
    name: Annotated[str, typer.Argument(help="Benchmark to run (see `hrc bench --list`).")] = "",
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
    quick: Annotated[bool, typer.Option("--quick", help="Fewer repetitions (smoke run).")] = False,
    list_: Annotated[bool, typer.Option("--list", help="List the benchmarks and exit.")] = False,
    bodies: Annotated[
        int | None,
        typer.Option("--bodies", min=1, max=4, help="loop: that many people in the cell (1-4)."),
    ] = None,
) -> None:
    """Run a benchmark; it prints its measurements (medians and p95 over many runs) as JSON."""
    names = _bench_names()
    if list_ or not name:
        typer.echo("\n".join(names))
        raise typer.Exit(0)
    if name not in names:
        raise typer.BadParameter(f"unknown benchmark {name!r}; choose one of: {', '.join(names)}")
    module = importlib.import_module(f"app.bench.{name}")
    if bodies is not None and name != "loop":
        raise typer.BadParameter(f"--bodies is an option of `hrc bench loop`, not of {name!r}")
    extra = {} if bodies is None else {"bodies": bodies}
    result = module.run(quick=quick, progress=not as_json, **extra)
    typer.echo(json.dumps(result, indent=None if as_json else 2, sort_keys=False))


app.add_typer(cell_app, name="cell")
app.add_typer(hmp_app, name="hmp")


# --- study records (app.study) --------------------------------------------------------------------------

db_app = typer.Typer(help="Study database: migrations.", no_args_is_help=True, rich_markup_mode=None)
app.add_typer(db_app, name="db")

_Scenario = Annotated[
    Path | None,
    typer.Option(
        help="TOML file of who else is in the simulated cell: passers-by, a second operator (default "
        "HRC_SCENARIO, else the operator alone; e.g. examples/scenario_passer_by.toml)."
    ),
]
_DbUrl = Annotated[
    str | None,
    typer.Option("--url", help="SQLAlchemy URL (default: HRC_DATABASE_URL, else SQLite in HRC_DATA_DIR)."),
]
_SessionSpec = Annotated[
    str, typer.Option("--session", help="Study session: 'latest' (newest), 'all', or a session id.")
]


_SettingsFile = Annotated[
    Path | None,
    typer.Option(
        "--settings",
        help="TOML file of settings overrides (Settings fields, e.g. the best.toml of `hrc tune`); they take "
        "precedence over HRC_* variables.",
    ),
]


def _load_settings(path: Path | None, **given: object) -> Settings:
    """Settings from the environment, the ``--settings`` file and the given options (None: not given)."""
    from pydantic import ValidationError

    from app.config import Settings, SettingsFileError, load_settings_file

    try:
        overrides = load_settings_file(path) if path is not None else {}
        return Settings(**{**overrides, **{k: v for k, v in given.items() if v is not None}})
    except SettingsFileError as exc:
        fail(f"--settings: {exc}")
    except ValidationError as exc:
        msgs = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        fail(f"invalid settings (HRC_* variables, --settings file, options): {msgs}")


def _with_study(url: str | None, run: Callable[[StudyRepository], Any]) -> Any:
    """``run(repo)`` on the study database at ``url``, closed afterwards; a ValueError (a bad argument of
    the run) becomes a usage error that names it."""
    repo = _open_study(url)
    try:
        return run(repo)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    finally:
        repo.close()


def _open_study(url: str | None) -> StudyRepository:
    from app.study.db import DatabaseError
    from app.study.repository import open_repository

    try:
        return open_repository(url)
    except DatabaseError as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(1) from exc


def _session_id(repo: StudyRepository, spec: str) -> int | None:
    from app.study.repository import NotFoundError

    try:
        chosen = repo.resolve_session(spec)
    except (NotFoundError, ValueError) as exc:
        raise typer.BadParameter(str(exc), param_hint="--session") from exc
    return None if chosen is None else chosen.id


@db_app.command("upgrade")
def db_upgrade(url: _DbUrl = None) -> None:
    """Migrate the study database to the newest schema revision (the app does this at start too)."""
    from sqlalchemy.engine import make_url

    from app.study.db import DatabaseError, default_database_url, upgrade_to_head

    url = url or default_database_url()
    try:
        upgrade_to_head(url)
    except DatabaseError as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(1) from exc
    typer.echo(f"study database at head: {make_url(url).render_as_string(hide_password=True)}")


@app.command()
def report(
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
    out: Annotated[
        Path | None, typer.Option("--out", help="Directory for table.md/.csv, summary.json, boxplots.png.")
    ] = None,
    session: _SessionSpec = "latest",
    sweep: Annotated[
        str | None, typer.Option("--sweep", help="Per-setting report of the sweep with this name.")
    ] = None,
    url: _DbUrl = None,
) -> None:
    """Study report: Table I per method, paired tests with p-values and effect sizes, tables and box plots.

    Tests: Wilcoxon signed-rank, or repeated-measures ANOVA where the paired differences pass Shapiro-Wilk.
    Files (table.md, table.csv, summary.json, boxplots.png) go to --out (default: HRC_DATA_DIR/report).
    With --sweep: Table I and the paired effect (95 % interval, p) per setting, sweep.json, sweep.csv and
    one effect_<parameter>.png per swept parameter.
    """
    from app.config import Settings
    from app.study.stats import markdown_table, summarize, write_report

    settings = Settings()
    if sweep is not None:
        _sweep_report(sweep, as_json=as_json, out=out, url=url or settings.resolved_database_url())
        return
    repo = _open_study(url or settings.resolved_database_url())
    try:
        session_id = _session_id(repo, session)
        rows = repo.metrics_rows(session_id=session_id, status="completed")
        summary = summarize(rows)
        summary["session_id"] = session_id
        if out is None and not as_json:
            out = settings.data_dir / "report"
        paths = write_report(rows, out, summary=summary) if out is not None else {}
    finally:
        repo.close()
    if as_json:
        typer.echo(json.dumps(summary, allow_nan=False))
        return
    typer.echo(markdown_table(summary))
    for kind, path in paths.items():
        typer.echo(f"{kind}: {path}")


@app.command("export")
def export_(
    out: Annotated[Path, typer.Option("--out", help="Directory for the CSV files.")],
    session: Annotated[
        str, typer.Option("--session", help="Study session: 'all' (default), 'latest', or a session id.")
    ] = "all",
    clips: Annotated[
        bool,
        typer.Option(
            "--clips/--no-clips",
            help="Also write each trial's recorded skeleton as npz clips under OUT/clips (for hrc hmp train "
            "--extra-clips and hrc hmp calibrate --clips).",
        ),
    ] = False,
    url: _DbUrl = None,
) -> None:
    """Export participants, trials, metrics (one row per trial) and events as CSV (UTF-8, ISO 8601 times)."""
    from app.study.export import export_all, export_clips

    repo = _open_study(url)
    try:
        session_id = _session_id(repo, session)
        paths = export_all(repo, out, session_id=session_id)
        clip_paths = export_clips(repo, out / "clips", session_id=session_id) if clips else []
    finally:
        repo.close()
    for table, path in paths.items():
        typer.echo(f"{table}: {path}")
    if clips:
        typer.echo(f"clips: {len(clip_paths)} in {out / 'clips'}")


@app.command()
def study(
    participants: Annotated[int, typer.Option("--participants", min=1, help="Simulated participants.")] = 10,
    duration: Annotated[
        float, typer.Option("--duration", min=0.1, help="Trial duration (simulated s).")
    ] = 300.0,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Study seed (participants, trials).")] = 7,
    workers: Annotated[
        int | None, typer.Option("--workers", min=0, help="Processes (default: one per core; 0: inline).")
    ] = None,
    frames: Annotated[bool, typer.Option("--frames/--no-frames", help="Record frames for replay.")] = True,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bar.")] = True,
    engine: Annotated[
        str, typer.Option("--engine", help="Where trials run: ray (default), process (a local pool), inline.")
    ] = "ray",
    address: Annotated[
        str | None,
        typer.Option("--address", help="Ray cluster address (default RAY_ADDRESS; none: a local cluster)."),
    ] = None,
    settings_file: _SettingsFile = None,
    population: Annotated[
        Path | None,
        typer.Option(
            help="TOML file of the simulated participants (default HRC_POPULATION, else the shipped "
            "app/assets/population.toml)."
        ),
    ] = None,
    scenario: _Scenario = None,
    url: _DbUrl = None,
) -> None:
    """Headless study: simulated participants x both methods, as Ray tasks or on a process pool, into the DB.

    Each participant runs both methods in counterbalanced order with the same participant parameters, on
    the simulated clock; the trials are stored under one new study session.
    """
    from app.study.runner import run_study

    settings = _load_settings(settings_file, population=population, scenario=scenario)
    result = _with_study(
        url,
        lambda repo: run_study(
            settings=settings,
            participants=participants,
            duration_s=duration,
            seed=seed,
            repo=repo,
            max_workers=workers,
            progress=progress,
            record_frames=frames,
            engine=engine,
            address=address,
        ),
    )
    typer.echo(json.dumps(result.to_json()))
    if result.aborted:
        typer.echo(f"{result.aborted} trials aborted; see `hrc export` (trials.csv, abort_reason)", err=True)


def _sweep_report(name: str, *, as_json: bool, out: Path | None, url: str) -> None:
    from app.config import Settings
    from app.study.stats import markdown_table
    from app.study.sweep import sweep_report, write_sweep_report

    repo = _open_study(url)
    try:
        rep = sweep_report(repo, name)
    except LookupError as exc:
        raise typer.BadParameter(str(exc), param_hint="--sweep") from exc
    finally:
        repo.close()
    if out is None and not as_json:
        out = Settings().data_dir / "report" / f"sweep-{name}"
    paths = write_sweep_report(rep, out) if out is not None else {}
    if as_json:
        typer.echo(json.dumps(rep, allow_nan=False))
        return
    for label, summary in rep["settings"].items():
        typer.echo(f"## {label}\n")
        typer.echo(markdown_table(summary))
        eff = summary["effects"]["completed_tasks"]
        typer.echo(
            f"completed tasks, proactive - reactive: {eff['mean_difference']} (95 % CI {eff['ci95']})\n"
        )
    for kind, path in paths.items():
        typer.echo(f"{kind}: {path}")


@app.command("sweep")
def sweep_(
    spec: Annotated[Path, typer.Argument(help="Sweep spec (TOML; see examples/sweep_deadline.toml).")],
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print the plan and the trial count.")] = False,
    workers: Annotated[
        int | None, typer.Option("--workers", min=0, help="CPUs/processes (default: every core; 0: inline).")
    ] = None,
    engine: Annotated[str, typer.Option("--engine", help="ray (default), process or inline.")] = "ray",
    address: Annotated[
        str | None, typer.Option("--address", help="Ray cluster address (default RAY_ADDRESS; none: local).")
    ] = None,
    frames: Annotated[bool, typer.Option("--frames/--no-frames", help="Record frames for replay.")] = False,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bar.")] = True,
    url: _DbUrl = None,
) -> None:
    """Settings sweep: every setting of SPEC x participants x methods, resumable (only the trials not
    stored yet run; a completed trial is stored once, under its setting's label and settings snapshot)."""
    from app.study.sweep import SweepSpecError, describe_plan, load_spec, run_sweep

    try:
        parsed = load_spec(spec)
    except SweepSpecError as exc:
        raise typer.BadParameter(str(exc), param_hint="SPEC") from exc
    if dry_run:
        typer.echo(json.dumps(describe_plan(parsed), indent=2))
        return
    result = _with_study(
        url,
        lambda repo: run_sweep(
            parsed,
            repo,
            engine=engine,
            workers=workers,
            address=address,
            progress=progress,
            record_frames=frames,
        ),
    )
    typer.echo(json.dumps(result.to_json()))
    if result.failed:
        typer.echo(f"{result.failed} trials failed; run the sweep again to retry them", err=True)


@app.command("tune")
def tune_(
    spec: Annotated[Path, typer.Argument(help="Tuning spec (TOML; see examples/tune_margins.toml).")],
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print the search and the trial count.")] = False,
    engine: Annotated[
        str, typer.Option("--engine", help="ray (Ray Tune, default) or inline (Optuna in this process).")
    ] = "ray",
    address: Annotated[
        str | None, typer.Option("--address", help="Ray cluster address (default RAY_ADDRESS; none: local).")
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Settings TOML of the best sample (default HRC_DATA_DIR/tune/NAME.toml)."),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
) -> None:
    """Tune planner and forecast settings with Ray Tune and Optuna on the tuning seeds 1000-1999.

    Each sample runs the spec's participants (seeds) x methods as headless trials; it scores the mean
    completed tasks per trial if no trial had a violation or a contact (else a large negative penalty).
    ISO/TS 15066 safety parameters are refused: they come from the cell's measurements. The best
    settings go to --out as a TOML for `hrc study --settings` / `hrc serve --settings`.
    """
    import logging

    from app.config import Settings
    from app.study.tune import TuneSpecError, describe_tune, load_tune_spec, run_tune, write_best_settings

    try:
        parsed = load_tune_spec(spec)
    except TuneSpecError as exc:
        raise typer.BadParameter(str(exc), param_hint="SPEC") from exc
    if dry_run:
        typer.echo(json.dumps(describe_tune(parsed), indent=None if as_json else 2))
        return
    if engine not in ("ray", "inline"):
        raise typer.BadParameter(f"--engine must be ray or inline, not {engine!r}")
    logging.basicConfig(level=logging.ERROR if as_json else logging.WARNING)
    result = run_tune(parsed, engine=engine, address=address)  # type: ignore[arg-type]
    summary = result.to_json(parsed)
    out = out or Settings().data_dir / "tune" / f"{parsed.name}.toml"
    try:
        summary["out"] = str(write_best_settings(result, parsed, out, spec_path=spec))
    except LookupError as exc:
        summary["out"] = None
        typer.echo(json.dumps(summary, indent=None if as_json else 2))
        typer.echo(str(exc), err=True)
        raise typer.Exit(1) from exc
    typer.echo(json.dumps(summary, indent=None if as_json else 2))


# --- server (app.api) ------------------------------------------------------------------------------------


@app.command()
def serve(
    host: Annotated[str | None, typer.Option(help="Bind address (default HRC_HOST, 127.0.0.1).")] = None,
    port: Annotated[int | None, typer.Option(help="API port (default HRC_PORT, 8000).")] = None,
    viser_port: Annotated[int | None, typer.Option(help="3D view port (default HRC_VISER_PORT).")] = None,
    log_level: Annotated[str, typer.Option(help="uvicorn log level.")] = "info",
    settings_file: _SettingsFile = None,
) -> None:
    """Start the operator server: REST API (/docs), live WebSockets, the runtime and the 3D view."""
    import logging

    from app.api.auth import TokenError
    from app.api.server import run_server

    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings = _load_settings(settings_file, host=host, port=port, viser_port=viser_port)  # validated
    load_workcell_or_fail(settings)  # a missing or invalid cell: one line with the file and the field
    _viewer_port_or_fail(settings)
    _predictor_or_fail(settings)
    try:
        run_server(settings, log_level=log_level, echo=lambda text: typer.echo(text, err=True))
    except TokenError as exc:  # the message says which file and what to do; no traceback needed
        fail(str(exc))


def _viewer_port_or_fail(settings: Any) -> None:
    """Stop with one line when another program holds the 3D view's port (before anything starts)."""
    from app.api.app import viewer_port_message

    try:
        from app.ui.viser_server import PortInUse, check_port_free
    except ImportError:  # no 3D view in this installation
        return
    try:
        check_port_free(settings.host, settings.viser_port)
    except PortInUse as exc:
        fail(viewer_port_message(exc.host, exc.port))


def _predictor_or_fail(settings: Any) -> None:
    """Stop with one line naming the file when the predictor's weights cannot be loaded (unless
    ``HRC_HMP_FALLBACK`` asks for constant velocity instead)."""
    from app.control.world import PredictorUnavailable, check_predictor_weights

    try:
        check_predictor_weights(settings)
    except PredictorUnavailable as exc:
        fail(str(exc))


@app.command()
def replay(
    trial_id: Annotated[int, typer.Argument(help="The trial to replay (see GET /api/trials).")],
    viser_port: Annotated[int, typer.Option(help="Port of the replay's 3D view.")] = 8081,
    host: Annotated[str, typer.Option(help="Bind address.")] = "127.0.0.1",
    url: _DbUrl = None,
) -> None:
    """Replay a recorded trial in the 3D view (time slider, play/pause, speed) until Ctrl-C."""
    import threading

    from app.config import Settings
    from app.study.repository import NotFoundError
    from app.ui.replay import ReplayError, TrialReplay, load_timeline

    repo = _open_study(url)
    cell = Settings().load_workcell()
    try:
        timeline = load_timeline(repo, trial_id, cell)
    except (NotFoundError, ReplayError) as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(1) from exc
    player = TrialReplay(timeline, cell, port=viser_port, host=host)
    player.start()
    typer.echo(f"replaying trial {trial_id} ({timeline.duration_s:.1f} s) at http://{host}:{player.port}")
    try:
        while not threading.Event().wait(1.0):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        player.stop()


# --- headless trials (app.control) --------------------------------------------------------------------------


@app.command()
def simulate(
    method: Annotated[
        str, typer.Option(help="proactive (predicted motion) or reactive (current pose held).")
    ] = "proactive",
    duration: Annotated[float, typer.Option(help="Simulated trial length (s).", min=0.1)] = 300.0,
    seed: Annotated[int, typer.Option(help="Seed of the simulated participant and trial.")] = 1,
    source: Annotated[
        str, typer.Option(help="sim (simulated operator) or replay (a recorded clip).")
    ] = "sim",
    clip: Annotated[
        Path | None, typer.Option(help="Clip for --source replay (default HRC_REPLAY_CLIP).")
    ] = None,
    forecast: Annotated[
        str,
        typer.Option(
            help="model (the motion predictor) or oracle (the simulated operator's own future: the bound of "
            "what proactive planning can gain; --method proactive --source sim only; about 3x slower)."
        ),
    ] = "model",
    population: Annotated[
        Path | None,
        typer.Option(
            help="TOML file of the simulated participants (default HRC_POPULATION, else the shipped "
            "app/assets/population.toml)."
        ),
    ] = None,
    scenario: _Scenario = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
) -> None:
    """Run one headless trial on the simulated clock and print its metrics."""
    import logging

    from app.config import Settings
    from app.control.headless import run_headless_trial

    if method not in ("proactive", "reactive"):
        raise typer.BadParameter(f"--method must be proactive or reactive, not {method!r}")
    if source not in ("sim", "replay"):
        raise typer.BadParameter(f"--source must be sim or replay, not {source!r}")
    if forecast not in ("model", "oracle"):
        raise typer.BadParameter(f"--forecast must be model or oracle, not {forecast!r}")
    if forecast == "oracle" and (method != "proactive" or source != "sim"):
        raise typer.BadParameter("--forecast oracle needs --method proactive and --source sim")
    logging.basicConfig(level=logging.ERROR if as_json else logging.WARNING)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # the reactive method needs no predictor
        pass
    from pydantic import ValidationError

    try:
        given = {k: v for k, v in (("population", population), ("scenario", scenario)) if v is not None}
        settings = Settings(**given)
    except ValidationError as exc:
        raise typer.BadParameter("; ".join(e["msg"] for e in exc.errors())) from exc
    try:
        result = run_headless_trial(
            settings=settings,
            method=method,
            duration_s=duration,
            seed=seed,
            source=source,
            clip=clip,
            forecast=forecast,  # type: ignore[arg-type]
        )
    except ValueError as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(2) from exc
    out = result.summary()
    if forecast == "oracle":
        out["forecast"] = "oracle"
    if settings.scenario is not None:
        out["scenario"] = str(settings.scenario)
    typer.echo(json.dumps(out, indent=None if as_json else 2))


def main() -> None:
    """Console entry point."""
    app()


if __name__ == "__main__":
    main()
