"""The ground-truth safety monitor: the judge of a trial, on the true robot and the true person.

It runs at the robot's servo rate on the robot's state and the *true* pose of the person (in simulation the
simulated operator or the replayed clip, never the tracker's frames that the supervisor acts on), and shares
nothing with the supervisor but the geometry of the bodies. For every robot part (capsule) and every check:

- the surface separation ``d`` to the person (capsule to capsule);
- the part's speed *toward* the person ``v_r``: how fast the robot's own motion closes the distance to the
  nearest body capsules (a part moving sideways or away counts 0);
- the person's speed toward the part ``v_h``: how fast the person's true motion closes it (likewise);
- ISO/TS 15066's ``S_p = v_h (T_r + T_s) + v_r T_r + S_s + C + Z_r``, with ``T_s`` and ``S_s`` from the
  one stopping model (:mod:`app.safety.stopping`) at the robot's current speed and ``T_r`` of the system
  (tracker latency + frame period + processing + controller cycle). The sensing uncertainty ``Z_d`` is not
  added: it stands for the difference between the person as measured and the true person, and the judge
  sees the true person (a system that keeps the measured separation above the full ``S_p`` keeps the true
  one above ``S_p - Z_d``).

A **violation** is a robot that is not at standstill with a part closer than its ``S_p``; a **contact** is a
robot that is not at standstill touching the person (``d <= 0``), the severe case, counted apart. An episode
lasts while consecutive checks violate: it ends when the robot is at standstill (every joint slower than
``standstill_radps``) or the separation has recovered. A braking robot is judged like any other until it is
at standstill. The same trial is also judged with ISO 13855's constant speeds instead of the measured ones
(1.6 m/s for the body, 2.0 m/s for a hand or arm reaching in) and reported apart (``violations_iso``): that
is what a cell without a person tracker would have to keep.

What it does not judge: the accuracy of the capsules themselves (a test checks that they enclose the UR5e's
meshes), contact forces (ISO/TS 15066's power and force limiting), or the person's safety against the static
scene.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from app.safety.ssm import SSMParams, required_separation
from app.safety.stopping import UR5E_STOP, StoppingModel

__all__ = [
    "ISO13855_SPEEDS",
    "GroundTruthMonitor",
    "MonitorEpisode",
    "MonitorSample",
    "MonitorTotals",
    "is_intrusion",
]

#: ISO 13855's constant approach speeds (m/s): the body (walking) and a hand or arm reaching in.
ISO13855_SPEEDS = {"body": 1.6, "arm": 2.0}
#: Joints whose bones are the arm and the hand (ISO 13855's 2.0 m/s).
_ARM_WORDS = ("shoulder-", "elbow", "wrist", "hand")


def is_intrusion(joint_speeds_mps: np.ndarray, *, body_mps: float = 5.0) -> bool:
    """Whether joint speeds (J,) (m/s) between two frames are beyond a person: the body (its median joint)
    faster than ``body_mps`` (a person walks at up to 2 m/s and runs at 3-5 m/s), or any joint faster than
    twice that (a hand in fast work reaches 2-3 m/s and in a throw up to about 10 m/s; beyond, a joint of the
    skeleton jumped: a tracking or recording glitch, or another person)."""
    v = np.asarray(joint_speeds_mps, dtype=np.float64)
    return bool(float(np.median(v)) > body_mps or float(v.max()) > 2.0 * body_mps)


class BodyGeometry(Protocol):
    """What the monitor needs of the collision model."""

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray: ...

    def part_speeds(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True, slots=True)
class MonitorSample:
    """One check of one robot part (the worst one of the check).

    Attributes:
        t: Time (s).
        part: The robot part (capsule name).
        separation_m: Its surface distance to the true person (m).
        required_m: Its ``S_p`` (m).
        robot_speed_mps: Its speed toward the person (m/s).
        human_speed_mps: The person's true speed toward it (m/s).
        violation: The robot was not at standstill and ``separation_m < required_m``.
        contact: The robot was not at standstill and touched the person.
    """

    t: float
    part: str
    separation_m: float
    required_m: float
    robot_speed_mps: float
    human_speed_mps: float
    violation: bool
    contact: bool

    def to_json(self) -> dict[str, Any]:
        return {
            "t": round(self.t, 4),
            "part": self.part,
            "separation_m": round(self.separation_m, 4),
            "required_m": round(self.required_m, 4),
            "robot_speed_mps": round(self.robot_speed_mps, 4),
            "human_speed_mps": round(self.human_speed_mps, 4),
        }


@dataclass(frozen=True, slots=True)
class MonitorEpisode:
    """One violation or contact episode, as the trial's JSON lists it.

    Attributes:
        kind: ``violation`` or ``contact``.
        intrusion: Started by an intrusion (counted apart, in ``violations_in_intrusions``).
        start_s: Time of its first check (s).
        duration_s: From its first check to its last (s); 0 for an episode of one check.
        first: Its first check.
        worst: Its check with the least ``separation - S_p``.
    """

    kind: str
    intrusion: bool
    start_s: float
    duration_s: float
    first: MonitorSample
    worst: MonitorSample

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "intrusion": self.intrusion,
            "start_s": round(self.start_s, 4),
            "duration_s": round(self.duration_s, 4),
            "first": self.first.to_json(),
            "worst": self.worst.to_json(),
        }


@dataclass(frozen=True, slots=True)
class MonitorTotals:
    """A trial's verdict (see the module docstring).

    Attributes:
        violations: Violation episodes.
        contacts: Contact episodes.
        violation_time_s: Time spent in violation (s).
        violations_iso: Violation episodes with ISO 13855's constant human speeds.
        intrusions: Checks at which the true person jumped faster than a person moves.
        violations_in_intrusions: Violation episodes that an intrusion started (not in ``violations``).
        min_separation_m: Smallest separation (m), robot moving or not.
        min_separation_moving_m: Smallest separation while the robot was not at standstill (m).
        worst: The check with the least ``separation - S_p`` while the robot moved (None if it never did).
        checks: Checks made.
        episodes: Every violation and contact episode (the first :attr:`GroundTruthMonitor.MAX_EPISODES`),
            with its first and worst check, so that each one can be read from the trial's JSON.
    """

    violations: int
    contacts: int
    violation_time_s: float
    violations_iso: int
    intrusions: int
    violations_in_intrusions: int
    min_separation_m: float
    min_separation_moving_m: float
    worst: MonitorSample | None
    checks: int
    episodes: tuple[MonitorEpisode, ...] = ()


class GroundTruthMonitor:
    """Judges the robot against the true person at every check (see the module docstring).

    Args:
        geometry: The robot's and the person's bodies (``pair_distances``, ``part_speeds``): the collision
            model's capsules.
        ssm: ``C``, ``Z_d``, ``Z_r`` (:class:`~app.safety.ssm.SSMParams`).
        part_names: The robot parts (capsules), in the geometry's order.
        human_capsules: The person's capsules, in the geometry's order (their names say which are arm and
            hand, for ISO 13855's 2.0 m/s).
        reaction_time_s: ``T_r`` of the system (:func:`app.safety.stopping.reaction_time_s`).
        stopping: The robot's stopping model.
        standstill_radps: The robot is at standstill when every joint is slower than this (rad/s): 0.01 rad/s
            (0.57 deg/s), at most 1 cm/s at the UR5e's 0.85 m reach. Our choice, not a standard's figure: a
            robot held still by the supervisor settles onto its set-point with a tail of a few mrad/s that
            no one would call motion, while every commanded motion is far faster.
        near_band_m: The capsules of the person within this of the nearest one to a part count for the
            directed speeds.
        fd_step_s: Time step of the robot's directed speed (finite difference along ``qd``).
        intrusion_speed_mps: The true person moving like no person moves between two checks
            (:func:`is_intrusion` with this body speed) is an intrusion: a person appearing, or a recording
            or a tracker jumping. A violation episode that starts within the reaction time ``T_r`` of an
            intrusion's last check (until then no system can have reacted to the jump; the jump itself,
            spread over a few checks, may open the episode a check or two after it was seen) is the
            intrusion's, not the planner's, until it ends (the robot at standstill or the separation
            recovered): it is counted apart (``violations_in_intrusions``), never dropped.
    """

    #: How many episodes :meth:`totals` lists (all are counted).
    MAX_EPISODES = 50

    def __init__(
        self,
        geometry: BodyGeometry,
        ssm: SSMParams,
        *,
        part_names: Sequence[str],
        human_capsules: Sequence[str],
        reaction_time_s: float,
        stopping: StoppingModel = UR5E_STOP,
        standstill_radps: float = 0.01,
        near_band_m: float = 0.05,
        fd_step_s: float = 1e-3,
        intrusion_speed_mps: float = 5.0,
    ) -> None:
        if not (math.isfinite(reaction_time_s) and reaction_time_s >= 0):
            raise ValueError(f"reaction_time_s must be a finite number >= 0, got {reaction_time_s!r}")
        self.geometry = geometry
        self.ssm = ssm
        self.part_names = tuple(part_names)
        self.stopping = stopping
        self.t_r = float(reaction_time_s)
        self.standstill_radps = float(standstill_radps)
        self.near_band_m = float(near_band_m)
        self.fd_step_s = float(fd_step_s)
        self.intrusion_speed_mps = float(intrusion_speed_mps)
        self.intrusions = 0
        self.violations_in_intrusions = 0
        self._intrusion_t = -math.inf  # time of the last check that saw an intrusion
        self._episode_intrusion = False  # the open violation episode is an intrusion's
        self._open: dict[str, _OpenEpisode] = {}  # the episodes under way, by kind
        self.episodes: list[MonitorEpisode] = []
        # judged on the true person, the sensing uncertainty Z_d is not added: it stands for the difference
        # between the measured and the true person, which the judge does not have (a system that keeps the
        # *measured* separation above S_p keeps the true one above S_p - Z_d)
        self._constant_m = float(ssm.intrusion_m + ssm.z_robot_m)
        arm = [any(w in name for w in _ARM_WORDS) for name in human_capsules]
        self.iso_speeds = np.where(arm, ISO13855_SPEEDS["arm"], ISO13855_SPEEDS["body"])
        self.checks = 0
        self.violations = 0
        self.contacts = 0
        self.violations_iso = 0
        self.violation_time_s = 0.0
        self.min_separation_m = math.inf
        self.min_separation_moving_m = math.inf
        self.worst: MonitorSample | None = None
        self._in = {"violation": False, "contact": False, "iso": False}
        self._last_t: float | None = None

    # ------------------------------------------------------------------------------------------------
    def check(
        self,
        t: float,
        q: np.ndarray,
        qd: np.ndarray,
        joints: np.ndarray,
        joints_before: np.ndarray,
        dt: float,
    ) -> MonitorSample:
        """Judge the robot at ``q``, ``qd`` (6,) against the true person at ``joints`` (J, 3), who was at
        ``joints_before`` ``dt`` seconds earlier. Returns the worst part of this check."""
        q = np.asarray(q, dtype=np.float64).reshape(6)
        qd = np.asarray(qd, dtype=np.float64).reshape(6)
        joints = np.asarray(joints, dtype=np.float64)
        before = np.asarray(joints_before, dtype=np.float64)
        tick = 0.0 if self._last_t is None else max(float(t) - self._last_t, 0.0)
        self._last_t = float(t)
        self.checks += 1
        if dt > 0 and is_intrusion(
            np.linalg.norm(joints - before, axis=1) / dt, body_mps=self.intrusion_speed_mps
        ):
            self.intrusions += 1
            self._intrusion_t = float(t)
        w_top = float(np.abs(qd).max())
        moving = w_top > self.standstill_radps
        d = self.geometry.pair_distances(q, np.stack([joints, before]))  # (2, L, M)
        d0 = d[0]
        sep = d0.min(axis=1)
        self.min_separation_m = min(self.min_separation_m, float(sep.min()))
        if not moving:
            self._close_episodes()
            i = int(np.argmin(sep))
            return MonitorSample(t, self._part(i), float(sep[i]), 0.0, 0.0, 0.0, False, False)
        self.min_separation_moving_m = min(self.min_separation_moving_m, float(sep.min()))
        near = d0 <= sep[:, None] + self.near_band_m
        v_h_pair = np.maximum(d[1] - d0, 0.0) / dt if dt > 0 else np.zeros_like(d0)
        h = self.fd_step_s
        d_ahead = self.geometry.pair_distances(q + h * qd, joints[None])[0]
        v_r_pair = np.maximum(d0 - d_ahead, 0.0) / h
        v_h = np.where(near, v_h_pair, 0.0).max(axis=1)
        v_r = np.where(near, v_r_pair, 0.0).max(axis=1)
        v_top = float(np.asarray(self.geometry.part_speeds(q[None], qd[None])).max())
        t_s = self.stopping.stop_time_s(v_top, w_top)
        s_s = self.stopping.stop_distance_m(v_r, t_s)
        t_r, c = self.t_r, self._constant_m
        req = required_separation(v_h, v_r, t_reaction_s=t_r, t_stop_s=t_s, constant_m=c, stop_distance_m=s_s)
        margin = sep - req
        i = int(np.argmin(margin))
        violation = bool(margin[i] < 0.0)
        contact = bool(sep.min() <= 0.0)
        # ISO 13855's constant speeds, per pair of capsules
        req_iso = required_separation(
            self.iso_speeds[None, :], v_r[:, None], t_reaction_s=t_r, t_stop_s=t_s, constant_m=c,
            stop_distance_m=s_s[:, None],
        )  # fmt: skip
        iso = bool(np.any(d0 < req_iso))
        sample = MonitorSample(
            t, self._part(i), float(sep[i]), float(req[i]), float(v_r[i]), float(v_h[i]), violation, contact
        )
        if self.worst is None or margin[i] < self.worst.separation_m - self.worst.required_m:
            self.worst = sample
        if violation:
            self.violation_time_s += tick
        self._episode("violation", violation, sample, float(margin[i]))
        self._episode("contact", contact, sample, float(margin[i]))
        self._episode("iso", iso, sample, float(margin[i]))
        return sample

    def totals(self) -> MonitorTotals:
        """The verdict so far."""
        return MonitorTotals(
            violations=self.violations,
            contacts=self.contacts,
            violation_time_s=round(self.violation_time_s, 6),
            violations_iso=self.violations_iso,
            intrusions=self.intrusions,
            violations_in_intrusions=self.violations_in_intrusions,
            min_separation_m=self.min_separation_m,
            min_separation_moving_m=self.min_separation_moving_m,
            worst=self.worst,
            checks=self.checks,
            # the episodes that ended, then those still under way (the trial may end inside one)
            episodes=tuple(self.episodes) + tuple(rec.episode(kind) for kind, rec in self._open.items()),
        )

    # ------------------------------------------------------------------------------------------------
    def _part(self, i: int) -> str:
        return self.part_names[i] if i < len(self.part_names) else str(i)

    def _episode(self, kind: str, now: bool, sample: MonitorSample, margin_m: float) -> None:
        if not now:
            self._end(kind)
            return
        if not self._in[kind]:
            if kind == "violation":
                self._episode_intrusion = sample.t - self._intrusion_t <= self.t_r
                if self._episode_intrusion:
                    self.violations_in_intrusions += 1
                else:
                    self.violations += 1
            elif kind == "contact":
                self.contacts += 1
            else:
                self.violations_iso += 1
            self._in[kind] = True
            if kind != "iso":
                intrusion = kind == "violation" and self._episode_intrusion
                self._open[kind] = _OpenEpisode(sample, sample, margin_m, sample.t, intrusion)
        elif kind in self._open:
            self._open[kind].update(sample, margin_m)

    def _end(self, kind: str) -> None:
        self._in[kind] = False
        if kind == "violation":
            self._episode_intrusion = False
        rec = self._open.pop(kind, None)
        if rec is not None and len(self.episodes) < self.MAX_EPISODES:
            self.episodes.append(rec.episode(kind))

    def _close_episodes(self) -> None:
        for kind in self._in:
            self._end(kind)


@dataclass(slots=True)
class _OpenEpisode:
    """An episode still under way: its first and worst check, and its last check's time."""

    first: MonitorSample
    worst: MonitorSample
    worst_margin_m: float
    last_t: float
    intrusion: bool

    def episode(self, kind: str) -> MonitorEpisode:
        """The episode so far."""
        return MonitorEpisode(
            kind, self.intrusion, self.first.t, self.last_t - self.first.t, self.first, self.worst
        )

    def update(self, sample: MonitorSample, margin_m: float) -> None:
        self.last_t = sample.t
        if margin_m < self.worst_margin_m:
            self.worst, self.worst_margin_m = sample, margin_m
