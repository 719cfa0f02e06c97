"""What holds the robot in a headless trial: the time the binding robot part spends in each mode of the
speed governor's read-out (:func:`app.safety.modes.part_modes`: free, SSM, PFL at a body region, stopped)
and which body region it keeps ``S_p`` from, with the mean path scale in each, and for the most common
(part, goal) pairs. Prints one JSON object.

    .venv/bin/python scripts/what_holds.py --seed 1000 --method proactive [--duration 300] [--every 0.1]

Uses the settings of the environment (``HRC_*``), like ``hrc simulate``; backup plans are charged a fixed
compute time (``--compute-s``), so a run is deterministic. Sampled every ``--every`` seconds of the trial
(the read-out costs about as much as a servo tick's governor, so not at every tick). Report seeds outside
1000-1999 (those are for tuning).
"""

from __future__ import annotations

import argparse
import json
import os
from collections import defaultdict
from typing import Any


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--method", default="proactive", choices=("proactive", "reactive"))
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--every", type=float, default=0.1, help="sampling period (s of trial time)")
    ap.add_argument("--compute-s", type=float, default=0.012, help="compute time charged per backup plan")
    ap.add_argument("--top", type=int, default=8, help="how many (part, goal) pairs to list")
    a = ap.parse_args()
    if not a.every > 0:
        ap.error(f"--every must be > 0, got {a.every}")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from app.config import Settings
    from app.control.headless import run_headless_trial
    from app.planning.collision import ROBOT_LINKS
    from app.safety.modes import binding_part

    by_mode: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])  # label -> [time, time x scale]
    by_part: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    next_t = [0.0]

    def observe(t: float, engine: Any) -> None:
        if t + 1e-9 < next_t[0]:
            return
        next_t[0] += a.every
        st = engine.supervisor.status()
        if not st.modes:
            return
        i = binding_part(st.modes)
        if i < 0:
            return
        m = st.modes[i]
        label = m.label if m.mode in ("free", "pfl") else f"{m.mode} from {m.held_from or '-'}"
        for table, key in ((by_mode, label), (by_part, f"{ROBOT_LINKS[i]} to {engine.task.current.goal}")):
            table[key][0] += a.every
            table[key][1] += a.every * st.scale

    res = run_headless_trial(
        settings=Settings(),
        method=a.method,
        duration_s=a.duration,
        seed=a.seed,
        fixed_compute_s=a.compute_s,
        observer=observe,
    )
    summary = res.summary()

    def rows(table: dict[str, list[float]], n: int | None = None) -> list[dict[str, Any]]:
        got = sorted(table.items(), key=lambda kv: -kv[1][0])[:n]
        return [
            {"what": k, "s": round(tm, 1), "share": round(tm / a.duration, 3), "scale": round(sc / tm, 3)}
            for k, (tm, sc) in got
            if tm > 0
        ]

    print(
        json.dumps(
            {
                "seed": a.seed,
                "method": a.method,
                "duration_s": a.duration,
                "completed_tasks": summary["completed_tasks"],
                "mean_speed_scale": round(summary["mean_speed_scale"], 3),
                "by_mode": rows(by_mode),
                "by_part_and_goal": rows(by_part, a.top),
            }
        )
    )


if __name__ == "__main__":
    main()
