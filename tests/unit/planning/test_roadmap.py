from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from app.config import R_WORLD_TOOL_DOWN, load_workcell
from app.planning import roadmap as roadmap_mod
from app.planning.collision import CollisionModel
from app.planning.kinematics import Q_MAX, Q_MIN, align_branches, within_limits
from app.planning.roadmap import (
    Roadmap,
    RoadmapConfig,
    RoadmapError,
    halton,
    lever_arms,
    load_or_build_roadmap,
    roadmap_key,
    station_poses,
)

SMALL = RoadmapConfig(num_nodes=40, k_neighbors=6)


@pytest.fixture(scope="module")
def cell():
    return load_workcell()


@pytest.fixture(scope="module")
def model(cell) -> CollisionModel:
    return CollisionModel(cell)


@pytest.fixture(scope="module")
def small(cell, model, tmp_path_factory: pytest.TempPathFactory) -> tuple[Roadmap, Path]:
    cache = tmp_path_factory.mktemp("roadmaps")
    return load_or_build_roadmap(cell, config=SMALL, cache_dir=cache, collision=model), cache


def test_from_arrays_builds_a_symmetric_read_only_csr() -> None:
    nodes = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    ik = np.zeros((3, 8, 6))
    valid = np.zeros((3, 8), bool)
    valid[:, 0] = True
    rm = Roadmap.from_arrays(nodes, ik, valid, np.array([[0, 1], [1, 2]]), station_nodes={"a": 2})
    assert rm.num_nodes == 3 and rm.num_edges == 2
    assert sorted(rm.neighbors(1).tolist()) == [0, 2] and rm.neighbors(0).tolist() == [1]
    np.testing.assert_array_equal(rm.edge_list(), [[0, 1], [1, 2]])
    assert rm.edge_branches.tolist() == [1, 1, 1, 1]  # branch 0 valid at both ends of every edge
    assert rm.resolve("a") == 2 and rm.resolve(1) == 1
    with pytest.raises(RoadmapError, match=r"unknown station 'b'.*a"):
        rm.resolve("b")
    with pytest.raises(RoadmapError, match="out of range"):
        rm.resolve(7)
    with pytest.raises(ValueError):
        rm.nodes[0, 0] = 1.0
    with pytest.raises(RoadmapError, match="edge endpoints"):
        Roadmap.from_arrays(nodes, ik, valid, np.array([[0, 5]]))


def test_halton_is_deterministic_and_low_discrepancy() -> None:
    h = halton(4)
    np.testing.assert_allclose(h[:3, 0], [0.5, 0.25, 0.75])
    np.testing.assert_allclose(h[:3, 1], [1 / 3, 2 / 3, 1 / 9])
    big = halton(4096)
    assert np.all((big >= 0) & (big < 1))
    counts = np.histogramdd(big, bins=(4, 4, 4))[0]
    assert counts.min() >= 50 and counts.max() <= 78  # 64 per cell, evenly spread
    np.testing.assert_array_equal(halton(10, skip=5), halton(15)[5:])


def test_lever_arms_bound_point_motion(cell, model) -> None:
    rng = np.random.default_rng(0)
    lever = lever_arms(cell)
    q = rng.uniform(-3, 3, size=(200, 6))
    dq = rng.normal(scale=1e-3, size=(200, 6))
    a0, b0, _ = model.robot_capsules(q)
    a1, b1, _ = model.robot_capsules(q + dq)
    moved = np.maximum(np.linalg.norm(a1 - a0, axis=-1), np.linalg.norm(b1 - b0, axis=-1)).max(axis=1)
    assert np.all(moved <= (np.abs(dq) * lever).sum(axis=1) * 1.001)


def test_small_roadmap_nodes_are_reachable_and_free(small, cell, model) -> None:
    rm, _ = small
    names = set(station_poses(cell))
    assert names == set(rm.station_nodes)  # every task pose of the default cell is usable
    assert rm.num_nodes == SMALL.num_nodes + len(names)
    poses = station_poses(cell)
    for name, p in poses.items():
        np.testing.assert_allclose(rm.nodes[rm.station_nodes[name]], p)
    # the pickup's approach pose lies straight above it, a drop station's also back from the person
    up = np.array([0.0, 0.0, cell.approach_height_m])
    np.testing.assert_allclose(poses["pickup_approach"] - poses["pickup"], up)
    spot = np.asarray(cell.operator.work_spot[:2])
    for st in cell.drop_stations:
        off = poses[f"{st.name}_approach"] - poses[st.name]
        assert off[2] == pytest.approx(cell.approach_height_m)
        assert np.linalg.norm(off[:2]) == pytest.approx(cell.approach_retreat_m)
        assert np.linalg.norm(poses[f"{st.name}_approach"][:2] - spot) > np.linalg.norm(
            poses[st.name][:2] - spot
        )
    assert np.all(rm.valid.any(axis=1))
    q = rm.ik[rm.valid]
    assert np.all(within_limits(q))
    T = model.kin.fk_tcp(q)
    node_of = np.repeat(np.arange(rm.num_nodes), rm.valid.sum(axis=1))
    np.testing.assert_allclose(T[:, :3, 3], rm.nodes[node_of], atol=1e-6)
    np.testing.assert_allclose(
        T[:, :3, :3], np.broadcast_to(R_WORLD_TOOL_DOWN, T[:, :3, :3].shape), atol=1e-6
    )
    assert np.all(model.static_clearance(q) >= SMALL.static_margin_m - 1e-9)
    assert not np.any(model.self_collision(q))


def test_small_roadmap_edges_are_statically_free_at_fine_resolution(small, model) -> None:
    rm, _ = small
    assert rm.num_edges > rm.num_nodes  # connected enough to plan on
    src = np.repeat(np.arange(rm.num_nodes), np.diff(rm.indptr))
    bits = ((rm.edge_branches[:, None].astype(int) >> np.arange(8)) & 1).astype(bool)
    e, b = np.nonzero(bits)
    qa = rm.ik[src[e], b]
    qb = align_branches(rm.ik[rm.indices[e], b], qa, q_min=Q_MIN, q_max=Q_MAX)
    frac = np.linspace(0.0, 1.0, 41)
    q = (qa[:, None] + frac[None, :, None] * (qb - qa)[:, None]).reshape(-1, 6)
    assert np.all(model.static_clearance(q) > 0.0)
    assert not np.any(model.self_collision(q))


def test_the_cache_key_follows_the_capsules(cell, monkeypatch) -> None:
    """A roadmap cached for other capsules is stale: the robot's capsule constants (in code) and the tool's
    capsule (in the cell) are part of the key."""
    from app.planning import collision

    key = roadmap_key(cell, SMALL)
    assert roadmap_key(load_workcell(), SMALL) == key  # deterministic
    changes = (
        (collision.ROBOT_LINK_RADII, "wrist_1", 0.05),
        (collision.ROBOT_LINK_EXTENSIONS, "elbow", (0.06, 0.0)),
        (collision.SELF_COLLISION_RADII, "base", 0.07),
    )
    for table, name, value in changes:
        with monkeypatch.context() as m:
            m.setitem(table, name, value)
            assert roadmap_key(cell, SMALL) != key, (name, value)
        assert roadmap_key(cell, SMALL) == key
    longer = cell.model_copy(update={"tool": cell.tool.model_copy(update={"capsule_length_m": 0.2})})
    assert roadmap_key(longer, SMALL) != key


def test_cache_is_reused_and_rebuilt_when_stale_or_corrupt(small, cell, model, monkeypatch, caplog) -> None:
    rm, cache = small
    path = cache / f"roadmap-{roadmap_key(cell, SMALL)}.npz"
    assert path.is_file()

    def no_build(*args: object, **kwargs: object) -> Roadmap:
        raise AssertionError("the cached roadmap should have been used")

    monkeypatch.setattr(roadmap_mod, "build_roadmap", no_build)
    again = load_or_build_roadmap(cell, config=SMALL, cache_dir=cache, collision=model)
    for k in ("nodes", "ik", "valid", "indptr", "indices", "edge_branches"):
        np.testing.assert_array_equal(getattr(again, k), getattr(rm, k))
    assert again.station_nodes == rm.station_nodes

    built: list[str] = []

    def fake_build(cell_, *, config, collision=None, key=""):
        built.append(key)
        return Roadmap.from_arrays(
            rm.nodes, rm.ik, rm.valid, rm.edge_list(), station_nodes=rm.station_nodes, key=key
        )

    monkeypatch.setattr(roadmap_mod, "build_roadmap", fake_build)
    # a changed cell has another key: a new roadmap is built
    moved = cell.model_copy(update={"approach_height_m": 0.15})
    assert roadmap_key(moved, SMALL) != roadmap_key(cell, SMALL)
    load_or_build_roadmap(moved, config=SMALL, cache_dir=cache, collision=model)
    assert built == [roadmap_key(moved, SMALL)]
    # a changed setting too
    load_or_build_roadmap(cell, config=RoadmapConfig(num_nodes=41, k_neighbors=6), cache_dir=cache)
    assert len(built) == 2
    # a corrupt cache file is rebuilt with a warning
    path.write_bytes(b"not an npz file")
    with caplog.at_level(logging.WARNING, logger="app.planning.roadmap"):
        load_or_build_roadmap(cell, config=SMALL, cache_dir=cache, collision=model)
    assert len(built) == 3
    assert any("unusable" in r.message for r in caplog.records)
    # ... and the rebuilt one was written back and loads again
    assert (
        load_or_build_roadmap(cell, config=SMALL, cache_dir=cache, collision=model).num_nodes == rm.num_nodes
    )
    assert len(built) == 3
