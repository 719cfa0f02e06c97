"""The live 3D view of the work cell, served by viser on its own port.

:class:`CellView` builds the scene graph of one work cell once (static geometry plus one handle per dynamic
element) and :meth:`CellView.apply` updates those handles *in place* from one runtime snapshot.
:class:`CellScene` owns a viser server and a thread that reads the runtime's bounded, drop-oldest snapshot
subscription and applies the newest snapshot at most ``rate_hz`` times a second, so the control loop never
waits for the viewer.

Frames: everything is drawn in the world frame of :mod:`app.config` (z up, metres, origin at the robot base).

Example::

    scene = CellScene(runtime, cell, port=8080)
    scene.start()          # http://127.0.0.1:8080
    ...
    scene.stop()
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from app.config import Box, WorkCell
from app.prediction.skeleton import BONES, JOINT_INDEX, NUM_JOINTS
from app.safety.modes import mode_text, region_text
from app.ui._geometry import segment_instances, unit_cylinder, unit_sphere
from app.ui.viser_server import ViserServerThread

if TYPE_CHECKING:
    import viser

logger = logging.getLogger(__name__)

#: ``robot_capsules(q (B, 6)) -> (a (B, L, 3), b (B, L, 3), r (L,))`` in the world frame (metres).
RobotCapsulesFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

RGB = tuple[int, int, int]

# Palette (RGB 0-255).
COLOR_TABLE: RGB = (196, 170, 132)
COLOR_TABLE_LEG: RGB = (120, 110, 100)
COLOR_CONVEYOR: RGB = (70, 76, 86)
COLOR_OBSTACLE: RGB = (150, 120, 90)
COLOR_STATION: RGB = (46, 134, 222)
COLOR_PICKUP: RGB = (16, 172, 132)
COLOR_HOME: RGB = (130, 130, 140)
COLOR_OPERATOR_AREA: RGB = (255, 190, 120)
COLOR_PERSON: RGB = (230, 126, 34)
COLOR_GHOST: RGB = (243, 156, 18)
#: The colour of each further tracked body (by its position in the frame; the first is COLOR_PERSON).
COLOR_BODIES: tuple[RGB, ...] = (COLOR_PERSON, (142, 68, 173), (22, 160, 133), (192, 57, 43), (41, 128, 185))
#: Most bodies whose tracker id is labelled (the labels are made once, like every handle).
MAX_BODY_LABELS = 8
COLOR_PLAN: RGB = (41, 98, 255)
COLOR_BACKUP: RGB = (142, 68, 173)
COLOR_ROADMAP: RGB = (120, 144, 156)
COLOR_OK: RGB = (39, 174, 96)
COLOR_WARN: RGB = (243, 156, 18)
COLOR_DANGER: RGB = (214, 48, 49)
COLOR_IDLE: RGB = (127, 140, 141)
COLOR_ROBOT: RGB = (176, 186, 198)
COLOR_PFL: RGB = (52, 152, 219)
#: The robot's capsules by what limits each part (:data:`app.safety.modes.PART_MODES`): running free in its
#: own grey, slowed by SSM amber, at a region's PFL speed blue, stopped red (the page's colours).
MODE_COLORS: dict[str, RGB] = {
    "free": COLOR_ROBOT,
    "ssm": COLOR_WARN,
    "pfl": COLOR_PFL,
    "stopped": COLOR_DANGER,
}

PERSON_BONE_RADIUS_M = 0.035
PERSON_JOINT_RADIUS_M = 0.042
PERSON_HEAD_RADIUS_M = 0.1
GHOST_BONE_RADIUS_M = 0.018
_MAX_COALESCE = 16
#: Highest refresh rate of the texts (state label, status panel) between state changes.
TEXT_RATE_HZ = 4.0


class Subscription(Protocol):
    """The runtime's bounded, drop-oldest snapshot queue (see ``Runtime.subscribe``)."""

    def get(self, timeout: float) -> Any | None: ...

    def close(self) -> None: ...


class SnapshotFeed(Protocol):
    """What the scene needs from the runtime: a snapshot now and a subscription to new ones."""

    def snapshot(self) -> Any: ...

    def subscribe(self, maxsize: int = 8) -> Subscription: ...


def state_style(state: str, *, estopped: bool = False, stale: bool = False) -> tuple[str, RGB]:
    """Display text and colour for a supervisor state.

    Args:
        state: The supervisor's state name (e.g. ``"nominal"``, ``"collision_avoidance"``, ``"idle"``).
        estopped: The E-stop is latched (wins over everything).
        stale: The skeleton stream is stale (the robot holds).

    Returns:
        ``(text, rgb)``: upper-case text with spaces, and green / amber / red / grey.
    """
    text = str(state or "unknown").replace("_", " ").replace("-", " ").strip().upper()
    low = text.lower()
    if estopped:
        return "E-STOP", COLOR_DANGER
    if stale:
        return f"{text} · STREAM STALE", COLOR_DANGER
    if any(k in low for k in ("stop", "fault", "error", "emergency")):
        return text, COLOR_DANGER
    if any(k in low for k in ("avoid", "replan", "slow", "hold", "wait")):
        return text, COLOR_WARN
    if any(k in low for k in ("nominal", "run", "exec", "moving")):
        return text, COLOR_OK
    return text, COLOR_IDLE


def _finite(a: Any, shape_tail: tuple[int, ...]) -> np.ndarray | None:
    """``a`` as a float array whose trailing shape is ``shape_tail`` and that is all finite, else None."""
    if a is None:
        return None
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim < len(shape_tail) or arr.shape[arr.ndim - len(shape_tail) :] != shape_tail:
        return None
    if arr.size == 0 or not np.all(np.isfinite(arr)):
        return None
    return arr


def _bodies(a: Any, ndim: int) -> np.ndarray | None:
    """``a`` as stacked bodies (..., B*J, 3) with ``ndim`` dimensions, B >= 1, all finite; else None."""
    arr = _finite(a, (3,))
    if arr is None or arr.ndim != ndim or arr.shape[-2] % NUM_JOINTS:
        return None
    return arr


def _path_segments(path: np.ndarray) -> np.ndarray:
    """Line segments (K - 1, 2, 3) through the points (K, 3)."""
    return np.stack([path[:-1], path[1:]], axis=1)


def _ghost_indices(horizon: int, count: int) -> np.ndarray:
    """Indices into a forecast of ``horizon`` samples for ``count`` ghosts (index 0, the observed pose,
    is drawn as the person; the ghosts spread over 1..H-1, the last one at the end of the horizon)."""
    if horizon < 2:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.round(np.linspace(1, horizon - 1, count)).astype(np.int64))


#: The group frame of each optional layer's nodes.
LAYER_GROUPS: dict[str, str] = {
    "roadmap": "/roadmap",
    "ghosts": "/forecast",
    "plans": "/plans",
    "separation": "/safety",
}
#: The GUI label of each optional layer.
LAYER_LABELS: dict[str, str] = {
    "roadmap": "Roadmap nodes",
    "ghosts": "Forecast ghosts",
    "plans": "Plans (TCP paths)",
    "separation": "Protective separation",
}


@dataclass(frozen=True)
class ClientLayers:
    """One viewer's layer toggles (GUI checkboxes) and its client-scoped group frames, by layer."""

    toggles: Mapping[str, Any]
    groups: Mapping[str, Any]


class CellView:
    """The scene graph of one work cell inside a viser server, updated in place from snapshots.

    All handles are created in the constructor; :meth:`apply` only assigns to them (positions, points,
    colours, visibility, text), so clients receive small property updates and the scene tree never grows.

    Args:
        server: The viser server (or a client handle) to draw into.
        cell: The work cell.
        robot_capsules: ``q (B, 6) -> (a (B, L, 3), b (B, L, 3), r (L,))`` world-frame link capsules.
        roadmap_nodes: Roadmap node positions (N, 3) in metres, drawn as points (toggled in the GUI).
        ghosts: Number of forecast poses drawn as fading ghost skeletons.
        gui: Add the GUI panel (status text and toggles).
    """

    def __init__(
        self,
        server: viser.ViserServer,
        cell: WorkCell,
        *,
        robot_capsules: RobotCapsulesFn,
        roadmap_nodes: np.ndarray | None = None,
        ghosts: int = 6,
        gui: bool = True,
    ) -> None:
        self._server = server
        self._cell = cell
        self._robot_capsules = robot_capsules
        self._n_ghosts = int(ghosts)
        self._handles: dict[str, Any] = {}
        self._show = {"roadmap": False, "ghosts": True, "plans": True, "separation": True}
        self._clients: dict[int, ClientLayers] = {}
        self._clients_lock = threading.Lock()
        self._has = {"ghosts": False, "plan": False, "backup": False, "separation": False}
        self.applied = 0
        self._last_text = ""
        self._last_text_t = -np.inf

        q0 = np.asarray(cell.robot.home_q, dtype=np.float64)[None]
        a, _b, r = robot_capsules(q0)
        assert a.ndim == 3 and a.shape[0] == 1 and a.shape[2] == 3, (
            f"capsule ends must be (1, L, 3), got {a.shape}"
        )
        self._n_links = a.shape[1]
        self._link_radius = np.asarray(r, dtype=np.float64).reshape(self._n_links)

        scene = server.scene
        scene.set_up_direction("+z")
        # No fog (it washes out a table-sized scene seen from ~3 m) and a hemisphere light instead of the
        # image-based environment map: similar look, and the scene shows at once in software WebGL (no
        # environment pre-filtering on the client).
        scene.configure_fog(near=8.0, far=30.0, enabled=False)
        scene.configure_environment_map(None)
        scene.add_light_hemisphere(
            "/lights/hemisphere", sky_color=(255, 255, 255), ground_color=(140, 130, 120), intensity=1.2
        )
        self._build_static(scene)
        self._build_dynamic(scene, roadmap_nodes)
        if gui:
            self._build_gui(server)
        self._set_robot(q0[0], COLOR_ROBOT)

    # ------------------------------------------------------------------ construction

    def _add_box(self, scene: Any, name: str, box: Box, color: RGB, *, opacity: float | None = None) -> None:
        c, s = np.cos(box.yaw / 2), np.sin(box.yaw / 2)
        self._handles[name] = scene.add_box(
            name,
            color=color,
            dimensions=tuple(box.size),
            position=tuple(box.center),
            wxyz=(c, 0.0, 0.0, s),
            opacity=opacity,
            flat_shading=True,
        )

    def _build_static(self, scene: Any) -> None:
        cell = self._cell
        floor_z = cell.operator.floor_z
        scene.add_grid(
            "/cell/floor",
            width=6.0,
            height=6.0,
            plane="xy",
            position=(0.4, 0.0, floor_z),
            cell_size=0.25,
            section_size=1.0,
            cell_color=(215, 220, 226),
            section_color=(170, 178, 188),
        )
        self._add_box(scene, "/cell/table", cell.table, COLOR_TABLE)
        # Four legs under the table top, down to the floor.
        top = cell.table
        bottom_z = top.center[2] - top.size[2] / 2
        leg_h = bottom_z - floor_z
        if leg_h > 0:
            for i, (sx, sy) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
                x = top.center[0] + sx * (top.size[0] / 2 - 0.06)
                y = top.center[1] + sy * (top.size[1] / 2 - 0.06)
                scene.add_box(
                    f"/cell/table_leg_{i}",
                    color=COLOR_TABLE_LEG,
                    dimensions=(0.05, 0.05, leg_h),
                    position=(x, y, floor_z + leg_h / 2),
                )
        self._add_box(scene, "/cell/conveyor", cell.conveyor.body, COLOR_CONVEYOR)
        for i, box in enumerate(cell.obstacles):
            self._add_box(scene, f"/cell/obstacle_{i}", box, COLOR_OBSTACLE)
        # Robot pedestal disc at the base.
        base = np.asarray(cell.robot.base_xyz, dtype=float)
        scene.add_cylinder(
            "/cell/robot_base",
            radius=0.09,
            height=0.02,
            color=(60, 64, 72),
            position=tuple(base + np.array([0.0, 0.0, 0.01])),
        )
        # Stations: small discs on the table under the task poses, with labels.
        table_top = top.center[2] + top.size[2] / 2
        stations = [(cell.conveyor.pickup, COLOR_PICKUP), (cell.home, COLOR_HOME)]
        stations += [(s, COLOR_STATION) for s in cell.drop_stations]
        for st, color in stations:
            x, y, z = st.xyz
            disc_z = (
                table_top + 0.004
                if st is not cell.conveyor.pickup
                else cell.conveyor.body.center[2] + (cell.conveyor.body.size[2] / 2 + 0.004)
            )
            if st is not cell.home:
                scene.add_cylinder(
                    f"/cell/stations/{st.name}/pad",
                    radius=0.05,
                    height=0.008,
                    color=color,
                    position=(x, y, disc_z),
                )
            scene.add_icosphere(
                f"/cell/stations/{st.name}/pose",
                radius=0.012,
                color=color,
                position=(x, y, z),
                subdivisions=2,
            )
            scene.add_label(
                f"/cell/stations/{st.name}/label",
                st.name,
                position=(x, y, z + 0.04),
                font_screen_scale=0.8,
                anchor="bottom-center",
            )
        # Where the person stands: a translucent patch on the floor.
        op = cell.operator
        scene.add_box(
            "/cell/operator_area",
            color=COLOR_OPERATOR_AREA,
            dimensions=(op.size_xy[0], op.size_xy[1], 0.004),
            position=(op.center_xy[0], op.center_xy[1], op.floor_z + 0.002),
            opacity=0.35,
        )

    def _build_dynamic(self, scene: Any, roadmap_nodes: np.ndarray | None) -> None:
        # Each optional layer's nodes live under one group frame: a node shows whether it has something to
        # show; the group, whether the layer is on (the server's default here, each client's own choice in
        # a client-scoped variant of the group, see _add_client).
        for key, group in LAYER_GROUPS.items():
            self._handles[f"layer_{key}"] = scene.add_frame(group, show_axes=False, visible=self._show[key])
        cyl_v, cyl_f = unit_cylinder(segments=18)
        sph_v, sph_f = unit_sphere(rings=8, sectors=14)
        L = self._n_links
        zeros3 = np.zeros((L, 3))
        ident = np.tile([1.0, 0.0, 0.0, 0.0], (L, 1))
        ones = np.ones((L, 3))
        h = self._handles
        h["robot_links"] = scene.add_batched_meshes_simple(
            "/robot/links",
            cyl_v,
            cyl_f,
            batched_wxyzs=ident,
            batched_positions=zeros3,
            batched_scales=ones,
            batched_colors=np.tile(COLOR_ROBOT, (L, 1)).astype(np.uint8),
            lod="off",
        )
        h["robot_joints"] = scene.add_batched_meshes_simple(
            "/robot/joints",
            sph_v,
            sph_f,
            batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (2 * L, 1)),
            batched_positions=np.zeros((2 * L, 3)),
            batched_scales=np.ones((2 * L, 3)),
            batched_colors=np.tile(COLOR_ROBOT, (2 * L, 1)).astype(np.uint8),
            lod="off",
        )
        nb = len(BONES)
        h["person_bones"] = scene.add_batched_meshes_simple(
            "/person/bones",
            cyl_v,
            cyl_f,
            batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (nb, 1)),
            batched_positions=np.zeros((nb, 3)),
            batched_scales=np.ones((nb, 3)),
            batched_colors=COLOR_PERSON,
            lod="off",
            visible=False,
        )
        joint_scale = np.full((NUM_JOINTS, 3), PERSON_JOINT_RADIUS_M)
        joint_scale[JOINT_INDEX["head"]] = PERSON_HEAD_RADIUS_M
        self._joint_scale = joint_scale
        self._shown_bodies: tuple[int, ...] | None = None  # the body ids drawn (their colours and scales)
        self._label_text = [""] * MAX_BODY_LABELS
        h["person_joints"] = scene.add_batched_meshes_simple(
            "/person/joints",
            sph_v,
            sph_f,
            batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (NUM_JOINTS, 1)),
            batched_positions=np.zeros((NUM_JOINTS, 3)),
            batched_scales=joint_scale,
            batched_colors=COLOR_PERSON,
            lod="off",
            visible=False,
        )
        ng = max(self._n_ghosts, 1) * nb
        h["forecast_ghosts"] = scene.add_batched_meshes_simple(
            "/forecast/ghosts",
            cyl_v,
            cyl_f,
            batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (ng, 1)),
            batched_positions=np.zeros((ng, 3)),
            batched_scales=np.zeros((ng, 3)),
            batched_colors=COLOR_GHOST,
            batched_opacities=np.full(ng, 0.3),
            lod="off",
            cast_shadow=False,
            visible=False,
        )
        dummy = np.zeros((1, 2, 3))
        h["plan"] = scene.add_line_segments(
            "/plans/executing", dummy, COLOR_PLAN, thickness=0.012, visible=False
        )
        h["backup"] = scene.add_line_segments(
            "/plans/backup", dummy, COLOR_BACKUP, thickness=0.008, visible=False
        )
        h["separation"] = scene.add_icosphere(
            "/safety/separation",
            radius=1.0,
            color=COLOR_OK,
            opacity=0.16,
            subdivisions=3,
            cast_shadow=False,
            receive_shadow=False,
            visible=False,
        )
        h["body_labels"] = [
            scene.add_label(f"/person/labels/{k}", "", position=(0.0, 0.0, 0.0), visible=False)
            for k in range(MAX_BODY_LABELS)
        ]
        h["tcp"] = scene.add_icosphere("/robot/tcp", radius=0.015, color=(30, 30, 30), subdivisions=2)
        h["state_label"] = scene.add_label(
            "/status/state",
            "IDLE",
            position=(0.0, 0.0, 1.05),
            font_screen_scale=1.2,
            anchor="bottom-center",
        )
        if roadmap_nodes is not None:
            nodes = np.asarray(roadmap_nodes, dtype=np.float32)
            assert nodes.ndim == 2 and nodes.shape[1] == 3, f"roadmap nodes must be (N, 3), got {nodes.shape}"
            h["roadmap"] = scene.add_point_cloud(
                "/roadmap/nodes",
                nodes,
                COLOR_ROADMAP,
                point_size=0.012,
                point_shape="circle",
                precision="float32",
                visible=True,
            )

    def _build_gui(self, server: Any) -> None:
        gui = server.gui
        gui.configure_theme(control_width="small", show_share_button=False, brand_color=(41, 98, 255))
        self._handles["gui_status"] = gui.add_markdown("**State:** IDLE")
        # The layer toggles are each viewer's own: built per client as it connects (a server without
        # clients, such as a client handle drawn into, has no toggles)
        on_connect = getattr(server, "on_client_connect", None)
        on_disconnect = getattr(server, "on_client_disconnect", None)
        if on_connect is not None and on_disconnect is not None:
            on_connect(self._add_client)
            on_disconnect(self._remove_client)

    def _add_client(self, client: Any) -> None:
        """One viewer's layer toggles: a GUI folder of its own and a client-scoped variant of each layer's
        group frame (viser shows a client's variant of a node instead of the server's to that client only),
        so its choices change its view and no one else's."""
        groups = {
            key: client.scene.add_frame(group, show_axes=False, visible=self._show[key])
            for key, group in LAYER_GROUPS.items()
        }
        toggles: dict[str, Any] = {}
        with client.gui.add_folder("Layers"):
            for key, label in LAYER_LABELS.items():
                enabled = key != "roadmap" or "roadmap" in self._handles
                box = client.gui.add_checkbox(label, initial_value=self._show[key], disabled=not enabled)
                box.on_update(self._make_toggle(box, groups[key]))
                toggles[key] = box
        with self._clients_lock:
            self._clients[int(client.client_id)] = ClientLayers(toggles=toggles, groups=groups)

    def _remove_client(self, client: Any) -> None:
        with self._clients_lock:
            self._clients.pop(int(client.client_id), None)

    @staticmethod
    def _make_toggle(box: Any, group: Any) -> Callable[[Any], None]:
        def _on_update(_event: Any) -> None:
            group.visible = bool(box.value)

        return _on_update

    def client_layers(self, client_id: int) -> ClientLayers | None:
        """A connected viewer's layer toggles and group frames (None for an unknown client)."""
        with self._clients_lock:
            return self._clients.get(int(client_id))

    # ------------------------------------------------------------------ updates

    @property
    def handles(self) -> Mapping[str, Any]:
        """The scene and GUI handles by role (read-only view; the handles themselves are long-lived)."""
        return MappingProxyType(self._handles)

    def set_layer(self, key: str, visible: bool) -> None:
        """Show or hide an optional layer (``"roadmap"``, ``"ghosts"``, ``"plans"`` or ``"separation"``) by
        default: for viewers that connect later, and in the server's own scene. A connected viewer keeps
        its own choice (its GUI toggles)."""
        if key not in self._show:
            raise ValueError(f"unknown layer {key!r}; expected one of {sorted(self._show)}")
        self._show[key] = visible
        self._handles[f"layer_{key}"].visible = visible

    def _set_robot(self, q: np.ndarray, color: RGB | np.ndarray) -> np.ndarray:
        """Place the robot's capsules at ``q`` (6,), coloured ``color``: one RGB, or one per link (L, 3)."""
        a, b, _r = self._robot_capsules(np.asarray(q, dtype=np.float64).reshape(1, 6))
        a, b = np.asarray(a)[0], np.asarray(b)[0]
        pos, wxyz, scale = segment_instances(a, b, self._link_radius)
        links, joints = self._handles["robot_links"], self._handles["robot_joints"]
        colors = np.broadcast_to(np.asarray(color, dtype=np.uint8), (self._n_links, 3))
        links.batched_positions = pos
        links.batched_wxyzs = wxyz
        links.batched_scales = scale
        links.batched_colors = np.ascontiguousarray(colors)
        joints.batched_positions = np.concatenate([a, b], axis=0)
        joints.batched_scales = np.repeat(np.tile(self._link_radius, 2)[:, None], 3, axis=1)
        joints.batched_colors = np.concatenate([colors, colors], axis=0)
        return b[-1]

    def _robot_colors(self, snap: Any, estopped: bool) -> RGB | np.ndarray:
        """One colour per link by the snapshot's ``part_modes`` (:data:`MODE_COLORS`), red under an
        E-stop, the robot's grey without modes (or with another number of parts than links)."""
        if estopped:
            return COLOR_DANGER
        modes = getattr(snap, "part_modes", None) or ()
        if len(modes) != self._n_links:
            return COLOR_ROBOT
        return np.array([MODE_COLORS.get(str(getattr(m, "mode", "")), COLOR_ROBOT) for m in modes])

    def _set_person(self, skeleton: np.ndarray | None, body_ids: tuple[int, ...] | None) -> None:
        """Every tracked body (``skeleton`` (B*J, 3) stacked), coloured by its place in the frame, and its
        tracker id over its head when ``body_ids`` are known. The instance arrays hold B bodies; colours,
        scales and labels are sent again only when the bodies change."""
        h = self._handles
        bones, joints = h["person_bones"], h["person_joints"]
        labels = h["body_labels"]
        if skeleton is None:
            bones.visible = False
            joints.visible = False
            if self._shown_bodies:
                for label in labels[: len(self._shown_bodies)]:
                    label.visible = False
            self._shown_bodies = None
            return
        B = len(skeleton) // NUM_JOINTS
        ids = tuple(body_ids) if body_ids is not None and len(body_ids) == B else None
        offsets = (np.arange(B) * NUM_JOINTS)[:, None]
        a = skeleton[(BONES[:, 0][None] + offsets).ravel()]
        b = skeleton[(BONES[:, 1][None] + offsets).ravel()]
        pos, wxyz, scale = segment_instances(a, b, PERSON_BONE_RADIUS_M)
        bones.batched_positions = pos
        bones.batched_wxyzs = wxyz
        bones.batched_scales = scale
        joints.batched_positions = skeleton
        key = ids if ids is not None else (-1,) * B
        if key != self._shown_bodies:  # another number (or ids) of bodies: their colours, sizes, labels
            colors = np.array([COLOR_BODIES[k % len(COLOR_BODIES)] for k in range(B)], dtype=np.uint8)
            bones.batched_colors = np.repeat(colors, len(BONES), axis=0)
            joints.batched_colors = np.repeat(colors, NUM_JOINTS, axis=0)
            joints.batched_wxyzs = np.tile([1.0, 0.0, 0.0, 0.0], (B * NUM_JOINTS, 1))
            joints.batched_scales = np.tile(self._joint_scale, (B, 1))
            for k, label in enumerate(labels):
                text = "" if ids is None or k >= B else f"#{ids[k]}"
                if text != self._label_text[k]:
                    label.text = text
                    self._label_text[k] = text
                label.visible = bool(text)
            self._shown_bodies = key
        if ids is not None:
            heads = skeleton[JOINT_INDEX["head"] :: NUM_JOINTS][: len(labels)]
            for label, head in zip(labels, heads, strict=False):
                label.position = (float(head[0]), float(head[1]), float(head[2]) + 0.25)
        bones.visible = True
        joints.visible = True

    def _set_forecast(self, forecast: np.ndarray | None) -> None:
        """Ghosts of every body's forecast (``forecast`` (H, B*J, 3) stacked as the skeleton)."""
        ghosts = self._handles["forecast_ghosts"]
        idx = _ghost_indices(0 if forecast is None else forecast.shape[0], self._n_ghosts)
        if forecast is None or len(idx) == 0 or forecast.shape[1] == 0:
            self._has["ghosts"] = False
            ghosts.visible = False
            return
        B = forecast.shape[1] // NUM_JOINTS
        nb = len(BONES) * B
        slots = max(self._n_ghosts, 1)
        poses = forecast[idx].reshape(len(idx), B, NUM_JOINTS, 3)  # (G, B, J, 3)
        a = poses[:, :, BONES[:, 0]].reshape(-1, 3)
        b = poses[:, :, BONES[:, 1]].reshape(-1, 3)
        pos, wxyz, scale = segment_instances(a, b, GHOST_BONE_RADIUS_M)
        # Fade with the horizon: near ghosts are more opaque than far ones.
        fade = np.linspace(0.5, 0.1, len(idx)) if len(idx) > 1 else np.array([0.35])
        opac = np.repeat(fade, nb)
        # Unused slots (short forecasts) collapse to zero scale.
        n_used = len(idx) * nb
        full_pos = np.zeros((slots * nb, 3))
        full_wxyz = np.tile([1.0, 0.0, 0.0, 0.0], (slots * nb, 1))
        full_scale = np.zeros((slots * nb, 3))
        full_opac = np.zeros(slots * nb)
        full_pos[:n_used], full_wxyz[:n_used], full_scale[:n_used], full_opac[:n_used] = (
            pos,
            wxyz,
            scale,
            opac,
        )
        ghosts.batched_positions = full_pos
        ghosts.batched_wxyzs = full_wxyz
        ghosts.batched_scales = full_scale
        ghosts.batched_opacities = full_opac
        self._has["ghosts"] = True
        ghosts.visible = True

    def _set_path(self, key: str, path: np.ndarray | None) -> None:
        handle = self._handles[key]
        if path is None or path.shape[0] < 2:
            self._has[key] = False
            handle.visible = False
            return
        handle.points = _path_segments(path)
        self._has[key] = True
        handle.visible = True

    def apply(self, snap: Any) -> None:
        """Update every dynamic element from one snapshot (in place; no handle is created or removed).

        Args:
            snap: A runtime ``Snapshot`` (or an object with the same attributes): ``state``, ``q (6,)``,
                ``p_world_tcp (3,)``, ``skeleton (B*J, 3) | None`` (every tracked body, stacked) with
                ``body_ids`` (B,) (optional: the labels), ``forecast (H, B*J, 3) | None``,
                ``plan_tcp (K, 3) | None``, ``backup_tcp (K, 3) | None``, ``required_separation_m``,
                ``separation_m``, ``speed_scale``, ``stale``, ``estopped``, ``method``, ``trial_id``,
                ``trial_elapsed_s``, ``trial_duration_s``.
        """
        q = _finite(getattr(snap, "q", None), (6,))
        if q is None or q.ndim != 1:
            raise ValueError("snapshot.q must be a finite (6,) joint vector")
        estopped = bool(getattr(snap, "estopped", False))
        stale = bool(getattr(snap, "stale", False))
        state = str(getattr(snap, "state", "unknown"))
        text, color = state_style(state, estopped=estopped, stale=stale)
        h = self._handles
        with self._server.atomic():
            p_flange_end = self._set_robot(q, self._robot_colors(snap, estopped))
            tcp = _finite(getattr(snap, "p_world_tcp", None), (3,))
            if tcp is None or tcp.ndim != 1:
                tcp = p_flange_end
            h["tcp"].position = tuple(tcp)
            h["tcp"].color = color

            skeleton = _bodies(getattr(snap, "skeleton", None), 2)
            self._set_person(skeleton, getattr(snap, "body_ids", None) or None)
            self._set_forecast(_bodies(getattr(snap, "forecast", None), 3))
            for key, attr in (("plan", "plan_tcp"), ("backup", "backup_tcp")):
                path = _finite(getattr(snap, attr, None), (3,))
                self._set_path(key, path if path is not None and path.ndim == 2 else None)

            required = getattr(snap, "required_separation_m", None)
            separation = getattr(snap, "separation_m", None)
            sphere = h["separation"]
            if required is not None and np.isfinite(required) and required > 0:
                sphere.position = tuple(tcp)
                sphere.scale = float(required)
                if separation is not None and np.isfinite(separation) and separation < required:
                    sphere.color = COLOR_DANGER
                elif separation is not None and np.isfinite(separation) and separation < 1.5 * required:
                    sphere.color = COLOR_WARN
                else:
                    sphere.color = COLOR_OK
                self._has["separation"] = True
                sphere.visible = True
            else:
                self._has["separation"] = False
                sphere.visible = False

            # Text re-renders the client's GUI: refresh it when the state, the mode or the runtime's shown
            # speed (the number the page prints too, itself refreshed a few times a second) changes, else at
            # most TEXT_RATE_HZ (on the snapshots' own clock, so that replays and tests behave the same)
            t = float(getattr(snap, "t", 0.0))
            shown = getattr(snap, "speed_shown", None)
            key = f"{text}|{getattr(snap, 'mode', None)}|{'' if shown is None else _speed_text(snap)}"
            if key != self._last_text or not (0.0 <= t - self._last_text_t < 1.0 / TEXT_RATE_HZ):
                self._last_text, self._last_text_t = key, t
                h["state_label"].text = headline(snap, text)
                if "gui_status" in h:
                    h["gui_status"].content = _status_markdown(snap, text, separation, required)
        self.applied += 1


def _fmt_m(v: Any) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{float(v):.2f} m"


def _speed_text(snap: Any) -> str:
    """The speed in per cent that the screens print (the snapshot's ``speed_shown``, held between the
    refreshes that the page shares, else its ``speed_scale``), rounded as the page rounds it
    (``Math.round``: halves up)."""
    speed = getattr(snap, "speed_shown", None)
    if speed is None:
        speed = getattr(snap, "speed_scale", None)
    if speed is None or not np.isfinite(speed):
        return "–"
    return f"{math.floor(100.0 * float(speed) + 0.5)}%"


def headline(snap: Any, text: str) -> str:
    """The one line of state, mode and speed that the 3D view's label shows, as the operator page's
    supervisor panel shows them (``NOMINAL · PFL · hand/fingers · speed 68%``): ``text`` from
    :func:`state_style`, the mode and speed from the same snapshot's ``mode`` and ``speed_scale``."""
    mode = getattr(snap, "mode", None)
    head = text if mode is None else f"{text} · {mode_text(mode)}"
    speed = _speed_text(snap)
    return head if speed == "–" else f"{head} · speed {speed}"  # a replay has no speed


def _status_markdown(snap: Any, text: str, separation: Any, required: Any) -> str:
    method = getattr(snap, "method", None) or "–"
    trial = getattr(snap, "trial_id", None)
    elapsed = getattr(snap, "trial_elapsed_s", None)
    duration = getattr(snap, "trial_duration_s", None)
    lines = [
        f"**State:** {text}",
        f"**Mode:** {mode_text(getattr(snap, 'mode', None))}",
        f"**Speed:** {_speed_text(snap)}",
        f"**Method:** {method}",
    ]
    if trial is not None:
        tail = ""
        if elapsed is not None and duration:
            tail = f" ({float(elapsed):.0f} / {float(duration):.0f} s)"
        lines.append(f"**Trial:** #{trial}{tail}")
    held_from = ""
    modes = getattr(snap, "part_modes", None) or ()
    k = getattr(snap, "limiting_part", -1)
    if isinstance(k, int) and 0 <= k < len(modes):
        name = snap.part_name(k) if hasattr(snap, "part_name") else f"part {k}"
        region = getattr(modes[k], "held_from", None)
        held_from = f", {name.replace('_', ' ')}" + (f" from the {region_text(region)}" if region else "")
    lines.append(f"**Separation:** {_fmt_m(separation)} (required {_fmt_m(required)}{held_from})")
    lines.append(f"**Snapshot:** t = {float(getattr(snap, 't', 0.0)):.3f} s")
    return "  \n".join(lines)


class CellScene:
    """A viser server that shows the work cell and follows the runtime live.

    Args:
        runtime: The runtime (anything with ``snapshot()`` and ``subscribe(maxsize)``).
        cell: The work cell to draw.
        port: TCP port of the viser server (0 picks a free one: read :attr:`port` after :meth:`start`; a
            port another program holds is an error, :class:`~app.ui.viser_server.PortInUse`).
        host: Interface to bind (default loopback).
        token: The operator token every viewer's socket must carry (None: open; see
            :mod:`app.ui.viser_server`).
        roadmap: A planner ``Roadmap`` (its ``nodes (N, 3)`` are drawn, toggled in the GUI); default: the
            runtime's ``roadmap`` attribute when it has one.
        rate_hz: Highest update rate of the view (snapshots in between are skipped).
        robot_capsules: Override of the robot's capsule model (default: ``CollisionModel(cell)``).
        ghosts: Number of forecast ghost skeletons.
    """

    def __init__(
        self,
        runtime: SnapshotFeed,
        cell: WorkCell,
        *,
        port: int,
        host: str = "127.0.0.1",
        roadmap: Any | None = None,
        rate_hz: float = 30.0,
        robot_capsules: RobotCapsulesFn | None = None,
        ghosts: int = 6,
        token: str | None = None,
    ) -> None:
        if not 0 < rate_hz <= 120:
            raise ValueError(f"rate_hz must be in (0, 120], got {rate_hz}")
        self._runtime = runtime
        self._cell = cell
        self._srv = ViserServerThread(host=host, port=port, name="hrc-scene", token=token)
        self._roadmap = roadmap
        self._period_s = 1.0 / rate_hz
        self._robot_capsules = robot_capsules
        self._ghosts = ghosts
        self._view: CellView | None = None
        self._sub: Subscription | None = None
        self.frames_applied = 0
        self.frames_skipped = 0
        self.errors = 0

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the viser server, draw the cell and follow the runtime on a background thread.

        Raises:
            RuntimeError: already started.
        """
        if self._srv.server is not None:
            raise RuntimeError("CellScene.start() called twice; call stop() first")
        capsules = self._robot_capsules
        if capsules is None:
            from app.planning.collision import CollisionModel

            capsules = CollisionModel(self._cell).robot_capsules
        # Default: the runtime's own roadmap (``Runtime.roadmap``, available once the runtime has started).
        roadmap = self._roadmap if self._roadmap is not None else getattr(self._runtime, "roadmap", None)
        nodes = None if roadmap is None else np.asarray(roadmap.nodes)

        def build(server: viser.ViserServer) -> None:
            server.initial_camera.up = (0.0, 0.0, 1.0)
            self._view = CellView(
                server, self._cell, robot_capsules=capsules, roadmap_nodes=nodes, ghosts=self._ghosts
            )
            self._view.apply(self._runtime.snapshot())
            self.frames_applied += 1
            self._sub = self._runtime.subscribe(maxsize=2)

        try:
            self._srv.start(build, self._run)
        except BaseException:
            self._view = None
            raise
        logger.info("3D view at http://%s:%d", self._srv.host, self.port)

    def stop(self) -> None:
        """Stop following the runtime and shut the viser server down (idempotent)."""
        self._srv.stop()
        if self._sub is not None:
            self._sub.close()
            self._sub = None

    def __enter__(self) -> CellScene:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ accessors

    @property
    def port(self) -> int:
        """The port the viser server is bound to (the requested one until :meth:`start`)."""
        return self._srv.port

    @property
    def host(self) -> str:
        return self._srv.host

    @property
    def running(self) -> bool:
        return self._srv.running

    @property
    def view(self) -> CellView:
        """The scene graph (available after :meth:`start`)."""
        if self._view is None:
            raise RuntimeError("CellScene.view is available after start()")
        return self._view

    @property
    def server(self) -> viser.ViserServer:
        server = self._srv.server
        if server is None:
            raise RuntimeError("CellScene.server is available after start()")
        return server

    # ------------------------------------------------------------------ worker

    def _run(self, stop: threading.Event) -> None:
        sub, view = self._sub, self._view
        assert sub is not None and view is not None
        last_error_log = -1e9
        while not stop.is_set():
            snap = sub.get(timeout=0.25)
            if snap is None:
                continue
            # Coalesce: draw only the newest snapshot that is already queued (bounded: the queue is small).
            for _ in range(_MAX_COALESCE):
                newer = sub.get(timeout=0.0)
                if newer is None:
                    break
                snap = newer
                self.frames_skipped += 1
            t0 = time.monotonic()
            try:
                view.apply(snap)
                self.frames_applied += 1
            except Exception:
                self.errors += 1
                if t0 - last_error_log > 5.0:
                    logger.exception("3D view update failed (%d failures so far)", self.errors)
                    last_error_log = t0
            rest = self._period_s - (time.monotonic() - t0)
            if rest > 0:
                stop.wait(rest)
