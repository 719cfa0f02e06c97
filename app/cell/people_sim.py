"""Every person in the simulated cell: the operator, a second operator, passers-by.

:class:`SimulatedPeople` is a :class:`~app.cell.source.HumanSource` made of the simulated operator
(:class:`~app.cell.operator_sim.SimulatedOperator`, body id :data:`OPERATOR_ID`), an optional second operator
at a side of the table (the same class at another work spot, id :data:`SECOND_OPERATOR_ID`) and walkers who
pass the robot now and then (:class:`Walker`, ids :data:`FIRST_WALKER_ID` + i), as a scenario file declares
(:mod:`app.cell.scenario`). Its frames and its truth are the stacked
:class:`~app.prediction.skeleton.HumanFrame` of every person present at that instant, in id order: a walker
is present while every joint of theirs lies in the tracked volume (:func:`tracked_volume`: the frame
checks' volume, :meth:`~app.cell.validation.CellVolume.from_workcell`, a little inset), so bodies appear
and disappear.

The division of work: each drop station's block is fetched by the operator whose work spot is nearest to it
(ties: the operator), unless the scenario lists the second operator's stations; a placement notification
goes to that operator only. Both assemble at their own spot and reach into the shared area now and then.

Walkers (:class:`Walker`): a procedural gait in the canonical joint set, with the bone lengths of a
participant of the population (their height): the pelvis moves along a straight or gently bowed path at
the pass's speed, bobbing with the stance leg; the stance foot stays on the floor, the swing foot lifts
and swings forward (minimum jerk), the knees bend by two-link inverse kinematics; the arms swing against
the legs, the chest counter-rotates the pelvis, the head stays upright at standing height. A pass is
scheduled by its closest approach to the robot (:attr:`Pass.t_closest`), at the drawn interval after the
previous one.

Determinism: the bodies come from the participant's seed, the passes and the operators' behaviour from the
trial's seed; nothing else is drawn.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from app.cell.operator_sim import OperatorParams, OracleForecaster, SimulatedOperator, _Body, _ry, _rz
from app.cell.population import Population
from app.cell.scenario import PassersBy, Scenario, ScenarioError
from app.cell.source import HumanSource
from app.cell.validation import CellVolume
from app.prediction.forecast import HumanForecast, Predictor, stack_forecasts
from app.prediction.profiles import min_jerk
from app.prediction.skeleton import NUM_JOINTS, HumanFrame

if TYPE_CHECKING:
    from app.config import WorkCell

__all__ = [
    "FIRST_WALKER_ID",
    "OPERATOR_ID",
    "SECOND_OPERATOR_ID",
    "Pass",
    "PeopleOracle",
    "SimulatedPeople",
    "Walker",
    "derived_seed",
    "second_operator_cell",
    "tracked_volume",
]

OPERATOR_ID = 0
SECOND_OPERATOR_ID = 1
FIRST_WALKER_ID = 2
#: How far (m) a walker's pelvis path keeps from the table and every static box (the body's half-width).
PATH_CLEARANCE_OF_BOXES_M = 0.25
#: The gait cycle (a stride): the stance share, where the planted foot starts (ahead of the hip, in strides)
#: and where its heel comes off (the share of the cycle); the heel's rise by toe-off and the swing foot's
#: lift, and the pelvis's vertical bob (m, for a person 1.65 m tall).
_STANCE, _FRONT, _HEEL_OFF = 0.6, 0.27, 0.45
_HEEL_RISE, _FOOT_LIFT, _BOB = 0.06, 0.1, 0.05


#: A walker is in the cell while every joint lies this far (m) inside the frame checks' volume, in x and y:
#: the tracker's noise (about 1 cm) never carries a joint of theirs out of it (which would lose the frame).
TRACKED_MARGIN_M = 0.1


def tracked_volume(cell: WorkCell) -> CellVolume:
    """Where a walker is in the cell: the frame checks' volume (:meth:`CellVolume.from_workcell`) less
    :data:`TRACKED_MARGIN_M` in x and y."""
    v = CellVolume.from_workcell(cell)
    inset = np.array([TRACKED_MARGIN_M, TRACKED_MARGIN_M, 0.0])
    return CellVolume(lo=v.lo + inset, hi=v.hi - inset)


def derived_seed(seed: int, *tags: int) -> int:
    """A seed for one part of the scenario, from a participant's or a trial's seed and tags."""
    return int(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, *tags]).generate_state(1)[0])


# ---------------------------------------------------------------------------------------------------------
# The second operator's work spot
# ---------------------------------------------------------------------------------------------------------
def second_operator_cell(cell: WorkCell, side: str, along_m: float) -> WorkCell:
    """``cell`` with its operator area moved to the table's ``side`` (``left``: +y, ``right``: -y) at ``x =
    along_m``, facing the table: the cell of the second operator. The area and the work spot keep the
    operator's relation to the table's edge (the area's centre as far beyond it, the spot as far inside)."""
    from app.config import OperatorArea

    op, table = cell.operator, cell.table
    if abs(table.yaw) > 1e-9:
        raise ScenarioError("a second operator needs a table that is not turned (table.yaw = 0)")
    s = 1.0 if side == "left" else -1.0
    edge_x = table.center[0] + table.size[0] / 2  # the operator's edge (the default cell: they face -x)
    edge_y = table.center[1] + s * table.size[1] / 2
    beyond = abs(op.center_xy[0] - edge_x)
    inside = abs(edge_x - op.work_spot[0])
    lo, hi = table.center[0] - table.size[0] / 2, table.center[0] + table.size[0] / 2
    if not lo + 0.1 <= along_m <= hi - 0.1:
        raise ScenarioError(
            f"second_operator.along_m = {along_m} m is not along the table's side (x within "
            f"[{lo + 0.1:.2f}, {hi - 0.1:.2f}] m)"
        )
    area = OperatorArea(
        center_xy=[along_m, edge_y + s * beyond],
        size_xy=[op.size_xy[1], op.size_xy[0]],
        floor_z=op.floor_z,
        facing_yaw=-s * math.pi / 2,
        work_spot=[along_m, edge_y - s * inside, op.work_spot[2]],
    )
    return cell.model_copy(update={"operator": area})


def _station_owners(cell: WorkCell, second: WorkCell, listed: Sequence[str]) -> dict[str, int]:
    names = [s.name for s in cell.drop_stations]
    unknown = sorted(set(listed) - set(names))
    if unknown:
        raise ScenarioError(
            f"second_operator.stations: {unknown} are not drop stations of the cell ({names})"
        )
    if listed:
        return {n: SECOND_OPERATOR_ID if n in listed else OPERATOR_ID for n in names}
    spot_a = np.asarray(cell.operator.work_spot[:2])
    spot_b = np.asarray(second.operator.work_spot[:2])
    owners = {}
    for s in cell.drop_stations:
        p = np.asarray(s.xyz[:2])
        nearer = np.linalg.norm(p - spot_b) < np.linalg.norm(p - spot_a)
        owners[s.name] = SECOND_OPERATOR_ID if nearer else OPERATOR_ID
    return owners


# ---------------------------------------------------------------------------------------------------------
# Walkers
# ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Pass:
    """One walk past the robot.

    Attributes:
        t_start: When the walker is at the path's start (outside the tracked volume) (s).
        t_closest: When they are closest to the robot's base (the path's middle) (s).
        t_end: When they reach the path's end (s).
        speed_mps: Walking speed (m/s).
        clearance_m: The pelvis path's closest horizontal approach to the robot's reach envelope (m).
        enter_from: Where they entered (``left``, ``right``, ``back``, ``front``).
        start_xy, end_xy: The path's ends (m, world).
        bow_xy: The bow of the path at its middle (m, world; towards the robot).
    """

    t_start: float
    t_closest: float
    t_end: float
    speed_mps: float
    clearance_m: float
    enter_from: str
    start_xy: tuple[float, float]
    end_xy: tuple[float, float]
    bow_xy: tuple[float, float]

    def point(self, u: np.ndarray | float) -> np.ndarray:
        """Path points (..., 2) at parameters ``u`` in [0, 1]."""
        u = np.asarray(u, dtype=float)[..., None]
        a, b, w = np.asarray(self.start_xy), np.asarray(self.end_xy), np.asarray(self.bow_xy)
        return a + (b - a) * u + w * np.sin(math.pi * u)


class _PathTable:
    """Arc length <-> parameter of a pass's path (the bow makes it no straight line)."""

    def __init__(self, p: Pass) -> None:
        self.u = np.linspace(0.0, 1.0, 257)
        pts = p.point(self.u)
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def u_at(self, s: float) -> float:
        return float(np.interp(s, self.s, self.u))


def _pass_geometry(
    cell: WorkCell, volume: CellVolume, enter_from: str, side: float, offset: float, bow: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ends and bow of a path whose middle lies ``offset`` from the base (horizontally), from a side."""
    base = np.asarray(cell.robot.base_xyz[:2], dtype=float)
    if enter_from in ("left", "right"):  # across the cell behind the robot
        normal = np.array([-1.0, 0.0])  # from the base towards the path
        direction = np.array([0.0, -1.0 if enter_from == "left" else 1.0])
    else:  # along the robot's left (side +1) or right (-1) side
        normal = np.array([0.0, side])
        direction = np.array([1.0 if enter_from == "back" else -1.0, 0.0])
    foot = base + normal * (offset + bow)
    corners = np.array([[x, y] for x in (volume.lo[0], volume.hi[0]) for y in (volume.lo[1], volume.hi[1])])
    half = float(np.max(np.abs((corners - foot) @ direction))) + 1.0
    return foot - half * direction, foot + half * direction, -normal * bow


def _box_distance_xy(
    box_center: Sequence[float], box_size: Sequence[float], yaw: float, p: np.ndarray
) -> float:
    c, h = np.asarray(box_center[:2]), np.asarray(box_size[:2]) / 2
    R = _rz(yaw)[:2, :2]
    q = np.abs((p - c) @ R) - h
    return float(np.min(np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(np.max(q, axis=-1), 0.0)))


def check_passers_by(cell: WorkCell, spec: PassersBy, areas: Sequence[WorkCell] = ()) -> None:
    """Refuse passes that would walk through the table, a static box or an operator's area.

    Raises:
        ScenarioError: naming the route and the clearance that does.
    """
    volume = CellVolume.from_workcell(cell)
    boxes = [(b.name, b.center, b.size, b.yaw) for b in cell.static_boxes]
    for c in [cell, *areas]:
        op = c.operator
        boxes.append(("an operator's area", [*op.center_xy, 0.0], [*op.size_xy, 1.0], 0.0))
    for enter in spec.enter_from:
        for side in (1.0, -1.0):
            for clearance in spec.clearance_m:
                for bow in spec.curve_m:
                    a, b, w = _pass_geometry(cell, volume, enter, side, spec.reach_m + clearance, bow)
                    u = np.linspace(0.0, 1.0, 401)[:, None]
                    pts = a + (b - a) * u + w * np.sin(math.pi * u)
                    for name, center, size, yaw in boxes:
                        d = _box_distance_xy(center, size, yaw, pts)
                        if d < PATH_CLEARANCE_OF_BOXES_M:
                            raise ScenarioError(
                                f"passers_by: a pass entering from the {enter} with clearance_m = "
                                f"{clearance} and curve_m = {bow} comes within {max(d, 0.0):.2f} m of "
                                f"{name} (at least {PATH_CLEARANCE_OF_BOXES_M} m: the walker's body); "
                                "raise clearance_m"
                            )


class Walker:
    """A person who walks past the robot now and then (see the module's docstring).

    Args:
        cell: The work cell (the robot's base, the floor, the tracked volume).
        spec: The scenario's passers-by.
        params: The walker's body (only ``height_m`` is used).
        seed: Seeds the passes.
        t0: Time of the first frame (s); the first pass's closest approach comes ``first_s`` after it.
    """

    def __init__(
        self, cell: WorkCell, spec: PassersBy, params: OperatorParams, *, seed: int, t0: float = 0.0
    ):
        self.cell = cell
        self.spec = spec
        self.params = params
        self.seed = int(seed)
        self.t0 = float(t0)
        self.body = _Body(params.height_m)
        self.volume = tracked_volume(cell)
        self.floor_z = float(cell.operator.floor_z)
        self._rng = np.random.default_rng([self.seed, 0x3A1C])
        self.passes: list[Pass] = []
        self._tables: list[_PathTable] = []
        self._starts: list[float] = []

    # -- the schedule -------------------------------------------------------------------------------------
    def _next_pass(self) -> None:
        rng, spec = self._rng, self.spec
        first = spec.first_s if spec.first_s is not None else spec.interval_s
        if self.passes:
            t_mid = self.passes[-1].t_closest + float(rng.uniform(*spec.interval_s))
        else:
            t_mid = self.t0 + float(rng.uniform(*first))
        enter = spec.enter_from[int(rng.integers(len(spec.enter_from)))]
        side = 1.0 if rng.random() < 0.5 else -1.0
        clearance = float(rng.uniform(*spec.clearance_m))
        bow = float(rng.uniform(*spec.curve_m))
        speed = float(rng.uniform(*spec.speed_mps))
        a, b, w = _pass_geometry(self.cell, self.volume, enter, side, spec.reach_m + clearance, bow)
        proto = Pass(0.0, 0.0, 0.0, speed, clearance, enter, tuple(a), tuple(b), tuple(w))
        table = _PathTable(proto)
        t_start = t_mid - 0.5 * table.length / speed
        if self.passes and t_start < self.passes[-1].t_end:  # never two passes of one walker at once
            t_start = self.passes[-1].t_end
            t_mid = t_start + 0.5 * table.length / speed
        p = dataclasses.replace(proto, t_start=t_start, t_closest=t_mid, t_end=t_start + table.length / speed)
        self.passes.append(p)
        self._tables.append(table)
        self._starts.append(p.t_start)

    def passes_until(self, t: float) -> list[Pass]:
        """The passes that start at or before ``t`` (planned as needed)."""
        while not self.passes or self.passes[-1].t_start <= t:
            self._next_pass()
        return [p for p in self.passes if p.t_start <= t]

    def _pass_at(self, t: float) -> tuple[Pass, _PathTable] | None:
        self.passes_until(t)
        i = bisect.bisect_right(self._starts, t) - 1
        if i < 0 or t > self.passes[i].t_end:
            return None
        return self.passes[i], self._tables[i]

    # -- the body -----------------------------------------------------------------------------------------
    def walking_pose(self, t: float) -> np.ndarray | None:
        """The walker's joints (J, 3) (m, world) at ``t`` while on a pass (in the cell or not), else None."""
        got = self._pass_at(t)
        if got is None:
            return None
        p, table = got
        s = (t - p.t_start) * p.speed_mps
        u = table.u_at(s)
        xy = p.point(u)
        tangent = p.point(min(u + 1e-3, 1.0)) - p.point(max(u - 1e-3, 0.0))
        heading = math.atan2(tangent[1], tangent[0])
        joints = self.gait(s, p.speed_mps)
        return joints @ _rz(heading).T + np.array([xy[0], xy[1], self.floor_z])

    def pose_at(self, t: float) -> np.ndarray | None:
        """The walker's joints (J, 3) at ``t`` if they are in the cell (every joint in the tracked volume)."""
        joints = self.walking_pose(t)
        if joints is None or not bool(np.all(self.volume.contains(joints))):
            return None
        return joints

    def gait(self, s: float, speed: float) -> np.ndarray:
        """Joints (J, 3) in the body frame (x forward, origin on the floor under the pelvis) after walking
        ``s`` metres at ``speed`` (m/s)."""
        b = self.body
        k = b.k
        step = self.params.height_m * (0.22 + 0.1 * speed)  # step length (m); a stride is two
        stride = 2.0 * step
        phase = s / stride
        leg = 0.995 * (b.l_thigh + b.l_shank)
        rise = _HEEL_RISE * k
        yaw_p = 0.06 * math.sin(2 * math.pi * phase)  # the pelvis turns with the forward leg
        R_p = _rz(yaw_p)
        out = np.empty((NUM_JOINTS, 3))
        feet, hips_xy = [], []
        for side, offset in ((1.0, 0.0), (-1.0, 0.5)):
            q = (phase + offset) % 1.0
            if q < _STANCE:  # planted from heel strike, the heel coming up before toe-off
                fx, stance = stride * (_FRONT - q), True
                fz = rise * ((q - _HEEL_OFF) / (_STANCE - _HEEL_OFF)) ** 2 if q > _HEEL_OFF else 0.0
            else:
                w = (q - _STANCE) / (1.0 - _STANCE)
                m = float(min_jerk(w))
                fx = stride * (_FRONT - _STANCE) + _STANCE * stride * m
                fz, stance = rise * (1.0 - m) + _FOOT_LIFT * k * math.sin(math.pi * w), False
            feet.append((np.array([fx, side * b.foot_y, b.ankle_z + fz]), stance))
            hips_xy.append(R_p @ np.array([0.0, side * b.hip_y, 0.0]))
        # the pelvis a few centimetres above its lowest (the front foot at heel strike, the back one at
        # toe-off), lower where a stance leg must reach its foot: the knees flex a little in mid-stance and
        # the pelvis bobs, as in walking
        dy2 = (b.foot_y - b.hip_y) ** 2
        front = math.sqrt(max(leg**2 - (_FRONT * stride + 0.01) ** 2 - dy2, 0.0))
        back = rise + math.sqrt(max(leg**2 - ((_STANCE - _FRONT) * stride + 0.01) ** 2 - dy2, 0.0))
        h = min(b.pelvis_z + b.hip_z - b.ankle_z, min(front, back) + _BOB * k)
        for (foot, stance), hip in zip(feet, hips_xy, strict=True):
            if stance:
                d2 = (foot[0] - hip[0]) ** 2 + (foot[1] - hip[1]) ** 2
                h = min(h, foot[2] - b.ankle_z + math.sqrt(max(leg**2 - d2, 0.0)))
        pelvis = np.array([0.0, 0.0, b.ankle_z + h - b.hip_z])
        lean = 0.04 + 0.03 * speed
        yaw_c = -0.6 * yaw_p
        R_half, R = _rz(0.5 * yaw_c) @ _ry(0.5 * lean), _rz(yaw_c) @ _ry(lean)
        spine = pelvis + R_half @ np.array([0.0, 0.0, b.l_spine])
        chest = spine + R @ np.array([0.0, 0.0, b.l_chest])
        neck = chest + R @ np.array([0.0, 0.0, b.l_neck])
        head = neck + _rz(yaw_c) @ np.array([0.0, 0.0, b.l_head])
        out[0], out[1], out[2], out[3], out[4] = pelvis, spine, chest, neck, head
        amp = 0.25 + 0.1 * speed
        for i, (side, offset) in enumerate(((1.0, 0.0), (-1.0, 0.5))):
            q = (phase + offset) % 1.0
            theta = -amp * math.cos(2 * math.pi * q)  # the arm swings against the leg of its side
            elbow_flex = 0.25 + 0.25 * max(math.sin(theta), 0.0) / max(math.sin(amp), 1e-6)
            sh = chest + R @ np.array([0.0, side * b.sh_y, b.sh_z])
            u1 = R @ _unit(np.array([math.sin(theta), side * 0.08, -math.cos(theta)]))
            u2 = R @ _unit(
                np.array([math.sin(theta + elbow_flex), side * 0.06, -math.cos(theta + elbow_flex)])
            )
            elbow = sh + b.l_upper * u1
            wrist = elbow + b.l_fore * u2
            base = 5 if i == 0 else 9
            out[base], out[base + 1], out[base + 2], out[base + 3] = sh, elbow, wrist, wrist + b.l_hand * u2
        for i, ((foot, _), hip_xy) in enumerate(zip(feet, hips_xy, strict=True)):
            hip = pelvis + hip_xy + np.array([0.0, 0.0, b.hip_z])
            knee, ankle = _two_link(hip, foot, b.l_thigh, b.l_shank)
            base = 13 if i == 0 else 16
            out[base], out[base + 1], out[base + 2] = hip, knee, ankle
        return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / float(np.linalg.norm(v))


def _two_link(a: np.ndarray, target: np.ndarray, l1: float, l2: float) -> tuple[np.ndarray, np.ndarray]:
    """Knee and ankle of a leg from the hip ``a`` to ``target``, the knee bending forward (+x); a target out
    of reach is brought within it along the same direction."""
    d_vec = target - a
    d = float(np.linalg.norm(d_vec))
    n = d_vec / d
    d = min(max(d, abs(l1 - l2) + 1e-6), 0.999 * (l1 + l2))
    x = (l1 * l1 - l2 * l2 + d * d) / (2.0 * d)
    r = math.sqrt(max(l1 * l1 - x * x, 0.0))
    pole = np.array([1.0, 0.0, 0.0])
    perp = pole - n * float(pole @ n)
    return a + n * x + _unit(perp) * r, a + n * d


# ---------------------------------------------------------------------------------------------------------
# The cell's people
# ---------------------------------------------------------------------------------------------------------
class SimulatedPeople(HumanSource):
    """Every simulated person of a scenario as one human source (see the module's docstring).

    Args:
        operators: ``{body id: operator}``, the operator under :data:`OPERATOR_ID`.
        walkers: ``{body id: walker}``.
        station_owner: ``{drop station: body id of the operator who fetches its blocks}`` (missing: the
            operator).
        scenario: The scenario they come from (for the records).
    """

    def __init__(
        self,
        operators: dict[int, SimulatedOperator],
        walkers: dict[int, Walker] | None = None,
        *,
        station_owner: dict[str, int] | None = None,
        scenario: Scenario | None = None,
    ) -> None:
        if OPERATOR_ID not in operators:
            raise ValueError(f"SimulatedPeople needs the operator (body id {OPERATOR_ID})")
        self.operators = dict(sorted(operators.items()))
        self.walkers = dict(sorted((walkers or {}).items()))
        if set(self.operators) & set(self.walkers):
            raise ValueError("SimulatedPeople: an id is both an operator's and a walker's")
        self.station_owner = dict(station_owner or {})
        self.scenario = scenario
        main = self.operators[OPERATOR_ID]
        self.t0, self.fps = main.t0, main.fps
        self.ids = tuple(sorted([*self.operators, *self.walkers]))

    @classmethod
    def from_scenario(
        cls,
        cell: WorkCell,
        scenario: Scenario,
        operator: SimulatedOperator,
        *,
        seed: int,
        participant_seed: int,
        population: Population | None = None,
    ) -> SimulatedPeople:
        """The people of ``scenario`` around ``operator`` (the trial's simulated operator): a second
        operator drawn from ``population`` (default: the shipped one) with the participant's seed, walkers
        with their own bodies; behaviour and passes from the trial's ``seed``.

        Raises:
            ScenarioError: the scenario does not fit the cell (a path through the table, an unknown station,
                a work spot off the table's side).
        """
        operators: dict[int, SimulatedOperator] = {OPERATOR_ID: operator}
        walkers: dict[int, Walker] = {}
        owners: dict[str, int] = {}
        areas = []
        if scenario.second_operator is not None:
            spec = scenario.second_operator
            cell2 = second_operator_cell(cell, spec.side, spec.along_m)
            owners = _station_owners(cell, cell2, spec.stations)
            mine = [st for st in cell.drop_stations if owners[st.name] == SECOND_OPERATOR_ID]
            if not mine:
                raise ScenarioError(
                    "second_operator: no drop station is nearer their work spot than the operator's; "
                    "list theirs in second_operator.stations"
                )
            cell2 = cell2.model_copy(update={"drop_stations": mine})  # they fetch (and know) only theirs
            areas.append(cell2)
            params = OperatorParams.draw(derived_seed(participant_seed, 0x5EC0, 1), population)
            operators[SECOND_OPERATOR_ID] = SimulatedOperator(
                cell2,
                params,
                seed=derived_seed(seed, 0x5EC0, 1),
                t0=operator.t0,
                fps=operator.fps,
                noise=operator.noise,
            )
        if scenario.passers_by is not None:
            spec_w = scenario.passers_by
            check_passers_by(cell, spec_w, areas)
            for i in range(spec_w.count):
                params = OperatorParams.draw(derived_seed(participant_seed, 0xA1C, i), population)
                walkers[FIRST_WALKER_ID + i] = Walker(
                    cell, spec_w, params, seed=derived_seed(seed, 0xA1C, i), t0=operator.t0
                )
        return cls(operators, walkers, station_owner=owners, scenario=scenario)

    # -- the people at an instant ---------------------------------------------------------------------
    def bodies_at(self, t: float, *, frames: bool = False) -> list[tuple[int, np.ndarray]]:
        """``(id, joints (J, 3))`` of every person present at ``t``, in id order: the true poses, or with
        ``frames`` the operators' frames at ``t`` (their own tracking noise, if they have it)."""
        out = []
        for i in self.ids:
            if i in self.operators:
                op = self.operators[i]
                if frames:
                    f = op.frame_at(t)
                    joints = None if f is None else f.joints
                else:
                    joints = op.pose_at(t) if t >= op.t0 else None
            else:
                joints = self.walkers[i].pose_at(t)
            if joints is not None:
                out.append((i, joints))
        return out

    def true_frame(self, t: float) -> HumanFrame | None:
        """Every person present at ``t`` as one noise-free frame stamped ``t`` (None before ``t0``): what a
        tracker sees (:class:`~app.cell.tracker.TrackedSource`)."""
        if t < self.t0:
            return None
        return _frame(t, self.bodies_at(t))

    def pose_at(self, t: float) -> np.ndarray:
        """The stacked true joints (B*J, 3) of the people present at ``t`` (the ids: :meth:`body_ids_at`)."""
        frame = self.true_frame(max(float(t), self.t0))
        assert frame is not None
        return frame.joints

    def body_ids_at(self, t: float) -> tuple[int, ...]:
        """The ids of the people present at ``t``, in the order of :meth:`pose_at`."""
        return tuple(i for i, _ in self.bodies_at(max(float(t), self.t0)))

    # -- the source protocol --------------------------------------------------------------------------
    def frame_at(self, t: float) -> HumanFrame | None:
        """The newest frame at or before ``t`` on the operator's frame grid: every person present then."""
        k = math.floor((t - self.t0) * self.fps + 1e-9)
        if k < 0:
            return None
        tk = self.t0 + k / self.fps
        return _frame(tk, self.bodies_at(tk, frames=True))

    def ground_truth(self) -> Callable[[float], HumanFrame]:
        """The truth: every person present at ``t``, with their ids (:meth:`true_frame`)."""
        return self._truth_at

    def _truth_at(self, t: float) -> HumanFrame:
        frame = self.true_frame(max(float(t), self.t0))
        assert frame is not None
        return frame

    def notify_block_placed(self, station: str, t: float) -> None:
        """Passed on to the operator who fetches from ``station`` (:attr:`station_owner`)."""
        self.operators[self.station_owner.get(station, OPERATOR_ID)].notify_block_placed(station, t)

    def passes_until(self, t: float) -> dict[int, list[Pass]]:
        """Every walker's passes that start at or before ``t``, by id."""
        return {i: w.passes_until(t) for i, w in self.walkers.items()}

    def describe(self) -> dict[str, object]:
        """Who is in the cell (for the records): the scenario, the ids, the bodies, the stations."""
        return {
            "scenario": None if self.scenario is None else self.scenario.model_dump(mode="json"),
            "operators": {str(i): op.params.to_dict() for i, op in self.operators.items()},
            "walkers": {str(i): {"height_m": w.params.height_m} for i, w in self.walkers.items()},
            "station_owner": dict(self.station_owner),
        }


def _frame(t: float, bodies: list[tuple[int, np.ndarray]]) -> HumanFrame:
    if not bodies:
        return HumanFrame(t, np.zeros((0, 3)), np.zeros(0), ())
    return HumanFrame(
        t,
        np.concatenate([j for _, j in bodies]),
        np.ones(len(bodies) * NUM_JOINTS),
        tuple(i for i, _ in bodies),
    )


class PeopleOracle(Predictor):
    """Every simulated person's own future as the forecast (the multi-person
    :class:`~app.cell.operator_sim.OracleForecaster`): for each body of the frame, an operator's future from
    a copy of that operator run ahead, a walker's from their pass (past the tracked volume too); stacked
    with the frame's ids (:func:`~app.prediction.forecast.stack_forecasts`). A person who enters within the
    horizon is not in the forecast until a frame shows them.

    Args:
        people: The trial's people (the same object the trial's source reads).
        horizon, margin_m, growth_mps, max_margin_m: As :class:`~app.cell.operator_sim.OracleForecaster`.
    """

    exact_within_horizon = True
    effective_kind = "OracleForecaster"

    def __init__(
        self,
        people: SimulatedPeople,
        *,
        horizon: int = 30,
        margin_m: float = 0.02,
        growth_mps: float = 1.6,
        max_margin_m: float = 1.0,
    ) -> None:
        self.people = people
        self.horizon = int(horizon)
        self.margin_m, self.growth_mps = float(margin_m), float(growth_mps)
        self.max_margin_m = max(float(max_margin_m), self.margin_m)
        self._operators = {
            i: OracleForecaster(
                op, horizon=horizon, margin_m=margin_m, growth_mps=growth_mps, max_margin_m=max_margin_m
            )
            for i, op in people.operators.items()
        }

    def reset(self) -> None:
        """Nothing to forget: the forecast comes from the people themselves."""

    def update(self, frame: HumanFrame) -> HumanForecast:
        """The future of every body of ``frame`` over the horizon (index 0: ``frame`` itself)."""
        dt = 1.0 / self.people.fps
        parts = []
        for k, body in enumerate(frame.split()):
            bid = frame.body_ids[k]
            if bid in self._operators:
                fc = self._operators[bid].update(body)
            else:
                joints = np.empty((self.horizon + 1, NUM_JOINTS, 3))
                joints[0] = body.joints
                walker = self.people.walkers.get(bid)
                for h in range(1, self.horizon + 1):
                    pose = None if walker is None else walker.walking_pose(frame.t + h * dt)
                    joints[h] = joints[h - 1] if pose is None else pose
                fc = HumanForecast(
                    t0=frame.t,
                    times=frame.t + dt * np.arange(self.horizon + 1),
                    joints=joints,
                    margins=np.full(self.horizon + 1, self.margin_m),
                    growth_mps=self.growth_mps,
                    max_margin_m=self.max_margin_m,
                )
            parts.append(dataclasses.replace(fc, body_ids=(bid,)))
        if not parts:
            return HumanForecast(
                t0=frame.t,
                times=np.array([frame.t]),
                joints=np.zeros((1, 0, 3)),
                margins=np.array([self.margin_m]),
                growth_mps=self.growth_mps,
                max_margin_m=self.max_margin_m,
                body_ids=(),
            )
        return stack_forecasts(parts, t0=frame.t)
