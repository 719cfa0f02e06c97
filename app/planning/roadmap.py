"""The static roadmap: TCP positions (tool pointing down), all their IK branches, statically free edges.

Paper, section II-A: the graph is built once from deterministic samples of end-effector positions with a fixed
tool orientation (6 DoF reduced to 3), avoiding static obstacles; the time-variant search then runs over it.
Here:

- **Nodes** are a Halton sequence of TCP positions in the reachable part of the work cell (a box above the
  table, clipped to the arm's reach) plus the task poses of the cell: ``home``, the conveyor ``pickup``, the
  drop stations (``A`` ... ``D`` in the default cell) and an approach pose ``<name>_approach`` above each of
  the latter (``cell.approach_height_m`` higher; a drop station's ``cell.approach_retreat_m`` back from the
  person). A node is kept when at least one of its 8 IK branches is within the joint limits, free of the
  static scene (with ``static_margin_m``) and free of self-collision; every such branch is stored.
- **Edges** join each node to its ``k`` nearest neighbours within ``radius_m``. An edge is kept when, for at
  least one branch ``b`` valid at both ends, the straight joint-space move between the two branch-``b``
  configurations (the shorter way round for every joint, as :func:`app.planning.kinematics.align_branches`
  picks it) is statically free at every interpolated configuration (at most ``check_step_rad`` apart in
  every joint). The bit ``b`` of ``edge_branches`` records which branches passed.
- The roadmap is **cached** on disk (npz) under a key that hashes the work cell's fingerprint, the roadmap
  settings and a format version; a changed cell or setting builds a new one, and a corrupt cache file is
  rebuilt with a warning.

A roadmap is immutable (its arrays are read-only) and is shared by concurrent searches: a search keeps all
its state in its own arrays.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from app.config import WorkCell
    from app.planning.collision import CollisionModel

logger = logging.getLogger(__name__)

#: Bumped whenever the build or the file layout changes, so old caches are not reused.
ROADMAP_FORMAT_VERSION = 1
NUM_BRANCHES = 8


class RoadmapError(ValueError):
    """A roadmap is malformed, or a goal name/index does not exist in it."""


@dataclass(frozen=True)
class Roadmap:
    """Nodes, IK branches and edges (CSR) of the static roadmap.

    Attributes:
        nodes: TCP positions (N, 3) in the world frame (m); the tool points down (yaw ``yaw``).
        ik: IK branches (N, 8, 6) in rad (entries of invalid branches are 0), every angle as IK returns it,
            in [-pi, pi]. A family of branches can therefore be split at +-pi (in the default cell the base
            angle runs from 1.69 at the pickup to 3.10 at C and -2.81 at D); edges are checked, and the
            search moves, between 2 pi-equivalents next to each other within the joint limits
            (:func:`app.planning.kinematics.align_branches`), so plans turn the short way across the split.
        valid: Which branches are usable (N, 8): within limits, statically free, no self-collision.
        indptr: CSR row pointers (N + 1,): the neighbours of node ``u`` are
            ``indices[indptr[u]:indptr[u + 1]]``. Edges are stored in both directions.
        indices: CSR column indices (E,), int64.
        edge_branches: (E,) uint8 bit mask: bit ``b`` set when the straight joint move between the two
            branch-``b`` configurations is statically free.
        station_nodes: Task pose name -> node index (``home``, ``pickup``, drop stations,
            ``<name>_approach``).
        yaw: Tool yaw about world z (rad) used for every node.
        key: The cache key the roadmap was built for ("" for hand-built ones).
        build_s: Seconds the build took (0 for hand-built ones).
    """

    nodes: np.ndarray
    ik: np.ndarray
    valid: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    edge_branches: np.ndarray
    station_nodes: dict[str, int] = field(default_factory=dict)
    yaw: float = 0.0
    key: str = ""
    build_s: float = 0.0

    def __post_init__(self) -> None:
        nodes = np.asarray(self.nodes, dtype=np.float64)
        N = nodes.shape[0] if nodes.ndim == 2 else -1
        if nodes.shape != (N, 3) or N < 1:
            raise RoadmapError(f"Roadmap.nodes must have shape (N, 3), N >= 1, got {nodes.shape}")
        ik = np.asarray(self.ik, dtype=np.float64)
        valid = np.asarray(self.valid, dtype=bool)
        indptr = np.asarray(self.indptr, dtype=np.int64)
        indices = np.asarray(self.indices, dtype=np.int64)
        edge_branches = np.asarray(self.edge_branches, dtype=np.uint8)
        if ik.shape != (N, NUM_BRANCHES, 6) or valid.shape != (N, NUM_BRANCHES):
            raise RoadmapError(f"Roadmap.ik/valid must be ({N}, 8, 6)/({N}, 8), got {ik.shape}/{valid.shape}")
        if indptr.shape != (N + 1,) or indptr[0] != 0 or np.any(np.diff(indptr) < 0):
            raise RoadmapError(f"Roadmap.indptr must be a CSR pointer array of shape ({N + 1},)")
        E = int(indptr[-1])
        if indices.shape != (E,) or edge_branches.shape != (E,):
            raise RoadmapError(f"Roadmap.indices/edge_branches must have shape ({E},)")
        if E and (indices.min() < 0 or indices.max() >= N):
            raise RoadmapError("Roadmap.indices out of range")
        for name, idx in self.station_nodes.items():
            if not 0 <= idx < N:
                raise RoadmapError(f"station {name!r} refers to node {idx}, outside 0..{N - 1}")
        ik = np.where(valid[..., None], np.nan_to_num(ik), 0.0)
        for a in (nodes, ik, valid, indptr, indices, edge_branches):
            a.setflags(write=False)
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "ik", ik)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "indptr", indptr)
        object.__setattr__(self, "indices", indices)
        object.__setattr__(self, "edge_branches", edge_branches)
        object.__setattr__(self, "station_nodes", dict(self.station_nodes))

    @classmethod
    def from_arrays(
        cls,
        nodes: np.ndarray,
        ik: np.ndarray,
        valid: np.ndarray,
        edges: np.ndarray,
        *,
        edge_branches: np.ndarray | None = None,
        station_nodes: dict[str, int] | None = None,
        yaw: float = 0.0,
        key: str = "",
        build_s: float = 0.0,
    ) -> Roadmap:
        """A roadmap from an undirected edge list (for hand-built roadmaps and the builder).

        Args:
            nodes: (N, 3) TCP positions. ik: (N, 8, 6) branches. valid: (N, 8) mask.
            edges: (E, 2) undirected node pairs (each stored once; both directions are created).
            edge_branches: (E,) uint8 masks of statically free branches per edge; default: every branch
                valid at both ends.
            station_nodes: Task pose name -> node index.
        """
        nodes = np.asarray(nodes, dtype=np.float64)
        valid = np.asarray(valid, dtype=bool)
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        N = nodes.shape[0]
        if edges.size and (edges.min() < 0 or edges.max() >= N):
            raise RoadmapError(f"edge endpoints must be in 0..{N - 1}")
        if edge_branches is None:
            both = valid[edges[:, 0]] & valid[edges[:, 1]]
            edge_branches = np.packbits(both, axis=1, bitorder="little")[:, 0]
        edge_branches = np.asarray(edge_branches, dtype=np.uint8).reshape(-1)
        if edge_branches.shape != (edges.shape[0],):
            raise RoadmapError(f"edge_branches must have shape ({edges.shape[0]},)")
        src = np.concatenate([edges[:, 0], edges[:, 1]])
        dst = np.concatenate([edges[:, 1], edges[:, 0]])
        eb = np.concatenate([edge_branches, edge_branches])
        order = np.lexsort((dst, src))
        src, dst, eb = src[order], dst[order], eb[order]
        indptr = np.zeros(N + 1, dtype=np.int64)
        np.add.at(indptr, src + 1, 1)
        indptr = np.cumsum(indptr)
        return cls(
            nodes=nodes,
            ik=ik,
            valid=valid,
            indptr=indptr,
            indices=dst,
            edge_branches=eb,
            station_nodes=dict(station_nodes or {}),
            yaw=yaw,
            key=key,
            build_s=build_s,
        )

    @property
    def num_nodes(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def num_edges(self) -> int:
        """Number of undirected edges."""
        return int(self.indices.shape[0] // 2)

    def neighbors(self, u: int) -> np.ndarray:
        """Neighbour node indices of node ``u``."""
        return self.indices[self.indptr[u] : self.indptr[u + 1]]

    def edge_list(self) -> np.ndarray:
        """Undirected edges (E, 2) with ``u < v`` (for drawing)."""
        src = np.repeat(np.arange(self.num_nodes), np.diff(self.indptr))
        keep = src < self.indices
        return np.stack([src[keep], self.indices[keep]], axis=1)

    def resolve(self, goal: str | int) -> int:
        """The node index of a goal given as a station name or a node index.

        Raises:
            RoadmapError: unknown station name or index out of range (the message lists the stations).
        """
        if isinstance(goal, str):
            if goal not in self.station_nodes:
                names = ", ".join(sorted(self.station_nodes)) or "none"
                raise RoadmapError(f"unknown station {goal!r}; this roadmap has: {names}")
            return int(self.station_nodes[goal])
        idx = int(goal)
        if not 0 <= idx < self.num_nodes:
            raise RoadmapError(f"goal node {idx} out of range 0..{self.num_nodes - 1}")
        return idx


# --------------------------------------------------------------------------------------------- static checks


class StaticChecker:
    """Fast static-scene and self-collision tests for batches of configurations.

    A box around each robot capsule is compared with (world-axis bounds of) the static boxes first; only the
    configurations with a capsule close to a box are passed to the exact
    :meth:`app.planning.collision.CollisionModel.static_clearance` (both are conservative: a reported gap
    never exceeds the true distance). Works with any model that has ``robot_capsules``,
    ``in_static_collision``/``static_clearance`` and ``self_collision``/``self_clearance``; without
    ``static_boxes``/``static_pairs`` attributes every configuration takes the exact path.
    """

    def __init__(self, collision: Any, *, margin_m: float = 0.0) -> None:
        self.collision = collision
        self.margin_m = float(margin_m)
        boxes = getattr(collision, "static_boxes", None)
        pairs = getattr(collision, "static_pairs", None)
        self._bounds: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        if boxes is not None and pairs is not None and len(boxes) > 0:
            lo, hi = [], []
            for box in boxes:
                c, hs, yaw = np.asarray(box.center, float), np.asarray(box.size, float) / 2.0, float(box.yaw)
                cy, sy = abs(math.cos(yaw)), abs(math.sin(yaw))
                ext = np.array([cy * hs[0] + sy * hs[1], sy * hs[0] + cy * hs[1], hs[2]])
                lo.append(c - ext)
                hi.append(c + ext)
            self._bounds = (np.array(lo), np.array(hi), np.asarray(pairs, dtype=bool))

    def clearance_lower_bound(self, q: np.ndarray, *, exact_below_m: float) -> np.ndarray:
        """A lower bound (B,) on each configuration's static clearance (m); exact where it is below
        ``exact_below_m``. +inf without static boxes."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
        if self._bounds is None:
            if hasattr(self.collision, "static_clearance"):
                return np.asarray(self.collision.static_clearance(q), dtype=np.float64)
            bad = self.collision.in_static_collision(q, margin_m=self.margin_m)
            return np.where(bad, -np.inf, np.inf)
        blo, bhi, pairs = self._bounds
        a, b, r = self.collision.robot_capsules(q)
        lo = np.minimum(a, b)
        hi = np.maximum(a, b)
        g = np.maximum(np.maximum(blo[None, None] - hi[:, :, None], lo[:, :, None] - bhi[None, None]), 0.0)
        gap = np.sqrt(np.einsum("nlbk,nlbk->nlb", g, g)) - r[None, :, None]
        gap = np.where(pairs[None], gap, np.inf).reshape(q.shape[0], -1).min(axis=1)
        need = np.flatnonzero(gap < exact_below_m)
        if need.size:
            gap[need] = self.collision.static_clearance(q[need])
        return gap

    def capsule_clearances(self, q: np.ndarray, *, exact_below_m: float) -> np.ndarray:
        """Lower bounds (B, L) on each robot capsule's static clearance (m), exact for configurations with a
        capsule whose bound is below ``exact_below_m``; +inf for capsules exempt from the static check."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
        if self._bounds is None:
            raise RoadmapError("capsule_clearances needs a collision model with static_boxes/static_pairs")
        blo, bhi, pairs = self._bounds
        a, b, r = self.collision.robot_capsules(q)
        lo = np.minimum(a, b)
        hi = np.maximum(a, b)
        g = np.maximum(np.maximum(blo[None, None] - hi[:, :, None], lo[:, :, None] - bhi[None, None]), 0.0)
        gap = np.sqrt(np.einsum("nlbk,nlbk->nlb", g, g)) - r[None, :, None]
        gap = np.where(pairs[None], gap, np.inf).min(axis=2)
        need = np.flatnonzero(gap.min(axis=1) < exact_below_m)
        if need.size:
            gap[need] = self.collision.static_distances(q[need]).min(axis=2)
        return gap

    def bad(self, q: np.ndarray) -> np.ndarray:
        """(B,) bool: closer than ``margin_m`` to the static scene, or self-colliding."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
        if q.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        if self._bounds is None:
            out = np.asarray(self.collision.in_static_collision(q, margin_m=self.margin_m), dtype=bool)
        else:
            out = self.clearance_lower_bound(q, exact_below_m=self.margin_m) < self.margin_m
        return out | np.asarray(self.collision.self_collision(q), dtype=bool)


# --------------------------------------------------------------------------------------------- building


@dataclass(frozen=True, slots=True)
class RoadmapConfig:
    """How the roadmap is built (all of it goes into the cache key).

    Attributes:
        num_nodes: Number of sampled nodes to keep (task poses come on top).
        x_range_m, y_range_m: Sampling box in the world frame (m); None: the table's extent.
        z_range_m: Heights of the TCP above the table top (m).
        min_axis_radius_m: Samples closer than this to the base's vertical axis are skipped (the
            shoulder singularity of a tool pointing down).
        k_neighbors: Edges per node (nearest neighbours by TCP distance) ...
        max_edge_m: ... not longer than this (m).
        max_edge_rad: A branch's straight move longer than this in any joint is not an edge (it crosses a
            wrap-around or a singularity of the branch).
        check_step_rad: Largest joint step between configurations checked along an edge (rad).
        static_margin_m: Clearance (m) required from the static scene at nodes and along edges.
        yaw: Tool yaw about world z (rad) for every node.
    """

    num_nodes: int = 1000
    x_range_m: tuple[float, float] | None = None
    y_range_m: tuple[float, float] | None = None
    z_range_m: tuple[float, float] = (0.05, 0.65)
    min_axis_radius_m: float = 0.2
    k_neighbors: int = 10
    max_edge_m: float = 0.3
    max_edge_rad: float = 1.2
    check_step_rad: float = 0.05
    static_margin_m: float = 0.01
    yaw: float = 0.0

    def __post_init__(self) -> None:
        if self.num_nodes < 1 or self.k_neighbors < 1:
            raise ValueError("RoadmapConfig.num_nodes and k_neighbors must be >= 1")
        if self.check_step_rad <= 0 or self.max_edge_m <= 0:
            raise ValueError("RoadmapConfig.check_step_rad and max_edge_m must be > 0")


def halton(n: int, *, skip: int = 0, bases: tuple[int, ...] = (2, 3, 5)) -> np.ndarray:
    """The Halton sequence: ``n`` points (n, len(bases)) in [0, 1), starting at index ``skip + 1``."""
    idx = np.arange(skip + 1, skip + n + 1, dtype=np.int64)
    out = np.zeros((n, len(bases)))
    for d, base in enumerate(bases):
        i = idx.copy()
        f = 1.0
        while np.any(i > 0):
            f /= base
            out[:, d] += f * (i % base)
            i //= base
    return out


def station_poses(cell: WorkCell) -> dict[str, np.ndarray]:
    """Task poses of a cell: ``home``, ``pickup``, every drop station and ``<name>_approach`` above the
    pickup and the drop stations (:meth:`app.config.WorkCell.approach_offset` from them), TCP positions (3,)
    in m."""
    out: dict[str, np.ndarray] = {cell.home.name: np.asarray(cell.home.xyz, dtype=float)}
    for st in (cell.conveyor.pickup, *cell.drop_stations):
        p = np.asarray(st.xyz, dtype=float)
        out[st.name] = p
        out[f"{st.name}_approach"] = p + cell.approach_offset(st.name)
    return out


#: The last joint (1..6) that moves each robot capsule of :data:`app.planning.collision.ROBOT_LINKS`.
_LINK_LAST_JOINT: dict[str, int] = {
    "base": 0,
    "shoulder": 1,
    "upper_arm": 2,
    "elbow": 2,
    "forearm": 3,
    "wrist_1": 4,
    "wrist_2": 4,
    "wrist_3": 5,
    "tool": 6,
}


def lever_arms(cell: WorkCell) -> np.ndarray:
    """Upper bounds (6,) in m on the distance of any point of the UR5e (capsules included) from each joint
    axis: the chain length from the joint to the end of the tool plus the largest capsule radius plus
    extension.

    A straight joint move by ``dq`` carries no point of the robot further than ``sum_j |dq_j| * lever[j]``
    (each joint turns every point beyond it on an arc of that radius at most).
    """
    from app.planning.collision import (
        FOREARM_OFFSET_M,
        ROBOT_LINK_EXTENSIONS,
        ROBOT_LINK_RADII,
        SHOULDER_OFFSET_M,
    )
    from app.planning.kinematics import A as DH_A
    from app.planning.kinematics import D as DH_D

    tool = float(np.linalg.norm(cell.tool.tcp_xyz))
    # a capsule's points lie within its radius of its segment, which reaches at most its longer extension
    # beyond the joint-axis end points that the chain lengths bound
    reach = (ROBOT_LINK_RADII[n] + max(ROBOT_LINK_EXTENSIONS.get(n, (0.0, 0.0))) for n in ROBOT_LINK_RADII)
    r = max(*reach, cell.tool.radius_m)
    wrist = abs(DH_D[4]) + abs(DH_D[5]) + tool + r
    forearm = FOREARM_OFFSET_M + abs(DH_A[2]) + abs(DH_D[3]) + wrist
    arm = SHOULDER_OFFSET_M + abs(DH_A[1]) + forearm
    return np.array([arm, arm, forearm, wrist, abs(DH_D[5]) + tool + r, tool + r])


def _aligned_to(q: np.ndarray, q_ref: np.ndarray, q_min: np.ndarray, q_max: np.ndarray) -> np.ndarray:
    """2 pi-shift each joint of q next to q_ref within the limits (the search uses the same rule)."""
    two_pi = 2.0 * math.pi
    nearest = q + two_pi * np.rint((q_ref - q) / two_pi)
    nearest = np.where(nearest > q_max, nearest - two_pi, nearest)
    nearest = np.where(nearest < q_min, nearest + two_pi, nearest)
    bad = (nearest > q_max) | (nearest < q_min)
    return np.where(bad, q, nearest)


def build_roadmap(
    cell: WorkCell,
    *,
    config: RoadmapConfig | None = None,
    collision: CollisionModel | None = None,
    key: str = "",
) -> Roadmap:
    """Build the roadmap of a work cell (deterministic: the same cell and config give the same roadmap).

    Nodes are the first Halton points (in the sampling box, outside the base's axis radius) with at least
    one usable IK branch, plus the task poses (a task pose without a usable branch is left out with a
    warning). An edge's branch ``b`` is free when a bound from the end configurations proves it (every
    capsule's clearance along the move is at least the mean of its end clearances minus half the farthest
    it can travel, ``sum_j |dq_j| * lever_arms(cell)[j]`` over the joints that move it; likewise for pairs
    of capsules and the joints between them), or else when every configuration at most ``check_step_rad``
    apart on the move passes the static and self-collision checks.
    """
    from scipy.spatial import cKDTree

    from app.planning.collision import CollisionModel

    cfg = config or RoadmapConfig()
    t_build = time.perf_counter()
    model = collision if collision is not None else CollisionModel(cell)
    kin = model.kin
    checker = StaticChecker(model, margin_m=cfg.static_margin_m)
    top = cell.table.center[2] + cell.table.size[2] / 2
    tc, ts = np.asarray(cell.table.center), np.asarray(cell.table.size)
    xr = cfg.x_range_m or (float(tc[0] - ts[0] / 2), float(tc[0] + ts[0] / 2))
    yr = cfg.y_range_m or (float(tc[1] - ts[1] / 2), float(tc[1] + ts[1] / 2))
    lo = np.array([xr[0], yr[0], top + cfg.z_range_m[0]])
    hi = np.array([xr[1], yr[1], top + cfg.z_range_m[1]])
    base = np.asarray(cell.robot.base_xyz, dtype=float)

    def usable(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q, valid = kin.ik_down(points, yaw=cfg.yaw)
        q = np.nan_to_num(q)
        flat = np.flatnonzero(valid.reshape(-1))
        if flat.size:
            bad = checker.bad(q.reshape(-1, 6)[flat])
            v = valid.reshape(-1).copy()
            v[flat[bad]] = False
            valid = v.reshape(valid.shape)
        return q, valid

    # -- task poses first (they keep their names), then Halton samples until num_nodes are usable
    stations = station_poses(cell)
    st_names = list(stations)
    st_q, st_valid = usable(np.array([stations[n] for n in st_names]))
    keep_st = st_valid.any(axis=1)
    for name, ok in zip(st_names, keep_st, strict=True):
        if not ok:
            logger.warning("roadmap: task pose %r has no usable IK branch; it is left out", name)
    pts_l, q_l, v_l = (
        [np.array([stations[n] for n in st_names])[keep_st]],
        [st_q[keep_st]],
        [st_valid[keep_st]],
    )
    count, skip = 0, 0
    chunk = max(256, cfg.num_nodes)
    while count < cfg.num_nodes:
        u = halton(chunk, skip=skip)
        skip += chunk
        p = lo + u * (hi - lo)
        p = p[np.linalg.norm(p[:, :2] - base[:2], axis=1) >= cfg.min_axis_radius_m]
        if p.shape[0] == 0:
            continue
        q, valid = usable(p)
        ok = np.flatnonzero(valid.any(axis=1))[: cfg.num_nodes - count]
        pts_l.append(p[ok])
        q_l.append(q[ok])
        v_l.append(valid[ok])
        count += ok.size
        if skip > 200 * cfg.num_nodes + 10000:
            raise RoadmapError(
                f"only {count} of {cfg.num_nodes} roadmap samples are reachable: widen the sampling box"
            )
    nodes = np.concatenate(pts_l)
    ik = np.concatenate(q_l)
    valid = np.concatenate(v_l)
    station_nodes = {n: i for i, n in enumerate(np.array(st_names)[keep_st].tolist())}
    N = nodes.shape[0]
    ik = np.where(valid[..., None], ik, 0.0)

    # -- candidate edges: k nearest neighbours within max_edge_m
    tree = cKDTree(nodes)
    k = min(cfg.k_neighbors + 1, N)
    _, nbr = tree.query(nodes, k=k, distance_upper_bound=cfg.max_edge_m)
    src = np.repeat(np.arange(N), k)
    dst = nbr.reshape(-1)
    ok = (dst < N) & (dst != src)
    a, b = np.minimum(src[ok], dst[ok]), np.maximum(src[ok], dst[ok])
    pairs = np.unique(np.stack([a, b], axis=1), axis=0)

    # -- per-branch static check of the straight joint moves. Shortcut: a capsule moved only by joints
    # 1..J(l) travels at most T_l = sum_{j <= J(l)} lever_j |dq_j|, so its clearance along the move is at
    # least
    # (c_a + c_b - T_l) / 2; two capsules move relative to each other only by the joints between them.
    from app.planning.collision import ROBOT_LINKS, SELF_COLLISION_PAIRS

    moved_by = np.array([_LINK_LAST_JOINT[name] for name in ROBOT_LINKS])  # J(l), 0 = fixed
    pair_i = np.array([p[0] for p in SELF_COLLISION_PAIRS])
    pair_k = np.array([p[1] for p in SELF_COLLISION_PAIRS])
    flat_valid = np.flatnonzero(valid.reshape(-1))
    n_links = len(ROBOT_LINKS)
    clear = np.full((N * NUM_BRANCHES, n_links), -np.inf)
    self_d = np.full((N * NUM_BRANCHES, len(SELF_COLLISION_PAIRS)), -np.inf)
    qf = ik.reshape(-1, 6)
    for c0 in range(0, flat_valid.size, 4096):
        sel = flat_valid[c0 : c0 + 4096]
        clear[sel] = checker.capsule_clearances(qf[sel], exact_below_m=cfg.static_margin_m + 0.25)
        self_d[sel] = model.self_distances(qf[sel])
    clear = clear.reshape(N, NUM_BRANCHES, n_links)
    self_d = self_d.reshape(N, NUM_BRANCHES, -1)
    qa = ik[pairs[:, 0]]  # (E, 8, 6)
    qb = _aligned_to(ik[pairs[:, 1]], qa, kin.q_min, kin.q_max)
    both = valid[pairs[:, 0]] & valid[pairs[:, 1]]
    span = np.abs(qb - qa)
    both &= span.max(axis=-1) <= cfg.max_edge_rad
    cum = np.concatenate(
        [np.zeros((*span.shape[:-1], 1)), np.cumsum(span * lever_arms(cell), axis=-1)], axis=-1
    )
    travel = cum[..., moved_by]  # (E, 8, L)
    static_lb = (clear[pairs[:, 0]] + clear[pairs[:, 1]] - travel) / 2
    rel = cum[..., moved_by[pair_k]] - cum[..., moved_by[pair_i]]
    self_lb = (self_d[pairs[:, 0]] + self_d[pairs[:, 1]] - np.abs(rel)) / 2
    easy = both & (static_lb.min(axis=-1) >= cfg.static_margin_m) & (self_lb.min(axis=-1) >= 0.0)
    free = easy.copy()
    hard_e, hard_b = np.nonzero(both & ~easy)
    if hard_e.size:
        A, B = qa[hard_e, hard_b], qb[hard_e, hard_b]
        n = np.maximum(np.ceil(np.abs(B - A).max(axis=1) / cfg.check_step_rad), 1).astype(np.int64)
        inner = np.maximum(n - 1, 0)
        owner = np.repeat(np.arange(hard_e.size), inner)
        i = np.arange(owner.size) - np.repeat(np.cumsum(inner) - inner, inner) + 1
        bad = np.zeros(hard_e.size, dtype=bool)
        for c0 in range(0, owner.size, 20000):
            o = owner[c0 : c0 + 20000]
            frac = (i[c0 : c0 + 20000] / n[o])[:, None]
            hit = checker.bad(A[o] + frac * (B[o] - A[o]))
            bad[o[hit]] = True
        free[hard_e, hard_b] = ~bad
    mask = np.packbits(free, axis=1, bitorder="little")[:, 0]
    keep = mask != 0
    roadmap = Roadmap.from_arrays(
        nodes,
        ik,
        valid,
        pairs[keep],
        edge_branches=mask[keep],
        station_nodes=station_nodes,
        yaw=cfg.yaw,
        key=key,
        build_s=time.perf_counter() - t_build,
    )
    logger.info(
        "roadmap built: %d nodes, %d edges (%d of %d branch moves needed interpolation) in %.1f s",
        N,
        roadmap.num_edges,
        hard_e.size,
        int(both.sum()),
        roadmap.build_s,
    )
    return roadmap


# --------------------------------------------------------------------------------------------- cache


def roadmap_key(cell: WorkCell, config: RoadmapConfig) -> str:
    """Cache key: a hash of the cell's fingerprint, the robot's capsules, the roadmap settings and the format
    version."""
    from app.planning.collision import robot_geometry_key

    payload = json.dumps(
        {
            "cell": cell.fingerprint(),
            "robot": robot_geometry_key(),
            "config": asdict(config),
            "version": ROADMAP_FORMAT_VERSION,
        },
        sort_keys=True,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:20]


def default_cache_dir() -> Path:
    """``$HRC_CACHE_DIR`` or ``$XDG_CACHE_HOME/hrc`` (``~/.cache/hrc``), plus ``roadmaps``."""
    env = os.environ.get("HRC_CACHE_DIR")
    if env:
        return Path(env) / "roadmaps"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "hrc" / "roadmaps"


def save_roadmap(roadmap: Roadmap, path: Path) -> None:
    """Write a roadmap to ``path`` (npz) atomically (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "station_nodes": roadmap.station_nodes,
        "yaw": roadmap.yaw,
        "key": roadmap.key,
        "build_s": roadmap.build_s,
        "version": ROADMAP_FORMAT_VERSION,
    }
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(
                fh,
                nodes=roadmap.nodes,
                ik=roadmap.ik,
                valid=roadmap.valid,
                indptr=roadmap.indptr,
                indices=roadmap.indices,
                edge_branches=roadmap.edge_branches,
                meta=np.array(json.dumps(meta)),
            )
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_roadmap(path: Path, *, expected_key: str | None = None) -> Roadmap:
    """Read a roadmap written by :func:`save_roadmap`.

    Raises:
        RoadmapError: unreadable, malformed, another format version, or another key than expected.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {k: data[k] for k in ("nodes", "ik", "valid", "indptr", "indices", "edge_branches")}
    except (OSError, ValueError, KeyError, json.JSONDecodeError, EOFError) as exc:
        raise RoadmapError(f"cannot read roadmap cache {path}: {exc}") from exc
    if meta.get("version") != ROADMAP_FORMAT_VERSION:
        raise RoadmapError(
            f"roadmap cache {path} has format {meta.get('version')}, need {ROADMAP_FORMAT_VERSION}"
        )
    if expected_key is not None and meta.get("key") != expected_key:
        raise RoadmapError(f"roadmap cache {path} was built for key {meta.get('key')}, need {expected_key}")
    return Roadmap(
        **arrays,
        station_nodes={str(k): int(v) for k, v in meta["station_nodes"].items()},
        yaw=float(meta["yaw"]),
        key=str(meta["key"]),
        build_s=float(meta.get("build_s", 0.0)),
    )


def load_or_build_roadmap(
    cell: WorkCell,
    *,
    config: RoadmapConfig | None = None,
    cache_dir: str | Path | None = None,
    collision: CollisionModel | None = None,
) -> Roadmap:
    """The cell's roadmap from the cache, or built (and cached) when missing, stale or corrupt.

    Args:
        cell: The work cell.
        config: Roadmap settings (default :class:`RoadmapConfig`).
        cache_dir: Where cached roadmaps live (default :func:`default_cache_dir`).
        collision: Collision model to build with (default ``CollisionModel(cell)``).

    The file name carries the key (cell fingerprint + settings), so a changed cell or setting builds a new
    roadmap; a cache file that cannot be read is rebuilt (and overwritten) with a warning.
    """
    cfg = config or RoadmapConfig()
    key = roadmap_key(cell, cfg)
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = directory / f"roadmap-{key}.npz"
    if path.is_file():
        try:
            return load_roadmap(path, expected_key=key)
        except (RoadmapError, ValueError) as exc:
            logger.warning("roadmap cache %s is unusable (%s); rebuilding it", path, exc)
    roadmap = build_roadmap(cell, config=cfg, collision=collision, key=key)
    try:
        save_roadmap(roadmap, path)
    except OSError as exc:
        logger.warning("could not write the roadmap cache %s: %s", path, exc)
    return roadmap
