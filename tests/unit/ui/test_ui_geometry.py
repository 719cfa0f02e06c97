"""Unit meshes and segment instances of the viser scene."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from app.ui._geometry import quat_z_to, segment_instances, unit_cylinder, unit_sphere


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate v (3,) by the unit quaternion q (w, x, y, z)."""
    w, u = q[0], q[1:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _euler_characteristic(vertices: np.ndarray, faces: np.ndarray) -> int:
    edges = {tuple(sorted(e)) for f in faces for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    return len(vertices) - len(edges) + len(faces)


def test_unit_cylinder_is_closed_and_unit_sized() -> None:
    v, f = unit_cylinder(segments=12)
    assert v.dtype == np.float32 and f.dtype == np.uint32
    assert np.allclose(v[:, 2].min(), -0.5) and np.allclose(v[:, 2].max(), 0.5)
    assert np.allclose(np.linalg.norm(v[:24, :2], axis=1), 1.0)
    assert _euler_characteristic(v, f) == 2  # a closed surface of genus 0
    assert f.max() < len(v)


def test_unit_cylinder_faces_point_outwards() -> None:
    v, f = unit_cylinder(segments=10)
    tri = v[f].astype(np.float64)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centroids = tri.mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normals, centroids) > 0)


def test_unit_sphere_is_closed_with_radius_one() -> None:
    v, f = unit_sphere(rings=6, sectors=9)
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-6)
    assert _euler_characteristic(v, f) == 2
    tri = v[f].astype(np.float64)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.einsum("ij,ij->i", normals, tri.mean(axis=1)) > 0)


def test_mesh_arguments_are_checked() -> None:
    with pytest.raises(ValueError, match="at least 3 segments"):
        unit_cylinder(segments=2)
    with pytest.raises(ValueError, match="rings >= 2"):
        unit_sphere(rings=1)


def test_quat_special_cases() -> None:
    q = quat_z_to(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    assert np.allclose(q[0], [1, 0, 0, 0])
    assert np.allclose(_rotate(q[1], np.array([0.0, 0.0, 1.0])), [0, 0, -1])
    assert np.allclose(q[2], [1, 0, 0, 0])  # zero direction: identity
    assert np.allclose(_rotate(q[3], np.array([0.0, 0.0, 1.0])), [1, 0, 0])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-5, 5, allow_nan=False), min_size=3, max_size=3))
@example([0.0, 0.0001, -3.0])  # a hair off -z: once taken for -z itself (1 + u_z cancelled)
@example([1e-9, 0.0, -1.0])
def test_quat_takes_z_onto_direction(d: list[float]) -> None:
    d_arr = np.asarray(d)
    n = np.linalg.norm(d_arr)
    q = quat_z_to(d_arr[None])[0]
    assert np.isclose(np.linalg.norm(q), 1.0)
    if n > 1e-9:
        assert np.allclose(_rotate(q, np.array([0.0, 0.0, 1.0])), d_arr / n, atol=1e-6)


def test_segment_instances_map_the_unit_cylinder_onto_segments() -> None:
    a = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    b = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 3.0]])
    pos, wxyz, scale = segment_instances(a, b, np.array([0.1, 0.2]))
    assert np.allclose(pos, (a + b) / 2)
    assert np.allclose(scale, [[0.1, 0.1, 1.0], [0.2, 0.2, 2.0]])
    for k in range(2):
        # The cylinder's end caps (0, 0, +-0.5), scaled and rotated, land on the segment ends.
        top = pos[k] + _rotate(wxyz[k], scale[k] * np.array([0.0, 0.0, 0.5]))
        bottom = pos[k] + _rotate(wxyz[k], scale[k] * np.array([0.0, 0.0, -0.5]))
        assert np.allclose(top, b[k]) and np.allclose(bottom, a[k])
