"""The static roadmap: TCP positions (tool pointing down), all their IK branches, statically free edges.

Paper, section II-A: the graph is built once from deterministic samples of end-effector positions with a fixed
tool orientation (6 DoF reduced to 3), avoiding static obstacles; the time-variant search then runs over it.
Here:

- **Nodes** are a Halton sequence of TCP positions in the reachable part of the work cell (a box above the
  table, clipped to the arm's reach) plus the task poses of the cell: ``home``, the conveyor ``pickup``, the
  drop stations (``A`` ... ``D`` in the default cell) and an approach pose ``<name>_approach`` above each of
  the latter (``cell.approach_height_m`` higher). A node is kept when at least one of its 8 IK branches is
  within the joint limits, free of the static scene (with ``static_margin_m``) and free of self-collision;
  every such branch is stored.
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

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    pass

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
        ik: IK branches (N, 8, 6) in rad (entries of invalid branches are 0).
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
