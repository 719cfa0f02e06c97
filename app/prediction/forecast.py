"""The forecast of a person's motion that the planner checks plans against, and the protocol of what makes
one (:class:`Predictor`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from app.prediction.skeleton import NUM_JOINTS, HumanFrame


@dataclass(frozen=True, slots=True)
class HumanForecast:
    """The predicted skeletons of the people in the cell over a horizon, with a margin that grows with the
    horizon.

    Index 0 is the latest observed pose at ``t0``; the following entries are predictions. The bodies are
    stacked as in :class:`~app.prediction.skeleton.HumanFrame` (body ``k``: joints ``k*J .. (k+1)*J - 1``);
    one body by default, none for a person-free cell. The margins are shared by every body (the largest of
    theirs).

    Attributes:
        t0: Time of the latest observed frame (s, runtime clock).
        times: Strictly increasing sample times (H,) in seconds; ``times[0] == t0``.
        joints: Poses (H, J, 3) in metres, world frame.
        margins: Extra clearance (H,) in metres that covers the forecast's error at each sample
            (e.g. a per-horizon error quantile measured on validation data); ``margins[0]`` covers tracking.
        growth_mps: Beyond the last sample the last pose is held and the margin grows at this speed (m/s).
        max_margin_m: Upper bound of the grown margin (m).
        body_ids: The tracker's id of each body (B,).
    """

    t0: float
    times: np.ndarray
    joints: np.ndarray
    margins: np.ndarray
    growth_mps: float = 0.0
    max_margin_m: float = 1.0
    body_ids: tuple[int, ...] = (0,)

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=np.float64)
        joints = np.asarray(self.joints, dtype=np.float64)
        margins = np.asarray(self.margins, dtype=np.float64)
        H = times.shape[0]
        ids = tuple(int(i) for i in self.body_ids)
        n = len(ids) * NUM_JOINTS
        if times.ndim != 1 or H < 1:
            raise ValueError(f"HumanForecast.times must have shape (H,), H >= 1, got {times.shape}")
        if len(set(ids)) != len(ids) or any(i < 0 for i in ids):
            raise ValueError(f"HumanForecast.body_ids must be distinct and >= 0, got {self.body_ids}")
        if joints.shape != (H, n, 3):
            raise ValueError(
                f"HumanForecast.joints must have shape ({H}, {n}, 3) for {len(ids)} bodies, "
                f"got {joints.shape}"
            )
        if margins.shape != (H,):
            raise ValueError(f"HumanForecast.margins must have shape ({H},), got {margins.shape}")
        if H > 1 and np.any(np.diff(times) <= 0):
            raise ValueError("HumanForecast.times must be strictly increasing")
        if not (np.all(np.isfinite(joints)) and np.all(np.isfinite(margins))):
            raise ValueError("HumanForecast contains NaN or infinite values")
        for a in (times, joints, margins):
            a.setflags(write=False)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "margins", margins)
        object.__setattr__(self, "body_ids", ids)

    @classmethod
    def hold(
        cls,
        frame: HumanFrame,
        *,
        margin_m: float = 0.0,
        growth_mps: float = 0.0,
        max_margin_m: float = 1.0,
    ) -> HumanForecast:
        """The people held still at ``frame``'s poses (the reactive baseline and the emergency plan)."""
        return cls(
            t0=frame.t,
            times=np.array([frame.t]),
            joints=frame.joints[None],
            margins=np.array([margin_m]),
            growth_mps=growth_mps,
            max_margin_m=max_margin_m,
            body_ids=frame.body_ids,
        )

    @property
    def bodies(self) -> int:
        """The number of bodies (B)."""
        return len(self.body_ids)

    @property
    def horizon_end(self) -> float:
        return float(self.times[-1])

    def poses_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated poses and margins at times ``t`` (K,).

        Returns:
            ``(joints (K, J, 3), margins (K,))``. Before ``t0`` the first pose is used; beyond the
            horizon the last pose is held and the margin grows by ``growth_mps`` per second, up to
            ``max_margin_m``.
        """
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        times = self.times
        if times.shape[0] == 1:
            idx0 = np.zeros(t.shape, dtype=np.int64)
            idx1 = idx0
            w = np.zeros(t.shape)
        else:
            tc = np.clip(t, times[0], times[-1])
            idx1 = np.clip(np.searchsorted(times, tc, side="right"), 1, times.shape[0] - 1)
            idx0 = idx1 - 1
            w = (tc - times[idx0]) / (times[idx1] - times[idx0])
        joints = self.joints[idx0] * (1.0 - w)[:, None, None] + self.joints[idx1] * w[:, None, None]
        margins = self.margins[idx0] * (1.0 - w) + self.margins[idx1] * w
        beyond = np.maximum(t - times[-1], 0.0)
        margins = np.minimum(margins + self.growth_mps * beyond, max(self.max_margin_m, self.margins.max()))
        return joints, margins

    def pose_at(self, t: float) -> tuple[np.ndarray, float]:
        """Pose (J, 3) and margin (m) at time ``t``."""
        joints, margins = self.poses_at(np.array([t]))
        return joints[0], float(margins[0])


def stack_forecasts(forecasts: Sequence[HumanForecast], *, t0: float) -> HumanForecast:
    """One forecast at ``t0`` of every body in ``forecasts`` (each of one or more bodies, made at ``t0`` or a
    frame or two before), on the sample times of the newest (the longest of those): each body's poses
    interpolated there (held beyond its own horizon), the margin at each time the largest of theirs (grown
    beyond a horizon as that forecast grows it), the growth and the bound the largest. No forecast: the
    person-free cell at ``t0``."""
    if not forecasts:
        return HumanForecast(
            t0=t0, times=np.array([t0]), joints=np.zeros((1, 0, 3)), margins=np.zeros(1), body_ids=()
        )
    if len(forecasts) == 1:
        return forecasts[0]
    ref = max(forecasts, key=lambda f: (f.t0, f.horizon_end, f.times.shape[0]))
    times = ref.times
    joints, margins = [], []
    for f in forecasts:
        if f.t0 > t0:
            raise ValueError(f"stack_forecasts: a forecast from after t0 ({f.t0} > {t0})")
        same = f.times is times or (f.times.shape == times.shape and np.array_equal(f.times, times))
        j, m = (f.joints, f.margins) if same else f.poses_at(times)  # on its own samples: itself
        joints.append(j)
        margins.append(m)
    return HumanForecast(
        t0=ref.t0,
        times=times,
        joints=np.concatenate(joints, axis=1),
        margins=np.max(margins, axis=0),
        growth_mps=max(f.growth_mps for f in forecasts),
        max_margin_m=max(f.max_margin_m for f in forecasts),
        body_ids=tuple(i for f in forecasts for i in f.body_ids),
    )


def half_step_grid(
    times: np.ndarray, joints: np.ndarray, margins: np.ndarray, half_margins: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A forecast's samples ``times`` (H + 1,), ``joints`` (H + 1, J, 3) and ``margins`` (H + 1,) with a
    sample inserted halfway between each two: the pose halfway (what linear interpolation gives there
    anyway) and that sample's own margin from ``half_margins`` (H,). Returns (2H + 1,), (2H + 1, J, 3),
    (2H + 1,)."""
    times = np.asarray(times, dtype=np.float64)
    joints = np.asarray(joints, dtype=np.float64)
    margins = np.asarray(margins, dtype=np.float64)
    half_margins = np.asarray(half_margins, dtype=np.float64)
    H = times.shape[0] - 1
    if joints.shape[0] != H + 1 or margins.shape != (H + 1,) or half_margins.shape != (H,):
        raise ValueError(
            f"half_step_grid: times {times.shape}, joints {joints.shape}, margins {margins.shape} and "
            f"half_margins {half_margins.shape} do not fit (H + 1 samples, H halves)"
        )
    t = np.empty(2 * H + 1)
    t[0::2], t[1::2] = times, 0.5 * (times[:-1] + times[1:])
    j = np.empty((2 * H + 1, *joints.shape[1:]))
    j[0::2], j[1::2] = joints, 0.5 * (joints[:-1] + joints[1:])
    m = np.empty(2 * H + 1)
    m[0::2], m[1::2] = margins, half_margins
    return t, j, m


class Predictor(Protocol):
    """A motion predictor as the trial engine and the runtime use it: the network
    (:class:`~app.prediction.predictor.MotionPredictor`), the simulated operator's oracle
    (:class:`~app.cell.operator_sim.OracleForecaster`) or a stand-in.

    The predictors subclass this protocol for the defaults of what most of them do not have, so that the
    callers ask for it instead of probing.

    Attributes:
        effective_kind: What forecasts: the network's kind, what runs instead of it, or for another
            predictor its class's name.
        weights_path: The network's weights file (None, the default: no file is involved).
        fallback_reason: Why a fallback runs instead of the network that was asked for (None, the default:
            it runs what was asked).
        exact_within_horizon: The forecast is exact over its horizon (the oracle's; False, the default): the
            fetch anticipation then adds only what lies beyond it.
    """

    effective_kind: str
    weights_path: Path | None = None
    fallback_reason: str | None = None
    exact_within_horizon: bool = False

    @property
    def arbitrated(self) -> bool:
        """The forecast is arbitrated online with the baselines (False, the default)."""
        return False

    def reset(self) -> None:
        """Forget the frames seen (a new trial, or another person)."""
        ...

    def observe(self, frame: HumanFrame) -> object:
        """Take ``frame`` into the history without forecasting (the forecast of the frame before is kept; the
        default forecasts and drops it)."""
        return self.update(frame)

    @property
    def whole_frame(self) -> bool:
        """:meth:`update` takes every body of a frame at once and forecasts them stacked (False, the default:
        it forecasts one body, and a cell of several people runs one predictor per body, :meth:`spawn`)."""
        return False

    def spawn(self) -> Predictor:
        """A predictor of the same kind for another person: what is learned of the model shared, nothing of
        this person's history (the default: this predictor cannot forecast more than one person)."""
        raise NotImplementedError(f"{type(self).__name__} forecasts one person only")

    def update(self, frame: HumanFrame) -> HumanForecast:
        """Take the newest frame and return the forecast from it."""
        ...
