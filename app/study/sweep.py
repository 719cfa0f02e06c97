"""Sweeps: a grid (or list) of settings overrides x simulated participants x methods, resumable.

A spec (TOML) names the sweep, the participants, the trial duration, the study seed, the methods and the
settings: either ``[grid]`` (every combination of the listed values) or ``[[settings]]`` tables (one
setting each, with an optional ``label``). Every override must be a field of :class:`app.config.Settings`
and pass its validation. Each trial has a deterministic key (sweep, setting label, participant, method,
seed); the driver stores a completed trial with its metrics, events and frames in one transaction under
that key (unique in the database), so a sweep started again with the same spec runs only the trials that
are missing or failed, and two drivers writing into one PostgreSQL database never store a trial twice.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.control.metrics import METHODS
from app.study.repository import ConflictError, StudyRepository, settings_snapshot
from app.study.runner import (
    TrialJob,
    TrialOutcome,
    make_executor,
    participant_code,
    participant_seeds,
    run_trial_job,
)
from app.study.schemas import ParticipantCreate, StudySessionCreate

log = logging.getLogger(__name__)

_SPEC_KEYS = {"name", "participants", "duration_s", "seed", "methods", "grid", "settings", "base"}


class SweepSpecError(ValueError):
    """A sweep spec that cannot run; the message says which entry and why."""


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep: ``settings`` holds ``(label, overrides)`` pairs in spec order."""

    name: str
    participants: int
    duration_s: float
    seed: int
    methods: tuple[str, ...]
    settings: tuple[tuple[str, dict[str, Any]], ...]
    base: dict[str, Any] = field(default_factory=dict)

    @property
    def swept(self) -> list[str]:
        """The settings fields that some setting overrides, in first-seen order."""
        return list(dict.fromkeys(k for _, o in self.settings for k in o))


@dataclass(frozen=True)
class SweepTrial:
    """One planned trial of a sweep (``job.trial_id`` is its index in the plan)."""

    key: str
    label: str
    job: TrialJob


@dataclass(frozen=True)
class SweepRunResult:
    """Summary of one :func:`run_sweep` call (``skipped``: stored already before this run; ``duplicates``:
    stored meanwhile by another driver)."""

    name: str
    planned: int
    skipped: int
    completed: int
    failed: int
    duplicates: int
    wall_s: float

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _label(overrides: Mapping[str, Any]) -> str:
    return ",".join(f"{k}={v}" for k, v in overrides.items()) or "defaults"


def _validate_settings(where: str, values: Mapping[str, Any]) -> dict[str, Any]:
    from app.config import validate_overrides

    return validate_overrides(where, values, error=SweepSpecError)


def parse_spec(data: Mapping[str, Any]) -> SweepSpec:
    """A :class:`SweepSpec` from the parsed TOML.

    Raises:
        SweepSpecError: an unknown key or setting, an invalid value, no settings, or a duplicate label.
    """
    unknown = sorted(set(data) - _SPEC_KEYS)
    if unknown:
        raise SweepSpecError(f"unknown spec keys {unknown}; allowed: {sorted(_SPEC_KEYS)}")
    name = data.get("name")
    if not isinstance(name, str) or not name.strip() or "|" in name:
        raise SweepSpecError("the spec needs a non-empty `name` without '|'")
    participants = data.get("participants", 10)
    if not isinstance(participants, int) or participants < 1:
        raise SweepSpecError(f"`participants` must be an integer >= 1, got {participants!r}")
    duration_s = data.get("duration_s", 300.0)
    if not isinstance(duration_s, (int, float)) or not duration_s > 0:
        raise SweepSpecError(f"`duration_s` must be a number > 0, got {duration_s!r}")
    seed = data.get("seed", 7)
    if not isinstance(seed, int) or seed < 0:
        raise SweepSpecError(f"`seed` must be an integer >= 0, got {seed!r}")
    methods = tuple(data.get("methods", METHODS))
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise SweepSpecError(f"`methods` must be a non-empty subset of {list(METHODS)}, got {list(methods)}")
    base = _validate_settings("[base]", data.get("base", {}))
    if ("grid" in data) == ("settings" in data):
        raise SweepSpecError("give the settings either as a [grid] table or as [[settings]] tables")
    settings: list[tuple[str, dict[str, Any]]] = []
    if "grid" in data:
        grid = data["grid"]
        for k, v in grid.items():
            if not isinstance(v, list) or not v:
                raise SweepSpecError(f"[grid] {k} must be a non-empty list of values, got {v!r}")
        keys = list(grid)
        for values in itertools.product(*(grid[k] for k in keys)):
            overrides = dict(zip(keys, values, strict=True))
            settings.append((_label(overrides), overrides))
    else:
        for i, entry in enumerate(data["settings"]):
            entry = dict(entry)
            label = str(entry.pop("label", "") or _label(entry))
            settings.append((label, entry))
            if "|" in label:
                raise SweepSpecError(f"[[settings]] #{i + 1}: the label {label!r} contains '|'")
    labels = [lab for lab, _ in settings]
    if len(set(labels)) != len(labels):
        raise SweepSpecError(f"setting labels must differ: {labels}")
    for label, overrides in settings:
        _validate_settings(f"setting {label!r}", {**base, **overrides})
    return SweepSpec(
        name=name.strip(),
        participants=participants,
        duration_s=float(duration_s),
        seed=seed,
        methods=methods,
        settings=tuple(settings),
        base=base,
    )


def load_spec(path: Path) -> SweepSpec:
    """Read and validate a sweep spec from a TOML file (see :func:`parse_spec`)."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise SweepSpecError(f"cannot read the sweep spec {path}: {exc}") from exc
    return parse_spec(data)


def trial_key(name: str, label: str, code: str, method: str, seed: int) -> str:
    """The deterministic identity of one sweep trial."""
    return f"{name}|{label}|{code}|{method}|{seed}"


def plan_sweep(spec: SweepSpec, *, record_frames: bool = False) -> list[SweepTrial]:
    """Every trial of the sweep, setting by setting, participant by participant (both methods with the
    same participant and trial seeds: paired, with common random numbers)."""
    from app.config import Settings

    out: list[SweepTrial] = []
    seeds = participant_seeds(spec.seed, spec.participants)
    for label, overrides in spec.settings:
        settings = Settings.model_validate({**spec.base, **overrides}).model_dump(mode="json")
        for i, (p_seed, t_seed) in enumerate(seeds):
            code = participant_code(spec.seed, i)
            for order_index, method in enumerate(spec.methods):
                job = TrialJob(
                    trial_id=len(out),
                    participant_code=code,
                    participant_seed=p_seed,
                    trial_seed=t_seed,
                    method=method,
                    order_index=order_index,
                    duration_s=spec.duration_s,
                    settings=settings,
                    record_frames=record_frames,
                )
                out.append(SweepTrial(trial_key(spec.name, label, code, method, t_seed), label, job))
    return out


def _participant_id(repo: StudyRepository, code: str, seed: int, p_seed: int) -> int:
    p = repo.get_participant_by_code(code)
    if p is None:
        try:
            p = repo.create_participant(
                ParticipantCreate(code=code, notes=f"simulated operator: seed {seed}, participant {p_seed}")
            )
        except ConflictError:  # another driver created it meanwhile
            p = repo.get_participant_by_code(code)
            assert p is not None
    return p.id


def run_sweep(
    spec: SweepSpec,
    repo: StudyRepository,
    *,
    engine: str = "ray",
    workers: int | None = None,
    address: str | None = None,
    progress: bool = True,
    record_frames: bool = False,
    trial_fn: Callable[[TrialJob], TrialOutcome] | None = None,
) -> SweepRunResult:
    """Run the trials of ``spec`` that are not stored yet and store each one as it completes.

    Args:
        spec: The validated sweep.
        repo: The study database (schema at head).
        engine: ``ray``, ``process`` or ``inline`` (see :func:`app.study.runner.make_executor`).
        workers: CPUs (Ray) or processes (default: every core); 0 runs inline.
        address: Ray cluster address (default ``RAY_ADDRESS``, else a local cluster).
        progress: A tqdm bar over the trials (with the time left) on stderr.
        record_frames: Store the trials' frames for replay.
        trial_fn: Runs one job (default :func:`app.study.runner.run_trial_job`).

    Returns:
        How many trials were planned, skipped (stored already), completed, failed, stored meanwhile by
        another driver, and the wall time (s).
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    trial_fn = trial_fn or run_trial_job
    plan = plan_sweep(spec, record_frames=record_frames)
    stored = repo.stored_trial_keys(prefix=f"{spec.name}|")
    todo = [t for t in plan if t.key not in stored]
    completed = failed = duplicates = 0
    if todo:
        session = repo.create_session(
            StudySessionCreate(
                name=f"sweep {spec.name}"[:200],
                notes=f"hrc sweep {spec.name}: {len(todo)} of {len(plan)} trials in this run",
            )
        )
        pids = {
            t.job.participant_code: _participant_id(
                repo, t.job.participant_code, spec.seed, t.job.participant_seed
            )
            for t in todo
        }
        workers_n = min((os.cpu_count() or 1) if workers is None else workers, len(todo))
        executor = make_executor(engine, workers_n, address=address)
        bar = tqdm(total=len(todo), unit="trial", desc=f"sweep {spec.name}", disable=not progress)
        try:
            order = sorted(todo, key=lambda t: (t.job.method != "proactive", t.job.trial_id))
            futures = {executor.submit(trial_fn, t.job): t for t in order}
            for fut in as_completed(futures):
                t = futures[fut]
                try:
                    outcome = fut.result()
                except Exception as exc:  # a lost worker: the trial stays missing and runs next time
                    outcome = TrialOutcome(t.job.trial_id, None, error=f"{type(exc).__name__}: {exc}")
                if outcome.error is not None or outcome.metrics is None or outcome.status != "completed":
                    failed += 1
                    why = (outcome.error or outcome.reason or outcome.status).splitlines()[0]
                    log.warning("sweep trial %s failed (it runs again next time): %s", t.key, why)
                else:
                    snapshot = settings_snapshot(_settings(t.job.settings))
                    new_id = repo.store_keyed_trial(
                        trial_key=t.key,
                        setting_label=t.label,
                        participant_id=pids[t.job.participant_code],
                        method=t.job.method,  # type: ignore[arg-type]
                        session_id=session.id,
                        order_index=t.job.order_index,
                        seed=t.job.trial_seed,
                        duration_s=t.job.duration_s,
                        settings={
                            **snapshot,
                            "participant_seed": t.job.participant_seed,
                            "source": "sim",
                            "sweep": spec.name,
                            "setting_label": t.label,
                        },
                        metrics=outcome.metrics,
                        events=outcome.events,
                        frames=outcome.frames,
                        started_at=outcome.started_at,
                    )
                    if new_id is None:
                        duplicates += 1
                    else:
                        completed += 1
                bar.update(1)
                bar.set_postfix(completed=completed, failed=failed)
        finally:
            bar.close()
            executor.shutdown(wait=False, cancel_futures=True)
    return SweepRunResult(
        name=spec.name,
        planned=len(plan),
        skipped=len(plan) - len(todo),
        completed=completed,
        failed=failed,
        duplicates=duplicates,
        wall_s=time.perf_counter() - t0,
    )


def _settings(values: Mapping[str, Any]) -> Any:
    from app.config import Settings

    return Settings.model_validate(dict(values))


def describe_plan(spec: SweepSpec) -> dict[str, Any]:
    """The ``--dry-run`` view: settings with their overrides, participants, methods, the trial count."""
    return {
        "name": spec.name,
        "settings": [{"label": lab, "overrides": o} for lab, o in spec.settings],
        "base": spec.base,
        "participants": spec.participants,
        "methods": list(spec.methods),
        "duration_s": spec.duration_s,
        "seed": spec.seed,
        "trials": len(spec.settings) * spec.participants * len(spec.methods),
    }


def _mean_ci(d: np.ndarray, level: float = 0.95) -> tuple[float | None, float | None]:
    from scipy import stats

    if d.size < 2:
        return None, None
    half = float(stats.t.ppf(0.5 + level / 2, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size))
    m = float(d.mean())
    return m - half, m + half


def sweep_report(repo: StudyRepository, name: str) -> dict[str, Any]:
    """Table I per setting and method, with the paired proactive-vs-reactive effect of every metric
    (mean difference, its 95 % t interval, the test's p-value) per setting.

    Raises:
        LookupError: no trial of the sweep ``name`` is stored.
    """
    from sqlalchemy import select

    from app.study.models import Trial
    from app.study.stats import per_participant, summarize_rows

    with repo.session() as s:
        q = select(Trial.id, Trial.setting_label, Trial.settings).where(
            Trial.trial_key.startswith(f"{name}|", autoescape=True), Trial.status == "completed"
        )
        labels: dict[int, str] = {}
        overrides: dict[str, dict[str, Any]] = {}
        for tid, label, settings in s.execute(q):
            labels[tid] = label
            overrides.setdefault(label, dict(settings or {}))
    if not labels:
        raise LookupError(f"no completed trial of the sweep {name!r} is stored")
    rows = [r for r in repo.metrics_rows(status="completed") if r["trial_id"] in labels]
    out: dict[str, Any] = {"sweep": name, "settings": {}}
    swept = sorted(_swept_fields(overrides.values()))

    def order(label: str) -> tuple[Any, ...]:  # by the swept values (numbers numerically), then label
        vals = [overrides[label].get(k) for k in swept]
        return (*((0, v) if isinstance(v, (int, float)) else (1, repr(v)) for v in vals), label)

    for label in sorted(overrides, key=order):
        sub = [r for r in rows if labels[r["trial_id"]] == label]
        summary = summarize_rows(sub)
        effects = {}
        for metric in summary["metrics"]:
            by = per_participant(sub, metric)
            codes = sorted(set(by["proactive"]) & set(by["reactive"]))
            d = np.array([by["proactive"][c] - by["reactive"][c] for c in codes], dtype=float)
            lo, hi = _mean_ci(d)
            effects[metric] = {
                "mean_difference": float(d.mean()) if d.size else None,
                "ci95": [lo, hi],
                "p_value": summary["p_values"].get(metric),
                "n_pairs": int(d.size),
            }
        summary["effects"] = effects
        summary["values"] = {k: overrides[label].get(k) for k in swept}
        out["settings"][label] = summary
    return out


def _swept_fields(snapshots: Sequence[dict[str, Any]] | Any) -> set[str]:
    """The settings fields whose values differ between the snapshots."""
    snaps = list(snapshots)
    keys = set().union(*(s.keys() for s in snaps)) - {"participant_seed", "setting_label", "source"}
    return {k for k in keys if len({repr(s.get(k)) for s in snaps}) > 1}


def sweep_csv(report: Mapping[str, Any]) -> str:
    """One CSV row per setting, method and metric: mean, sd, n, and the paired effect with its interval."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(
        ["setting", "method", "metric", "mean", "sd", "n", "mean_difference", "ci_low", "ci_high", "p"]
    )
    for label, summary in report["settings"].items():
        for metric in summary["metrics"]:
            eff = summary["effects"][metric]
            for method in METHODS:
                cell = summary[method][metric]
                stats = [cell["mean"], cell["sd"], cell["n"], eff["mean_difference"], *eff["ci95"]]
                w.writerow([label, method, metric, *stats, eff["p_value"]])
    return buf.getvalue()


def write_sweep_report(report: Mapping[str, Any], out: Path) -> dict[str, Path]:
    """``sweep.json``, ``sweep.csv`` and one ``effect_<parameter>.png`` per swept parameter (the
    proactive-minus-reactive completed tasks against the parameter, with 95 % intervals) into ``out``."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "sweep.json", "csv": out / "sweep.csv"}
    paths["json"].write_text(json.dumps(report, indent=2, allow_nan=False))
    paths["csv"].write_text(sweep_csv(report))
    settings = report["settings"]
    params = list(dict.fromkeys(k for s in settings.values() for k in s["values"]))
    for param in params:
        xs, ys, lo, hi = [], [], [], []
        for summary in settings.values():
            eff = summary["effects"]["completed_tasks"]
            if param not in summary["values"] or eff["mean_difference"] is None:
                continue
            xs.append(summary["values"][param])
            ys.append(eff["mean_difference"])
            lo.append(eff["ci95"][0] if eff["ci95"][0] is not None else eff["mean_difference"])
            hi.append(eff["ci95"][1] if eff["ci95"][1] is not None else eff["mean_difference"])
        fig, ax = plt.subplots(figsize=(5, 3.5))
        pos = list(range(len(xs)))
        y = np.array(ys, dtype=float)
        ax.errorbar(pos, y, yerr=[y - np.array(lo), np.array(hi) - y], fmt="o-", capsize=4)
        ax.set_xticks(pos, [str(x) for x in xs])
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xlabel(param)
        ax.set_ylabel("completed tasks: proactive - reactive")
        ax.set_title(f"sweep {report['sweep']}")
        fig.tight_layout()
        paths[f"effect_{param}"] = out / f"effect_{param}.png"
        fig.savefig(paths[f"effect_{param}"], dpi=100)
        plt.close(fig)
    return paths
