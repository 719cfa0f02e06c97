"""Run ``hrc simulate`` for a range of seeds and both methods in parallel and print the safety table:
one row per seed and method with the ground-truth monitor's verdict, as JSON lines and a Markdown table.

    .venv/bin/python scripts/seed_table.py --seeds 1-10 --duration 300 [--source replay --clip PATH]
        [--forecast oracle] [--workers 2] [--out table.jsonl]

Uses the settings of the environment (``HRC_*``), like ``hrc simulate``. Report seeds outside 1000-1999
(those are for tuning).
"""

from __future__ import annotations

import argparse
import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

COLUMNS = (
    "completed_tasks",
    "stop_replans",
    "stop_replans_moving",
    "violations",
    "violations_person_faster",
    "contacts",
    "harmful_contacts",
    "exceedance_s",
    "max_approach_mps",
    "violations_measured_vh",
    "intrusions",
    "min_separation_moving_m",
    "mean_speed_scale",
    "time_stopped_s",
)


def _run(args: tuple[int, str, float, str, str | None, str]) -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    seed, method, duration, source, clip, forecast = args
    from app.config import Settings
    from app.control.headless import run_headless_trial

    res = run_headless_trial(
        settings=Settings(),
        method=method,
        duration_s=duration,
        seed=seed,
        source=source,
        clip=clip,
        forecast=forecast,
    )
    return {"seed": seed, "source": source, "clip": clip, "forecast": forecast, **res.summary()}


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--methods", default="proactive,reactive")
    ap.add_argument("--source", default="sim", choices=("sim", "replay"))
    ap.add_argument("--clip", action="append", default=None, help="replay clip(s); one row per clip")
    ap.add_argument(
        "--forecast",
        default="model",
        choices=("model", "oracle"),
        help="proactive's forecast: the motion predictor, or the simulated operator's own future (sim only)",
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    clips = a.clip or [None]
    jobs = [
        (s, m, a.duration, a.source, c, a.forecast)
        for c in clips
        for s in _seeds(a.seeds)
        for m in a.methods.split(",")
    ]
    rows = []
    with ProcessPoolExecutor(a.workers) as pool:
        for row in pool.map(_run, jobs):
            rows.append(row)
            line = json.dumps(row)
            print(line, flush=True)
            if a.out is not None:
                with a.out.open("a") as fp:
                    fp.write(line + "\n")
    key = "clip" if a.source == "replay" else "seed"
    print(f"\n| {key} | method | " + " | ".join(COLUMNS) + " |")
    print("|---|---|" + "---|" * len(COLUMNS))
    for r in rows:
        cells = []
        for c in COLUMNS:
            v = r.get(c)
            cells.append("-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v)))
        name = Path(r["clip"]).stem if key == "clip" else r["seed"]
        print(f"| {name} | {r['method']} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
