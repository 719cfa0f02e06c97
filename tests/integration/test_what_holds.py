"""``scripts/what_holds.py``: the time by what limits the robot, from the governor's own read-out."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, str(ROOT / "scripts" / "what_holds.py"), "--seed", "11", *args]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)


def test_the_modes_cover_the_trial_once() -> None:
    out = _run("--duration", "6")
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout)
    assert got["seed"] == 11 and got["method"] == "proactive" and got["duration_s"] == 6.0
    modes = got["by_mode"]
    assert modes and {m["what"].split(" ")[0].split(":")[0] for m in modes} <= {
        "free",
        "ssm",
        "pfl",
        "stopped",
    }
    # sampled every 0.1 s from the first tick: the samples cover the trial once
    assert abs(sum(m["s"] for m in modes) - 6.0) <= 0.25
    assert all(0.0 <= m["scale"] <= 1.0 and 0.0 < m["share"] <= 1.0 for m in modes)
    pairs = got["by_part_and_goal"]
    assert 0 < len(pairs) < 8  # a short trial: every (part, goal) pair is listed, and they cover it too
    assert abs(sum(p["s"] for p in pairs) - sum(m["s"] for m in modes)) <= 0.25


def test_a_sampling_period_of_zero_is_refused() -> None:
    out = _run("--every", "0")
    assert out.returncode == 2 and "--every must be > 0" in out.stderr
