"""The ground-truth safety monitor: the judge of a trial, on the true robot and the true person.

It runs at the robot's servo rate on the robot's state and the *true* pose of the person (in simulation the
simulated operator or the replayed clip, never the tracker's frames that the supervisor acts on), and shares
nothing with the supervisor but the geometry of the bodies and the rules of the safety model
(:mod:`app.safety.pfl`): speed and separation monitoring combined with power and force limiting, with ISO
13855's person. For every robot part (capsule), every capsule of the person and every check:

- the surface separation ``d`` (capsule to capsule);
- the part's speed *toward* that capsule ``v_r``: how fast the robot's own motion closes the distance;
- the person's true speed toward the part ``v_true``: how fast the person's true motion closes it;
- the governor's ``v_h`` rule: ISO 13855's speed of the capsule's region (2.0 m/s for a hand or arm,
  1.6 m/s for the body), the true speed where it is faster;
- ISO/TS 15066's ``S_p = v_h (T_r + T_s) + v_r T_r + S_s + C + Z_r``, with ``T_s`` and ``S_s`` from the
  one stopping model (:mod:`app.safety.stopping`) at the robot's current speed and ``T_r`` of the system.
  The sensing uncertainty ``Z_d`` is not added: the judge sees the true person;
- the region's permissible contact speed (ISO/TS 15066 Annex A; quasi-static where a hand or forearm lies
  on the scene; none for skull, face and neck).

What it counts, while the robot is not at standstill:

- a **violation**: a part closer than its ``S_p`` to a capsule while its speed toward that capsule is above
  the region's permissible speed. An episode that a person approaching faster than ISO 13855's speed opened
  (before the robot could react and stop: within ``T_r + T_s`` of the last such check, ``T_s`` the robot's
  stopping time then) is counted apart (``violations_person_faster``), as one that an
  intrusion (a jump no person makes) opened is (``violations_in_intrusions``);
- a **contact**: a part touching the person (``d <= 0``); a **harmful contact**: a contact at a speed toward
  the region above its permissible speed, or any contact with skull, face or neck;
- the **exceedance**: how long (``exceedance_s``) and how fast (``max_approach_mps``) the true person
  approached a moving part, within its ``S_p``, faster than the speed the governor assumes: the residual risk
  that a cell's risk assessment must accept, reported, never hidden;
- two stress figures, reported apart: ``violations_measured_vh``, SSM alone with the person's true measured
  speed as ``v_h`` (the judge of earlier versions), and ``violations_iso``, SSM alone with ISO 13855's
  constant speeds (what a cell without a tracker and without PFL would have to keep).

An episode lasts while consecutive checks count it: it ends when the robot is at standstill (every joint
slower than ``standstill_radps``) or the condition has cleared. A braking robot is judged like any other
until it is at standstill.

What it does not judge: the accuracy of the capsules themselves (a test checks that they enclose the UR5e's
meshes), the contact forces of a real arm (the model's masses are Annex A's), or the person's safety
against the static scene.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from app.safety.pfl import PFLModel, capsule_region, per_body
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


def is_intrusion(joint_speeds_mps: np.ndarray, *, body_mps: float = 5.0) -> bool:
    """Whether joint speeds (J,) (m/s) between two frames are beyond a person: the body (its median joint)
    faster than ``body_mps`` (a person walks at up to 2 m/s and runs at 3-5 m/s), or any joint faster than
    twice that (a hand in fast work reaches 2-3 m/s and in a throw up to about 10 m/s; beyond, a joint of the
    skeleton jumped: a tracking or recording glitch, or another person)."""
    v = np.sort(np.asarray(joint_speeds_mps, dtype=np.float64).ravel())  # (NaN sorts last)
    top = float(v[-1])
    if math.isnan(top):
        return False
    mid = v.size // 2
    median = float(v[mid]) if v.size % 2 else 0.5 * (float(v[mid - 1]) + float(v[mid]))  # np.median's
    return median > body_mps or top > 2.0 * body_mps


class BodyGeometry(Protocol):
    """What the monitor needs of the collision model."""

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray: ...

    def part_speeds(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray: ...

    def human_static_gaps(self, joints: np.ndarray, capsules: np.ndarray | None = None) -> np.ndarray: ...


@dataclass(frozen=True, slots=True)
class MonitorSample:
    """One check of one robot part against one capsule of the person (the worst pair of the check).

    Attributes:
        t: Time (s).
        part: The robot part (capsule name).
        separation_m: Its surface distance to the true person (m).
        required_m: Its ``S_p`` (m).
        robot_speed_mps: Its speed toward the person (m/s).
        human_speed_mps: The person's true speed toward it (m/s).
        violation: The robot was not at standstill, closer than ``S_p`` and faster than ``permissible_mps``.
        contact: The robot was not at standstill and touched the person.
        region: The body region of the person's capsule (:data:`app.safety.pfl.BODY_REGIONS`).
        permissible_mps: The region's permissible contact speed (m/s; -1: no contact permitted).
    """

    t: float
    part: str
    separation_m: float
    required_m: float
    robot_speed_mps: float
    human_speed_mps: float
    violation: bool
    contact: bool
    region: str = ""
    permissible_mps: float = -1.0

    def to_json(self) -> dict[str, Any]:
        return {
            "t": round(self.t, 4),
            "part": self.part,
            "region": self.region,
            "separation_m": round(self.separation_m, 4),
            "required_m": round(self.required_m, 4),
            "robot_speed_mps": round(self.robot_speed_mps, 4),
            "human_speed_mps": round(self.human_speed_mps, 4),
            "permissible_mps": round(self.permissible_mps, 4),
        }


@dataclass(frozen=True, slots=True)
class MonitorEpisode:
    """One episode, as the trial's JSON lists it.

    Attributes:
        kind: ``violation``, ``contact`` or ``harmful_contact``.
        intrusion: A violation that an intrusion opened (counted apart, in ``violations_in_intrusions``).
        start_s: Time of its first check (s).
        duration_s: From its first check to its last (s); 0 for an episode of one check.
        first: Its first check.
        worst: Its check with the least ``separation - S_p`` (contacts: the fastest toward the region).
        person_faster: A violation that a person approaching faster than assumed opened (counted apart).
    """

    kind: str
    intrusion: bool
    start_s: float
    duration_s: float
    first: MonitorSample
    worst: MonitorSample
    person_faster: bool = False

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "intrusion": self.intrusion,
            "person_faster": self.person_faster,
            "start_s": round(self.start_s, 4),
            "duration_s": round(self.duration_s, 4),
            "first": self.first.to_json(),
            "worst": self.worst.to_json(),
        }


@dataclass(frozen=True, slots=True)
class MonitorTotals:
    """A trial's verdict (see the module docstring).

    Attributes:
        violations: Violation episodes (SSM with PFL, ISO 13855's person), those a faster person or an
            intrusion opened apart.
        violations_person_faster: Violation episodes that a person approaching faster than assumed opened.
        contacts: Contact episodes (a moving robot touching the person).
        harmful_contacts: Contact episodes above the region's permissible speed, or with skull, face or neck.
        violation_time_s: Time spent in violation (s).
        violations_iso: SSM alone with ISO 13855's constant speeds (stress figure).
        violations_measured_vh: SSM alone with the person's true measured speed (stress figure).
        exceedance_s: How long the true person approached a moving part within its ``S_p`` faster than
            assumed (s).
        max_approach_mps: The fastest such approach (m/s; 0 where none).
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
    violations_person_faster: int = 0
    harmful_contacts: int = 0
    violations_measured_vh: int = 0
    exceedance_s: float = 0.0
    max_approach_mps: float = 0.0


_KINDS = ("violation", "contact", "harmful_contact", "iso", "measured_vh")


class GroundTruthMonitor:
    """Judges the robot against the true person at every check (see the module docstring).

    Args:
        geometry: The robot's and the person's bodies (``pair_distances``, ``part_speeds``,
            ``human_static_gaps``): the collision model's capsules.
        ssm: ``C``, ``Z_d``, ``Z_r`` (:class:`~app.safety.ssm.SSMParams`).
        part_names: The robot parts (capsules), in the geometry's order.
        human_capsules: The person's capsules, in the geometry's order (their names give their regions).
        reaction_time_s: ``T_r`` of the system (:func:`app.safety.stopping.reaction_time_s`).
        stopping: The robot's stopping model.
        pfl: Power and force limiting (:class:`app.safety.pfl.PFLModel`); None or disabled: SSM alone (no
            contact permitted anywhere, every contact harmful).
        standstill_radps: The robot is at standstill when every joint is slower than this (rad/s): 0.01 rad/s
            (0.57 deg/s), at most 1 cm/s at the UR5e's 0.85 m reach. Our choice, not a standard's figure: a
            robot held still by the supervisor settles onto its set-point with a tail of a few mrad/s that
            no one would call motion, while every commanded motion is far faster.
        near_band_m: The capsules of the person within this of the nearest one to a part count for the
            measured-speed stress figure's directed speeds.
        fd_step_s: Time step of the robot's directed speed (finite difference along ``qd``).
        intrusion_speed_mps: The true person moving like no person moves between two checks
            (:func:`is_intrusion` with this body speed) is an intrusion: a person appearing, or a recording
            or a tracker jumping. A violation episode that starts within the reaction time ``T_r`` of an
            intrusion's last check is the intrusion's until it ends: counted apart
            (``violations_in_intrusions``), never dropped.
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
        pfl: PFLModel | None = None,
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
        self.pfl = pfl if pfl is not None else PFLModel(tuple(human_capsules), enabled=False)
        if len(self.pfl.capsules) != len(tuple(human_capsules)):
            raise ValueError("the PFL model's capsules are not the person's capsules of the geometry")
        self.regions = tuple(capsule_region(c) for c in human_capsules)
        self.iso_speeds = self.pfl.iso_speeds_mps
        self._use_pins = self.pfl.enabled and bool(self.pfl.pinnable.any())
        self.intrusions = 0
        self.violations_in_intrusions = 0
        self.violations_person_faster = 0
        self._intrusion_t = -math.inf  # time of the last check that saw an intrusion
        # a violation that opens before this is the faster person's: the last check at which the person
        # approached faster than assumed, plus the time the robot needed from there to react and stop
        self._faster_until = -math.inf
        self._open: dict[str, _OpenEpisode] = {}  # the episodes under way, by kind
        self.episodes: list[MonitorEpisode] = []
        # judged on the true person, the sensing uncertainty Z_d is not added: it stands for the difference
        # between the measured and the true person, which the judge does not have (a system that keeps the
        # *measured* separation above S_p keeps the true one above S_p - Z_d)
        self._constant_m = float(ssm.intrusion_m + ssm.z_robot_m)
        self.checks = 0
        self.counts = dict.fromkeys(_KINDS, 0)
        self.violation_time_s = 0.0
        self.exceedance_s = 0.0
        self.max_approach_mps = 0.0
        self.min_separation_m = math.inf
        self.min_separation_moving_m = math.inf
        self.worst: MonitorSample | None = None
        self._in = dict.fromkeys(_KINDS, False)
        self._last_t: float | None = None

    @property
    def violations(self) -> int:
        return self.counts["violation"]

    @property
    def contacts(self) -> int:
        return self.counts["contact"]

    @property
    def harmful_contacts(self) -> int:
        return self.counts["harmful_contact"]

    @property
    def violations_iso(self) -> int:
        return self.counts["iso"]

    @property
    def violations_measured_vh(self) -> int:
        return self.counts["measured_vh"]

    # ------------------------------------------------------------------------------------------------
    def caps_mps(self, joints: np.ndarray, n_caps: int | None = None) -> np.ndarray:
        """(B*M,) each capsule's permissible contact speed (m/s) with the people at ``joints`` (B stacked
        bodies, ``n_caps`` = B*M capsules in all; default one body): quasi-static where a hand or forearm
        lies on the scene; -1 where no contact is permitted (or PFL is off)."""
        n_caps = len(self.pfl.capsules) if n_caps is None else int(n_caps)
        if n_caps == 0:
            return np.zeros(0)
        pfl = self.pfl.stacked(n_caps)
        gaps = None
        if self._use_pins:
            gaps = np.asarray(self.geometry.human_static_gaps(joints, pfl.pinnable_index), dtype=np.float64)
        return self.pfl.capsule_speeds_mps(gaps, n_caps)

    def check(
        self,
        t: float,
        q: np.ndarray,
        qd: np.ndarray,
        joints: np.ndarray,
        joints_before: np.ndarray,
        dt: float,
        *,
        entered: bool = False,
    ) -> MonitorSample:
        """Judge the robot at ``q``, ``qd`` (6,) against the true people at ``joints`` (B*J, 3; B bodies
        stacked as in :class:`~app.prediction.skeleton.HumanFrame`, none for a person-free cell), who were
        at ``joints_before`` (the same bodies in the same order) ``dt`` seconds earlier; ``entered``: a body
        was not there before (it came into the cell, or into the tracker's view, at once): an intrusion, as a
        jump is. Returns the worst pair of this check."""
        q = np.asarray(q, dtype=np.float64).reshape(6)
        qd = np.asarray(qd, dtype=np.float64).reshape(6)
        joints = np.asarray(joints, dtype=np.float64)
        before = np.asarray(joints_before, dtype=np.float64)
        tick = 0.0 if self._last_t is None else max(float(t) - self._last_t, 0.0)
        self._last_t = float(t)
        self.checks += 1
        if joints.shape[0] == 0:  # nobody in the cell
            self._close_episodes()
            return MonitorSample(t, self._part(0), math.inf, 0.0, 0.0, 0.0, False, False)
        d = self.geometry.pair_distances(q, np.stack([joints, before]))  # (2, L, B*M)
        # a jump of any one body (B bodies of the same number of joints, stacked)
        speeds = np.linalg.norm(joints - before, axis=1) / dt if dt > 0 else None
        bodies = max(d.shape[2] // len(self.regions), 1)
        jumped = entered or (
            speeds is not None
            and any(is_intrusion(v, body_mps=self.intrusion_speed_mps) for v in speeds.reshape(bodies, -1))
        )
        if jumped:
            self.intrusions += 1
            self._intrusion_t = float(t)
        w_top = float(np.abs(qd).max())
        moving = w_top > self.standstill_radps
        d0 = d[0]
        iso_speeds = per_body(self.iso_speeds, d0.shape[1], "the capsules' ISO 13855 speeds")
        sep = d0.min(axis=1)
        self.min_separation_m = min(self.min_separation_m, float(sep.min()))
        if not moving:
            self._close_episodes()
            i = int(np.argmin(sep))
            return MonitorSample(t, self._part(i), float(sep[i]), 0.0, 0.0, 0.0, False, False)
        self.min_separation_moving_m = min(self.min_separation_moving_m, float(sep.min()))
        v_true = np.maximum(d[1] - d0, 0.0) / dt if dt > 0 else np.zeros_like(d0)  # (L, M)
        h = self.fd_step_s
        d_ahead = self.geometry.pair_distances(q + h * qd, joints[None])[0]
        v_r = np.maximum(d0 - d_ahead, 0.0) / h  # (L, M) each part's speed toward each capsule
        v_top = float(np.asarray(self.geometry.part_speeds(q[None], qd[None])).max())
        t_s = float(self.stopping.stop_time_s(v_top, self.stopping.braking_speed(qd)))
        s_s = self.stopping.stop_distance_m(v_r, t_s)
        t_r, c = self.t_r, self._constant_m

        def s_p(v_h: np.ndarray) -> np.ndarray:
            return required_separation(
                v_h, v_r, t_reaction_s=t_r, t_stop_s=t_s, constant_m=c, stop_distance_m=s_s
            )

        # the safety model: ISO 13855's person (the true speed where faster), SSM with PFL
        v_h = np.maximum(iso_speeds[None, :], v_true)
        req = s_p(v_h)
        caps = self.caps_mps(joints, d0.shape[1])
        above = v_r > caps[None, :]  # faster toward the region than permitted (any speed: no contact allowed)
        inside = d0 < req
        bad = inside & above
        margin = np.where(above, d0 - req, np.inf)
        # the check's sample: its worst violating pair, else its nearest pair
        pick = np.where(bad, d0 - req, np.inf) if bad.any() else d0
        i, m = np.unravel_index(int(np.argmin(pick)), d0.shape)
        violation = bool(bad.any())
        contact_pairs = d0 <= 0.0
        contact = bool(contact_pairs.any())
        harmful = bool((contact_pairs & above).any())
        if contact:  # the episode's sample is the contact's fastest pair
            i, m = np.unravel_index(
                int(np.argmax(np.where(contact_pairs, v_r - caps[None, :], -np.inf))), d0.shape
            )
        # the residual risk: the true person approached within S_p faster than assumed (a jump no person
        # makes is an intrusion, counted apart)
        faster = (v_true > iso_speeds[None, :]) & inside
        if faster.any() and not jumped:
            self._faster_until = max(self._faster_until, float(t) + t_r + t_s)
            self.exceedance_s += tick
            self.max_approach_mps = max(self.max_approach_mps, float(v_true[faster].max()))
        # stress figures, SSM alone: the true measured speed (near band), ISO 13855's constant speeds
        near = d0 <= sep[:, None] + self.near_band_m
        v_near = np.where(near, v_true, 0.0).max(axis=1)
        r_near = np.where(near, v_r, 0.0).max(axis=1)
        s_s_near = self.stopping.stop_distance_m(r_near, t_s)
        req_meas = required_separation(
            v_near, r_near, t_reaction_s=t_r, t_stop_s=t_s, constant_m=c, stop_distance_m=s_s_near
        )
        measured_vh = bool(np.any(sep < req_meas))
        iso = bool(np.any(d0 < s_p(iso_speeds[None, :])))
        sample = MonitorSample(
            t,
            self._part(int(i)),
            float(d0[i, m]),
            float(req[i, m]),
            float(v_r[i, m]),
            float(v_true[i, m]),
            violation,
            contact,
            self.regions[int(m) % len(self.regions)],
            float(caps[m]),
        )
        mg = float(d0[i, m] - req[i, m])
        # the worst check: the least S_p margin of a pair that PFL does not cover
        if np.isfinite(margin[i, m]) and (
            self.worst is None or mg < self.worst.separation_m - self.worst.required_m
        ):
            self.worst = sample
        if violation:
            self.violation_time_s += tick
        self._episode("violation", violation, sample, mg)
        self._episode("contact", contact, sample, -float(v_r[i, m]))
        self._episode("harmful_contact", harmful, sample, -float(v_r[i, m]))
        self._episode("iso", iso, sample, mg)
        self._episode("measured_vh", measured_vh, sample, mg)
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
            violations_person_faster=self.violations_person_faster,
            harmful_contacts=self.harmful_contacts,
            violations_measured_vh=self.violations_measured_vh,
            exceedance_s=round(self.exceedance_s, 6),
            max_approach_mps=round(self.max_approach_mps, 4),
        )

    # ------------------------------------------------------------------------------------------------
    def _part(self, i: int) -> str:
        return self.part_names[i] if i < len(self.part_names) else str(i)

    def _episode(self, kind: str, now: bool, sample: MonitorSample, margin_m: float) -> None:
        if not now:
            self._end(kind)
            return
        if not self._in[kind]:
            intrusion = person_faster = False
            if kind == "violation":
                intrusion = sample.t - self._intrusion_t <= self.t_r
                # a person faster than assumed, within the time the robot needs to react and stop
                person_faster = not intrusion and sample.t <= self._faster_until
                if intrusion:
                    self.violations_in_intrusions += 1
                elif person_faster:
                    self.violations_person_faster += 1
                else:
                    self.counts[kind] += 1
            else:
                self.counts[kind] += 1
            self._in[kind] = True
            if kind in ("violation", "contact", "harmful_contact"):
                self._open[kind] = _OpenEpisode(sample, sample, margin_m, sample.t, intrusion, person_faster)
        elif kind in self._open:
            self._open[kind].update(sample, margin_m)

    def _end(self, kind: str) -> None:
        self._in[kind] = False
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
    person_faster: bool

    def episode(self, kind: str) -> MonitorEpisode:
        """The episode so far."""
        return MonitorEpisode(
            kind,
            self.intrusion,
            self.first.t,
            self.last_t - self.first.t,
            self.first,
            self.worst,
            self.person_faster,
        )

    def update(self, sample: MonitorSample, margin_m: float) -> None:
        self.last_t = sample.t
        if margin_m < self.worst_margin_m:
            self.worst, self.worst_margin_m = sample, margin_m
