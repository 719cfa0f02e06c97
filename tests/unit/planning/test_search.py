"""Time-variant A* on small hand-built roadmaps with known answers.

The "robot" is a ball (radius 5 cm) at ``q[:3]`` (metres; the other joints only select branches), the person
a set of balls at its joints, so every answer can be worked out by hand. The validity check at the end of
each test is written independently of the planner: it samples the trajectory at 100 Hz, differentiates it
itself and computes point distances itself.
"""

from __future__ import annotations

import heapq
import itertools

import numpy as np
import pytest

from app.planning.roadmap import Roadmap
from app.planning.search import Planner, PlannerConfig
from app.planning.search.config import PHASES
from app.planning.trajectory import Plan, Trajectory
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import BONES, NUM_JOINTS
from app.safety.ssm import SSMParams, forecast_clearance
from app.safety.stopping import StoppingModel

R_ROBOT = 0.05
R_HUMAN = 0.05
SSM = SSMParams(t_reaction_s=0.01, t_stop_s=0.0, intrusion_m=0.0, z_human_m=0.1, z_robot_m=0.0)
#: The toy robot stops at once (no ``S_s``): the scenes below are laid out for ``S_r`` alone.
INSTANT_STOP = StoppingModel(decel_mps2=1e9, joint_decel_radps2=1e9)
Q_LIM = 3.0


class PointRobot:
    """A ball robot at q[:3]; a person of balls at the joints (bones of length 0); boxes as static scene."""

    def __init__(self, boxes: list[tuple[tuple[float, ...], tuple[float, ...]]] | None = None) -> None:
        self.boxes = boxes or []
        self.distance_calls = 0

    def robot_capsules(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.asarray(q, dtype=float).reshape(-1, 6)
        return q[:, None, :3].copy(), q[:, None, :3].copy(), np.array([R_ROBOT])

    def human_capsules(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        joints = np.asarray(joints, dtype=float)
        return joints[:, BONES[:, 0]], joints[:, BONES[:, 1]], np.full(len(BONES), R_HUMAN)

    def distance_to_human_paired(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        self.distance_calls += 1
        d = np.linalg.norm(np.asarray(joints) - np.asarray(q)[:, None, :3], axis=-1).min(axis=1)
        return d - R_ROBOT - R_HUMAN

    def in_static_collision(self, q: np.ndarray, *, margin_m: float = 0.0) -> np.ndarray:
        q = np.asarray(q, dtype=float).reshape(-1, 6)
        hit = np.zeros(q.shape[0], dtype=bool)
        for lo, hi in self.boxes:
            g = np.maximum(np.maximum(np.asarray(lo) - q[:, :3], q[:, :3] - np.asarray(hi)), 0.0)
            hit |= np.linalg.norm(g, axis=1) < R_ROBOT + margin_m
        return hit

    def self_collision(self, q: np.ndarray) -> np.ndarray:
        return np.zeros(np.asarray(q).reshape(-1, 6).shape[0], dtype=bool)


def config(**kw: object) -> PlannerConfig:
    base = dict(
        ssm=SSM,
        stopping=INSTANT_STOP,
        q_min=(-Q_LIM,) * 6,
        q_max=(Q_LIM,) * 6,
        qd_max=(1.0,) * 6,
        qdd_max=(1000.0,) * 6,
        speed_fraction=0.5,
        accel_fraction=1.0,
        corridor_margin_m=0.0,
        slow_speed_fractions=(),
        start_neighbors=1,
        goal_hold_s=0.2,
        fallback_slack_s=0.0,
        lever_arm_m=1.0,
    )
    base.update(kw)
    return PlannerConfig(**base)  # type: ignore[arg-type]


def roadmap(points: list[tuple[float, float]], edges: list[tuple[int, int]], **stations: int) -> Roadmap:
    pts = np.array([[x, y, 0.0] for x, y in points])
    ik = np.zeros((len(pts), 8, 6))
    ik[:, 0, :3] = pts
    valid = np.zeros((len(pts), 8), dtype=bool)
    valid[:, 0] = True
    return Roadmap.from_arrays(pts, ik, valid, np.array(edges), station_nodes=stations)


def person(times: list[float], spots: list[tuple[float, float]], *, growth: float = 0.0) -> HumanForecast:
    """A person of balls all at one spot per sample (z = 0), margin 0."""
    joints = np.array([np.tile([x, y, 0.0], (NUM_JOINTS, 1)) for x, y in spots])
    return HumanForecast(
        t0=times[0], times=np.array(times), joints=joints, margins=np.zeros(len(times)), growth_mps=growth
    )


def q_of(x: float, y: float) -> np.ndarray:
    return np.array([x, y, 0.0, 0.0, 0.0, 0.0])


def assert_valid(
    traj: Trajectory,
    forecast: HumanForecast | None,
    *,
    hold_s: float,
    ssm: SSMParams = SSM,
    stopping: StoppingModel = INSTANT_STOP,
) -> None:
    """Independent check: 100 Hz samples within the joint limits and at least the required separation."""
    t = np.arange(traj.t_start, traj.t_end + hold_s + 1e-9, 0.01)
    q = traj.q(t)
    assert np.all(np.abs(q) <= Q_LIM + 1e-9)
    if forecast is None:
        return
    eps = 1e-5
    dq = traj.q(t + eps) - traj.q(t - eps)
    v = np.linalg.norm(dq[:, :3], axis=1) / (2 * eps)
    w = np.abs(dq).max(axis=1) / (2 * eps)
    joints, margins = forecast.poses_at(t)
    d = np.linalg.norm(joints - q[:, None, :3], axis=-1).min(axis=1) - R_ROBOT - R_HUMAN
    need = forecast_clearance(v, margins, ssm, w_top_radps=w, stopping=stopping)
    worst = int(np.argmin(d - need))
    assert d[worst] >= need[worst] - 1e-9, (
        f"violation at t={t[worst]:.3f}: {d[worst]:.4f} < {need[worst]:.4f}"
    )


def dijkstra(rm: Roadmap, start: int, goal: int, speed: float) -> tuple[list[int], float]:
    """Plain shortest path with edge time = max-norm joint distance / speed (the planner's cruise model)."""
    dist = {start: 0.0}
    prev: dict[int, int] = {}
    heap = [(0.0, start)]
    while heap:
        d, u = heapq.heappop(heap)
        if u == goal:
            break
        if d > dist[u]:
            continue
        for v in rm.neighbors(u).tolist():
            nd = d + float(np.max(np.abs(rm.ik[v, 0] - rm.ik[u, 0]))) / speed
            if nd < dist.get(v, np.inf):
                dist[v] = nd
                prev[v] = u
                heapq.heappush(heap, (nd, v))
    path = [goal]
    while path[-1] != start:
        path.append(prev[path[-1]])
    return path[::-1], dist[goal]


def path_time(rm: Roadmap, nodes: list[int]) -> float:
    return sum(float(np.max(np.abs(rm.ik[b, 0] - rm.ik[a, 0]))) / 0.5 for a, b in itertools.pairwise(nodes))


def random_graph(seed: int, n: int = 30) -> Roadmap:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0.0, 2.0, size=(n, 2))
    pts[0], pts[1] = (0.0, 0.0), (2.0, 2.0)
    edges = [(i, j) for i, j in itertools.combinations(range(n), 2) if np.linalg.norm(pts[i] - pts[j]) < 0.7]
    return roadmap([tuple(p) for p in pts], edges, s=0, g=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_without_a_person_the_search_is_plain_a_star(seed: int) -> None:
    rm = random_graph(seed)
    before = {
        k: getattr(rm, k).copy() for k in ("nodes", "ik", "valid", "indptr", "indices", "edge_branches")
    }
    planner = Planner(rm, PointRobot(), config=config(shortcut=False))  # the search's own path
    _, cost = dijkstra(rm, 0, 1, speed=0.5)
    for workers in (1, 4):
        res = planner.plan(q_start=rm.ik[0, 0], t_start=0.0, goal="g", forecast=None, workers=workers)
        assert res.ok, res.reason
        nodes = res.plan.nodes.tolist()
        assert nodes[0] == 0 and nodes[-1] == 1
        # a path of the graph, as short as the plain shortest path (max-norm costs can tie)
        for a, b in itertools.pairwise(nodes):
            assert b in rm.neighbors(a).tolist()
        assert path_time(rm, nodes) == pytest.approx(cost, abs=1e-9)
        # cruise model plus the (tiny) acceleration ramps at start and end
        assert res.plan.t_end == pytest.approx(cost, abs=3e-3)
        assert_valid(res.trajectory, None, hold_s=0.0)
    for k, arr in before.items():
        np.testing.assert_array_equal(getattr(rm, k), arr)  # the search never writes into the roadmap
        assert not getattr(rm, k).flags.writeable


def test_a_query_reports_where_its_time_went() -> None:
    # a planner clock that advances 1 ms per reading: every phase is timed with the planner's own clock
    # and the phases together never exceed the query
    ticks = itertools.count()
    rm = random_graph(0)
    planner = Planner(rm, PointRobot(), config=config(), timer=lambda: next(ticks) * 1e-3)
    res = planner.plan(q_start=rm.ik[0, 0], t_start=0.0, goal="g", forecast=None)
    assert res.ok, res.reason
    assert set(res.phases_s) == set(PHASES)
    assert res.phases_s["search"] > 0 and res.phases_s["finish"] > 0
    assert sum(res.phases_s.values()) <= res.compute_s
    # a query that ends before any search reports none
    bad = Planner(rm, PointRobot(), config=config(q_max=(0.5,) * 6))
    out = bad.plan(q_start=np.full(6, 1.0), t_start=0.0, goal="g", forecast=None)
    assert not out.ok and out.phases_s is None


def test_a_person_crossing_an_edge_makes_the_robot_wait() -> None:
    # a corridor 0 - 0.2 - ... - 1.0; the person stands next to x = 0.6 between t = 0.8 and 1.6 only
    rm = roadmap([(0.2 * i, 0.0) for i in range(6)], [(i, i + 1) for i in range(5)], s=0, g=5)
    fc = person(
        [0.0, 0.7, 0.75, 1.6, 1.65, 4.0],
        [(0.6, 3.0), (0.6, 3.0), (0.6, 0.15), (0.6, 0.15), (0.6, 3.0), (0.6, 3.0)],
    )
    planner = Planner(rm, PointRobot(), config=config(max_wait_s=1.5))
    static = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=None)
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc)
    assert static.ok and res.ok, res.reason
    q = res.plan.q
    waits = [i for i in range(len(q) - 1) if np.allclose(q[i], q[i + 1])]
    assert waits, "expected a wait in the plan"
    # the robot passes x = 0.6 only after the person has left (0.15 m away needs 0.2 m + speed term)
    traj = res.trajectory
    t = np.arange(traj.t_start, traj.t_end, 0.01)
    near = np.abs(traj.q(t)[:, 0] - 0.6) < 0.11
    assert np.all((t[near] < 0.75) | (t[near] > 1.6))
    assert res.plan.t_end > static.plan.t_end + 0.3
    assert_valid(traj, fc, hold_s=0.2)


def test_a_person_standing_on_the_short_way_makes_the_robot_detour() -> None:
    # short way s - m - g (2 s); the long way s - d1 - d2 - g (4.4 s); the person stands at m
    rm = roadmap(
        [(0.0, 0.0), (0.5, 0.0), (1.0, 0.0), (0.0, 0.6), (1.0, 0.6)],
        [(0, 1), (1, 2), (0, 3), (3, 4), (4, 2)],
        s=0,
        g=2,
    )
    fc = person([0.0], [(0.5, -0.1)])
    planner = Planner(rm, PointRobot(), config=config(shortcut=False))  # the search's own path
    static = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=None)
    assert [n for n in static.plan.nodes.tolist() if n >= 0] == [0, 1, 2]
    for workers in (1, 3):
        res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc, workers=workers)
        assert res.ok, res.reason
        assert [n for n in res.plan.nodes.tolist() if n >= 0] == [0, 3, 4, 2]
        assert_valid(res.trajectory, fc, hold_s=0.2)


def test_an_unreachable_goal_is_a_clear_failure() -> None:
    rm = roadmap([(0.0, 0.0), (0.3, 0.0), (1.5, 1.5)], [(0, 1)], s=0, g=2)
    planner = Planner(rm, PointRobot(), config=config())
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=None)
    assert not res.ok and res.plan is None and res.trajectory is None
    assert "unreachable" in res.reason
    assert res.blocked is None  # no person: the roadmap has no way


def test_a_person_staying_at_the_goal_fails_instead_of_returning_an_unchecked_path() -> None:
    rm = roadmap([(0.0, 0.0), (0.4, 0.0), (0.8, 0.0)], [(0, 1), (1, 2)], s=0, g=2)
    fc = person([0.0, 1.0], [(2.0, 2.0), (0.8, 0.05)])  # walks up to the goal and stays
    planner = Planner(rm, PointRobot(), config=config(max_wait_s=0.5))
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc)
    assert not res.ok and res.plan is None
    assert res.reason.startswith("goal blocked by the person") and res.blocked == "goal"


def test_start_in_violation_and_unknown_goal() -> None:
    rm = roadmap([(0.0, 0.0), (0.4, 0.0)], [(0, 1)], s=0, g=1)
    planner = Planner(rm, PointRobot(), config=config())
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=person([0.0], [(0.05, 0.0)]))
    assert not res.ok and "start" in res.reason and res.blocked == "start"
    from app.planning.roadmap import RoadmapError

    with pytest.raises(RoadmapError, match="unknown station"):
        planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="nowhere", forecast=None)


def test_the_nearest_branch_is_taken_first() -> None:
    # every node has two branches at the same position: joint 4 at 0 or at 1 (the ball ignores it)
    pts = [(0.0, 0.0), (0.3, 0.0), (0.6, 0.0)]
    rm0 = roadmap(pts, [(0, 1), (1, 2)], s=0, g=2)
    ik = rm0.ik.copy()
    valid = rm0.valid.copy()
    ik[:, 1] = ik[:, 0]
    ik[:, 1, 3] = 1.0
    valid[:, 1] = True
    rm = Roadmap.from_arrays(rm0.nodes, ik, valid, rm0.edge_list(), station_nodes={"g": 2})
    planner = Planner(rm, PointRobot(), config=config())
    for j4 in (0.0, 1.0):
        start = np.array([0.0, 0.0, 0.0, j4, 0.0, 0.0])
        res = planner.plan(q_start=start, t_start=0.0, goal="g", forecast=None)
        assert res.ok
        np.testing.assert_allclose(res.plan.q[:, 3], j4)


def test_deadline_uses_the_injected_clock() -> None:
    ticks = itertools.count()
    rm = random_graph(0)
    planner = Planner(rm, PointRobot(), config=config(), timer=lambda: float(next(ticks)))
    res = planner.plan(q_start=rm.ik[0, 0], t_start=0.0, goal="g", forecast=None, deadline_s=2.5)
    assert not res.ok and res.reason == "deadline"


def test_emergency_stays_when_safe_and_escapes_when_not() -> None:
    rm = roadmap([(0.0, 0.0), (0.3, 0.0), (0.6, 0.0), (0.9, 0.0)], [(0, 1), (1, 2), (2, 3)], g=3)
    planner = Planner(rm, PointRobot(), config=config(emergency_hold_s=0.2))
    far = person([0.0, 1.0], [(3.0, 3.0), (2.0, 2.0)])
    res = planner.emergency(q_start=q_of(0.3, 0.0), t_start=0.0, forecast=far, horizon_s=0.15)
    assert res.ok and res.reason == "stay"
    np.testing.assert_allclose(res.trajectory.q(0.1), q_of(0.3, 0.0))
    # the person comes to stand 0.18 m from the robot (needs 0.2 m): the robot backs away from them
    near = person([0.0, 1.0], [(0.42, 0.1), (0.0, 0.0)])
    res = planner.emergency(q_start=q_of(0.3, 0.0), t_start=0.0, forecast=near, horizon_s=0.15)
    assert res.ok and res.reason == "ok", res.reason
    end = res.trajectory.q(res.trajectory.t_end)
    assert end[0] < 0.3  # moved away from the person (x = 0.42)
    assert res.trajectory.t_end >= 0.15
    d = np.linalg.norm(
        res.trajectory.q(np.linspace(0, res.trajectory.t_end, 50))[:, :2] - [0.42, 0.1], axis=1
    )
    assert np.all(np.diff(d) >= -1e-9)  # never closer than it started


def test_static_obstacles_block_start_connections() -> None:
    # the start is connected to its 2 nearest nodes; a box lies between the start and the nearer one
    rm = roadmap([(0.3, 0.0), (0.0, 0.5), (0.6, 0.6)], [(0, 2), (1, 2)], g=2)
    model = PointRobot(boxes=[((0.12, -0.2, -0.2), (0.18, 0.2, 0.2))])
    planner = Planner(rm, model, config=config(start_neighbors=2))
    res = planner.plan(q_start=q_of(0.0, 0.0), t_start=0.0, goal="g", forecast=None)
    assert res.ok
    assert [n for n in res.plan.nodes.tolist() if n >= 0] == [1, 2]


def _time_to_go(rm: Roadmap, goal: int, speed: float) -> np.ndarray:
    """Plain Dijkstra from the goal (branch 0, max-norm joint distance / speed): the true time-to-go."""
    dist = np.full(rm.num_nodes, np.inf)
    dist[goal] = 0.0
    heap = [(0.0, goal)]
    while heap:
        d, u = heapq.heappop(heap)
        if d > dist[u]:
            continue
        for v in rm.neighbors(u).tolist():
            nd = d + float(np.max(np.abs(rm.ik[v, 0] - rm.ik[u, 0]))) / speed
            if nd < dist[v]:
                dist[v] = nd
                heapq.heappush(heap, (nd, v))
    return dist


@pytest.mark.parametrize("seed", [0, 3])
def test_the_static_heuristic_is_the_true_time_to_go_and_never_more(seed: int) -> None:
    rm = random_graph(seed, n=40)
    planner = Planner(rm, PointRobot(), config=config(shortcut=False))  # h bounds the search's paths
    for goal in (1, 7):
        truth = _time_to_go(rm, goal, 0.5)
        h = planner._heuristic_table(goal)[:, 0]
        reach = np.isfinite(truth)
        assert np.all(h[reach] <= truth[reach] + 1e-9)  # admissible
        np.testing.assert_allclose(h[reach], truth[reach], atol=1e-9)  # and exact on a one-branch roadmap
        assert np.all(np.isinf(h[~reach]))  # nodes that cannot reach the goal are pruned
    # plain A* with it still returns a shortest path (the test above) and the plan lasts at least h
    res = planner.plan(q_start=rm.ik[0, 0], t_start=0.0, goal="g", forecast=None)
    assert res.ok
    assert res.plan.t_end >= planner._heuristic_table(1)[0, 0] - 1e-9


def test_a_goal_that_cannot_be_entered_once_the_person_holds_still_fails_fast() -> None:
    # a corridor s - a - b - g and a grid of 64 nodes behind the start; the person comes to stand beside
    # the corridor between b and g (the goal itself stays free) before the robot could get there
    corridor = [(0.0, 0.0), (0.3, 0.0), (0.6, 0.0), (0.9, 0.0)]
    side = [(-0.1 - 0.1 * i, -0.35 + 0.1 * j) for i in range(8) for j in range(8)]
    pts = corridor + side
    edges = [(0, 1), (1, 2), (2, 3), (0, 4 + 3), (0, 4 + 4)]
    for i in range(8):
        for j in range(8):
            k = 4 + 8 * i + j
            if j + 1 < 8:
                edges.append((k, k + 1))
            if i + 1 < 8:
                edges.append((k, k + 8))
    rm = roadmap(pts, edges, s=0, g=3)
    fc = person([0.0, 0.2, 0.25], [(3.0, 3.0), (3.0, 3.0), (0.7, 0.1)])
    exhaustive = Planner(rm, PointRobot(), config=config(probe_after_expansions=10**6))
    probed = Planner(rm, PointRobot(), config=config(probe_after_expansions=5))
    slow = exhaustive.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc)
    fast = probed.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc, workers=4)
    for res in (slow, fast):
        assert not res.ok and res.plan is None and res.trajectory is None
    assert "blocked once the person holds still" in fast.reason
    assert fast.blocked == "goal"
    assert fast.expanded < 20 < len(side) <= slow.expanded  # the exhaustive search visits the side area
    # the same goal is planned to when the person stands further off the corridor
    away = person([0.0, 0.2, 0.25], [(3.0, 3.0), (3.0, 3.0), (0.7, 0.35)])
    res = probed.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=away, workers=4)
    assert res.ok, res.reason
    assert res.blocked is None
    assert_valid(res.trajectory, away, hold_s=0.2)


def test_a_failed_query_says_whether_the_person_was_in_the_way() -> None:
    from app.planning.search.config import blocked_by_person

    assert blocked_by_person("start configuration violates the separation at t_start") == "start"
    assert blocked_by_person("goal blocked by the person for good") == "goal"
    assert blocked_by_person("goal blocked by the person from t=+0.40 s on") == "goal"
    reason = "goal unreachable: every way into it is blocked once the person holds still (t=+0.50 s), ..."
    assert blocked_by_person(reason) == "goal"
    for other in (
        "goal unreachable: no safe path found after 12 expansions",
        "trajectory failed verification against the forecast",
        "deadline",
        "goal node has no valid IK branch",
        "ok",
    ):
        assert blocked_by_person(other) is None, other


def test_a_hand_resting_beside_the_goal_makes_the_robot_creep_in() -> None:
    # the speed term matters here: S_r + S_s = 0.3 s x robot speed; the person's ball rests 0.25 m beside g
    ssm = SSMParams(t_reaction_s=0.3, t_stop_s=0.0, intrusion_m=0.0, z_human_m=0.1, z_robot_m=0.0)
    rm = roadmap([(0.0, 0.0), (0.3, 0.0), (0.6, 0.0)], [(0, 1), (1, 2)], s=0, g=2)
    fc = person([0.0], [(0.6, 0.25)])
    cruise_only = Planner(rm, PointRobot(), config=config(ssm=ssm, max_wait_s=0.0))
    creeping = Planner(rm, PointRobot(), config=config(ssm=ssm, slow_speed_fractions=(0.2, 0.08)))
    assert not cruise_only.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc).ok
    res = creeping.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc)
    assert res.ok, res.reason
    assert_valid(res.trajectory, fc, hold_s=0.2, ssm=ssm)
    # the last 0.3 m take far longer than at 0.2 of full speed (1.5 s): the robot creeps in
    t_b = res.plan.times[np.flatnonzero(np.abs(res.plan.q[:, 0] - 0.3) < 1e-9)[-1]]
    assert res.plan.t_end - t_b > 2.0


def test_profile_samples_bound_the_path_speed_between_samples() -> None:
    from app.planning.search.profiles import _profile_arrays, _profile_samples

    rng = np.random.default_rng(2)
    A = 2.0
    for _ in range(200):
        f = float(rng.choice([0.5, 0.2, 0.08]))
        u0 = float(rng.uniform(0.0, f))
        L = float(rng.uniform(0.0, 0.4))
        end = bool(rng.random() < 0.5)
        dur = float(_profile_arrays(np.array([u0]), np.array([L]), np.array([f]), A, np.array([end]))[0][0])
        s = np.linspace(0.0, dur, 401)
        one = np.ones_like(s)
        frac, _ = _profile_samples(s, s, u0 * one, L * one, dur * one, f * one, A, np.full(s.shape, end))
        assert frac[0] == pytest.approx(0.0, abs=1e-9) and frac[-1] == pytest.approx(1.0, abs=1e-6)
        assert np.all(np.diff(frac) >= -1e-12)
        speed = np.gradient(frac * L, s) if dur > 0 else np.zeros_like(s)
        # the bound over [s_k, s_k+1] is at least the (numerical) speed anywhere inside it
        _, bound = _profile_samples(
            s[1:], s[:-1], u0 * one[1:], L * one[1:], dur * one[1:], f * one[1:], A, np.full(s.size - 1, end)
        )
        inside = np.maximum(speed[1:], speed[:-1])
        assert np.all(bound >= inside - 2e-3 * max(f, 1e-3))
        assert np.all(bound <= f + 1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_batched_search_with_lookahead_keeps_the_sequential_plan_cost(seed: int) -> None:
    rm = random_graph(seed, n=40)
    fc = person([0.0, 1.0, 2.0], [(1.0, 0.2), (1.2, 1.0), (0.8, 1.6)])
    planner = Planner(rm, PointRobot(), config=config(slow_speed_fractions=(0.2,), max_wait_s=0.6))
    costs = []
    for workers in (1, 4, 16, 64):
        res = planner.plan(q_start=rm.ik[0, 0], t_start=0.0, goal="g", forecast=fc, workers=workers)
        assert res.ok, res.reason
        assert_valid(res.trajectory, fc, hold_s=0.2)
        costs.append(res.plan.t_end)
    np.testing.assert_allclose(costs, costs[0], atol=0.05)


def test_a_spline_that_would_cut_a_corner_into_an_obstacle_stops_at_the_waypoints() -> None:
    # s -> m -> g bends left; the spline through m swings out to the right, toward a box that the straight
    # move s -> m clears by 1.4 cm (the ball robot's radius is 5 cm)
    rm = roadmap([(0.0, 0.0), (0.5, 0.1), (0.6, 0.6)], [(0, 1), (1, 2)], s=0, g=2)
    box = ((0.25, -0.3, -0.2), (0.4, -0.015, 0.2))
    model = PointRobot(boxes=[box])
    planner = Planner(rm, model, config=config(qdd_max=(2.0,) * 6, shortcut=False))
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=None)
    assert res.ok, res.reason
    t = np.arange(res.trajectory.t_start, res.trajectory.t_end + 1e-9, 0.01)
    assert not np.any(model.in_static_collision(res.trajectory.q(t)))
    # the plain spline through the corner would have hit the box
    smooth = planner._fit(res.plan, None)
    assert smooth is not None
    assert np.any(model.in_static_collision(smooth.q(np.arange(smooth.t_start, smooth.t_end, 0.01))))


# --------------------------------------------------------------------------------------------- shortcuts
def u_shape() -> Roadmap:
    """s (0, 0) -> d1 (0, 0.6) -> d2 (1, 0.6) -> g (1, 0): the only way round is a U; s - g is no edge."""
    return roadmap([(0.0, 0.0), (0.0, 0.6), (1.0, 0.6), (1.0, 0.0)], [(0, 1), (1, 2), (2, 3)], s=0, g=3)


def test_a_zig_zag_path_becomes_one_straight_move_that_is_faster_and_valid() -> None:
    # the only way is a zig-zag in y (0.3 per edge) while x advances 0.2 per edge: 4 x 0.6 s, direct 1.6 s
    pts = [(0.0, 0.0), (0.2, 0.3), (0.4, 0.0), (0.6, 0.3), (0.8, 0.0)]
    rm = roadmap(pts, [(i, i + 1) for i in range(4)], s=0, g=4)
    fc = person([0.0, 1.0], [(0.4, -1.0), (0.4, -0.9)])  # beside the corridor, never in the way
    for forecast in (None, fc):
        raw = Planner(rm, PointRobot(), config=config(shortcut=False)).plan(
            q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=forecast
        )
        res = Planner(rm, PointRobot(), config=config()).plan(
            q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=forecast
        )
        assert raw.ok and res.ok, (raw.reason, res.reason)
        assert raw.plan.q.shape[0] == 5  # the search's path visits every node
        assert res.plan.q.shape[0] == 2 and res.plan.nodes.tolist() == [0, 4]
        assert res.trajectory.duration < raw.trajectory.duration - 0.6
        assert res.trajectory.duration == pytest.approx(0.8 / 0.5, abs=0.05)
        assert_valid(res.trajectory, forecast, hold_s=0.2)


def test_the_clearance_holds_the_stopping_models_stop() -> None:
    """A sample's clearance holds the robot's stop by the planner's stopping model at its speeds (the
    governor's and the monitor's model): a sample that keeps the clearance of a robot that stops at once
    breaks that of one braking at 1 m/s^2 and 1 rad/s^2, the more so the faster its joints turn; the plan past
    the person then creeps, and keeps that clearance all the way."""
    rm = roadmap([(0.0, 0.0), (1.0, 0.0)], [(0, 1)], s=0, g=1)
    fc = person([0.0], [(0.5, 0.3)])  # the straight move passes the person 0.2 m apart (surfaces)
    slow = StoppingModel(decel_mps2=1.0, joint_decel_radps2=1.0)
    q, t = q_of(0.5, 0.0)[None], np.zeros(1)

    def keeps(stopping: StoppingModel, v: float, w: float) -> bool:
        sep = Planner(rm, PointRobot(), config=config(stopping=stopping))._separation(fc, extra_m=0.0)
        return bool(sep.check(q, t, np.array([v]), np.array([w]))[0])

    # needed: Z_d 0.1 + v T_r (0.01 v) + S_s = v T_s / 2, T_s = max(v / 1, w / 1) with the slow brake
    assert keeps(INSTANT_STOP, 0.6, 0.6)  # 0.106
    assert not keeps(slow, 0.6, 0.6)  # 0.106 + 0.18
    assert keeps(slow, 0.3, 0.3)  # 0.103 + 0.045
    assert not keeps(slow, 0.3, 0.9)  # 0.103 + 0.135: the joints' stop rules
    assert keeps(slow, 0.0, 0.0)
    fast = Planner(rm, PointRobot(), config=config()).plan(
        q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc
    )
    creep = Planner(rm, PointRobot(), config=config(stopping=slow, slow_speed_fractions=(0.2, 0.08))).plan(
        q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc
    )
    assert fast.ok and creep.ok, (fast.reason, creep.reason)
    assert creep.trajectory.duration > 2.0 * fast.trajectory.duration
    assert_valid(creep.trajectory, fc, hold_s=0.2, stopping=slow)
    with pytest.raises(AssertionError, match="violation"):
        assert_valid(
            fast.trajectory, fc, hold_s=0.2, stopping=slow
        )  # at cruise speed it would not stop in time


@pytest.mark.parametrize("rounds", [2, 3])  # 2: the last move is the search's own, checked after the rounds
def test_a_person_on_the_direct_move_keeps_the_detour_where_they_are_in_the_way(rounds: int) -> None:
    rm = u_shape()
    planner = Planner(rm, PointRobot(), config=config(shortcut_rounds=rounds))
    raw = Planner(rm, PointRobot(), config=config(shortcut=False))
    # the person stands on the straight line s - g: that shortcut is never taken, but s - d2 passes them
    # 0.16 m away (0.1 m needed) and cuts the corner at d1
    blocking = person([0.0], [(0.5, 0.0)])
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=blocking)
    unshortened = raw.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=blocking)
    assert res.ok and unshortened.ok, res.reason
    assert res.plan.nodes.tolist() == [0, 2, 3]
    assert res.trajectory.duration < unshortened.trajectory.duration
    assert_valid(res.trajectory, blocking, hold_s=0.2)
    # the shortcut is checked over time: a person who arrives on that line only after the robot has passed
    # does not block it, one who is there while the robot would be does
    late = person([0.0, 4.9, 5.0], [(0.5, -2.0), (0.5, -2.0), (0.5, 0.0)])
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=late)
    assert res.ok and res.plan.nodes.tolist() == [0, 3]
    assert_valid(res.trajectory, late, hold_s=0.2)
    early = person([0.0, 0.9, 1.0, 1.5, 1.6], [(0.5, -2.0), (0.5, -2.0), (0.5, 0.0), (0.5, 0.0), (0.5, -2.0)])
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=early)
    assert res.ok and res.plan.nodes.tolist() != [0, 3]
    assert_valid(res.trajectory, early, hold_s=0.2)


def test_a_box_on_the_direct_move_keeps_the_detour() -> None:
    rm = u_shape()
    model = PointRobot(boxes=[((0.45, -0.2, -0.2), (0.55, 0.15, 0.2))])  # across the line s - g only
    res = Planner(rm, model, config=config()).plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=None)
    assert res.ok
    assert res.plan.nodes.tolist() == [0, 2, 3]  # s - d2 passes the box's corner (0.45, 0.15) 0.05 m clear
    t = np.arange(res.trajectory.t_start, res.trajectory.t_end + 1e-9, 0.01)
    assert not np.any(model.in_static_collision(res.trajectory.q(t)))


def test_a_shortcut_that_fails_verification_falls_back_to_the_search_path() -> None:
    # a shortcut straight through a box (as a faulty shortcut step would propose it) never comes out:
    # the fitted shortcut is verified like any plan and the search's own path is returned instead
    rm = u_shape()
    model = PointRobot(boxes=[((0.45, -0.2, -0.2), (0.55, 0.2, 0.2))])
    planner = Planner(rm, model, config=config())
    reference = Planner(rm, model, config=config(shortcut=False)).plan(
        q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=None
    )
    proposed: list[Plan] = []

    def through_the_box(waypoints: Plan, sep: object, *, hold_s: float) -> Plan:
        bad = Plan(times=[0.0, 2.0], q=[q_of(0, 0), q_of(1.0, 0.0)], nodes=[0, 3])
        proposed.append(bad)
        return bad

    planner._shortcut = through_the_box  # type: ignore[method-assign]
    res = planner.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=None)
    assert proposed and res.ok
    assert res.plan.nodes.tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(res.trajectory.knot_q, reference.trajectory.knot_q)
    t = np.arange(res.trajectory.t_start, res.trajectory.t_end + 1e-9, 0.01)
    assert not np.any(model.in_static_collision(res.trajectory.q(t)))


def test_waits_and_the_moves_before_them_are_kept() -> None:
    # the corridor of the waiting test: the part before the wait keeps the search's times exactly
    rm = roadmap([(0.2 * i, 0.0) for i in range(6)], [(i, i + 1) for i in range(5)], s=0, g=5)
    fc = person(
        [0.0, 0.7, 0.75, 1.6, 1.65, 4.0],
        [(0.6, 3.0), (0.6, 3.0), (0.6, 0.15), (0.6, 0.15), (0.6, 3.0), (0.6, 3.0)],
    )
    short = Planner(rm, PointRobot(), config=config(max_wait_s=1.5))
    raw = Planner(rm, PointRobot(), config=config(max_wait_s=1.5, shortcut=False))
    res = short.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc)
    ref = raw.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc)
    assert res.ok and ref.ok
    q = res.plan.q
    waits = [i for i in range(len(q) - 1) if np.allclose(q[i], q[i + 1])]
    assert waits
    # up to the end of the wait both trajectories are the same
    t_dep = res.plan.times[waits[-1] + 1]
    ts = np.linspace(0.0, t_dep, 50)
    np.testing.assert_allclose(res.trajectory.q(ts), ref.trajectory.q(ts), atol=1e-9)
    assert res.trajectory.t_end <= ref.trajectory.t_end + 1e-9
    assert_valid(res.trajectory, fc, hold_s=0.2)
