"""``hrc bench planning``: the time-variant planner on the reference scenario set, each query timed once.

Every query (the reference scenarios of :func:`app.planning.scenarios.reference_queries`: 60 seeded
synthetic operators reaching in, and 20 recorded CMU clips placed at the operator's side when the clips are
present) is run ONCE in each configuration below, all in the same run and interleaved query by query (the
order of the configurations rotates from one query to the next), so that the load of a shared machine falls
on all of them alike. Every timed call has the same compute budget, ``deadline_s = DEADLINE_S``:

* ``plan_ms``: sequential time-variant A* (``workers=1``) against the query's forecast person;
* ``parallel_plan_ms``: the batched search (``workers=WORKERS``) on the same query. It is *not* threads or
  processes: one thread pops up to ``WORKERS`` states per step (the best one with a lookahead chain along the
  static shortest path) and checks their moves in one vectorised, compiled call (``parallel_kind``);
* ``static_ms`` / ``parallel_static_ms``: the same two searches with no person (``forecast=None``);
* ``emergency_ms``: the emergency plan (person held, horizon ``F + D``) from the query's start.

Each is ``{"p50", "p95", "n"}`` in wall-clock milliseconds over the queries that configuration SOLVED
(``n`` of them); its failures are in ``failures`` (counts by reason, per configuration) and not in the
times. ``cpu_ms`` gives the same statistics of the thread's CPU time, which the other processes of a busy
machine disturb much less.

* ``time_variant_over_static``: per query, the time-variant time over the static time of the SAME query
  with the same ``workers`` (``sequential``: ``plan / static``; ``parallel``: ``parallel_plan /
  parallel_static``), over the queries where both succeeded; ``p50``/``p95`` of those ratios and ``n``.
* ``success_rate`` (parallel), ``sequential_success_rate``, ``emergency_success_rate``: shares of all queries.
* ``success_rate_solvable``: the share of the *solvable* queries that the parallel search solved within
  its budget. A query is solvable when some search returned a verified plan for it: any of the timed
  time-variant searches, or else a generous one, sequential with the same planner settings but
  ``max_expansions = GENEROUS_EXPANSIONS`` and a ``GENEROUS_DEADLINE_S`` budget (untimed). It is exhaustive
  over the search's own moves (roadmap, IK branches, slower speeds, waits) within the planner's policy
  limits, which it keeps (plans arriving later than ``max_plan_s`` are never searched for). ``solvable``
  counts them; ``unsolvable`` the queries the generous search proved to have no such plan; ``undecided``
  those where it ran out of its budget too (counted as not solvable).
* ``violations``: returned trajectories (sequential, parallel, generous and emergency) that break the
  requirement in an independent check: sampled at 100 Hz, joint limits, and the surface distance (from
  :meth:`CollisionModel.distance_to_human_paired`) against :func:`app.safety.ssm.forecast_clearance` for
  the robot speed obtained by differentiating the trajectory's capsule points numerically. It must be 0.
* ``threads``: whether threads help on this machine: queries per second of independent ``parallel_plan``
  queries sharing one planner, in one thread and in ``os.cpu_count()`` threads (throughput for a caller
  with several queries at once; a single query is not split over threads). Processes are not measured.
* ``phases_ms``: where the time of each search configuration's successful queries goes, per phase of
  :attr:`app.planning.search.PlanResult.phases_s` (``search``: the separation check's set-up and the A*;
  ``shortcut``; ``finish``: fitting the trajectory, its SSM-aware timing and its verification):
  ``{"p50", "p95", "n"}`` (ms) per phase and ``share``, each phase's part of their summed wall time.
* ``by_source``: the figures per kind of person (``synthetic``, ``recorded``).
* ``scaling``: ``{"p50", "p95", "n"}`` of the parallel plan time (successful queries) on roadmaps of about
  1k, 4k and 16k nodes (built and cached on first use, which takes minutes; ``--quick`` reports only those
  already cached and ``null`` for the rest).

Before timing, one untimed static plan per goal fills the planner's per-goal heuristic cache (a live planner
keeps it from one frame to the next) and one untimed call per configuration loads the compiled kernels.
``load_avg`` is the machine's 1-minute load average at the end of the run.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from app.safety.stopping import StoppingModel

DEADLINE_S = 1.0
WORKERS = 32
HORIZON_S = 1.0 / 30.0 + 0.1  # F + D: one camera frame + the backup-plan deadline
GENEROUS_EXPANSIONS = 200_000  # the generous search (solvability): 10x the planner's default bound
GENEROUS_DEADLINE_S = 60.0
SCALING = {"1k": 1000, "4k": 4000, "16k": 16000}
CMU_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "cmu_mocap"
#: The timed configurations, in the order of the first query (later queries rotate it).
CONFIGS = ("plan", "parallel_plan", "static", "parallel_static", "emergency")
PARALLEL_KIND = (
    f"one thread, {WORKERS}-wide vectorised batches (up to {WORKERS} states popped per step, the best "
    "with a lookahead chain, their moves checked in one compiled call); no threads or processes"
)


@dataclass(frozen=True, slots=True)
class Run:
    """One timed call: wall and thread CPU time (s), whether it returned a verified plan, and why not; with
    the time (s) of each of :data:`app.planning.search.config.PHASES` where the planner reports them."""

    wall_s: float
    cpu_s: float
    ok: bool
    reason: str = "ok"
    expanded: int = 0
    phases_s: tuple[float, ...] | None = None


def _run_of(res: Any, wall_s: float, cpu_s: float) -> Run:
    """The :class:`Run` of one timed planner call's result ``res``."""
    from app.planning.search.config import PHASES

    phases = None if res.phases_s is None else tuple(float(res.phases_s[p]) for p in PHASES)
    return Run(wall_s, cpu_s, bool(res.ok), res.reason, res.expanded, phases)


def phases_ms(runs: Sequence[Run]) -> dict[str, Any]:
    """Where the successful runs' time went: per phase of :data:`app.planning.search.config.PHASES` the
    ``{"p50", "p95", "n"}`` of its time (ms), and ``share``: each phase's part of their summed wall time."""
    from app.planning.search.config import PHASES

    ok = [(r.wall_s, r.phases_s) for r in runs if r.ok and r.phases_s is not None]
    out: dict[str, Any] = {p: percentiles([ph[i] for _, ph in ok], scale=1e3) for i, p in enumerate(PHASES)}
    total = sum(w for w, _ in ok)
    out["share"] = {
        p: (round(sum(ph[i] for _, ph in ok) / total, 3) if total > 0 else None) for i, p in enumerate(PHASES)
    }
    return out


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(msg, file=sys.stderr, flush=True)


def percentiles(values: Sequence[float], *, scale: float = 1.0, digits: int = 3) -> dict[str, Any]:
    """``{"p50", "p95", "n"}`` of ``values`` x ``scale`` (``None`` percentiles when empty)."""
    if len(values) == 0:
        return {"p50": None, "p95": None, "n": 0}
    arr = np.asarray(values, dtype=np.float64) * scale
    return {
        "p50": round(float(np.percentile(arr, 50)), digits),
        "p95": round(float(np.percentile(arr, 95)), digits),
        "n": len(values),
    }


def successful_ms(runs: Sequence[Run], *, cpu: bool = False) -> dict[str, Any]:
    """Percentiles (ms) of the wall (or CPU) times of the successful runs only."""
    return percentiles([r.cpu_s if cpu else r.wall_s for r in runs if r.ok], scale=1e3)


def per_query_ratios(num: Sequence[Run], den: Sequence[Run]) -> list[float]:
    """``num[i].wall_s / den[i].wall_s`` for every query ``i`` where both runs succeeded."""
    if len(num) != len(den):
        raise ValueError(f"per_query_ratios: {len(num)} against {len(den)} runs; both must be per query")
    return [a.wall_s / b.wall_s for a, b in zip(num, den, strict=True) if a.ok and b.ok and b.wall_s > 0]


def reason_key(reason: str) -> str:
    """A failure reason without its numbers: ``"goal blocked by the person from t=+0.40 s on"`` ->
    ``"goal blocked by the person"``, ``"goal unreachable: every way ..."`` -> ``"goal unreachable"``."""
    return reason.split(":")[0].split(" from ")[0].split(" after ")[0].strip()


def failure_counts(runs: Sequence[Run]) -> dict[str, int]:
    """Failed runs counted by :func:`reason_key` of their reason."""
    out: dict[str, int] = {}
    for r in runs:
        if not r.ok:
            key = reason_key(r.reason)
            out[key] = out.get(key, 0) + 1
    return dict(sorted(out.items()))


def solvability(solved: Sequence[Sequence[bool]], generous: Sequence[bool | None]) -> list[bool | None]:
    """Per query: True when any search in ``solved`` (one flag list per configuration) or the generous
    search found a verified plan, False when the generous search ran to the end without one, None when it
    ran out of its budget (undecided)."""
    out: list[bool | None] = []
    for i, g in enumerate(generous):
        out.append(True if g or any(flags[i] for flags in solved) else g)
    return out


def solvable_success(runs: Sequence[Run], solvable: Sequence[bool | None]) -> float | None:
    """Share of the solvable queries (``solvable[i] is True``) that ``runs`` solved; None with none."""
    idx = [i for i, s in enumerate(solvable) if s is True]
    if not idx:
        return None
    return round(sum(runs[i].ok for i in idx) / len(idx), 4)


def _rate(runs: Sequence[Run]) -> float | None:
    return round(sum(r.ok for r in runs) / len(runs), 4) if runs else None


def summarise(runs: dict[str, list[Run]], generous: Sequence[bool | None]) -> dict[str, Any]:
    """The headline figures from the per-query runs of every configuration (``runs[name][i]``: query
    ``i`` in configuration ``name``, every name of :data:`CONFIGS`) and the generous search's verdicts
    (True: a plan; False: none; None: undecided; a query solved by a timed search need not have one)."""
    n = len(generous)
    if any(len(runs[c]) != n for c in CONFIGS):
        raise ValueError("summarise: every configuration needs one run per query")
    solvable = solvability([[r.ok for r in runs["plan"]], [r.ok for r in runs["parallel_plan"]]], generous)
    ratios = {
        "sequential": per_query_ratios(runs["plan"], runs["static"]),
        "parallel": per_query_ratios(runs["parallel_plan"], runs["parallel_static"]),
    }
    out: dict[str, Any] = {f"{c}_ms": successful_ms(runs[c]) for c in CONFIGS}
    out["time_variant_over_static"] = {k: percentiles(v, digits=2) for k, v in ratios.items()}
    out["success_rate"] = _rate(runs["parallel_plan"])
    out["sequential_success_rate"] = _rate(runs["plan"])
    out["emergency_success_rate"] = _rate(runs["emergency"])
    out["success_rate_solvable"] = solvable_success(runs["parallel_plan"], solvable)
    out["sequential_success_rate_solvable"] = solvable_success(runs["plan"], solvable)
    out["solvable"] = sum(s is True for s in solvable)
    out["unsolvable"] = sum(s is False for s in solvable)
    out["undecided"] = sum(s is None for s in solvable)
    out["failures"] = {c: failure_counts(runs[c]) for c in CONFIGS}
    out["cpu_ms"] = {c: successful_ms(runs[c], cpu=True) for c in CONFIGS}
    out["phases_ms"] = {c: phases_ms(runs[c]) for c in CONFIGS[:4]}
    out["expanded_p50"] = {
        c: float(np.median([r.expanded for r in runs[c]])) if runs[c] else None for c in CONFIGS[:4]
    }
    return out


def count_violations(
    traj: Any,
    forecast: Any,
    model: Any,
    ssm: Any,
    *,
    hold_s: float,
    stopping: StoppingModel,
    contact_only: tuple[bool, ...] = (),
    limits: tuple[np.ndarray, np.ndarray] | None = None,
    contact_speed_mps: tuple[float, ...] = (),
) -> int:
    """1 if the trajectory breaks the limits or the separation anywhere on a 100 Hz grid, else 0: the
    clearance of :func:`app.safety.ssm.forecast_clearance` with the robot's speeds there (central
    differences) and the planner's stopping model ``stopping``; from a person capsule flagged in
    ``contact_only`` (one flag per capsule of :data:`app.planning.collision.HUMAN_CAPSULES`, the planner's
    ``PlannerConfig.contact_only``) only ``Z_d``, and nothing where the robot moves no faster than that
    capsule's ``contact_speed_mps`` (``PlannerConfig.contact_speed_mps``), as the planner's trajectory
    checks ask of it. ``limits``:
    the joint position limits ``(q_min, q_max)`` the planner keeps (the cell's; default: the UR5e's)."""
    from app.planning.kinematics import Q_MAX, Q_MIN
    from app.safety.ssm import forecast_clearance

    q_min, q_max = (Q_MIN, Q_MAX) if limits is None else limits
    t = np.arange(traj.t_start, traj.t_end + hold_s + 1e-9, 0.01)
    q = traj.q(t)
    if np.any(q < q_min - 1e-9) or np.any(q > q_max + 1e-9):
        return 1
    eps = 1e-5
    q0, q1 = traj.q(t - eps), traj.q(t + eps)
    a0, b0, _ = model.robot_capsules(q0)
    a1, b1, _ = model.robot_capsules(q1)
    v = np.maximum(np.linalg.norm(a1 - a0, axis=-1), np.linalg.norm(b1 - b0, axis=-1)).max(axis=1) / (2 * eps)
    w = stopping.braking_speed((q1 - q0) / (2 * eps))
    joints, margins = forecast.poses_at(t)
    d = model.distance_to_human_paired(q, joints)
    need = forecast_clearance(v, margins, ssm, w_top_radps=w, stopping=stopping)
    short = np.flatnonzero(d < need - 1e-9)
    if short.size == 0 or not any(contact_only):
        return int(short.size > 0)
    soft = np.asarray(contact_only, dtype=bool)
    free = np.asarray(contact_speed_mps, dtype=np.float64) if contact_speed_mps else np.full(soft.shape, -1.0)
    for k in short.tolist():  # the few samples too close to some capsule: each capsule's own requirement
        pair = model.pair_distances(q[k], joints[k][None])[0].min(axis=0)  # (M,) over the robot's parts
        req = np.where(soft, min(ssm.z_human_m, float(need[k])), float(need[k]))
        req = np.where(soft & (v[k] <= free), -np.inf, req)  # a permissible contact asks nothing
        if np.any(pair < req - 1e-9):
            return 1
    return 0


def _planner_config() -> Any:
    """The runtime's planner settings: its clearance with the ``T_r`` of the default installation and its
    contact clearance per body region (:meth:`app.control.stack.PlanningStack.for_cell`)."""
    from app.config import Settings
    from app.control.engine import EngineOptions
    from app.control.stack import contact_clearance
    from app.planning.search import PlannerConfig

    settings = Settings()
    config = PlannerConfig(**contact_clearance(settings))
    return config.with_reaction_time(settings.reaction_time_s(EngineOptions().servo_period_s))


def _governor_model(ssm: Any) -> Any:
    """The speed governor of a trial under the default settings, as the planner predicts it (the runtime's
    SSM-aware timing, ``HRC_SSM_TIMING``)."""
    from app.config import Settings
    from app.control.engine import EngineOptions, governor_model, supervisor_config

    settings, options = Settings(), EngineOptions()
    return governor_model(settings, ssm, supervisor_config(settings, "proactive", options), options)


def _as_executed(res: Any, forecast: Any, model: Any, timing: Any) -> Any:
    """The trajectory of a plan at the timing it was verified at (the governor's predicted one)."""
    from app.planning.ssm_timing import PredictedTiming

    return PredictedTiming.of(res.trajectory, forecast, model, timing)


def _timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    """``fn()``'s result and the wall-clock and thread CPU time (s) of that one call."""
    c0 = time.thread_time()
    t0 = time.perf_counter()
    got = fn()
    return got, time.perf_counter() - t0, time.thread_time() - c0


def _roadmap(cell: Any, model: Any, num_nodes: int | None, *, build: bool) -> tuple[Any, float, float] | None:
    """(roadmap, build_s, load_s); build_s is the time of the build that made the cached file."""
    from app.planning.roadmap import (
        RoadmapConfig,
        default_cache_dir,
        load_or_build_roadmap,
        load_roadmap,
        roadmap_key,
    )

    cfg = RoadmapConfig() if num_nodes is None else RoadmapConfig(num_nodes=num_nodes)
    path = default_cache_dir() / f"roadmap-{roadmap_key(cell, cfg)}.npz"
    if not path.is_file() and not build:
        return None
    rm = load_or_build_roadmap(cell, config=cfg, collision=model)
    t0 = time.perf_counter()
    load_roadmap(path, expected_key=rm.key)
    return rm, rm.build_s, time.perf_counter() - t0


def _held(forecast: Any, t_start: float) -> Any:
    """The forecast person held still at their pose at ``t_start`` (what the emergency plan is checked
    against)."""
    from app.prediction.forecast import HumanForecast
    from app.prediction.skeleton import HumanFrame

    joints, margin = forecast.pose_at(t_start)
    return HumanForecast.hold(
        HumanFrame(t_start, joints),
        margin_m=margin,
        growth_mps=forecast.growth_mps,
        max_margin_m=forecast.max_margin_m,
    )


def _warm_goals(planner: Any, queries: Sequence[Any]) -> None:
    """One untimed static plan per goal: fills the planner's per-goal heuristic cache."""
    seen: set[str] = set()
    for qr in queries:
        if qr.goal not in seen:
            seen.add(qr.goal)
            planner.plan(q_start=qr.q_start, t_start=qr.t_start, goal=qr.goal, forecast=None)


def _calls(planner: Any, qr: Any, timing: Any = None) -> dict[str, Callable[[], Any]]:
    """The timed call of every configuration on one query (the time-variant ones with the governor's model
    ``timing``: the SSM-aware timing of the runtime)."""
    common = {"q_start": qr.q_start, "t_start": qr.t_start, "goal": qr.goal, "deadline_s": DEADLINE_S}
    return {
        "plan": lambda: planner.plan(**common, forecast=qr.forecast, workers=1, timing=timing),
        "parallel_plan": lambda: planner.plan(**common, forecast=qr.forecast, workers=WORKERS, timing=timing),
        "static": lambda: planner.plan(**common, forecast=None, workers=1),
        "parallel_static": lambda: planner.plan(**common, forecast=None, workers=WORKERS),
        "emergency": lambda: planner.emergency(
            q_start=qr.q_start, t_start=qr.t_start, forecast=qr.forecast, horizon_s=HORIZON_S
        ),
    }


def _threads(planner: Any, queries: Sequence[Any]) -> dict[str, Any]:
    """Throughput of independent ``parallel_plan`` queries on one shared planner: in one thread, then in
    ``os.cpu_count()`` threads (the compiled kernels release the GIL; the search's Python bookkeeping holds
    it). Says whether threads would help a caller with several queries at once; one query's latency is not
    shortened by them."""
    from concurrent.futures import ThreadPoolExecutor

    n_threads = max(os.cpu_count() or 1, 2)
    timing = _governor_model(planner.config.ssm)
    calls = [_calls(planner, qr, timing)["parallel_plan"] for qr in queries]
    t0 = time.perf_counter()
    for call in calls:
        call()
    one = time.perf_counter() - t0
    with ThreadPoolExecutor(n_threads) as pool:
        t0 = time.perf_counter()
        list(pool.map(lambda call: call(), calls))
        many = time.perf_counter() - t0
    return {
        "threads": n_threads,
        "queries": len(calls),
        "queries_per_s_1_thread": round(len(calls) / one, 1),
        f"queries_per_s_{n_threads}_threads": round(len(calls) / many, 1),
        "speedup": round(one / many, 2),
    }


def _scaling(
    cell: Any, model: Any, queries: Sequence[Any], *, quick: bool, progress: bool
) -> tuple[dict[str, Any], dict[str, int | None]]:
    from app.planning.search import Planner

    scaling: dict[str, Any] = {}
    nodes: dict[str, int | None] = {}
    for name, n in SCALING.items():
        _log(progress, f"scaling roadmap {name} ...")
        got = _roadmap(cell, model, n, build=not quick)
        if got is None:
            scaling[name] = None
            nodes[name] = None
            continue
        planner = Planner(got[0], model, config=_planner_config())
        timing = _governor_model(planner.config.ssm)
        sub = queries[: (6 if quick else 20)]
        _warm_goals(planner, sub)
        runs = []
        for qr in sub:
            res, w, c = _timed(_calls(planner, qr, timing)["parallel_plan"])
            runs.append(_run_of(res, w, c))
        scaling[name] = successful_ms(runs)
        nodes[name] = got[0].num_nodes
    return scaling, nodes


def run(*, quick: bool, progress: bool) -> dict[str, Any]:
    """Run the benchmark; returns the JSON object described in the module docstring."""
    from app.config import load_workcell
    from app.planning.collision import CollisionModel
    from app.planning.scenarios import reference_queries
    from app.planning.search import Planner

    cell = load_workcell()
    model = CollisionModel(cell)
    _log(progress, "roadmap (default) ...")
    got = _roadmap(cell, model, None, build=True)
    assert got is not None
    rm, build_s, load_s = got
    t0 = time.perf_counter()
    planner = Planner(rm, model, config=_planner_config())
    init_s = time.perf_counter() - t0
    generous_planner = Planner(
        rm, model, config=dataclasses.replace(planner.config, max_expansions=GENEROUS_EXPANSIONS)
    )
    generous_deadline_s = 5.0 if quick else GENEROUS_DEADLINE_S
    ssm = planner.config.ssm
    timing = _governor_model(ssm)
    n_syn = 12 if quick else 60
    queries = reference_queries(cell, rm, n=n_syn, seed=7)
    if not quick and (CMU_DIR / "index.json").is_file():
        queries += reference_queries(cell, rm, n=20, seed=8, source="recorded", cmu_dir=CMU_DIR)
    _log(progress, f"{len(queries)} queries on {rm.num_nodes} nodes ...")
    _warm_goals(planner, queries)
    _warm_goals(generous_planner, queries)
    for call in _calls(planner, queries[0]).values():
        call()
    runs: dict[str, list[Run]] = {c: [] for c in CONFIGS}
    generous: list[bool | None] = []
    violations = 0
    checked = 0
    for i, qr in enumerate(queries):
        calls = _calls(planner, qr, timing)
        order = CONFIGS[i % len(CONFIGS) :] + CONFIGS[: i % len(CONFIGS)]
        results: dict[str, Any] = {}
        for name in order:
            res, w, c = _timed(calls[name])
            results[name] = res
            runs[name].append(_run_of(res, w, c))
        for name in ("plan", "parallel_plan"):
            if results[name].ok:
                executed = _as_executed(results[name], qr.forecast, model, timing)
                violations += count_violations(
                    executed,
                    qr.forecast,
                    model,
                    ssm,
                    hold_s=planner.config.goal_hold_s,
                    stopping=planner.config.stopping,
                    contact_only=planner.config.contact_only,
                    contact_speed_mps=planner.config.contact_speed_mps,
                    limits=(planner.q_min, planner.q_max),
                )
                checked += 1
        if results["plan"].ok or results["parallel_plan"].ok:
            generous.append(True)  # a verified plan exists; the generous search would add nothing
        else:
            res = generous_planner.plan(
                q_start=qr.q_start,
                t_start=qr.t_start,
                goal=qr.goal,
                forecast=qr.forecast,
                workers=1,
                deadline_s=generous_deadline_s,
                timing=timing,
            )
            undecided = reason_key(res.reason) == "deadline" or res.reason.startswith("no plan within")
            generous.append(True if res.ok else (None if undecided else False))
            if res.ok:
                violations += count_violations(
                    _as_executed(res, qr.forecast, model, timing),
                    qr.forecast,
                    model,
                    ssm,
                    hold_s=planner.config.goal_hold_s,
                    stopping=planner.config.stopping,
                    contact_only=planner.config.contact_only,
                    contact_speed_mps=planner.config.contact_speed_mps,
                    limits=(planner.q_min, planner.q_max),
                )
                checked += 1
        em = results["emergency"]
        if em.ok:
            joints, margin = qr.forecast.pose_at(qr.t_start)
            d_start = float(model.distance_to_human_paired(qr.q_start[None], joints[None])[0])
            from app.safety.ssm import forecast_clearance

            # an escape (the start already too close) follows its own rule: never closer than at the start
            if d_start >= float(forecast_clearance(0.0, margin, ssm, w_top_radps=0.0)):
                violations += count_violations(
                    em.trajectory,
                    _held(qr.forecast, qr.t_start),
                    model,
                    ssm,
                    hold_s=planner.config.emergency_hold_s,
                    stopping=planner.config.stopping,
                    contact_only=planner.config.contact_only,
                    contact_speed_mps=planner.config.contact_speed_mps,
                    limits=(planner.q_min, planner.q_max),
                )
                checked += 1
        if progress and (i + 1) % 10 == 0:
            _log(progress, f"  {i + 1}/{len(queries)}")
    _log(progress, "threads ...")
    threads = _threads(planner, queries[: (12 if quick else 60)])
    scaling, scaling_nodes = _scaling(cell, model, queries, quick=quick, progress=progress)
    kinds = [qr.source.split(":")[0] for qr in queries]
    by_source: dict[str, dict[str, Any]] = {}
    for kind in sorted(set(kinds)):
        idx = [i for i, k in enumerate(kinds) if k == kind]
        sub = summarise({c: [runs[c][i] for i in idx] for c in CONFIGS}, [generous[i] for i in idx])
        by_source[kind] = {"queries": len(idx)} | {
            k: sub[k]
            for k in (
                "success_rate",
                "success_rate_solvable",
                "solvable",
                "parallel_plan_ms",
                "plan_ms",
                "static_ms",
                "parallel_static_ms",
                "time_variant_over_static",
            )
        }
    return {
        "queries": len(queries),
        **summarise(runs, generous),
        "violations": violations,
        "trajectories_checked": checked,
        "by_source": by_source,
        "parallel_kind": PARALLEL_KIND,
        "threads": threads,
        "timing": "each query timed once per configuration, configurations interleaved per query",
        "ssm_timing": "on: the time-variant searches verify each plan at the timing the speed governor is "
        "predicted to give it (the runtime's default), and the 100 Hz check checks it at that timing",
        "clearance": {
            "t_reaction_s": planner.config.ssm.t_reaction_s,
            "stopping": {
                "decel_mps2": planner.config.stopping.decel_mps2,
                "joint_decel_radps2": list(planner.config.stopping.joint_decel_radps2),
                "delay_s": planner.config.stopping.delay_s,
            },
        },
        "workers": WORKERS,
        "deadline_s": DEADLINE_S,
        "generous": {"workers": 1, "max_expansions": GENEROUS_EXPANSIONS, "deadline_s": generous_deadline_s},
        "roadmap_nodes": rm.num_nodes,
        "roadmap_edges": rm.num_edges,
        "roadmap_build_s": round(build_s, 3),
        "roadmap_load_s": round(load_s, 4),
        "planner_init_s": round(init_s, 3),
        "scaling": scaling,
        "scaling_nodes": scaling_nodes,
        "quick": quick,
        "load_avg": round(os.getloadavg()[0], 2),
    }
