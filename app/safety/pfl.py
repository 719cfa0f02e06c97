"""ISO/TS 15066 power and force limiting (PFL) inside the protective separation, and ISO 13855's person.

The safety model of the cell is speed and separation monitoring combined with power and force limiting
(Lucci, Lacevic, Zanchettin, Rocco, "Combining speed and separation monitoring with power and force limiting
for safe collaborative robotics applications", IEEE RA-L 5(4), 2020): a robot part may be closer to a body
region than SSM's ``S_p`` as long as its speed toward that region stays within the region's permissible
contact speed, so that a contact, should the person move into it, stays within the limits of ISO/TS 15066
Annex A. Skull, face and neck admit no contact: there SSM alone applies.

Annex A's energy balance for a transient contact: ``E = F^2 / (2 k) = mu v^2 / 2`` gives

    v_max = F / sqrt(mu k),   mu = (1 / m_H + 1 / m_R)^-1,   m_R = M / 2 + m_L

with ``F`` the permissible transient force (twice the quasi-static force of Table A.2), ``k`` the region's
effective spring constant and ``m_H`` its effective mass (Table A.3), ``M`` the moving mass of the robot and
``m_L`` its payload (gripper and part). Where the region could be pinned against the static scene (a hand
lying on the table under the tool) the contact would be quasi-static (clamping): the quasi-static force of
Table A.2 without the factor 2.

The person's approach speed ``v_h`` is ISO 13855's: 2.0 m/s for a hand or an arm reaching in, 1.6 m/s for
the body walking (ISO 13855:2010, 6.2.3 and 6.3), raised where the tracker measures a faster approach, never
lowered.

Every figure's source is on the table below (:data:`BODY_REGIONS`); the docs' safety-model page repeats
them with what the combined mode asks of a cell's risk assessment. All lengths in metres, speeds in m/s,
masses in kg, forces in N, spring constants in N/m.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from app.safety._kernels import PFLLevels, pfl_extra

__all__ = [
    "BODY_REGIONS",
    "ISO13855_ARM_MPS",
    "ISO13855_BODY_MPS",
    "UR5E_MOVING_MASS_KG",
    "BodyRegion",
    "PFLModel",
    "capsule_region",
    "effective_mass_kg",
    "permissible_speed_mps",
    "pfl_extra",
    "pfl_levels",
]

#: ISO 13855:2010's approach speed of a hand or an arm reaching toward a hazard (m/s).
ISO13855_ARM_MPS = 2.0
#: ISO 13855:2010's approach speed of the body walking toward a hazard (m/s).
ISO13855_BODY_MPS = 1.6

#: The UR5e's moving mass ``M`` (kg): the links that move (shoulder 3.761, upper arm 8.058, forearm 2.846,
#: wrist 1 1.370, wrist 2 1.300, wrist 3 0.365), from Universal Robots' UR5e description
#: (ros-industrial ``universal_robot``, ``ur_e_description/urdf/ur5e.urdf.xacro``); the base (4.0) is fixed.
UR5E_MOVING_MASS_KG = 3.761 + 8.058 + 2.846 + 1.370 + 1.300 + 0.365


@dataclass(frozen=True, slots=True)
class BodyRegion:
    """One body region of ISO/TS 15066 Annex A.

    Attributes:
        name: The region (Table A.2's names).
        force_n: Permissible quasi-static force ``F`` (N), Table A.2.
        spring_n_per_m: Effective spring constant ``k`` (N/m), Table A.3.
        mass_kg: Effective mass ``m_H`` of the region (kg), Table A.3.
        contact_allowed: False for skull, face and neck: no contact permitted (A.3.2), SSM alone.
        iso13855_mps: ISO 13855's approach speed of the region (m/s): a hand or arm 2.0, the body 1.6.
    """

    name: str
    force_n: float
    spring_n_per_m: float
    mass_kg: float
    contact_allowed: bool
    iso13855_mps: float


def _r(
    name: str, f: float, k_n_per_mm: float, m: float, *, allowed: bool = True, arm: bool = False
) -> BodyRegion:
    return BodyRegion(
        name, f, k_n_per_mm * 1000.0, m, allowed, ISO13855_ARM_MPS if arm else ISO13855_BODY_MPS
    )


#: The body regions of ISO/TS 15066:2016 Annex A: quasi-static force (Table A.2), effective spring constant
#: and effective mass (Table A.3). Checked value by value against the tables as a UR e-Series ROS 2 safety
#: controller transcribes them (``SafetyController.compute_PFL_vel_lim``, Tables A.2 and A.3 in its header);
#: the factor 2 for transient contact is Annex A's (A.3.2).
BODY_REGIONS: dict[str, BodyRegion] = {
    r.name: r
    for r in (
        _r("skull_forehead", 130, 150, 4.4, allowed=False),
        _r("face", 65, 75, 4.4, allowed=False),
        _r("neck", 150, 50, 1.2, allowed=False),
        _r("back_shoulders", 210, 35, 40),
        _r("chest", 140, 25, 40),
        _r("abdomen", 110, 10, 40),
        _r("pelvis", 180, 25, 40),
        _r("upper_arm_elbow", 150, 30, 3, arm=True),
        _r("lower_arm_wrist", 160, 40, 2, arm=True),
        _r("hand_fingers", 140, 75, 0.6, arm=True),
        _r("thigh_knee", 220, 50, 75),
        _r("lower_leg", 130, 60, 75),
    )
}

#: The region of each bone group of the person's capsules (:data:`app.planning.collision.HUMAN_CAPSULES`,
#: named ``parent-child`` by the joints they join; the head is a sphere that holds the skull and the face,
#: judged by the stricter of the two, both without contact).
_CHILD_REGION = {
    "spine": "abdomen",
    "chest": "chest",
    "neck": "neck",
    "head": "neck",
    "shoulder": "back_shoulders",
    "elbow": "upper_arm_elbow",
    "wrist": "lower_arm_wrist",
    "hand": "hand_fingers",
    "hip": "pelvis",
    "knee": "thigh_knee",
    "ankle": "lower_leg",
}

#: Regions that can lie on the table and be pinned there by a part coming down (quasi-static contact).
PINNABLE = ("hand_fingers", "lower_arm_wrist")


def capsule_region(capsule: str) -> str:
    """The body region (:data:`BODY_REGIONS`) of one of the person's capsules, by its name (``"head"``, or a
    bone ``"parent-child"``)."""
    if capsule == "head":
        return "skull_forehead"
    child = capsule.split("-", 1)[-1]
    key = child[2:] if child[:2] in ("l_", "r_") else child
    if key not in _CHILD_REGION:
        raise ValueError(f"no body region for the person's capsule {capsule!r}")
    return _CHILD_REGION[key]


def effective_mass_kg(region_mass_kg: float, robot_mass_kg: float, payload_kg: float) -> float:
    """Annex A's reduced mass ``mu = (1/m_H + 1/m_R)^-1`` with ``m_R = M / 2 + m_L`` (kg)."""
    m_r = 0.5 * robot_mass_kg + payload_kg
    return 1.0 / (1.0 / region_mass_kg + 1.0 / m_r)


def permissible_speed_mps(
    region: BodyRegion, *, robot_mass_kg: float, payload_kg: float, quasi_static: bool = False
) -> float:
    """The largest speed (m/s) of a robot part toward ``region`` at which a contact stays within Annex A:
    ``F / sqrt(mu k)``, ``F`` twice Table A.2's force for a transient contact, Table A.2's force where the
    region could be pinned (``quasi_static``). 0 where no contact is permitted (skull, face, neck)."""
    if not region.contact_allowed:
        return 0.0
    mu = effective_mass_kg(region.mass_kg, robot_mass_kg, payload_kg)
    force = region.force_n * (1.0 if quasi_static else 2.0)
    return force / math.sqrt(mu * region.spring_n_per_m)


@dataclass(frozen=True)
class PFLModel:
    """The permissible contact speeds and ISO 13855 approach speeds of the person's capsules.

    Attributes:
        capsules: The person's capsules (names, in the collision model's order).
        robot_mass_kg: ``M``, the robot's moving mass (kg).
        payload_kg: ``m_L``, the gripper and the part it carries (kg).
        pin_gap_m: A hand or forearm capsule whose surface is within this of a static surface below the
            robot could be pinned there (quasi-static contact). Our choice (a hand resting on the table or
            a few centimetres above it), not a standard's figure.
        enabled: False: SSM alone (no contact permitted anywhere), the paper's setting.
    """

    capsules: tuple[str, ...]
    robot_mass_kg: float = UR5E_MOVING_MASS_KG
    payload_kg: float = 1.0
    pin_gap_m: float = 0.05
    enabled: bool = True

    def __post_init__(self) -> None:
        for name in ("robot_mass_kg", "payload_kg", "pin_gap_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"PFLModel.{name} must be a finite number >= 0, got {v!r}")
        if self.robot_mass_kg <= 0:
            raise ValueError("PFLModel.robot_mass_kg must be > 0")

    @classmethod
    def for_capsules(cls, capsules: Sequence[str], **kwargs: object) -> PFLModel:
        return cls(tuple(capsules), **kwargs)  # type: ignore[arg-type]

    def stacked(self, n_caps: int) -> PFLModel:
        """This model for ``n_caps`` capsules of B stacked bodies, each with :attr:`capsules` (itself for
        one body; :class:`~app.prediction.skeleton.HumanFrame` stacks the bodies of a capture)."""
        m = len(self.capsules)
        if n_caps == m:
            return self
        if m == 0 or n_caps % m:
            raise ValueError(f"PFLModel: {n_caps} capsules are no whole number of bodies of {m} capsules")
        return _stacked(self, n_caps // m)

    @cached_property
    def regions(self) -> tuple[str, ...]:
        """Each capsule's body region."""
        return tuple(capsule_region(c) for c in self.capsules)

    @cached_property
    def iso_speeds_mps(self) -> np.ndarray:
        """(M,) ISO 13855's approach speed of each capsule (m/s)."""
        return np.array([BODY_REGIONS[r].iso13855_mps for r in self.regions])

    def _speeds(self, quasi_static: bool) -> np.ndarray:
        if not self.enabled:
            return np.full(len(self.capsules), -1.0)
        out = np.array(
            [
                permissible_speed_mps(
                    BODY_REGIONS[r],
                    robot_mass_kg=self.robot_mass_kg,
                    payload_kg=self.payload_kg,
                    quasi_static=quasi_static,
                )
                for r in self.regions
            ]
        )
        # no contact permitted: -1, below any speed (a part at rest included)
        return np.where(out > 0.0, out, -1.0)

    @cached_property
    def transient_mps(self) -> np.ndarray:
        """(M,) each capsule's permissible transient-contact speed (m/s); -1 where no contact is permitted."""
        return self._speeds(False)

    @cached_property
    def quasi_static_mps(self) -> np.ndarray:
        """(M,) each capsule's permissible quasi-static speed (m/s); -1 where no contact is permitted."""
        return self._speeds(True)

    @cached_property
    def pinnable(self) -> np.ndarray:
        """(M,) bool: the capsules that can be pinned against the scene (hands, forearms)."""
        return np.array([r in PINNABLE for r in self.regions])

    @cached_property
    def pinnable_index(self) -> np.ndarray:
        """The indices of :attr:`pinnable`'s capsules."""
        return np.flatnonzero(self.pinnable)

    def levels(
        self,
        d_pairs: np.ndarray,
        v_pairs: np.ndarray | None,
        static_gaps_m: np.ndarray | None,
        *,
        band_m: float,
    ) -> tuple[PFLLevels, np.ndarray]:
        """The governor's :class:`~app.safety._kernels.PFLLevels` for robot parts at the distances
        ``d_pairs`` (L, M) from the person's capsules, who approach each at ``v_pairs`` (L, M) (None: each
        level at the part's own worst case), the capsules' gaps to the scene ``static_gaps_m`` (M,) (None:
        none pinned): each capsule's permissible speed, quasi-static where pinned (:func:`pfl_levels`). With
        PFL off: one level, every capsule (its approach speed still by capsule). And the capsules' speeds
        (M,) behind them."""
        caps = self.capsule_speeds_mps(static_gaps_m, np.shape(d_pairs)[1])
        return PFLLevels(*pfl_levels(d_pairs, caps, v_pairs, band_m=band_m)), caps

    def capsule_speeds_mps(self, static_gaps_m: np.ndarray | None, n_caps: int) -> np.ndarray:
        """(M,) each of the ``n_caps`` capsules' permissible speed (m/s) as :meth:`levels` takes it:
        quasi-static where the capsule lies within :attr:`pin_gap_m` of the scene (``static_gaps_m`` (M,);
        None: none pinned), -1 everywhere with PFL off."""
        if not self.enabled:
            return np.full(n_caps, -1.0)
        model = self.stacked(n_caps)
        pinned = None
        if static_gaps_m is not None:
            pinned = pinned_capsules(static_gaps_m, model.pinnable, pin_gap_m=self.pin_gap_m)
        return model.caps_mps(pinned)

    def caps_mps(self, pinned: np.ndarray | None = None) -> np.ndarray:
        """(M,) each capsule's permissible speed (m/s): quasi-static where ``pinned`` (M,) is True."""
        if pinned is None:
            return self.transient_mps
        return np.where(np.asarray(pinned, dtype=bool), self.quasi_static_mps, self.transient_mps)


def per_body(per_capsule: Sequence[float] | np.ndarray, n_caps: int, name: str) -> np.ndarray:
    """(B*M,) a value per capsule of one body (M,) repeated for each of B stacked bodies, ``n_caps`` = B*M
    capsules in all (ValueError where ``n_caps`` is no whole number of bodies)."""
    one = np.asarray(per_capsule, dtype=np.float64)
    m = one.shape[0]
    if m == 0 or n_caps % m:
        raise ValueError(f"{name} has {m} capsules per body, which {n_caps} capsules are no multiple of")
    return np.tile(one, n_caps // m)


@functools.lru_cache(maxsize=16)
def _stacked(model: PFLModel, bodies: int) -> PFLModel:
    return dataclasses.replace(model, capsules=model.capsules * bodies)


def pinned_capsules(capsule_gaps_m: np.ndarray, pinnable: np.ndarray, *, pin_gap_m: float) -> np.ndarray:
    """(M,) bool: the pinnable capsules whose surface gap to the static scene (M,) (m, from the collision
    model) is within ``pin_gap_m``."""
    return np.asarray(pinnable, dtype=bool) & (np.asarray(capsule_gaps_m, dtype=np.float64) <= pin_gap_m)


def pfl_levels(
    d_pairs: np.ndarray,
    caps_mps: np.ndarray,
    v_pairs: np.ndarray | None = None,
    *,
    band_m: float = 0.25,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The separation that SSM must keep per robot part as a function of its speed, from the surface
    distances ``d_pairs`` (L, M) of the robot's parts to the person's capsules and their permissible speeds
    ``caps_mps`` (M,) (-1: no contact permitted).

    Returns ``(levels, extra, v_h)``: ``levels`` (K,) the distinct permissible speeds, ascending, the first
    -1 (the capsules that admit no contact; there is always that level); ``extra`` (L, K) >= 0: a part
    moving toward the person at ``v`` must keep ``S_p`` from the capsules whose permissible speed is below
    ``v``, that is from ``min_m d[l, m] + extra[l, k]`` with ``k`` the last level below ``v`` (inf where no
    capsule lies at or below that level); ``v_h`` (L, K): the approach speed of those capsules (of
    ``v_pairs`` (L, M), the person's speed toward each part per capsule, over the capsules within ``band_m``
    of the level's nearest one; inf without ``v_pairs``). A part at or below every capsule's speed keeps
    ``S_p`` from the no-contact ones alone; with PFL off (every cap -1) ``extra`` is 0 and ``S_p`` holds
    from all.
    """
    d = np.ascontiguousarray(d_pairs, dtype=np.float64)
    caps = np.ascontiguousarray(caps_mps, dtype=np.float64)
    levels = np.unique(np.append(caps, -1.0))
    extra = np.empty((d.shape[0], levels.shape[0]))
    v_h = np.empty((d.shape[0], levels.shape[0]))
    v = np.zeros_like(d) if v_pairs is None else np.ascontiguousarray(v_pairs, dtype=np.float64)
    pfl_extra(d, v, caps, levels, float(band_m), extra, v_h)  # compiled; the tests hold its NumPy form
    if v_pairs is None:
        v_h[:] = np.inf
    return levels, extra, v_h
