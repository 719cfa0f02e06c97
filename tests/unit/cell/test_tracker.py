"""The tracker model delays, noises and drops the true frames as set, deterministically."""

from __future__ import annotations

import numpy as np
import pytest

from app.cell.tracker import TrackedSource, TrackerModel
from app.prediction.skeleton import NUM_JOINTS, HumanFrame


class _Linear:
    """A true person whose every joint sits at x = t (m): a frame's pose tells its time."""

    def __init__(self) -> None:
        self.placed: list[tuple[str, float]] = []

    def frame_at(self, t: float) -> HumanFrame | None:
        if t < 0:
            return None
        joints = np.zeros((NUM_JOINTS, 3))
        joints[:, 0] = t
        return HumanFrame(t=t, joints=joints)

    def notify_block_placed(self, station: str, t: float) -> None:
        self.placed.append((station, t))


def test_frames_arrive_latency_late_stamped_with_their_capture_time() -> None:
    model = TrackerModel(latency_s=0.06, noise_m=0.0, drop_p=0.0, burst_p=0.0)
    src = TrackedSource(_Linear(), model)
    assert src.frame_at(0.05) is None  # frame 0 is captured at 0 and delivered at 0.06
    for t in np.arange(0.06, 3.0, 0.008):
        f = src.frame_at(float(t))
        k = np.floor((t - 0.06) * 30.0 + 1e-9)
        assert f is not None
        assert f.t == pytest.approx(k / 30.0)
        assert f.joints[:, 0] == pytest.approx(np.full(NUM_JOINTS, k / 30.0))  # the truth at capture
        assert t - f.t >= 0.06 - 1e-9 and t - f.t < 0.06 + 1 / 30.0


def test_noise_has_the_set_standard_deviation_and_is_the_same_however_asked() -> None:
    model = TrackerModel(latency_s=0.0, noise_m=0.01, drop_p=0.0, burst_p=0.0)
    src = TrackedSource(_Linear(), model, seed=3)
    times = np.arange(0, 2000) / 30.0 + 1e-6
    err = np.stack([src.frame_at(float(t)).joints[:, 0] - np.floor(t * 30 + 1e-9) / 30 for t in times])
    assert err.std() == pytest.approx(0.01, rel=0.05)
    assert abs(err.mean()) < 0.001
    again = TrackedSource(_Linear(), model, seed=3)
    for t in times[::-97][:20]:  # backwards, sparse
        assert np.array_equal(again.frame_at(float(t)).joints, src.frame_at(float(t)).joints)
    other = TrackedSource(_Linear(), model, seed=4)
    assert not np.array_equal(other.frame_at(5.0).joints, src.frame_at(5.0).joints)


def test_single_drops_happen_at_the_set_rate_and_the_last_frame_is_held() -> None:
    model = TrackerModel(latency_s=0.0, noise_m=0.0, drop_p=0.2, burst_p=0.0)
    src = TrackedSource(_Linear(), model, seed=1)
    n = 20000
    lost = np.array([src.dropped(k) for k in range(n)])
    assert lost.mean() == pytest.approx(0.2, abs=0.015)
    k = int(np.flatnonzero(lost[1:])[0]) + 1  # a lost frame after frame 0
    held = src.frame_at(k / 30.0 + 1e-6)
    assert held is not None and held.t < k / 30.0 - 1e-9  # still the frame before


def test_bursts_last_at_most_the_set_time_and_cover_the_expected_share() -> None:
    model = TrackerModel(latency_s=0.0, noise_m=0.0, drop_p=0.0, burst_p=0.01, max_burst_s=0.3)
    src = TrackedSource(_Linear(), model, seed=2)
    n = 60000
    lost = np.array([src.dropped(k) for k in range(n)])
    L = 9  # 0.3 s at 30 Hz: lengths uniform in 1..9 frames
    # a frame is lost when a burst started d frames before it lasts more than d frames
    expected = 1.0 - np.prod([1.0 - 0.01 * (L - d) / L for d in range(L)])
    assert lost.mean() == pytest.approx(expected, rel=0.1)
    assert _longest_run(lost) >= 5  # bursts are longer than single frames
    # rare bursts do not overlap: each lasts at most max_burst_s
    rare = TrackedSource(_Linear(), TrackerModel(drop_p=0.0, burst_p=0.002, max_burst_s=0.3), seed=2)
    lost = np.array([rare.dropped(k) for k in range(n)])
    assert lost.any() and _longest_run(lost) <= L


def _longest_run(lost: np.ndarray) -> int:
    best = run = 0
    for x in lost:
        run = run + 1 if x else 0
        best = max(best, run)
    return best


def test_the_tracker_passes_placements_on_to_the_truth_and_checks_its_settings() -> None:
    truth = _Linear()
    TrackedSource(truth).notify_block_placed("A", 1.5)
    assert truth.placed == [("A", 1.5)]
    with pytest.raises(ValueError, match="latency_s"):
        TrackerModel(latency_s=-0.1)
    with pytest.raises(ValueError, match="noise_m"):
        TrackerModel(noise_m=float("nan"))
    ideal = TrackedSource(_Linear(), TrackerModel.ideal())
    assert ideal.frame_at(1.0).joints[0, 0] == pytest.approx(1.0)
