"""Tuning: a search over planner and forecast settings with Ray Tune and Optuna, on the tuning seeds only.

A spec (TOML) names the run, the simulated participants (``seeds = { first = 1000, last = 1003 }``: one
participant per seed, its participant and trial seed both that seed, as ``hrc simulate --seed``), the
methods, the trial duration, ``num_samples`` (settings tried), ``concurrency`` (samples at once) and the
``[space]``: one entry per setting, ``{ low = .., high = .. }`` (optionally ``log = true`` or ``step = ..``;
integers for integer settings, ``high`` included) or ``{ choices = [..] }``.

Rules (issue 20): only planner and forecast settings are tuned (:data:`TUNABLE`); ISO/TS 15066 safety
parameters (speed and separation monitoring, the person's speed and acceleration, the robot's stopping
model, the tracker and its frame period) come from the cell's measurements and are refused; and tuning uses
the simulation seeds 1000-1999 (:data:`TUNING_SEEDS`) only, so that an evaluation on other seeds (e.g.
``hrc study --seed 7``) is not tuned on.

Each sample runs every participant x method as a headless trial (:func:`app.study.runner.run_trial_job`) in
one Ray Tune trial (one CPU) and scores the mean completed tasks per trial when no trial had a violation of
the protective separation or a contact (``violations``, ``contacts`` in the metrics) and none failed; else
the sample is infeasible and scores ``-INFEASIBLE_PENALTY`` per violation, contact and failed trial (finite,
so that Optuna learns away from it and the JSON stays valid). The best feasible sample's settings are
written as a settings TOML (``hrc study --settings FILE``, ``hrc serve --settings FILE``).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import tempfile
import time
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from app.control.metrics import METHODS
from app.study.runner import TrialJob, TrialOutcome, ray_worker_env, run_trial_job

#: The settings a tuning run may search: the planner's (D, search width) and the forecast's.
TUNABLE = (
    "deadline_s",
    "planner_workers",
    "anticipate_fetch",
    "fetch_reaction_s",
    "hmp_weights",
    "hmp_quantiles",
)
#: The simulation seeds tuning may use; every other seed is left for the evaluation.
TUNING_SEEDS = range(1000, 2000)
#: The score of an infeasible sample, per violation, contact and failed trial (negated).
INFEASIBLE_PENALTY = 1000.0

#: ISO/TS 15066 and measurement parameters, by name, with where each comes from.
SAFETY_PARAMETERS: dict[str, str] = {
    "frame_period_s": "the tracking camera's frame period",
    "camera_pose": "the tracking camera's calibration",
    "v_human_mps": "v_h, the person's speed",
    "t_reaction_s": "T_r, the robot system's reaction time",
    "t_stop_s": "T_s, the robot's stopping time",
    "intrusion_m": "C, the intrusion distance",
    "z_human_m": "Z_d, the tracker's position uncertainty",
    "z_robot_m": "Z_r, the robot's position uncertainty",
    "tracking_margin_m": "the tracker's error",
    "human_accel_mps2": "the person's worst-case acceleration (speed governor)",
    "human_speed_max_mps": "the person's fastest approach (speed governor)",
}
#: Parts of a name that mark a safety or measurement parameter (also for settings added later).
_SAFETY_WORDS = (
    "ssm",
    "tracker",
    "tracking",
    "stopping",
    "t_stop",
    "brake",
    "human_speed",
    "v_human",
    "human_accel",
    "intrusion",
    "z_human",
    "z_robot",
    "t_reaction",
    "separation",
    "monitor",
    "latency",
    "noise",
)
_SPEC_KEYS = {"name", "seeds", "duration_s", "methods", "num_samples", "concurrency", "sampler_seed", "space"}
_RANGE_KEYS = {"low", "high", "log", "step"}

Engine = Literal["ray", "inline"]


class TuneSpecError(ValueError):
    """A tuning spec that cannot run; the message names the entry and why."""


@dataclass(frozen=True)
class Param:
    """One searched setting: a range (``low``..``high``, ``high`` included; ``log`` or ``step``) of
    ``kind`` ``float`` or ``int``, or ``choices``."""

    name: str
    kind: Literal["float", "int", "choice"]
    low: float | None = None
    high: float | None = None
    log: bool = False
    step: float | None = None
    choices: tuple[Any, ...] = ()

    def distribution(self) -> Any:
        """The Optuna distribution (the same for Ray Tune's ``OptunaSearch`` and the inline search)."""
        import optuna.distributions as d

        if self.kind == "choice":
            return d.CategoricalDistribution(list(self.choices))
        if self.kind == "int":
            return d.IntDistribution(int(self.low), int(self.high), log=self.log, step=int(self.step or 1))
        return d.FloatDistribution(float(self.low), float(self.high), log=self.log, step=self.step)

    def to_json(self) -> dict[str, Any]:
        if self.kind == "choice":
            return {"choices": list(self.choices)}
        out: dict[str, Any] = {"kind": self.kind, "low": self.low, "high": self.high}
        if self.log:
            out["log"] = True
        if self.step is not None:
            out["step"] = self.step
        return out


@dataclass(frozen=True)
class TuneSpec:
    """A validated tuning spec (seeds ``first``..``last``, both included)."""

    name: str
    first_seed: int
    last_seed: int
    duration_s: float
    methods: tuple[str, ...]
    num_samples: int
    concurrency: int
    sampler_seed: int
    space: tuple[Param, ...]

    @property
    def seeds(self) -> list[int]:
        return list(range(self.first_seed, self.last_seed + 1))

    @property
    def trials_per_sample(self) -> int:
        return len(self.seeds) * len(self.methods)


def _safety_reason(key: str) -> str | None:
    if key in SAFETY_PARAMETERS:
        return SAFETY_PARAMETERS[key]
    low = key.lower()
    word = next((w for w in _SAFETY_WORDS if w in low), None)
    return None if word is None else f"its name says '{word}'"


def _check_key(key: str) -> None:
    from app.config import Settings

    reason = _safety_reason(key)
    if reason is not None:
        raise TuneSpecError(
            f"[space] {key} ({reason}) is an ISO/TS 15066 safety or measurement parameter: it comes from "
            f"the cell's measurements and is never tuned (tunable: {', '.join(TUNABLE)})"
        )
    if key not in Settings.model_fields:
        raise TuneSpecError(
            f"[space] {key}: unknown key, not a setting of app.config.Settings "
            f"(tunable: {', '.join(TUNABLE)})"
        )
    if key not in TUNABLE:
        why = "the methods come from `methods`" if key == "method" else "not a planner or forecast parameter"
        raise TuneSpecError(f"[space] {key}: a setting, but {why} (tunable: {', '.join(TUNABLE)})")


def _validate_value(key: str, value: Any) -> None:
    from pydantic import ValidationError

    from app.config import Settings

    try:
        Settings.model_validate({key: value})
    except ValidationError as exc:
        msgs = "; ".join(e["msg"] for e in exc.errors())
        raise TuneSpecError(f"[space] {key}: {value!r} is not a valid value: {msgs}") from exc


def _parse_param(key: str, entry: Any) -> Param:
    from app.config import Settings

    _check_key(key)
    if not isinstance(entry, Mapping):
        raise TuneSpecError(
            f"[space] {key}: give {{ low = .., high = .. }} or {{ choices = [..] }}, not {entry!r}"
        )
    if "choices" in entry:
        extra = sorted(set(entry) - {"choices"})
        if extra:
            raise TuneSpecError(f"[space] {key}: unknown key {', '.join(extra)} beside `choices`")
        choices = entry["choices"]
        if not isinstance(choices, list) or not choices:
            raise TuneSpecError(f"[space] {key}: `choices` must be a non-empty list, got {choices!r}")
        for c in choices:
            _validate_value(key, c)
        return Param(key, "choice", choices=tuple(choices))
    unknown = sorted(set(entry) - _RANGE_KEYS)
    if unknown:
        raise TuneSpecError(
            f"[space] {key}: unknown key {', '.join(unknown)}; a range has "
            f"{', '.join(sorted(_RANGE_KEYS))}, a list `choices`"
        )
    annotation = Settings.model_fields[key].annotation
    if annotation not in (int, float):
        raise TuneSpecError(f"[space] {key}: not a number; give {{ choices = [..] }}")
    kind: Literal["float", "int"] = "int" if annotation is int else "float"
    low, high, step, log = (
        entry.get("low"),
        entry.get("high"),
        entry.get("step"),
        bool(entry.get("log", False)),
    )
    number = int if kind == "int" else (int, float)
    for what, v in (("low", low), ("high", high)):
        if not isinstance(v, number) or isinstance(v, bool):
            raise TuneSpecError(
                f"[space] {key}: `{what}` must be {'an integer' if kind == 'int' else 'a number'}"
            )
        _validate_value(key, v)
    if not low < high:
        raise TuneSpecError(f"[space] {key}: `low` ({low}) must be below `high` ({high})")
    if step is not None and (log or not isinstance(step, number) or not step > 0):
        raise TuneSpecError(f"[space] {key}: `step` must be a number > 0, and not with `log`")
    if log and not low > 0:
        raise TuneSpecError(f"[space] {key}: `log = true` needs `low` > 0")
    return Param(key, kind, low=low, high=high, log=log, step=step)


def _int(data: Mapping[str, Any], key: str, default: int, minimum: int) -> int:
    v = data.get(key, default)
    if not isinstance(v, int) or isinstance(v, bool) or v < minimum:
        raise TuneSpecError(f"`{key}` must be an integer >= {minimum}, got {v!r}")
    return v


def parse_tune_spec(data: Mapping[str, Any]) -> TuneSpec:
    """A :class:`TuneSpec` from the parsed TOML.

    Raises:
        TuneSpecError: an unknown key (named), a safety parameter or other untunable setting in the space,
            seeds outside :data:`TUNING_SEEDS`, or an invalid value.
    """
    unknown = sorted(set(data) - _SPEC_KEYS)
    if unknown:
        raise TuneSpecError(
            f"unknown spec key {', '.join(unknown)}; allowed: {', '.join(sorted(_SPEC_KEYS))}"
        )
    name = data.get("name")
    if not isinstance(name, str) or not name.strip():
        raise TuneSpecError("the spec needs a non-empty `name`")
    seeds = data.get("seeds")
    if not isinstance(seeds, Mapping) or set(seeds) != {"first", "last"}:
        raise TuneSpecError(f"`seeds` must be {{ first = 1000, last = 1003 }} (both included), got {seeds!r}")
    first, last = seeds["first"], seeds["last"]
    if not all(isinstance(s, int) and not isinstance(s, bool) for s in (first, last)) or first > last:
        raise TuneSpecError(
            f"`seeds`: first and last must be integers with first <= last, got {first!r}, {last!r}"
        )
    if first not in TUNING_SEEDS or last not in TUNING_SEEDS:
        raise TuneSpecError(
            f"`seeds` {first}-{last} leave the tuning seeds {TUNING_SEEDS.start}-{TUNING_SEEDS.stop - 1}: "
            "tune only on those and evaluate on other seeds"
        )
    duration_s = data.get("duration_s", 60.0)
    if not isinstance(duration_s, (int, float)) or isinstance(duration_s, bool) or not duration_s > 0:
        raise TuneSpecError(f"`duration_s` must be a number > 0, got {duration_s!r}")
    methods = data.get("methods", ["proactive"])
    if not isinstance(methods, list) or not methods or any(m not in METHODS for m in methods):
        raise TuneSpecError(f"`methods` must be a non-empty subset of {list(METHODS)}, got {methods!r}")
    space = data.get("space")
    if not isinstance(space, Mapping) or not space:
        raise TuneSpecError(
            f"the spec needs a [space] with at least one setting (tunable: {', '.join(TUNABLE)})"
        )
    return TuneSpec(
        name=name.strip(),
        first_seed=first,
        last_seed=last,
        duration_s=float(duration_s),
        methods=tuple(dict.fromkeys(methods)),
        num_samples=_int(data, "num_samples", 10, 1),
        concurrency=_int(data, "concurrency", 1, 1),
        sampler_seed=_int(data, "sampler_seed", 0, 0),
        space=tuple(_parse_param(k, v) for k, v in space.items()),
    )


def load_tune_spec(path: str | Path) -> TuneSpec:
    """Read and validate a tuning spec (see :func:`parse_tune_spec`)."""
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise TuneSpecError(f"cannot read the tuning spec {path}: {exc}") from exc
    return parse_tune_spec(data)


def describe_tune(spec: TuneSpec) -> dict[str, Any]:
    """The ``--dry-run`` view: the space, the seeds and methods, and how many headless trials it runs."""
    return {
        "name": spec.name,
        "space": {p.name: p.to_json() for p in spec.space},
        "seeds": [spec.first_seed, spec.last_seed],
        "participants": len(spec.seeds),
        "methods": list(spec.methods),
        "duration_s": spec.duration_s,
        "num_samples": spec.num_samples,
        "concurrency": spec.concurrency,
        "trials_per_sample": spec.trials_per_sample,
        "headless_trials": spec.num_samples * spec.trials_per_sample,
        "objective": objective_text(),
    }


def objective_text() -> str:
    return (
        "maximise the mean completed tasks per trial (participant x method) subject to zero violations, "
        f"zero contacts and no failed trial; an infeasible sample scores -{INFEASIBLE_PENALTY:g} per "
        "violation, contact and failed trial"
    )


# --- evaluation of one sample -----------------------------------------------------------------------------


def sample_jobs(spec: TuneSpec, base: Mapping[str, Any], params: Mapping[str, Any]) -> list[TrialJob]:
    """The headless trials of one sample: every seed x method with ``base`` settings (JSON) + ``params``."""
    from app.config import Settings

    settings = Settings.model_validate({**base, **params}).model_dump(mode="json")
    jobs = []
    for seed in spec.seeds:
        for order_index, method in enumerate(spec.methods):
            jobs.append(
                TrialJob(
                    trial_id=len(jobs),
                    participant_code=f"tune-{seed}",
                    participant_seed=seed,
                    trial_seed=seed,
                    method=method,
                    order_index=order_index,
                    duration_s=spec.duration_s,
                    settings=settings,
                    record_frames=False,
                )
            )
    return jobs


def score_outcomes(outcomes: Sequence[TrialOutcome]) -> dict[str, Any]:
    """The objective of one sample from its trials (see the module docstring)."""
    ok = [o for o in outcomes if o.error is None and o.metrics is not None and o.status == "completed"]
    failed = len(outcomes) - len(ok)
    violations = sum(int(o.metrics.get("violations", 0)) for o in outcomes if o.metrics)
    # contacts within the power and force limits are the safety model's; a harmful one is infeasible
    contacts = sum(int(o.metrics.get("harmful_contacts") or 0) for o in outcomes if o.metrics)
    tasks = [float(o.metrics["completed_tasks"]) for o in ok]  # type: ignore[index]
    mean_tasks = sum(tasks) / len(outcomes) if outcomes else 0.0
    feasible = bool(outcomes) and failed == 0 and violations == 0 and contacts == 0
    score = mean_tasks if feasible else -INFEASIBLE_PENALTY * max(violations + contacts + failed, 1)
    return {
        "score": score,
        "feasible": feasible,
        "mean_completed_tasks": mean_tasks,
        "violations": violations,
        "harmful_contacts": contacts,
        "failed": failed,
        "trials": len(outcomes),
        "wall_s": sum(o.wall_s for o in outcomes),
    }


def evaluate_sample(spec: TuneSpec, base: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    """Run one sample's trials here, one after the other, and score them."""
    return score_outcomes([run_trial_job(job) for job in sample_jobs(spec, base, params)])


def _ray_trainable(config: dict[str, Any], *, spec: TuneSpec, base: dict[str, Any]) -> None:
    """A Ray Tune trial: one sample (``config``: the searched settings)."""
    from ray import tune

    tune.report(evaluate_sample(spec, base, _absolute(config)))


# --- the search ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TuneResult:
    """A finished search: every sample (``params`` and its score), the best feasible one (None if none)."""

    name: str
    engine: str
    samples: tuple[dict[str, Any], ...]
    best: dict[str, Any] | None
    wall_s: float

    def to_json(self, spec: TuneSpec) -> dict[str, Any]:
        return {
            "name": self.name,
            "engine": self.engine,
            "seeds": [spec.first_seed, spec.last_seed],
            "methods": list(spec.methods),
            "duration_s": spec.duration_s,
            "num_samples": spec.num_samples,
            "objective": objective_text(),
            "best_params": None if self.best is None else self.best["params"],
            "best_score": None if self.best is None else self.best["score"],
            "trials": list(self.samples),
            "wall_s": round(self.wall_s, 3),
        }


def base_settings() -> dict[str, Any]:
    """This process's settings (environment, ``.env``) as JSON, paths made absolute for the workers."""
    from app.config import Settings

    out = Settings().model_dump(mode="json")
    for key, field in Settings.model_fields.items():
        if out.get(key) is not None and "Path" in str(field.annotation):
            out[key] = str(Path(out[key]).resolve())
    return out


def _absolute(params: Mapping[str, Any]) -> dict[str, Any]:
    """The sampled settings as the trials get them: floats to 12 digits (a stepped range gives 0.9, not
    0.9000000000000001) and path choices made absolute (a Ray Tune trial may run in its own directory)."""
    from app.config import Settings

    out = {}
    for k, v in params.items():
        if isinstance(v, float):
            v = float(f"{v:.12g}")
        elif isinstance(v, str) and "Path" in str(Settings.model_fields[k].annotation):
            v = str(Path(v).resolve())
        out[k] = v
    return out


def _rounded(params: Mapping[str, Any]) -> dict[str, Any]:
    return {k: float(f"{v:.12g}") if isinstance(v, float) else v for k, v in params.items()}


def _row(
    i: int, params: Mapping[str, Any], metrics: Mapping[str, Any] | None, error: str | None
) -> dict[str, Any]:
    row: dict[str, Any] = {"trial": i, "params": _rounded(params)}
    if metrics is None:
        row.update(score=None, feasible=False, error=error)
    else:
        keys = (
            "score",
            "feasible",
            "mean_completed_tasks",
            "violations",
            "harmful_contacts",
            "failed",
            "wall_s",
        )
        row.update({k: metrics.get(k) for k in keys})
    return row


def _run_inline(spec: TuneSpec, base: dict[str, Any]) -> list[dict[str, Any]]:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    dists = {p.name: p.distribution() for p in spec.space}
    study = optuna.create_study(
        direction="maximize", sampler=optuna.samplers.TPESampler(seed=spec.sampler_seed)
    )
    rows = []
    for i in range(spec.num_samples):
        trial = study.ask(dists)
        metrics = evaluate_sample(spec, base, _absolute(trial.params))
        study.tell(trial, metrics["score"])
        rows.append(_row(i, trial.params, metrics, None))
    return rows


def _sample_index(result: Any) -> int:
    """The order in which Ray Tune created a trial (its experiment tag starts with the 1-based index)."""
    tag = str((result.metrics or {}).get("experiment_tag", ""))
    head = tag.split("_", 1)[0]
    return int(head) if head.isdigit() else sys.maxsize


def _run_ray(spec: TuneSpec, base: dict[str, Any], address: str | None) -> list[dict[str, Any]]:
    import ray
    from ray import tune
    from ray.tune.search.optuna import OptunaSearch

    owns = not ray.is_initialized()
    if owns:
        address = address or os.environ.get("RAY_ADDRESS") or None
        env = {**ray_worker_env(local=address is None), "RAY_CHDIR_TO_TRIAL_DIR": "0"}
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address is None:
            kwargs["num_cpus"] = spec.concurrency
        ray.init(address=address, runtime_env={"env_vars": env}, **kwargs)
    try:
        search = OptunaSearch(
            space={p.name: p.distribution() for p in spec.space},
            metric="score",
            mode="max",
            seed=spec.sampler_seed,
        )
        trainable = tune.with_resources(
            tune.with_parameters(_ray_trainable, spec=spec, base=base), {"cpu": 1}
        )
        with (
            tempfile.TemporaryDirectory(prefix="hrc-tune-") as storage,
            contextlib.redirect_stdout(sys.stderr),
        ):
            tuner = tune.Tuner(
                trainable,
                tune_config=tune.TuneConfig(
                    search_alg=search,
                    num_samples=spec.num_samples,
                    max_concurrent_trials=spec.concurrency,
                ),
                run_config=tune.RunConfig(name=f"tune-{spec.name}", storage_path=storage, verbose=0),
            )
            grid = tuner.fit()
            results = [grid[i] for i in range(len(grid))]
        rows = []
        for i, r in enumerate(sorted(results, key=_sample_index)):
            params = {p.name: (r.config or {}).get(p.name) for p in spec.space}
            ok = r.error is None and r.metrics and "score" in r.metrics
            error = None if ok else str(r.error)[:1000]
            rows.append(_row(i, params, r.metrics if ok else None, error))
        return rows
    finally:
        if owns and ray.is_initialized():
            ray.shutdown()


def run_tune(spec: TuneSpec, *, engine: Engine = "ray", address: str | None = None) -> TuneResult:
    """Search ``spec``'s space: Optuna's TPE sampler through Ray Tune (``engine="ray"``: one CPU per sample,
    ``spec.concurrency`` at once, on a local cluster or the one at ``address``/``RAY_ADDRESS``) or in this
    process, one sample after the other (``engine="inline"``, for debugging)."""
    if engine not in ("ray", "inline"):
        raise ValueError(f"unknown engine {engine!r}; choose ray or inline")
    t0 = time.perf_counter()
    base = base_settings()
    rows = _run_inline(spec, base) if engine == "inline" else _run_ray(spec, base, address)
    feasible = [r for r in rows if r.get("feasible")]
    best = max(feasible, key=lambda r: r["score"]) if feasible else None
    return TuneResult(spec.name, engine, tuple(rows), best, time.perf_counter() - t0)


def _toml_value(v: Any) -> str:
    import json

    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write {v} to a settings file")
        return repr(v)
    if isinstance(v, int):
        return str(v)
    return json.dumps(str(v))  # a TOML basic string


def write_best_settings(
    result: TuneResult, spec: TuneSpec, out: Path, *, spec_path: Path | None = None
) -> Path:
    """Write the best sample's settings (only the tuned keys) as a settings TOML with a comment header.

    Raises:
        LookupError: no sample was feasible (nothing is written).
    """
    if result.best is None:
        raise LookupError(
            f"no feasible sample in the tuning run {spec.name!r}: every one had a violation, a "
            "contact or a failed trial; nothing written"
        )
    best = result.best
    header = [
        f"# hrc tune: the best settings of the tuning run {spec.name!r}",
        f"# spec: {spec_path if spec_path is not None else spec.name}",
        f"# seeds: {spec.first_seed}-{spec.last_seed} (the tuning seeds: evaluate on others), methods: "
        f"{', '.join(spec.methods)}, {spec.duration_s:g} s trials, {len(result.samples)} samples "
        f"({result.engine})",
        f"# score: {best['score']:.4g} mean completed tasks per trial, 0 violations, 0 contacts",
        f"# date: {datetime.now(UTC).isoformat(timespec='seconds')}",
        "# use: hrc study --settings FILE, hrc serve --settings FILE",
    ]
    body = [f"{k} = {_toml_value(v)}" for k, v in best["params"].items()]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join([*header, *body]) + "\n", encoding="utf-8")
    return out
