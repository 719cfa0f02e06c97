"""``hrc bench planning``: the time-variant planner on the reference scenario set.

Measured in one run, on the default work cell and its default roadmap (built and cached on first use):

* ``plan_ms``: sequential time-variant A* (``workers=1``) against the scenario's forecast person;
* ``parallel_plan_ms``: the batched parallel search (``workers`` states per step) on the same queries;
* ``static_ms``: plain A* over the same roadmap with no person (``forecast=None``, ``workers=1``);
* ``emergency_ms``: the emergency plan (person held, horizon ``F + D``) from each query's start;
* ``success_rate``: share of the queries for which the parallel search returned a verified plan
  (``sequential_success_rate`` likewise); every query has a compute budget of ``DEADLINE_S``. Some queries
  have no safe plan (the person reaches to the goal and stays near it); ``parallel_failures`` counts the
  reasons and ``parallel_plan_ms_successful`` / ``plan_ms_successful`` give the times of the queries that
  succeeded (extra keys: the headline ``p50``/``p95`` are over all queries, failures included);
* ``time_variant_over_static_p50``: the time-variant searches' median over the static search's median
  (wall clock and thread CPU time); ``by_source``: the figures per kind of person (``synthetic``: the
  seeded reaching operator; ``recorded``: CMU clips placed at the operator's side, reaching in);
* ``violations``: returned trajectories (sequential, parallel and emergency) that break the requirement in
  an independent check: sampled at 100 Hz, joint limits, and the surface distance (from
  :meth:`CollisionModel.distance_to_human_paired`) against
  :func:`app.safety.ssm.forecast_clearance` for the robot speed obtained by differentiating the
  trajectory's capsule points numerically. It must be 0.
* ``scaling``: p50 of the parallel plan time on roadmaps of about 1k, 4k and 16k nodes (built and cached on
  first use, which takes minutes; ``--quick`` reports only those already cached and ``null`` for the rest).

Times are wall-clock milliseconds (``p50``/``p95`` over the queries; each query is timed ``REPEATS`` times and
its median counts, so that a brief stall of a shared machine does not land in the p95); ``cpu_ms`` gives the
same statistics of the thread's CPU time, which the other processes of a busy shared machine disturb much
less. ``load_avg`` is the machine's 1-minute load average at the end of the run.
"""

from __future__ import annotations

import os
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

DEADLINE_S = 1.0
REPEATS = 3  # timed calls per query (``--quick``: 1); each query's time is their median
WORKERS = 32
HORIZON_S = 1.0 / 30.0 + 0.1  # F + D: one camera frame + the backup-plan deadline
SCALING = {"1k": 1000, "4k": 4000, "16k": 16000}
CMU_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "cmu_mocap"


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(msg, file=sys.stderr, flush=True)


def _stats(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p95": None}
    arr = np.asarray(values) * 1e3
    return {"p50": round(float(np.percentile(arr, 50)), 3), "p95": round(float(np.percentile(arr, 95)), 3)}


def count_violations(traj: Any, forecast: Any, model: Any, ssm: Any, *, hold_s: float) -> int:
    """1 if the trajectory breaks the limits or the separation anywhere on a 100 Hz grid, else 0."""
    from app.planning.kinematics import Q_MAX, Q_MIN
    from app.safety.ssm import forecast_clearance

    t = np.arange(traj.t_start, traj.t_end + hold_s + 1e-9, 0.01)
    q = traj.q(t)
    if np.any(q < Q_MIN - 1e-9) or np.any(q > Q_MAX + 1e-9):
        return 1
    eps = 1e-5
    a0, b0, _ = model.robot_capsules(traj.q(t - eps))
    a1, b1, _ = model.robot_capsules(traj.q(t + eps))
    v = np.maximum(np.linalg.norm(a1 - a0, axis=-1), np.linalg.norm(b1 - b0, axis=-1)).max(axis=1) / (2 * eps)
    joints, margins = forecast.poses_at(t)
    d = model.distance_to_human_paired(q, joints)
    return int(np.any(d < forecast_clearance(v, margins, ssm) - 1e-9))


def _timed(fn: Any, repeats: int = 1) -> tuple[Any, float, float]:
    """``fn()``'s result (its first call) and the median wall-clock and thread CPU time of ``repeats`` calls
    (the planner is deterministic; repeating a query and taking its median keeps the brief stalls of a
    shared machine out of the per-query time)."""
    out = None
    walls, cpus = [], []
    for i in range(max(repeats, 1)):
        c0 = time.thread_time()
        t0 = time.perf_counter()
        got = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.thread_time() - c0)
        if i == 0:
            out = got
    return out, float(np.median(walls)), float(np.median(cpus))


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
    planner = Planner(rm, model)
    init_s = time.perf_counter() - t0
    ssm = planner.config.ssm
    hold = planner.config.goal_hold_s
    n_syn = 12 if quick else 60
    queries = reference_queries(cell, rm, n=n_syn, seed=7)
    if not quick and (CMU_DIR / "index.json").is_file():
        queries += reference_queries(cell, rm, n=20, seed=8, source="recorded", cmu_dir=CMU_DIR)
    _log(progress, f"{len(queries)} queries on {rm.num_nodes} nodes ...")
    repeats = 1 if quick else REPEATS
    wall: dict[str, list[float]] = {"plan": [], "parallel": [], "static": [], "emergency": []}
    cpu: dict[str, list[float]] = {k: [] for k in wall}
    ok_seq = ok_par = ok_em = 0
    ok_wall: list[float] = []
    ok_wall_seq: list[float] = []
    ok_flags: dict[str, list[bool]] = {"plan": [], "parallel": []}
    reasons: dict[str, int] = {}
    violations = 0
    checked = 0
    expanded: dict[str, list[int]] = {"plan": [], "parallel": [], "static": []}
    for i, qr in enumerate(queries):
        common = {"q_start": qr.q_start, "t_start": qr.t_start, "goal": qr.goal}
        res, w, c = _timed(partial(planner.plan, **common, forecast=None, workers=1), repeats)
        wall["static"].append(w)
        cpu["static"].append(c)
        expanded["static"].append(res.expanded)
        for key, workers in (("plan", 1), ("parallel", WORKERS)):
            res, w, c = _timed(
                partial(planner.plan, **common, forecast=qr.forecast, workers=workers, deadline_s=DEADLINE_S),
                repeats,
            )
            wall[key].append(w)
            cpu[key].append(c)
            expanded[key].append(res.expanded)
            ok_flags[key].append(bool(res.ok))
            if key == "plan" and res.ok:
                ok_wall_seq.append(w)
            if key == "parallel":
                if res.ok:
                    ok_wall.append(w)
                else:
                    why = res.reason.split(":")[0].split(" from ")[0].split(" after ")[0]
                    reasons[why] = reasons.get(why, 0) + 1
            if res.ok:
                ok_seq += key == "plan"
                ok_par += key == "parallel"
                violations += count_violations(res.trajectory, qr.forecast, model, ssm, hold_s=hold)
                checked += 1
        res, w, c = _timed(
            partial(
                planner.emergency,
                q_start=qr.q_start,
                t_start=qr.t_start,
                forecast=qr.forecast,
                horizon_s=HORIZON_S,
            ),
            repeats,
        )
        wall["emergency"].append(w)
        cpu["emergency"].append(c)
        if res.ok:
            ok_em += 1
            joints, margin = qr.forecast.pose_at(qr.t_start)
            from app.prediction.forecast import HumanForecast

            held = HumanForecast(
                t0=qr.t_start,
                times=np.array([qr.t_start]),
                joints=joints[None],
                margins=np.array([margin]),
                growth_mps=qr.forecast.growth_mps,
                max_margin_m=qr.forecast.max_margin_m,
            )
            d_start = float(model.distance_to_human_paired(qr.q_start[None], joints[None])[0])
            from app.safety.ssm import forecast_clearance

            # an escape (the start already too close) follows its own rule: never closer than at the start
            if d_start >= float(forecast_clearance(0.0, margin, ssm)):
                violations += count_violations(
                    res.trajectory, held, model, ssm, hold_s=planner.config.emergency_hold_s
                )
                checked += 1
        if progress and (i + 1) % 10 == 0:
            _log(progress, f"  {i + 1}/{len(queries)}")
    scaling: dict[str, float | None] = {}
    scaling_nodes: dict[str, int | None] = {}
    for name, n in SCALING.items():
        _log(progress, f"scaling roadmap {name} ...")
        got_s = _roadmap(cell, model, n, build=not quick)
        if got_s is None:
            scaling[name] = None
            scaling_nodes[name] = None
            continue
        rm_s = got_s[0]
        pl_s = Planner(rm_s, model)
        times = []
        for qr in queries[: (6 if quick else 20)]:
            res, w, _ = _timed(
                partial(
                    pl_s.plan,
                    q_start=qr.q_start,
                    t_start=qr.t_start,
                    goal=qr.goal,
                    forecast=qr.forecast,
                    workers=WORKERS,
                    deadline_s=DEADLINE_S,
                )
            )
            times.append(w)
        scaling[name] = _stats(times)["p50"]
        scaling_nodes[name] = rm_s.num_nodes
    n = len(queries)
    by_source: dict[str, dict[str, Any]] = {}
    kinds = [qr.source.split(":")[0] for qr in queries]
    for kind in sorted(set(kinds)):
        idx = [i for i, k in enumerate(kinds) if k == kind]
        by_source[kind] = {
            "queries": len(idx),
            "success_rate": round(sum(ok_flags["parallel"][i] for i in idx) / len(idx), 4),
            "parallel_plan_ms": _stats([wall["parallel"][i] for i in idx]),
            "plan_ms": _stats([wall["plan"][i] for i in idx]),
            "static_ms": _stats([wall["static"][i] for i in idx]),
        }

    def ratio(a: str, b: str, source: dict[str, list[float]]) -> float | None:
        num, den = np.median(source[a]) if source[a] else None, np.median(source[b]) if source[b] else None
        return round(float(num / den), 2) if num is not None and den else None

    out = {
        "queries": n,
        "success_rate": round(ok_par / n, 4) if n else None,
        "sequential_success_rate": round(ok_seq / n, 4) if n else None,
        "emergency_success_rate": round(ok_em / n, 4) if n else None,
        "violations": violations,
        "trajectories_checked": checked,
        "plan_ms": _stats(wall["plan"]),
        "parallel_plan_ms": _stats(wall["parallel"]),
        "parallel_plan_ms_successful": _stats(ok_wall),
        "plan_ms_successful": _stats(ok_wall_seq),
        "parallel_failures": reasons,
        "emergency_ms": _stats(wall["emergency"]),
        "static_ms": _stats(wall["static"]),
        "cpu_ms": {k: _stats(v) for k, v in cpu.items()},
        "time_variant_over_static_p50": {
            "sequential": ratio("plan", "static", wall),
            "parallel": ratio("parallel", "static", wall),
            "sequential_cpu": ratio("plan", "static", cpu),
            "parallel_cpu": ratio("parallel", "static", cpu),
        },
        "by_source": by_source,
        "expanded_p50": {k: float(np.median(v)) for k, v in expanded.items()},
        "workers": WORKERS,
        "deadline_s": DEADLINE_S,
        "repeats": repeats,
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
    return out
