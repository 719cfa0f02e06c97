"""What limits each robot part's speed now: the operator's read-out of the speed governor.

Per robot part, one of four modes (:data:`PART_MODES`):

- ``free``: the governor does not limit the part (it may run at the full path speed);
- ``ssm``: it is slowed by its separation: braking now, it must keep ``S_p`` from the body regions it could
  not touch at its speed (ISO/TS 15066 5.5.4.2.3);
- ``pfl``: it moves at the permissible contact speed of a body region next to it (ISO/TS 15066 Annex A,
  power and force limiting inside ``S_p``): a little faster and it would have to keep ``S_p`` from that
  region too (:mod:`app.safety.pfl`);
- ``stopped``: it may not move at all: within ``S_p(0)`` of a region that admits no contact (the
  supervisor's stop rule), no safe speed above zero, or the robot is held (E-stop, fault, stale stream, a
  stop & replan).

:func:`part_modes` classifies the parts from the governor's own inputs (the supervisor's latest
:class:`~app.safety._kernels.PartSeparation`, the robot's :class:`~app.safety._kernels.RobotMotion`, the
:class:`~app.safety._kernels.ServoGovernor`), with the compiled envelope of the servo tick
(:func:`app.safety._kernels.max_scale`) per part, and gives each part the separation the governor holds it to
at its current speed (the braking envelope's requirement, the ``S_p`` of its binding level with the person's
worst-case approach over the brake). It reads and changes nothing of the governor: the supervisor calls it
at the snapshot rate, never per servo tick. Lengths in metres, speeds in m/s, scales 0..1.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from app.safety._kernels import PartSeparation, RobotMotion, ServoGovernor, law_scale, max_scale

__all__ = [
    "PART_MODES",
    "REGION_LABELS",
    "PartMode",
    "PartModeName",
    "RegionMap",
    "binding_part",
    "mode_text",
    "part_modes",
    "region_text",
]

PartModeName = Literal["free", "ssm", "pfl", "stopped"]
#: The modes of a robot part, from the least limited to the most.
PART_MODES: tuple[PartModeName, ...] = ("free", "ssm", "pfl", "stopped")

#: How the operator's screens name the body regions of :data:`app.safety.pfl.BODY_REGIONS`.
REGION_LABELS: dict[str, str] = {
    "skull_forehead": "skull/forehead",
    "face": "face",
    "neck": "neck",
    "back_shoulders": "back/shoulders",
    "chest": "chest",
    "abdomen": "abdomen",
    "pelvis": "pelvis",
    "upper_arm_elbow": "upper arm/elbow",
    "lower_arm_wrist": "lower arm/wrist",
    "hand_fingers": "hand/fingers",
    "thigh_knee": "thigh/knee",
    "lower_leg": "lower leg",
}

#: A part slower than this (m/s) at full path speed does not move (the governor's own threshold).
_MOVING_MPS = 1e-4


@dataclass(frozen=True, slots=True)
class RegionMap:
    """Which body region each robot part is measured against, at the frame the governor last measured.

    Attributes:
        d_pairs: (L, M) surface distances of the robot's parts to the person's capsules (m).
        caps_mps: (M,) each capsule's permissible contact speed (m/s; -1: no contact), quasi-static where
            pinned, as the governor's levels were built from (:meth:`app.safety.pfl.PFLModel.caps_mps`).
        regions: (M,) each capsule's body region (:func:`app.safety.pfl.capsule_region`).
    """

    d_pairs: np.ndarray
    caps_mps: np.ndarray
    regions: tuple[str, ...]

    def __post_init__(self) -> None:
        d = np.asarray(self.d_pairs, dtype=np.float64)
        caps = np.asarray(self.caps_mps, dtype=np.float64)
        if d.ndim != 2 or caps.shape != (d.shape[1],) or len(self.regions) != d.shape[1]:
            raise ValueError(
                f"RegionMap: d_pairs must be (L, M) with caps_mps and regions (M,), got {d.shape}, "
                f"{caps.shape} and {len(self.regions)} regions"
            )

    def nearest(self, part: int, upto_mps: float) -> str | None:
        """The region of the nearest capsule to ``part`` whose permissible speed is at most ``upto_mps``
        (those it keeps ``S_p`` from at that level), None when there is none."""
        return self._nearest(part, np.asarray(self.caps_mps) <= upto_mps + 1e-12)

    def between(self, part: int, above_mps: float, upto_mps: float) -> str | None:
        """The region of the nearest capsule to ``part`` whose permissible speed is above ``above_mps`` and
        at most ``upto_mps`` (those a part speeding up from one level to the other starts to keep ``S_p``
        from)."""
        caps = np.asarray(self.caps_mps)
        return self._nearest(part, (caps > above_mps + 1e-12) & (caps <= upto_mps + 1e-12))

    def _nearest(self, part: int, sel: np.ndarray) -> str | None:
        if not sel.any():
            return None
        d = np.where(sel, np.asarray(self.d_pairs)[part], np.inf)
        return self.regions[int(np.argmin(d))]


@dataclass(frozen=True, slots=True)
class PartMode:
    """What limits one robot part now (:func:`part_modes`).

    Attributes:
        mode: One of :data:`PART_MODES`.
        region: ``pfl``: the body region whose permissible contact speed the part is at; else
            :attr:`held_from`.
        held_from: The body region the part keeps ``S_p`` from at its speed (the nearest of those it could
            not touch at that speed; for a ``stopped`` part, the one that stops it). None where no person
            was seen or no region map was given.
        separation_m: The part's separation from the capsules it keeps ``S_p`` from (m, as measured less the
            tracking margin; inf: nobody seen).
        required_m: The separation the governor holds the part to at its current speed, measured the same
            way (m): braking now, ``S_p`` at every instant of the brake with the person's worst-case approach
            since the frame and over the brake; for a ``stopped`` part, what it would need to move at all.
        limit_scale: The largest path scale this part alone allows (0..1).
        v_toward_mps: The part's speed toward the person now (m/s; negative: moving away).
    """

    mode: PartModeName
    region: str | None
    held_from: str | None
    separation_m: float
    required_m: float
    limit_scale: float
    v_toward_mps: float

    @property
    def label(self) -> str:
        """``free``, ``ssm``, ``stopped`` or ``pfl:<region>``."""
        return f"pfl:{self.region}" if self.mode == "pfl" and self.region else self.mode

    @property
    def text(self) -> str:
        """The mode as the operator's screens show it: ``free``, ``SSM``, ``PFL · hand/fingers``,
        ``stopped``."""
        return mode_text(self.label)

    @property
    def margin_m(self) -> float:
        """``separation_m - required_m`` (m; inf where nobody was seen)."""
        if not math.isfinite(self.separation_m):
            return math.inf
        return self.separation_m - self.required_m


def mode_text(label: str | None) -> str:
    """A mode's label (:attr:`PartMode.label`: ``free``, ``ssm``, ``pfl:<region>``, ``stopped``) as the
    operator's screens show it; ``–`` for none."""
    if not label:
        return "–"
    if label.startswith("pfl"):
        region = label.partition(":")[2]
        return f"PFL · {region_text(region)}" if region else "PFL"
    return "SSM" if label == "ssm" else label


def region_text(region: str) -> str:
    """A body region (:data:`app.safety.pfl.BODY_REGIONS`) as the operator's screens name it."""
    return REGION_LABELS.get(region, region.replace("_", " "))


def _level(v: float, levels: np.ndarray) -> int:
    """:func:`app.safety._kernels._pfl_level`: the last level whose permissible speed is below ``v``."""
    k = 0
    for j in range(1, levels.shape[0]):
        if levels[j] < v:
            k = j
    return k


def _approach(v0: np.ndarray, dt: np.ndarray, v_max_h: float, accel: float) -> tuple[np.ndarray, np.ndarray]:
    """The kernels' ``_approach`` over arrays: worst-case approach (m) and speed (m/s) after ``dt`` (s)."""
    dt = np.maximum(dt, 0.0)
    vmax = max(v_max_h, float(v0))
    if accel <= 0.0:
        return v0 * dt, np.full_like(dt, float(v0))
    t1 = (vmax - v0) / accel
    acc = np.minimum(dt, t1)
    dist = v0 * acc + 0.5 * accel * acc * acc + vmax * np.maximum(dt - t1, 0.0)
    return dist, np.minimum(v0 + accel * dt, vmax)


def _need(sc: float, vh: float, vp: float, rate: float, env_u: np.ndarray, params: np.ndarray) -> float:
    """The braking envelope's requirement (:func:`app.safety._kernels.max_scale`'s check) at scale ``sc``:
    the largest of ``x_h(t) + travel(t) + S_p(t)`` over the instants of a brake from ``sc`` (m)."""
    s0, t_r, v_max_h, accel = params[0], params[1], params[3], params[4]
    r = max(rate, 1e-6)
    a = rate * vp
    v = sc * vp
    t = env_u * sc / r
    x_h, v_h = _approach(np.float64(vh), t, v_max_h, accel)
    travel = v * t - 0.5 * a * t * t
    s_t = sc - rate * t
    v_part = np.maximum(s_t * vp, 0.0)
    need = np.maximum(v_h, 0.0) * (t_r + s_t / r) + (v_part * t_r + v_part * (0.5 * (s_t / r)) + s0)
    return float(np.max(x_h + travel + need))


def part_modes(
    parts: PartSeparation,
    robot: RobotMotion,
    governor: ServoGovernor,
    *,
    scale: float,
    dt_h: float,
    rate: float,
    regions: RegionMap | None = None,
    held: bool = False,
) -> tuple[PartMode, ...]:
    """Classify every robot part (L,) by what limits its speed (:class:`PartMode`).

    Args:
        parts: The governor's last measurement of the person (the supervisor's latest).
        robot: The robot's motion at scale 1 as the governor's tick reads it.
        governor: The governor's constants (separation model, law, grid, brake instants).
        scale: The path scale now.
        dt_h: Seconds since the middle of the person's speed window (NaN: no measurement yet, the person's
            fastest approach), as :func:`app.safety._kernels.governed_scale` takes it (there: to the next
            tick).
        rate: How fast a brake lowers the scale now (1/s; inf: a path at rest).
        regions: The body regions behind the levels (None: no region named).
        held: The robot is held whatever the separation (E-stop, fault, stale stream, a stop & replan):
            every part is ``stopped``.

    Returns:
        One :class:`PartMode` per part, in the parts' order.
    """
    params = governor.separation
    s0, t_r, v_max_h, accel = (float(params[i]) for i in (0, 1, 3, 4))
    levels, extra, v_lv = parts.pfl.levels, parts.pfl.extra, parts.pfl.v_h
    moving = bool(np.any(robot.v_part > _MOVING_MPS))
    grid = governor.scales
    step = float(grid[1] - grid[0]) if grid.shape[0] > 1 else 1.0
    rate = rate if math.isfinite(rate) else 1e6  # a path at rest stops at once
    scale = min(max(float(scale), 0.0), 1.0)

    def nearest(i: int, lv: int) -> str | None:
        return None if regions is None else regions.nearest(i, float(levels[lv]))

    out: list[PartMode] = []
    for i in range(parts.sep_m.shape[0]):
        sep_m = float(parts.sep_m[i])
        # the separation's lower bound now and the person's speed, as the servo tick takes them
        if math.isnan(dt_h):
            d, vh = sep_m, v_max_h
        else:
            x1, v1 = _approach(np.float64(parts.v_h0[i]), np.array([dt_h]), v_max_h, accel)
            d = sep_m - (float(x1[0]) - float(parts.x_h0[i])) - float(robot.closed_m[i])
            vh = float(v1[0])
        vp = float(robot.v_toward[i])
        row = (levels, np.ascontiguousarray(extra[i : i + 1]), np.ascontiguousarray(v_lv[i : i + 1]))
        limit = 1.0
        if moving:
            one = (np.array([d]), np.array([vh]), np.array([vp]))
            limit = float(max_scale(*one, rate, 0.0, 1.0, grid, governor.env_u, params, *row))
            if governor.law.shape[0] > 0:
                vm = np.array([max(float(parts.v_h0[i]), 0.0)])
                limit = min(limit, max(float(law_scale(one[0], one[2], vm, governor.law, *row)), 0.0))
        # the scale whose requirement is shown, and the level it is held at
        if sep_m + float(extra[i, 0]) <= s0 + t_r * float(parts.v_h0[i]):
            # the supervisor's stop rule: within S_p(0) of a region that admits no contact
            mode: PartModeName = "stopped"
            sc, lv, limit = 0.0, 0, 0.0
        elif held or limit <= 0.0:
            mode = "stopped"
            sc = step if moving and not held else 0.0  # what it would need to move at all
            lv = _level(sc * vp, levels)
        else:
            sc = scale
            lv = _level(sc * vp, levels)
            nxt = min(limit + step, 1.0)  # the next scale of the grid, which the governor refused
            lv_at, lv_next = _level(limit * vp, levels), _level(nxt * vp, levels)
            if limit >= 1.0 - 1e-9:
                mode = "free"
            elif lv_next > lv_at and (
                d + float(extra[i, lv_at])
                >= _need(nxt, min(vh, float(v_lv[i, lv_at])), vp, rate, governor.env_u, params)
            ):
                # faster, it would have to keep S_p from a region it may touch at this speed, and it
                # could not: it is at that region's permissible speed (else its S_p holds it: SSM)
                mode = "pfl"
            else:
                mode = "ssm"
        need = _need(sc, min(vh, float(v_lv[i, lv])), vp, rate, governor.env_u, params)
        if governor.law.shape[0] > 0:  # the speed-scaling law's S_p, at the measured speed (law_scale)
            vm = min(max(float(parts.v_h0[i]), 0.0), float(v_lv[i, lv]))
            law = governor.law
            need = max(need, vm * law[0] + law[1] + max(sc * vp, 0.0) * law[2])
        # both as measured: the requirement plus what the person and the part may have closed since
        required, separation = need + (sep_m - d), sep_m + float(extra[i, lv])
        held_from = nearest(i, lv) if math.isfinite(separation) else None
        region = held_from
        if mode == "pfl" and regions is not None:
            region = regions.between(i, float(levels[lv_at]), float(levels[lv_next]))
        limit = 0.0 if held else limit
        out.append(PartMode(mode, region, held_from, separation, float(required), limit, scale * vp))
    return tuple(out)


def binding_part(modes: Sequence[PartMode]) -> int:
    """The index of the part that limits the robot: the smallest allowed scale, then the smallest margin
    between its separation and the one it is held to (-1 for no part)."""
    if not modes:
        return -1
    return min(range(len(modes)), key=lambda i: (modes[i].limit_scale, modes[i].margin_m))
