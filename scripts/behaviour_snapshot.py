#!/usr/bin/env python
"""Record what the planner and the trial engine *do*, to prove that a restructuring changed nothing.

``record OUT.json`` plans every query of ``hrc bench planning`` (the sequential, parallel, static and
emergency searches; the synthetic queries, and the recorded ones when ``../shared`` has the CMU clips)
and runs ``hrc simulate`` for both methods on seeds 1 and 2 for 120 s. It stores the planned node sequences,
knot times and joint positions of every query, and every trial's metrics without the wall-clock ones
(compute times, ``sim_speedup``), plus a digest of its event log.

``compare A.json B.json`` prints what differs (exit 1) or ``identical`` (exit 0). Floats are compared
exactly: the point is to show that nothing moved.

The trials charge a fixed compute time per backup plan (``fixed_compute_s``) instead of the measured one,
so that the result does not depend on how busy the machine is; everything else is the default
``hrc simulate``.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

WALL_CLOCK_KEYS = {"avg_planning_time_s", "sim_speedup", "wall_s"}
ROOT = Path(__file__).resolve().parents[1]
CMU_DIR = ROOT.parent / "shared" / "data" / "cmu_mocap"
sys.path.insert(0, str(ROOT))  # the checkout this script lives in, not the one the venv was installed from


def _plan_record(res: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"ok": bool(res.ok), "reason": res.reason.split(" after ")[0]}
    if res.plan is not None:
        out["nodes"] = [int(n) for n in res.plan.nodes]
        out["times"] = [float(t) for t in res.plan.times]
        out["q"] = np.round(np.asarray(res.plan.q), 12).tolist()
    return out


def record_plans() -> list[dict[str, Any]]:
    from app.bench.planning import HORIZON_S, WORKERS
    from app.config import load_workcell
    from app.planning.collision import CollisionModel
    from app.planning.roadmap import load_or_build_roadmap
    from app.planning.scenarios import reference_queries
    from app.planning.search import Planner

    cell = load_workcell()
    model = CollisionModel(cell)
    rm = load_or_build_roadmap(cell, collision=model)
    planner = Planner(rm, model)
    queries = reference_queries(cell, rm, n=60, seed=7)
    if (CMU_DIR / "index.json").is_file():
        queries += reference_queries(cell, rm, n=20, seed=8, source="recorded", cmu_dir=CMU_DIR)
    out = []
    for qr in queries:
        common = {"q_start": qr.q_start, "t_start": qr.t_start, "goal": qr.goal}
        rec = {
            "static": _plan_record(planner.plan(**common, forecast=None, workers=1)),
            # no compute deadline: the result must not depend on the machine's load
            "plan": _plan_record(planner.plan(**common, forecast=qr.forecast, workers=1)),
            "parallel": _plan_record(planner.plan(**common, forecast=qr.forecast, workers=WORKERS)),
            "emergency": _plan_record(
                planner.emergency(
                    q_start=qr.q_start, t_start=qr.t_start, forecast=qr.forecast, horizon_s=HORIZON_S
                )
            ),
        }
        out.append(rec)
    return out


def record_trials(duration_s: float) -> dict[str, Any]:
    from app.config import Settings
    from app.control.headless import run_headless_trial

    out: dict[str, Any] = {}
    for method in ("proactive", "reactive"):
        for seed in (1, 2):
            res = run_headless_trial(
                settings=Settings(),
                method=method,  # type: ignore[arg-type]
                duration_s=duration_s,
                seed=seed,
                fixed_compute_s=0.005,
            )
            metrics = {k: v for k, v in res.summary().items() if k not in WALL_CLOCK_KEYS}
            events = json.dumps([repr(e) for e in res.events], sort_keys=True).encode()
            metrics["events_sha256"] = hashlib.sha256(events).hexdigest()
            metrics["events"] = len(res.events)
            out[f"{method}-{seed}"] = metrics
    return out


def _diff(a: Any, b: Any, path: str, diffs: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                diffs.append(f"{path}.{k}: only in {'B' if k not in a else 'A'}")
            else:
                _diff(a[k], b[k], f"{path}.{k}", diffs)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            diffs.append(f"{path}: length {len(a)} != {len(b)}")
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            _diff(x, y, f"{path}[{i}]", diffs)
    elif a != b:
        diffs.append(f"{path}: {a!r} != {b!r}")


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "record":
        import torch

        torch.set_num_threads(1)
        snap = {"plans": record_plans(), "trials": record_trials(120.0)}
        Path(argv[1]).write_text(json.dumps(snap))
        n_ok = sum(r["parallel"]["ok"] for r in snap["plans"])
        print(f"recorded {len(snap['plans'])} queries ({n_ok} parallel plans), {len(snap['trials'])} trials")
        return 0
    if len(argv) == 3 and argv[0] == "compare":
        a, b = (json.loads(Path(p).read_text()) for p in argv[1:])
        diffs: list[str] = []
        _diff(a, b, "", diffs)
        if not diffs:
            print(f"identical: {len(a['plans'])} queries x 4 searches, {len(a['trials'])} trials")
            return 0
        print(f"{len(diffs)} differences:")
        print("\n".join(diffs[:200]))
        return 1
    print(__doc__, file=sys.stderr)
    print("usage: behaviour_snapshot.py record OUT.json | compare A.json B.json", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
