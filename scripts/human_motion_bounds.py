#!/usr/bin/env python
"""The person's worst case for the speed governor, measured on recorded motion: the 99th percentile of joint
speeds and of joint accelerations in a folder of clips (``.npz``: ``positions`` (T, J, 3) in m, ``fps``).

    .venv/bin/python scripts/human_motion_bounds.py ../shared/data/cmu_mocap/train

Speeds are frame-to-frame; accelerations are the change of a joint's velocity (measured over the
supervisor's 0.1 s speed window) over 0.1, 0.2 and 0.3 s, divided by that time. Frames in which any joint
moves faster than 5 m/s (a tracking jump, an intrusion for the runtime) are left out. Use the training or
tuning clips, never the ones results are reported on. Prints JSON.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

JUMP_MPS = 5.0
WINDOW_S = 0.1


def bounds(folder: Path) -> dict:
    files = sorted(folder.glob("*.npz"))
    if not files:
        raise SystemExit(f"no .npz clips in {folder}")
    speeds: list[np.ndarray] = []
    accels: dict[float, list[np.ndarray]] = {0.1: [], 0.2: [], 0.3: []}
    frames = 0
    for f in files:
        with np.load(f) as d:
            p = np.asarray(d["positions"], dtype=np.float64)
            fps = float(d["fps"])
        frames += p.shape[0]
        sp = np.linalg.norm(p[1:] - p[:-1], axis=-1) * fps  # (T - 1, J)
        jump = sp.max(axis=1) > JUMP_MPS
        speeds.append(sp[~jump].ravel())
        k = max(round(WINDOW_S * fps), 1)
        vw = (p[k:] - p[:-k]) * (fps / k)  # (T - k, J, 3)
        bad = np.array([jump[i : i + k].any() for i in range(p.shape[0] - k)])
        for lag, out in accels.items():
            n = max(round(lag * fps), 1)
            if vw.shape[0] <= n:
                continue
            dv = np.linalg.norm(vw[n:] - vw[:-n], axis=-1) * (fps / n)
            out.append(dv[~(bad[n:] | bad[:-n])].ravel())
    s = np.concatenate(speeds)
    res = {
        "clips": len(files),
        "frames": frames,
        "speed_mps": {"p99": float(np.percentile(s, 99)), "p99.9": float(np.percentile(s, 99.9))},
    }
    for lag, out in accels.items():
        a = np.concatenate(out)
        pct = {q: float(np.percentile(a, float(q[1:]))) for q in ("p95", "p99")}
        res[f"accel_mps2_over_{lag:.1f}s"] = pct
    return res


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    print(json.dumps(bounds(Path(sys.argv[1])), indent=2))
