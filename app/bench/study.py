"""``hrc bench study``: trials per minute of the study engines on this machine, and Ray's start-up time.

The same headless trials (simulated participants x both methods, ``duration_s`` simulated seconds each,
no frames recorded, nothing written to a database) run through each engine of
:func:`app.study.runner.make_executor` with one worker per core: ``inline`` (one after the other in this
process), ``process_pool`` (a spawn ``ProcessPoolExecutor``) and ``ray`` (Ray tasks, one CPU each, on a
local cluster). ``trials_per_min`` counts from the first submission to the last result; for Ray the
cluster is started before that clock and its start-up is reported apart as ``ray_startup_s``, as is the
process pool's first-result latency inside its own number (spawned workers import the app).

Prints one JSON object.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import as_completed
from typing import Any

log = logging.getLogger(__name__)


def _jobs(n_participants: int, duration_s: float) -> list[Any]:
    from app.config import Settings
    from app.study.runner import TrialJob, participant_code, participant_seeds

    settings = Settings().model_dump(mode="json")
    jobs = []
    for i, (p_seed, t_seed) in enumerate(participant_seeds(2026, n_participants)):
        for order_index, method in enumerate(("proactive", "reactive")):
            jobs.append(
                TrialJob(
                    trial_id=len(jobs),
                    participant_code=participant_code(2026, i),
                    participant_seed=p_seed,
                    trial_seed=t_seed,
                    method=method,
                    order_index=order_index,
                    duration_s=duration_s,
                    settings=settings,
                    record_frames=False,
                )
            )
    return jobs


def _throughput(executor: Any, jobs: list[Any]) -> tuple[float, int]:
    """(trials per minute, failed trials) of ``jobs`` through ``executor``."""
    from app.study.runner import run_trial_job

    t0 = time.perf_counter()
    futures = [executor.submit(run_trial_job, job) for job in jobs]
    failed = sum(1 for f in as_completed(futures) if f.result().error is not None)
    return 60.0 * len(jobs) / (time.perf_counter() - t0), failed


def run(*, quick: bool = False, progress: bool = True, duration_s: float | None = None) -> dict[str, Any]:
    """Measure the three engines on ``2 x cores`` trials (``quick``: 4 s simulated each, else 60 s: a
    study's trials are 300 s, and with short ones the workers' start-up and imports dominate)."""
    from app.study.runner import InlineExecutor, make_executor

    workers = os.cpu_count() or 1
    duration = duration_s if duration_s is not None else (4.0 if quick else 60.0)
    jobs = _jobs(max(1, workers), duration)
    out: dict[str, Any] = {"workers": workers, "trials": len(jobs), "trial_duration_s": duration}
    rates: dict[str, float] = {}
    failed: dict[str, int] = {}

    rates["inline"], failed["inline"] = _throughput(InlineExecutor(), jobs)
    if progress:
        log.info("inline: %.2f trials/min", rates["inline"])
    pool = make_executor("process", workers)
    try:
        rates["process_pool"], failed["process_pool"] = _throughput(pool, jobs)
    finally:
        pool.shutdown(wait=True)
    t0 = time.perf_counter()
    ray_ex = make_executor("ray", workers)
    out["ray_startup_s"] = round(time.perf_counter() - t0, 3)
    try:
        rates["ray"], failed["ray"] = _throughput(ray_ex, jobs)
    finally:
        ray_ex.shutdown()
    out["trials_per_min"] = {k: round(v, 3) for k, v in rates.items()}
    out["ray_vs_process_pool"] = round(rates["ray"] / rates["process_pool"], 3)
    out["failed_trials"] = failed
    return out
