"""Small geometry helpers for the viser scene: unit meshes and segment-to-instance transforms.

Pure numpy; no viser import, so the maths is tested on its own.
"""

from __future__ import annotations

import numpy as np


def unit_cylinder(*, segments: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder of radius 1 along z from z = -0.5 to z = +0.5.

    Returns:
        ``(vertices (V, 3) float32, faces (F, 3) uint32)``, faces wound counter-clockwise seen from outside.
    """
    if segments < 3:
        raise ValueError(f"a cylinder needs at least 3 segments, got {segments}")
    ang = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    bottom = np.concatenate([ring, np.full((segments, 1), -0.5)], axis=1)
    top = np.concatenate([ring, np.full((segments, 1), 0.5)], axis=1)
    centers = np.array([[0.0, 0.0, -0.5], [0.0, 0.0, 0.5]])
    vertices = np.concatenate([bottom, top, centers], axis=0)
    i = np.arange(segments)
    j = (i + 1) % segments
    side_a = np.stack([i, j, segments + j], axis=1)
    side_b = np.stack([i, segments + j, segments + i], axis=1)
    cb, ct = 2 * segments, 2 * segments + 1
    cap_bottom = np.stack([np.full(segments, cb), j, i], axis=1)
    cap_top = np.stack([np.full(segments, ct), segments + i, segments + j], axis=1)
    faces = np.concatenate([side_a, side_b, cap_bottom, cap_top], axis=0)
    return vertices.astype(np.float32), faces.astype(np.uint32)


def unit_sphere(*, rings: int = 8, sectors: int = 14) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 1 centred at the origin.

    Returns:
        ``(vertices (V, 3) float32, faces (F, 3) uint32)``.
    """
    if rings < 2 or sectors < 3:
        raise ValueError(f"a sphere needs rings >= 2 and sectors >= 3, got {rings}, {sectors}")
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]  # polar angles of the inner rings
    phi = np.linspace(0.0, 2.0 * np.pi, sectors, endpoint=False)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring_xyz = np.stack(
        [st * np.cos(phi)[None], st * np.sin(phi)[None], np.broadcast_to(ct, (rings - 1, sectors))], axis=-1
    ).reshape(-1, 3)
    north, south = np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -1.0]])
    vertices = np.concatenate([ring_xyz, north, south], axis=0)
    n_idx, s_idx = len(ring_xyz), len(ring_xyz) + 1
    faces = []
    for s in range(sectors):
        s1 = (s + 1) % sectors
        faces.append((n_idx, s, s1))
        last = (rings - 2) * sectors
        faces.append((s_idx, last + s1, last + s))
        for r in range(rings - 2):
            a, b = r * sectors + s, r * sectors + s1
            c, d = (r + 1) * sectors + s, (r + 1) * sectors + s1
            faces.append((a, c, d))
            faces.append((a, d, b))
    return vertices.astype(np.float32), np.asarray(faces, dtype=np.uint32)


def quat_z_to(direction: np.ndarray) -> np.ndarray:
    """Quaternions (wxyz) of the shortest rotations that take +z onto each direction.

    Args:
        direction: Directions (N, 3); they need not be unit length. A zero direction gives the identity.

    Returns:
        Unit quaternions (N, 4) in (w, x, y, z) order.
    """
    d = np.asarray(direction, dtype=np.float64)
    assert d.ndim == 2 and d.shape[1] == 3, f"direction must be (N, 3), got {d.shape}"
    n = np.linalg.norm(d, axis=1)
    u = np.zeros_like(d)
    ok = n > 1e-12
    u[ok] = d[ok] / n[ok, None]
    u[~ok] = (0.0, 0.0, 1.0)
    # q = (1 + z.u, z x u), normalised; z x u = (-u_y, u_x, 0). Near -z, 1 + u_z cancels: it is computed as
    # (u_x^2 + u_y^2) / (1 - u_z) there, so that a direction a hair off -z keeps its own axis.
    s2 = u[:, 0] ** 2 + u[:, 1] ** 2
    w = np.where(u[:, 2] >= 0.0, 1.0 + u[:, 2], s2 / (1.0 - np.minimum(u[:, 2], 0.0)))
    q = np.stack([w, -u[:, 1], u[:, 0], np.zeros(len(u))], axis=1)
    opposite = (s2 == 0.0) & (u[:, 2] < 0.0)  # u == -z: rotate by pi about x
    q[opposite] = (0.0, 1.0, 0.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def segment_instances(
    a: np.ndarray, b: np.ndarray, radius: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Instance transforms that stretch :func:`unit_cylinder` onto the segments ``a[i] -> b[i]``.

    Args:
        a: Segment start points (N, 3), metres, world frame.
        b: Segment end points (N, 3).
        radius: Radius per segment (N,) or one radius for all (m).

    Returns:
        ``(positions (N, 3), wxyzs (N, 4), scales (N, 3))``: the segment midpoints, the rotations of +z onto
        the segments, and per-axis scales ``(r, r, length)``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    assert a.shape == b.shape and a.ndim == 2 and a.shape[1] == 3, f"a, b must be (N, 3), got {a.shape}"
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (a.shape[0],))
    d = b - a
    length = np.linalg.norm(d, axis=1)
    scales = np.stack([r, r, length], axis=1)
    return (a + b) / 2.0, quat_z_to(d), scales
