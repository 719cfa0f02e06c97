"""Headless study runner: simulated participants x {proactive, reactive}, on a process pool or Ray.

Every simulated participant gets its own parameters from a seed derived from the study seed; it runs both
methods with the *same* participant parameters and the same trial seed (a paired design with common random
numbers), in the counterbalanced order of :meth:`StudyRepository.suggest_method_order`. Trials run in a
``ProcessPoolExecutor`` (one process per core by default), as Ray tasks (``engine="ray"``: a local
in-process cluster, or the cluster at ``RAY_ADDRESS``) or inline, through
:func:`app.control.runtime.run_headless_trial` on the simulated clock; only the parent process writes the
database: the trial rows first (status ``running``, so that a killed study leaves them to be marked aborted
at the next start), then each trial's metrics, events and recorded frames in one transaction as it ends.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import sys
import time
import traceback
from collections.abc import Callable, Mapping
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field, is_dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
from sqlalchemy.exc import SQLAlchemyError

from app.control.metrics import TrialEvent
from app.study.repository import RecordedFrames, StudyRepository, TrialStateError, settings_snapshot
from app.study.schemas import ParticipantCreate, StudySessionCreate

log = logging.getLogger(__name__)

_THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


@dataclass(frozen=True)
class TrialJob:
    """One headless trial to run in a worker process (everything in it pickles)."""

    trial_id: int
    participant_code: str
    participant_seed: int
    trial_seed: int
    method: str
    order_index: int
    duration_s: float
    settings: dict[str, Any]
    record_frames: bool = True


@dataclass(frozen=True)
class TrialOutcome:
    """What a worker sends back: the trial's metrics (``TrialMetrics`` fields), events and frames, how it
    ended (``status`` ``completed`` or ``aborted`` with the runtime's ``reason``), or the error that broke
    it (then ``metrics`` is None)."""

    trial_id: int
    metrics: dict[str, Any] | None
    events: list[TrialEvent] = field(default_factory=list)
    frames: RecordedFrames | None = None
    error: str | None = None
    started_at: datetime | None = None
    wall_s: float = 0.0
    status: str = "completed"
    reason: str | None = None


@dataclass(frozen=True)
class StudyRunResult:
    """Summary of one :func:`run_study` call."""

    session_id: int
    participant_ids: tuple[int, ...]
    trial_ids: tuple[int, ...]
    completed: int
    aborted: int
    wall_s: float

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def participant_seeds(seed: int, n: int) -> list[tuple[int, int]]:
    """``(participant_seed, trial_seed)`` for participants 0..n-1 of a study with ``seed`` (independent
    streams from ``numpy.random.SeedSequence``; participant i's seeds do not depend on n)."""
    children = np.random.SeedSequence(seed).spawn(n)
    return [(int(c.generate_state(2)[0]), int(c.generate_state(2)[1])) for c in children]


def participant_code(seed: int, index: int) -> str:
    """The code of simulated participant ``index`` (from 0) of the study with ``seed``."""
    return f"sim-s{seed}-p{index + 1:02d}"


def frames_from_result(frames: Any) -> RecordedFrames | None:
    """Recorded frames from whatever the runtime returned: None, a :class:`RecordedFrames`, an object or
    mapping with ``t``/``times``, ``q`` and ``skeleton``/``joints`` arrays (and ``body_ids`` with a
    skeleton of several bodies, :mod:`app.cell.bodies`), or a sequence of per-frame objects or mappings with
    those fields (a None skeleton becomes a NaN row)."""
    if frames is None:
        return None
    if isinstance(frames, RecordedFrames):
        return frames

    def get(obj: Any, *names: str) -> Any:
        for name in names:
            if isinstance(obj, Mapping) and name in obj:
                return obj[name]
            if not isinstance(obj, Mapping) and hasattr(obj, name):
                return getattr(obj, name)
        return None

    t = get(frames, "t", "times")
    if t is not None and not isinstance(frames, (list, tuple)):
        q = get(frames, "q")
        skeleton = get(frames, "skeleton", "joints", "skeletons")
        if len(np.atleast_1d(t)) == 0:
            return None
        body_ids = get(frames, "body_ids") if skeleton is not None else None
        return RecordedFrames(t=np.asarray(t), q=np.asarray(q), skeleton=skeleton, body_ids=body_ids)
    seq = list(frames)
    if not seq:
        return None
    ts = np.array([float(get(f, "t")) for f in seq])
    qs = np.stack([np.asarray(get(f, "q"), dtype=np.float32) for f in seq])
    sks = [get(f, "skeleton", "joints") for f in seq]
    skeleton = None
    shapes = {np.shape(s) for s in sks if s is not None}
    if len(shapes) == 1:
        (shape,) = shapes
        nan = np.full(shape, np.nan, dtype=np.float32)
        skeleton = np.stack([nan if s is None else np.asarray(s, dtype=np.float32) for s in sks])
    return RecordedFrames(t=ts, q=qs, skeleton=skeleton)


def _init_worker() -> None:
    """Worker start-up: one BLAS/torch thread per process (the pool already uses every core).

    The variables reach the libraries loaded from here on (torch, onnxruntime); the BLAS that NumPy
    loaded while this module was imported is limited through threadpoolctl.
    """
    for name in _THREAD_ENV:
        os.environ[name] = "1"
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def run_trial_job(job: TrialJob) -> TrialOutcome:
    """Run one headless trial (in a worker process) with :func:`app.control.runtime.run_headless_trial`.

    Never raises for a failed trial: the error comes back in :attr:`TrialOutcome.error`.
    """
    started_at = datetime.now(UTC)
    t0 = time.perf_counter()
    try:
        from app.config import Settings

        try:
            from app.control.runtime import run_headless_trial
        except ImportError:  # the runtime module re-exports it; fall back to where it is defined
            from app.control.headless import run_headless_trial

        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)
        settings = Settings.model_validate(job.settings)
        result = run_headless_trial(
            settings=settings,
            method=job.method,
            duration_s=job.duration_s,
            seed=job.trial_seed,
            participant_seed=job.participant_seed,
            source="sim",
        )
        metrics = result.metrics
        metrics_dict = asdict(metrics) if is_dataclass(metrics) else dict(metrics)
        frames = frames_from_result(getattr(result, "frames", None)) if job.record_frames else None
        return TrialOutcome(
            trial_id=job.trial_id,
            metrics=metrics_dict,
            events=list(result.events),
            frames=frames,
            started_at=started_at,
            wall_s=time.perf_counter() - t0,
            status=str(getattr(result, "status", "completed")),
            reason=getattr(result, "reason", None),
        )
    except Exception as exc:
        tb = traceback.format_exc(limit=8)
        log.error("headless trial %d failed: %s", job.trial_id, exc)
        return TrialOutcome(
            trial_id=job.trial_id,
            metrics=None,
            error=f"{type(exc).__name__}: {exc}\n{tb}",
            started_at=started_at,
            wall_s=time.perf_counter() - t0,
        )


def _make_executor(max_workers: int) -> Executor:
    # spawn: workers do not inherit the parent's threads, engine or locks (fork with threads is unsafe).
    return ProcessPoolExecutor(
        max_workers=max_workers, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker
    )


ENGINES = ("inline", "process", "ray")


class _RayExecutor(Executor):
    """Submits each job as a Ray task (one CPU, one BLAS/torch thread inside) and hands back a
    ``concurrent.futures.Future`` for its result; the driver stores the outcomes as they arrive.

    Connects to the cluster at ``address`` (or ``RAY_ADDRESS``); without either it starts a local
    in-process cluster with ``num_cpus`` CPUs (default: every core). Only the job (settings as JSON, seeds,
    method, duration) travels to the workers; the outcome (metrics, events, frames) travels back.
    """

    def __init__(self, *, address: str | None = None, num_cpus: int | None = None) -> None:
        import ray

        self._ray = ray
        self._owns = not ray.is_initialized()
        if self._owns:
            address = address or os.environ.get("RAY_ADDRESS") or None
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if address is None:
                kwargs["num_cpus"] = num_cpus
            ray.init(address=address, **kwargs)
        env = ray_worker_env(local=address is None)
        self._remote = ray.remote(_ray_task).options(num_cpus=1, max_retries=2, runtime_env={"env_vars": env})

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        return self._remote.remote(fn, *args, **kwargs).future()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()


def ray_worker_env(*, local: bool) -> dict[str, str]:
    """Environment variables of a Ray worker: one BLAS/OpenMP thread each; on a ``local`` cluster also the
    driver's import path (the workers import what the driver imports, from here)."""
    env = {name: "1" for name in _THREAD_ENV}
    if local:
        paths = [os.getcwd(), *(p for p in sys.path if p and os.path.isdir(p))]
        env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    return env


def _ray_task(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """The body of a Ray task: thread limits as in a pool worker, then the job."""
    _init_worker()
    return fn(*args, **kwargs)


def make_executor(engine: str, workers: int, *, address: str | None = None) -> Executor:
    """The executor of ``engine`` (``inline``, ``process`` or ``ray``) with ``workers`` processes/CPUs
    (``workers`` 0 always means inline)."""
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
    if engine == "inline" or workers == 0:
        return InlineExecutor()
    if engine == "process":
        return _make_executor(workers)
    return _RayExecutor(address=address, num_cpus=workers)


def _ray_errors() -> tuple[type[BaseException], ...]:
    """Ray's errors for a lost worker or node (empty when Ray was never imported)."""
    ray_exc = sys.modules.get("ray.exceptions")
    if ray_exc is None:
        return ()
    return (ray_exc.RayError,)


class InlineExecutor(Executor):
    """Runs each job in the calling process at submit time (``max_workers=0``: debugging and tests)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        fut: Future[Any] = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:
            fut.set_exception(exc)
        return fut


def plan_study(
    repo: StudyRepository,
    *,
    participants: int,
    duration_s: float,
    seed: int,
    settings: Any,
    record_frames: bool = True,
    session_name: str | None = None,
) -> tuple[int, list[int], list[TrialJob]]:
    """Create the study session, the participants (reused when their code exists: same seed, same
    simulated person) and one ``running`` trial per participant and method. Returns
    ``(session_id, participant_ids, jobs)``, the jobs in participant order."""
    if participants < 1:
        raise ValueError(f"participants must be >= 1, got {participants}")
    if not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    snapshot = settings_snapshot(settings)
    name = (
        session_name
        or f"headless study: {participants} participants x 2 methods x {duration_s:g} s, seed {seed}"
    )
    session = repo.create_session(
        StudySessionCreate(
            name=name[:200],
            notes=f"hrc study --participants {participants} --duration {duration_s:g} --seed {seed}",
        )
    )
    participant_ids: list[int] = []
    jobs: list[TrialJob] = []
    for i, (p_seed, t_seed) in enumerate(participant_seeds(seed, participants)):
        code = participant_code(seed, i)
        p = repo.get_participant_by_code(code) or repo.create_participant(
            ParticipantCreate(
                code=code, notes=f"simulated operator: study seed {seed}, participant seed {p_seed}"
            )
        )
        participant_ids.append(p.id)
        for order_index, method in enumerate(repo.suggest_method_order(p.id)):
            trial = repo.create_trial(
                participant_id=p.id,
                method=method,  # type: ignore[arg-type]
                session_id=session.id,
                order_index=order_index,
                seed=t_seed,
                duration_s=duration_s,
                settings={**snapshot, "participant_seed": p_seed, "source": "sim"},
            )
            jobs.append(
                TrialJob(
                    trial_id=trial.id,
                    participant_code=code,
                    participant_seed=p_seed,
                    trial_seed=t_seed,
                    method=method,
                    order_index=order_index,
                    duration_s=duration_s,
                    settings=settings.model_dump(mode="json")
                    if hasattr(settings, "model_dump")
                    else dict(settings),
                    record_frames=record_frames,
                )
            )
    return session.id, participant_ids, jobs


def _store(repo: StudyRepository, outcome: TrialOutcome) -> bool:
    """Write one outcome; True when the trial completed."""
    if outcome.error is not None or outcome.metrics is None:
        reason = (outcome.error or "the runtime returned no metrics")[:2000]
        repo.finish_trial(
            outcome.trial_id,
            status="aborted",
            reason=reason,
            events=outcome.events,
            started_at=outcome.started_at,
        )
        return False
    if outcome.status != "completed":  # the runtime ended it early (e.g. a robot fault): kept, not analysed
        repo.finish_trial(
            outcome.trial_id,
            status="aborted",
            reason=f"the runtime ended the trial: {outcome.reason or outcome.status}",
            metrics=outcome.metrics,
            events=outcome.events,
            frames=outcome.frames,
            started_at=outcome.started_at,
        )
        return False
    repo.finish_trial(
        outcome.trial_id,
        status="completed",
        metrics=outcome.metrics,
        events=outcome.events,
        frames=outcome.frames,
        started_at=outcome.started_at,
    )
    return True


def run_study(
    *,
    participants: int,
    duration_s: float,
    seed: int,
    repo: StudyRepository,
    settings: Any = None,
    max_workers: int | None = None,
    progress: bool = True,
    record_frames: bool = True,
    session_name: str | None = None,
    trial_fn: Callable[[TrialJob], TrialOutcome] | None = None,
    engine: str = "process",
    address: str | None = None,
) -> StudyRunResult:
    """Run a whole headless study and store it under one new study session.

    Args:
        participants: Number of simulated participants (each runs both methods).
        duration_s: Simulated duration of each trial (s).
        seed: Study seed: participant parameters and trial seeds derive from it.
        repo: Where the results go (schema at head).
        settings: Application settings for every trial (default ``Settings()``).
        max_workers: Worker processes (default ``os.cpu_count()``); 0 runs every trial in this process.
        progress: Show a tqdm progress bar on stderr.
        record_frames: Store the trials' frames (robot q and skeleton at 30 Hz) for replay.
        trial_fn: Runs one job (a picklable top-level function when ``max_workers`` > 0); default
            :func:`run_trial_job`.
        engine: ``process`` (a local process pool), ``ray`` (Ray tasks, one CPU each) or ``inline``.
        address: Ray cluster address (default ``RAY_ADDRESS``, else a local in-process cluster).

    Returns:
        The session id, participant and trial ids, how many trials completed and aborted, the wall time.
    """
    from tqdm import tqdm

    if settings is None:
        from app.config import Settings

        settings = Settings()
    trial_fn = trial_fn or run_trial_job
    t0 = time.perf_counter()
    session_id, participant_ids, jobs = plan_study(
        repo,
        participants=participants,
        duration_s=duration_s,
        seed=seed,
        settings=settings,
        record_frames=record_frames,
        session_name=session_name,
    )
    workers = (os.cpu_count() or 1) if max_workers is None else max_workers
    workers = min(workers, len(jobs))
    log.info(
        "study session %d: %d trials on %s",
        session_id,
        len(jobs),
        f"{workers} processes" if workers else "this process",
    )
    completed = aborted = 0
    pending = {job.trial_id for job in jobs}
    executor = make_executor(engine, workers, address=address)
    bar = tqdm(total=len(jobs), unit="trial", desc="study", disable=not progress, dynamic_ncols=True)
    try:
        # longest first: the proactive trials (the predictor runs every frame) take about 1.6x as long as the
        # reactive ones; starting them first keeps the last process from running alone at the end
        order = sorted(jobs, key=lambda j: (j.method != "proactive", j.trial_id))
        futures = {executor.submit(trial_fn, job): job for job in order}
        for fut in as_completed(futures):
            job = futures[fut]
            try:
                outcome = fut.result()
            except BrokenProcessPool as exc:
                outcome = TrialOutcome(job.trial_id, None, error=f"worker process died: {exc}")
            except _ray_errors() as exc:  # the task's worker or node died more often than Ray retries
                outcome = TrialOutcome(job.trial_id, None, error=f"Ray worker lost: {exc}")
            except Exception as exc:
                outcome = TrialOutcome(job.trial_id, None, error=f"{type(exc).__name__}: {exc}")
            ok = _store(repo, outcome)
            pending.discard(job.trial_id)
            if ok:
                completed += 1
            else:
                aborted += 1
                why = (outcome.error or outcome.reason or outcome.status).splitlines()[0]
                log.warning(
                    "trial %d (%s, %s) aborted: %s", job.trial_id, job.participant_code, job.method, why
                )
            bar.update(1)
            bar.set_postfix(completed=completed, aborted=aborted)
    finally:
        bar.close()
        executor.shutdown(wait=not pending, cancel_futures=True)
        for trial_id in sorted(pending):  # interrupted (Ctrl-C) or failed before all results came back
            try:
                repo.finish_trial(trial_id, status="aborted", reason="the study run was interrupted")
            except (TrialStateError, SQLAlchemyError) as exc:
                log.error("could not mark trial %d aborted: %s", trial_id, exc)
            aborted += 1
    return StudyRunResult(
        session_id=session_id,
        participant_ids=tuple(participant_ids),
        trial_ids=tuple(job.trial_id for job in jobs),
        completed=completed,
        aborted=aborted,
        wall_s=time.perf_counter() - t0,
    )
