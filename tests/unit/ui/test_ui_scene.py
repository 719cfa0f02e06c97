"""The viser scene: built once, then updated in place from runtime snapshots (no browser)."""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pytest

from app.config import load_workcell
from app.prediction.skeleton import BONES, JOINT_INDEX, NUM_JOINTS
from app.ui.scene import (
    COLOR_DANGER,
    COLOR_IDLE,
    COLOR_OK,
    COLOR_WARN,
    CellScene,
    CellView,
    state_style,
)

viser = pytest.importorskip("viser")

L_LINKS = 4


@dataclass(frozen=True)
class FakeSnapshot:
    """The attributes of the runtime's Snapshot that the scene reads (CONTRACTS.md)."""

    t: float
    state: str = "nominal"
    q: np.ndarray = field(default_factory=lambda: np.zeros(6))
    p_world_tcp: np.ndarray = field(default_factory=lambda: np.array([0.3, 0.0, 0.4]))
    skeleton: np.ndarray | None = None
    forecast: np.ndarray | None = None
    plan_tcp: np.ndarray | None = None
    backup_tcp: np.ndarray | None = None
    required_separation_m: float | None = 0.4
    separation_m: float | None = 1.0
    speed_scale: float = 1.0
    stale: bool = False
    estopped: bool = False
    method: str | None = "proactive"
    trial_id: int | None = None
    trial_elapsed_s: float | None = None
    trial_duration_s: float | None = None


def fake_capsules(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A toy arm: L_LINKS vertical capsules whose x offset is q[:, 0] (so q visibly moves them)."""
    q = np.asarray(q, dtype=float)
    z = np.arange(L_LINKS + 1) * 0.2
    pts = np.zeros((q.shape[0], L_LINKS + 1, 3))
    pts[:, :, 2] = z
    pts[:, :, 0] = q[:, :1]
    return pts[:, :-1], pts[:, 1:], np.full(L_LINKS, 0.05)


def skeleton(x: float = 1.3, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([x, 0.0, 0.0]) + rng.uniform(-0.3, 0.3, (NUM_JOINTS, 3))


@pytest.fixture()
def server() -> Iterator[Any]:
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        yield s
    finally:
        s.stop()


@pytest.fixture(scope="module")
def cell() -> Any:
    return load_workcell()


def node_names(server: Any) -> set[str]:
    return set(server.scene._handle_from_node_name)


def test_state_style_colours() -> None:
    assert state_style("nominal") == ("NOMINAL", COLOR_OK)
    assert state_style("collision_avoidance")[1] == COLOR_WARN
    assert state_style("stop_replan")[1] == COLOR_DANGER
    assert state_style("idle") == ("IDLE", COLOR_IDLE)
    assert state_style("nominal", estopped=True) == ("E-STOP", COLOR_DANGER)
    text, color = state_style("nominal", stale=True)
    assert "STALE" in text and color == COLOR_DANGER


def test_apply_updates_handles_in_place(server: Any, cell: Any) -> None:
    view = CellView(server, cell, robot_capsules=fake_capsules, roadmap_nodes=np.zeros((5, 3)), ghosts=4)
    handles_before = dict(view.handles)
    names_before = node_names(server)

    sk = skeleton()
    forecast = np.stack([sk + 0.01 * k for k in range(10)])
    plan = np.linspace([0.3, -0.5, 0.2], [0.6, 0.3, 0.1], 12)
    snaps = [
        FakeSnapshot(
            t=0.0, q=np.full(6, 0.1), skeleton=sk, forecast=forecast, plan_tcp=plan, backup_tcp=plan[:5]
        ),
        FakeSnapshot(
            t=0.1, q=np.full(6, -0.2), state="collision_avoidance", separation_m=0.5, speed_scale=0.4
        ),
        FakeSnapshot(t=0.2, q=np.full(6, 0.3), skeleton=sk + 0.1, plan_tcp=plan[:7], estopped=True),
    ]
    for snap in snaps:
        view.apply(snap)
        # Same handle objects, same scene nodes: nothing is created or removed by an update.
        assert dict(view.handles) == handles_before
        assert all(view.handles[k] is handles_before[k] for k in handles_before)
        assert node_names(server) == names_before
    assert view.applied == len(snaps)

    h = view.handles
    # Last snapshot: robot moved to x = 0.3, person shown at the new pose, no forecast, plan shortened.
    links = h["robot_links"]
    assert np.allclose(links.batched_positions[:, 0], 0.3, atol=1e-5)
    assert np.allclose(links.batched_scales[:, 2], 0.2, atol=1e-5)
    assert np.all(links.batched_colors == np.array(COLOR_DANGER, dtype=np.uint8))  # E-stop: red arm
    assert h["person_joints"].visible and h["person_bones"].visible
    assert np.allclose(h["person_joints"].batched_positions, sk + 0.1, atol=1e-5)
    assert not h["forecast_ghosts"].visible
    assert h["plan"].visible and h["plan"].points.shape == (6, 2, 3)
    assert np.allclose(h["plan"].points[:, 0], plan[:6], atol=1e-5)
    assert not h["backup"].visible
    assert h["state_label"].text.startswith("E-STOP")


def test_person_forecast_and_separation(server: Any, cell: Any) -> None:
    view = CellView(server, cell, robot_capsules=fake_capsules, ghosts=3)
    sk = skeleton()
    forecast = np.stack([sk + np.array([0.05 * k, 0.0, 0.0]) for k in range(31)])
    view.apply(
        FakeSnapshot(
            t=1.0,
            skeleton=sk,
            forecast=forecast,
            required_separation_m=0.35,
            separation_m=0.3,
            p_world_tcp=np.array([0.4, 0.1, 0.3]),
        )
    )
    h = view.handles
    ghosts = h["forecast_ghosts"]
    nb = len(BONES)
    assert ghosts.visible
    # Three ghosts at indices 1, 15, 30: the last one ends the horizon; the near ones are more opaque.
    pos = ghosts.batched_positions.reshape(3, nb, 3)
    mids = (forecast[:, BONES[:, 0]] + forecast[:, BONES[:, 1]]) / 2
    assert np.allclose(pos[0], mids[1], atol=1e-5) and np.allclose(pos[2], mids[30], atol=1e-5)
    opac = ghosts.batched_opacities.reshape(3, nb)
    assert np.all(np.diff(opac[:, 0]) < 0)
    sphere = h["separation"]
    assert sphere.visible and np.isclose(sphere.scale, 0.35)
    assert np.allclose(sphere.position, [0.4, 0.1, 0.3])
    assert tuple(sphere.color) == COLOR_DANGER  # 0.30 m < 0.35 m required
    assert np.allclose(h["tcp"].position, [0.4, 0.1, 0.3])

    # The person leaves: skeleton, ghosts and sphere colour follow; no separation -> sphere hidden.
    view.apply(FakeSnapshot(t=2.0, required_separation_m=None, separation_m=None))
    assert not h["person_joints"].visible and not ghosts.visible and not sphere.visible


def test_invalid_arrays_are_hidden_not_drawn(server: Any, cell: Any) -> None:
    view = CellView(server, cell, robot_capsules=fake_capsules)
    bad = skeleton()
    bad[3] = np.nan
    view.apply(FakeSnapshot(t=0.0, skeleton=bad, plan_tcp=np.zeros((1, 3)), forecast=np.zeros((5, 7, 3))))
    h = view.handles
    assert not h["person_joints"].visible  # NaN joint: not drawn
    assert not h["plan"].visible  # a single point is no path
    assert not h["forecast_ghosts"].visible  # wrong joint count
    with pytest.raises(ValueError, match=r"snapshot\.q"):
        view.apply(FakeSnapshot(t=0.0, q=np.full(6, np.nan)))


def test_layer_toggles(server: Any, cell: Any) -> None:
    """A layer's group frame says whether it is on (by default); a node, whether it has something to show."""
    nodes = np.random.default_rng(1).uniform(size=(20, 3))
    view = CellView(server, cell, robot_capsules=fake_capsules, roadmap_nodes=nodes)
    h = view.handles
    assert not h["layer_roadmap"].visible  # off by default
    view.set_layer("roadmap", True)
    assert h["layer_roadmap"].visible
    plan = np.linspace([0.3, -0.5, 0.2], [0.6, 0.3, 0.1], 5)
    view.apply(FakeSnapshot(t=0.0, plan_tcp=plan))
    assert h["plan"].visible and h["layer_plans"].visible
    view.set_layer("plans", False)
    assert not h["layer_plans"].visible
    view.apply(FakeSnapshot(t=0.1, plan_tcp=plan))
    assert not h["layer_plans"].visible  # stays hidden while the layer is off
    view.set_layer("plans", True)
    assert h["layer_plans"].visible and h["plan"].visible
    layers = {"/roadmap/nodes", "/plans/executing", "/forecast/ghosts", "/safety/separation"}
    assert layers <= node_names(server)
    with pytest.raises(ValueError, match="unknown layer"):
        view.set_layer("nope", True)


# ---------------------------------------------------------------------------------------------- CellScene


class FakeSubscription:
    """Bounded, drop-oldest, like ``Runtime.subscribe``."""

    def __init__(self, maxsize: int) -> None:
        self.q: queue.Queue[Any] = queue.Queue(maxsize)
        self.closed = False

    def put(self, item: Any) -> None:
        while True:
            try:
                self.q.put_nowait(item)
                return
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self.q.get_nowait()

    def get(self, timeout: float) -> Any | None:
        try:
            return self.q.get(timeout=timeout) if timeout > 0 else self.q.get_nowait()
        except queue.Empty:
            return None

    def close(self) -> None:
        self.closed = True


class FakeRuntime:
    def __init__(self, backlog: list[Any] | None = None) -> None:
        self.latest = FakeSnapshot(t=0.0, state="idle")
        self.subs: list[FakeSubscription] = []
        self.backlog = backlog or []
        self.lock = threading.Lock()

    def snapshot(self) -> Any:
        return self.latest

    def subscribe(self, maxsize: int = 8) -> FakeSubscription:
        sub = FakeSubscription(max(maxsize, len(self.backlog), 1))
        for s in self.backlog:
            sub.put(s)
        with self.lock:
            self.subs.append(sub)
        return sub

    def publish(self, snap: Any) -> None:
        """Never blocks, whatever the scene does (a full queue drops its oldest entry)."""
        self.latest = snap
        with self.lock:
            for s in self.subs:
                s.put(snap)


def wait_for(cond: Any, what: str, *, tries: int = 500) -> None:
    for _ in range(tries):
        if cond():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


def test_cell_scene_follows_the_runtime_and_stops(cell: Any) -> None:
    rt = FakeRuntime()
    scene = CellScene(rt, cell, port=0, robot_capsules=fake_capsules)
    assert scene.port == 0
    scene.start()
    try:
        assert scene.port > 0 and scene.running
        assert scene.frames_applied == 1  # the initial snapshot
        assert scene.view.handles["state_label"].text.startswith("IDLE")
        handles = dict(scene.view.handles)
        names = node_names(scene.server)
        for k in range(1, 6):
            rt.publish(FakeSnapshot(t=k * 0.1, q=np.full(6, 0.05 * k), skeleton=skeleton(seed=k)))
        last = rt.latest
        wait_for(
            lambda: np.allclose(scene.view.handles["robot_links"].batched_positions[:, 0], 0.25, atol=1e-5),
            "the newest snapshot to be drawn",
        )
        assert np.allclose(scene.view.handles["person_joints"].batched_positions, last.skeleton, atol=1e-5)
        assert dict(scene.view.handles) == handles and node_names(scene.server) == names
        with pytest.raises(RuntimeError, match="twice"):
            scene.start()
    finally:
        scene.stop()
    assert not scene.running
    assert rt.subs[0].closed
    scene.stop()  # idempotent


def test_cell_scene_coalesces_a_backlog_and_survives_bad_snapshots(cell: Any) -> None:
    backlog = [FakeSnapshot(t=0.1 * k, q=np.full(6, 0.1 * k)) for k in range(1, 4)]
    rt = FakeRuntime(backlog=backlog)
    with CellScene(rt, cell, port=0, robot_capsules=fake_capsules, rate_hz=60) as scene:
        # The three queued snapshots are coalesced: only the newest is drawn.
        wait_for(lambda: scene.frames_applied >= 2, "the backlog to be drawn")
        assert scene.frames_skipped == 2
        assert np.allclose(scene.view.handles["robot_links"].batched_positions[:, 0], 0.3, atol=1e-5)
        # A broken snapshot is logged and counted; the thread keeps going.
        rt.publish(replace(backlog[0], q=np.full(6, np.nan)))
        wait_for(lambda: scene.errors == 1, "the bad snapshot to be rejected")
        rt.publish(FakeSnapshot(t=1.0, q=np.full(6, -0.4)))
        wait_for(
            lambda: np.allclose(scene.view.handles["robot_links"].batched_positions[:, 0], -0.4, atol=1e-5),
            "drawing to resume after a bad snapshot",
        )
        assert scene.running


def test_cell_scene_checks_its_arguments(cell: Any) -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        CellScene(FakeRuntime(), cell, port=0, rate_hz=0)
    scene = CellScene(FakeRuntime(), cell, port=0, robot_capsules=fake_capsules)
    with pytest.raises(RuntimeError, match="after start"):
        _ = scene.view


def test_cell_scene_default_robot_model_is_the_collision_model(cell: Any) -> None:
    """Without an override the arm is drawn from ``CollisionModel.robot_capsules`` (the planner's model)."""
    from app.planning.collision import CollisionModel

    rt = FakeRuntime()
    q = np.asarray(cell.robot.home_q)
    rt.latest = FakeSnapshot(t=0.0, q=q)
    with CellScene(rt, cell, port=0) as scene:
        a, b, r = CollisionModel(cell).robot_capsules(q[None])
        links = scene.view.handles["robot_links"]
        assert links.batched_positions.shape == (a.shape[1], 3)
        assert np.allclose(links.batched_positions, ((a + b) / 2)[0], atol=1e-4)
        assert np.allclose(links.batched_scales[:, 0], r, atol=1e-6)


def test_texts_refresh_on_state_change_and_at_most_a_few_times_a_second(server: Any, cell: Any) -> None:
    view = CellView(server, cell, robot_capsules=fake_capsules)
    label = view.handles["state_label"]
    view.apply(FakeSnapshot(t=10.0, speed_scale=1.0))
    assert label.text == "NOMINAL · speed 100%"
    view.apply(FakeSnapshot(t=10.1, speed_scale=0.5))  # same state, 0.1 s later: text kept
    assert label.text == "NOMINAL · speed 100%"
    view.apply(FakeSnapshot(t=10.2, state="collision_avoidance", speed_scale=0.4))  # new state: at once
    assert label.text == "COLLISION AVOIDANCE · speed 40%"
    view.apply(FakeSnapshot(t=10.5, state="collision_avoidance", speed_scale=0.3))  # 0.3 s later: refreshed
    assert label.text == "COLLISION AVOIDANCE · speed 30%"
    assert "**State:** COLLISION AVOIDANCE" in view.handles["gui_status"].content


def test_the_runtimes_own_snapshot_and_subscription_drive_the_scene(cell: Any) -> None:
    """Contract check against SUP's real ``Snapshot`` and ``Subscription`` (not the doubles above)."""
    from app.control.results import Snapshot
    from app.control.runtime import Subscription

    def snap(t: float, x: float, **kw: Any) -> Snapshot:
        sk = skeleton(seed=int(t * 10))
        return Snapshot(
            t=t,
            trial_id=3,
            state="nominal",
            method="proactive",
            speed_scale=0.8,
            separation_m=0.9,
            required_separation_m=0.35,
            planning_ms=(12.0, 15.0),
            counters={"plans_computed": 2},
            q=np.full(6, x),
            p_world_tcp=np.array([0.4, 0.0, 0.3]),
            skeleton=sk,
            forecast=np.stack([sk] * 5),
            plan_tcp=np.linspace([0.4, 0.0, 0.3], [0.6, 0.2, 0.1], 8),
            trial_elapsed_s=t,
            trial_duration_s=60.0,
            **kw,
        )

    class Runtime:
        def __init__(self) -> None:
            self.sub: Subscription | None = None

        def snapshot(self) -> Snapshot:
            return snap(0.0, 0.0)

        def subscribe(self, maxsize: int = 8) -> Subscription:
            self.sub = Subscription(maxsize)
            return self.sub

    rt = Runtime()
    with CellScene(rt, cell, port=0, robot_capsules=fake_capsules) as scene:
        assert rt.sub is not None
        for k in range(1, 20):  # more than the queue holds: the oldest are dropped, never blocking
            rt.sub.put(snap(k / 30, 0.01 * k))
        wait_for(
            lambda: np.allclose(scene.view.handles["robot_links"].batched_positions[:, 0], 0.19, atol=1e-5),
            "the newest real snapshot to be drawn",
        )
        assert scene.view.handles["plan"].visible and scene.view.handles["forecast_ghosts"].visible
        rt.sub.put(snap(1.0, 0.2, estopped=True))
        wait_for(lambda: scene.view.handles["state_label"].text.startswith("E-STOP"), "the E-stop to show")
    assert rt.sub.closed


def test_roadmap_nodes_default_to_the_runtimes_roadmap(cell: Any) -> None:
    class Roadmap:
        nodes = np.random.default_rng(2).uniform(-0.5, 0.5, (30, 3))

    rt = FakeRuntime()
    rt.roadmap = Roadmap()  # type: ignore[attr-defined]
    with CellScene(rt, cell, port=0, robot_capsules=fake_capsules) as scene:
        points = scene.view.handles["roadmap"]
        assert points.points.shape == (30, 3)
        assert not scene.view.handles["layer_roadmap"].visible  # toggled on from a viewer's GUI


# ---------------------------------------------------------------------------------------------- viewers

TOKEN = "scene-token-0123456789abcdef"


def _connect_viewer(port: int) -> Any:
    """A viewer as viser's browser client connects: its WebSocket (with the token), then its camera (viser
    counts a client as connected from its first camera message)."""
    import msgspec
    from viser import _messages
    from websockets.sync.client import connect

    ws = connect(
        f"ws://127.0.0.1:{port}/?token={TOKEN}",
        subprotocols=[f"viser-v{viser.__version__}"],
        open_timeout=10,
        close_timeout=5,
        max_size=None,
    )
    camera = _messages.ViewerCameraMessage(
        wxyz=(1.0, 0.0, 0.0, 0.0),
        position=(2.0, -2.0, 1.5),
        fov=1.0,
        near=0.01,
        far=100.0,
        image_height=480,
        image_width=640,
        look_at=(0.0, 0.0, 0.0),
        up_direction=(0.0, 0.0, 1.0),
    )
    ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
    return ws


def test_layer_toggles_are_each_viewers_own(cell: Any) -> None:
    """Two viewers: each has its own layer toggles; one switching a layer on changes its own group frame
    (a client-scoped variant) and neither the other's nor the server's."""

    class Roadmap:
        nodes = np.random.default_rng(3).uniform(-0.5, 0.5, (10, 3))

    rt = FakeRuntime()
    with CellScene(rt, cell, port=0, robot_capsules=fake_capsules, roadmap=Roadmap(), token=TOKEN) as scene:
        a, b = _connect_viewer(scene.port), _connect_viewer(scene.port)
        try:
            wait_for(lambda: len(scene.server.get_clients()) == 2, "both viewers to connect")
            ids = sorted(scene.server.get_clients())
            wait_for(lambda: all(scene.view.client_layers(i) is not None for i in ids), "their toggles")
            mine, theirs = (scene.view.client_layers(i) for i in ids)
            assert mine is not None and theirs is not None and mine.toggles is not theirs.toggles
            assert not mine.groups["roadmap"].visible and not theirs.groups["roadmap"].visible
            mine.toggles["roadmap"].value = True  # as the viewer's checkbox does
            wait_for(lambda: mine.groups["roadmap"].visible, "the viewer's roadmap to show")
            mine.toggles["plans"].value = False
            wait_for(lambda: not mine.groups["plans"].visible, "the viewer's plans to hide")
            assert not theirs.groups["roadmap"].visible and theirs.groups["plans"].visible
            assert not theirs.toggles["roadmap"].value and theirs.toggles["plans"].value
            h = scene.view.handles
            assert not h["layer_roadmap"].visible and h["layer_plans"].visible  # the server's default
            assert "gui_toggle_roadmap" not in h  # no toggle shared by every viewer
        finally:
            a.close()
            b.close()
        wait_for(lambda: not scene.server.get_clients(), "the viewers to leave")
        wait_for(lambda: scene.view.client_layers(ids[0]) is None, "their toggles to go")


def _part(mode: str, region: str | None = None, held_from: str | None = "skull_forehead", limit: float = 1.0):
    from app.safety.modes import PartMode

    return PartMode(mode, region or held_from, held_from, 0.8, 0.45, limit, 0.5)  # type: ignore[arg-type]


def test_the_robot_is_coloured_by_each_parts_mode_and_the_label_says_what_the_page_says(
    server: Any, cell: Any
) -> None:
    """Each capsule in its part's mode's colour; the label and the status panel show the state, the mode and
    the speed of the same snapshot, in the words of the operator page (the snapshot's ``mode_text``)."""
    from app.control.results import Snapshot
    from app.ui.scene import MODE_COLORS, headline

    view = CellView(server, cell, robot_capsules=fake_capsules)
    modes = (
        _part("free"),
        _part("ssm", limit=0.9),
        _part("pfl", "hand_fingers", limit=0.675),
        _part("stopped", limit=0.0),
    )
    snap = Snapshot(
        t=3.25, trial_id=1, state="collision_avoidance", method="proactive", speed_scale=0.0,
        separation_m=0.8, required_separation_m=0.45, planning_ms=(), counters={}, q=np.zeros(6),
        p_world_tcp=np.array([0.3, 0.0, 0.4]), part_modes=modes, part_names=("a", "b", "tool", "d"),
    )  # fmt: skip
    view.apply(snap)
    h = view.handles
    want = np.array([MODE_COLORS[m.mode] for m in modes], dtype=np.uint8)
    assert np.array_equal(h["robot_links"].batched_colors, want)
    assert np.array_equal(h["robot_joints"].batched_colors, np.concatenate([want, want]))
    page = snap.to_json()
    assert snap.mode == "stopped" and page["mode_text"] == "stopped" and page["limiting_part"] == "d"
    assert h["state_label"].text == headline(snap, "COLLISION AVOIDANCE")
    assert h["state_label"].text == "COLLISION AVOIDANCE · stopped · speed 0%"
    status = h["gui_status"].content
    assert "**State:** COLLISION AVOIDANCE" in status and "**Mode:** stopped" in status
    assert "**Speed:** 0%" in status and "t = 3.250 s" in status
    assert "0.80 m (required 0.45 m, d from the skull/forehead)" in status
    assert [p["text"] for p in page["parts"]] == ["free", "SSM", "PFL · hand/fingers", "stopped"]

    # the mode changes with the state unchanged: the label follows at once; an E-stop turns the arm red
    view.apply(replace(snap, t=3.26, part_modes=(*modes[:3], _part("free")), speed_scale=0.5))
    assert h["state_label"].text == "COLLISION AVOIDANCE · PFL · hand/fingers · speed 50%"
    view.apply(replace(snap, t=3.3, estopped=True))
    assert np.all(h["robot_links"].batched_colors == np.array(COLOR_DANGER, dtype=np.uint8))
    assert h["state_label"].text == "E-STOP · stopped · speed 0%"
    # without modes (a replay, no trial) the arm keeps its grey and the label the state and speed alone
    view.apply(FakeSnapshot(t=4.0, speed_scale=0.25))
    assert h["state_label"].text == "NOMINAL · speed 25%"
    # the speed the page prints (the runtime's shown speed, held between refreshes) is the one the label
    # prints, and a new one shows at once, whatever the time since the last refresh of the texts
    view.apply(replace(snap, t=5.0, estopped=False, speed_scale=0.61, speed_shown=0.5))
    assert h["state_label"].text.endswith("speed 50%") and snap.to_json()["speed_shown"] == 0.0
    view.apply(replace(snap, t=5.01, estopped=False, speed_scale=0.64, speed_shown=0.64))
    assert h["state_label"].text.endswith("speed 64%") and "**Speed:** 64%" in h["gui_status"].content


@dataclass(frozen=True)
class BodiesSnapshot(FakeSnapshot):
    body_ids: tuple[int, ...] = ()


def test_every_tracked_body_is_drawn_with_its_id(server: Any, cell: Any) -> None:
    view = CellView(server, cell, robot_capsules=fake_capsules, ghosts=2)
    h = view.handles
    a, b = skeleton(1.3, seed=1), skeleton(2.0, seed=2)
    two = np.concatenate([a, b])
    forecast = np.stack([two + np.array([0.02 * k, 0.0, 0.0]) for k in range(10)])
    view.apply(BodiesSnapshot(t=0.0, skeleton=two, body_ids=(3, 7), forecast=forecast))
    nb = len(BONES)
    assert h["person_joints"].visible and np.allclose(h["person_joints"].batched_positions, two, atol=1e-5)
    assert len(h["person_joints"].batched_scales) == 2 * NUM_JOINTS
    bones = h["person_bones"].batched_positions
    assert bones.shape == (2 * nb, 3)
    mids_b = (b[BONES[:, 0]] + b[BONES[:, 1]]) / 2
    assert np.allclose(bones[nb:], mids_b, atol=1e-5)  # the second body's bones are its own
    colors = h["person_joints"].batched_colors
    assert not np.array_equal(colors[0], colors[NUM_JOINTS])  # told apart by colour
    labels = h["body_labels"]
    assert [lb.text for lb in labels[:2]] == ["#3", "#7"] and labels[0].visible and labels[1].visible
    assert not labels[2].visible
    head = JOINT_INDEX["head"]
    assert np.allclose(labels[1].position, b[head] + np.array([0.0, 0.0, 0.25]), atol=1e-5)
    # the ghosts of both bodies' forecasts
    ghosts = h["forecast_ghosts"]
    assert ghosts.visible and ghosts.batched_positions.shape == (2 * 2 * nb, 3)
    # one body left: one body drawn, one label
    view.apply(BodiesSnapshot(t=0.1, skeleton=b, body_ids=(7,)))
    assert h["person_joints"].batched_positions.shape == (NUM_JOINTS, 3)
    assert labels[0].text == "#7" and labels[0].visible and not labels[1].visible
    # nobody in view: nothing drawn
    view.apply(BodiesSnapshot(t=0.2, skeleton=np.zeros((0, 3)), body_ids=()))
    assert not h["person_joints"].visible and not labels[0].visible
