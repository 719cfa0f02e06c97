"""Frame validation: every bad-input case is rejected with its reason and counted; the stale watchdog."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from app.cell.clock import SimClock
from app.cell.validation import (
    REJECT_REASONS,
    CellVolume,
    FrameRejected,
    FrameValidator,
    StaleWatchdog,
    ValidatedSource,
)
from app.config import load_workcell
from app.prediction.skeleton import NUM_JOINTS, HumanFrame

CELL = load_workcell()


def _pose(offset: float = 0.0) -> np.ndarray:
    """A plausible standing pose at the operator's place (world frame)."""
    j = np.zeros((NUM_JOINTS, 3))
    j[:, 0] = 1.38 + offset
    j[:, 2] = np.linspace(-0.7, 0.9, NUM_JOINTS)
    return j


@pytest.fixture
def validator() -> FrameValidator:
    return FrameValidator.for_workcell(CELL)


def test_a_good_frame_passes(validator: FrameValidator) -> None:
    frame = validator.validate(0.0, _pose())
    assert isinstance(frame, HumanFrame)
    np.testing.assert_array_equal(frame.confidence, 1.0)
    assert validator.counters["accepted"] == 1
    assert validator.counters["rejected"] == 0


@pytest.mark.parametrize(
    ("bad", "reason"),
    [
        ("nan_joint", "non_finite"),
        ("inf_joint", "non_finite"),
        ("nan_time", "non_finite"),
        ("nan_confidence", "non_finite"),
        ("too_few_joints", "joint_count"),
        ("too_many_joints", "joint_count"),
        ("flat_joints", "joint_count"),
        ("short_confidence", "joint_count"),
        ("far_away", "out_of_range"),
        ("below_floor", "out_of_range"),
        ("too_high", "out_of_range"),
        ("confidence_above_one", "bad_confidence"),
        ("strings", "malformed"),
    ],
)
def test_each_bad_input_is_rejected_and_counted(validator: FrameValidator, bad: str, reason: str) -> None:
    j, c, t = _pose(), np.ones(NUM_JOINTS), 1.0
    if bad == "nan_joint":
        j[4, 1] = np.nan
    elif bad == "inf_joint":
        j[7, 2] = np.inf
    elif bad == "nan_time":
        t = math.nan
    elif bad == "nan_confidence":
        c[3] = np.nan
    elif bad == "too_few_joints":
        j = j[:-1]
    elif bad == "too_many_joints":
        j = np.vstack([j, j[:1]])
    elif bad == "flat_joints":
        j = j.reshape(-1)
    elif bad == "short_confidence":
        c = c[:5]
    elif bad == "far_away":
        j[8] = [8.0, 0.0, 0.2]  # a hand 8 m away
    elif bad == "below_floor":
        j[15, 2] = CELL.operator.floor_z - 1.0
    elif bad == "too_high":
        j[4, 2] = CELL.operator.floor_z + 3.5
    elif bad == "confidence_above_one":
        c[0] = 1.5
    elif bad == "strings":
        j = [["a", "b", "c"]] * NUM_JOINTS
    with pytest.raises(FrameRejected) as info:
        validator.validate(t, j, c)
    assert info.value.reason == reason
    counters = validator.counters
    assert counters[f"rejected_{reason}"] == 1
    assert counters["rejected"] == 1
    assert counters["accepted"] == 0
    # a rejected frame does not move the timestamp: the next good frame at the same time is accepted
    validator.validate(1.0, _pose())
    assert validator.counters["accepted"] == 1


def test_duplicated_and_backwards_timestamps_are_rejected(validator: FrameValidator) -> None:
    validator.validate(1.0, _pose())
    with pytest.raises(FrameRejected) as dup:
        validator.validate(1.0, _pose(0.01))
    assert dup.value.reason == "duplicate_timestamp"
    with pytest.raises(FrameRejected) as back:
        validator.validate(0.9, _pose(0.01))
    assert back.value.reason == "backwards_timestamp"
    validator.validate(1.1, _pose())
    c = validator.counters
    assert (c["accepted"], c["rejected_duplicate_timestamp"], c["rejected_backwards_timestamp"]) == (2, 1, 1)
    assert set(k.removeprefix("rejected_") for k in c if k.startswith("rejected_")) == set(REJECT_REASONS)
    validator.reset()
    assert validator.counters["accepted"] == 0 and validator.last_t is None
    validator.validate(0.5, _pose())  # after a reset, earlier times are fine again


def test_check_applies_the_same_rules_to_built_frames(validator: FrameValidator) -> None:
    validator.check(HumanFrame(0.0, _pose()))
    with pytest.raises(FrameRejected, match="out_of_range"):
        validator.check(HumanFrame(0.1, _pose(10.0)))
    with pytest.raises(FrameRejected, match="duplicate"):
        validator.check(HumanFrame(0.0, _pose()))


def test_cell_volume_covers_table_and_operator_but_not_beyond() -> None:
    vol = CellVolume.from_workcell(CELL, margin_m=0.5)
    assert vol.contains(np.array([1.38, 0.0, 0.9]))  # operator's head
    assert vol.contains(np.array([0.5, 0.3, 0.05]))  # a drop station
    assert not vol.contains(np.array([1.38, 0.0, -1.2]))  # below the floor
    assert not vol.contains(np.array([4.0, 0.0, 0.5]))
    with pytest.raises(ValueError):
        CellVolume(lo=np.zeros(3), hi=np.zeros(3))
    with pytest.raises(ValueError, match="unknown rejection reason"):
        FrameRejected("because")


def test_stale_watchdog_reports_after_100_ms_and_recovers() -> None:
    dog = StaleWatchdog()
    assert dog.timeout_s == 0.1
    assert dog.is_stale(0.0)  # nothing yet
    assert dog.age(0.0) == math.inf
    dog.feed(1.0)
    assert not dog.is_stale(1.05)
    assert not dog.is_stale(1.1)
    assert dog.is_stale(1.1001)
    assert dog.poll(1.05) == "resumed"
    assert dog.poll(1.06) is None
    assert dog.poll(1.2) == "stale"
    assert dog.poll(1.3) is None
    dog.feed(1.31)
    assert dog.poll(1.32) == "resumed"
    assert dog.stale_events == 1
    dog.feed(0.5)  # an older time does not move the watchdog back
    assert dog.age(1.32) == pytest.approx(0.01)
    with pytest.raises(ValueError):
        StaleWatchdog(0.0)


def test_stale_watchdog_expecting_frames_counts_from_the_start() -> None:
    dog = StaleWatchdog(0.35)
    dog.expect_from(10.0)  # a trial starts; the first frame comes after the tracker's latency
    assert not dog.is_stale(10.0) and not dog.is_stale(10.35)
    assert dog.poll(10.1) is None
    assert dog.is_stale(10.36) and dog.poll(10.36) == "stale"  # no frame at all: stale after the timeout
    seen = StaleWatchdog(0.35)
    seen.feed(1.0)
    seen.expect_from(10.0)  # frames came and stopped long ago: still stale
    assert seen.is_stale(10.0)


class _ListSource:
    """A source that returns prepared frames by time (some of them bad)."""

    def __init__(self, frames: list[HumanFrame]) -> None:
        self.frames = frames
        self.notified: list[tuple[str, float]] = []

    def frame_at(self, t: float) -> HumanFrame | None:
        older = [f for f in self.frames if f.t <= t]
        return older[-1] if older else None

    def notify_block_placed(self, station: str, t: float) -> None:
        self.notified.append((station, t))


def test_validated_source_passes_only_valid_new_frames() -> None:
    frames = [HumanFrame(k / 30, _pose(0.001 * k)) for k in range(6)]
    frames[2] = HumanFrame(frames[2].t, _pose(20.0))  # out of range
    src = ValidatedSource(_ListSource(frames), validator=FrameValidator.for_workcell(CELL))
    clock = SimClock()
    got = []
    for _ in range(12):  # 60 Hz polling of a 30 Hz source: each frame is asked for twice
        f = src.poll(clock.now())
        if f is not None:
            got.append(f.t)
        clock.advance(1 / 60)
    assert got == pytest.approx([0.0, 1 / 30, 3 / 30, 4 / 30, 5 / 30])
    assert src.counters["accepted"] == 5
    assert src.counters["rejected_out_of_range"] == 1
    assert src.counters["rejected_duplicate_timestamp"] == 0  # asking twice is not a duplicate
    assert src.last_rejection is not None and src.last_rejection.reason == "out_of_range"
    # while the bad frame is the newest, the last valid one stays available
    again = ValidatedSource(_ListSource(frames), validator=FrameValidator.for_workcell(CELL))
    assert again.frame_at(0.0).t == 0.0
    assert again.frame_at(1 / 30).t == pytest.approx(1 / 30)
    assert again.frame_at(2 / 30 + 0.001).t == pytest.approx(1 / 30)
    assert not src.is_stale(clock.now())
    assert src.is_stale(clock.now() + 0.2)
    src.notify_block_placed("A", 1.0)
    assert src.source.notified == [("A", 1.0)]


def test_the_frames_time_in_the_software_starts_when_the_source_hands_it_over() -> None:
    """``handed_over`` (where the engine's frame-to-decision time starts) moves when the inner source hands
    over a new frame, after the source has made it, and not when the same frame is asked for again."""
    frames = [HumanFrame(k / 30, _pose(0.001 * k)) for k in range(3)]
    inner = _ListSource(frames)
    made: list[float] = []

    def frame_at(t: float) -> HumanFrame | None:
        made.append(time.perf_counter())  # the source at work: not the software's time
        return _ListSource.frame_at(inner, t)

    inner.frame_at = frame_at  # type: ignore[method-assign]
    src = ValidatedSource(inner, validator=FrameValidator.for_workcell(CELL))
    assert src.poll(0.0) is not None
    first = src.handed_over
    assert first >= made[-1]
    assert src.poll(0.01) is None and src.handed_over == first  # the same frame again
    assert src.poll(1 / 30) is not None and src.handed_over > first and src.handed_over >= made[-1]


@pytest.mark.parametrize(
    ("t", "joints", "confidence", "reason"),
    [
        (1.0, None, [5.0] * NUM_JOINTS, "bad_confidence"),  # not clipped to 1
        (1.0, None, [-3.0] * NUM_JOINTS, "bad_confidence"),
        (1.0, None, ["0.5"] * NUM_JOINTS, "malformed"),  # a string is not a number
        (1.0, None, [True] * NUM_JOINTS, "malformed"),  # nor is a boolean
        (1.0, "strings", None, "malformed"),
        (1.0, "booleans", None, "malformed"),
        (1.0, "huge_int", None, "out_of_range"),
        (1.0, None, np.full(NUM_JOINTS, 0.1), "no_valid_joint"),  # nothing seen well enough to track
        (True, None, None, "bad_timestamp"),
        ("1.0", None, None, "bad_timestamp"),
        (1e308, None, None, "bad_timestamp"),
        (10**400, None, None, "bad_timestamp"),  # float() would raise OverflowError
        (-math.inf, None, None, "non_finite"),
    ],
)
def test_values_are_checked_as_sent_never_coerced(
    validator: FrameValidator, t: object, joints: object, confidence: object, reason: str
) -> None:
    j = _pose()
    if joints == "strings":
        j = [[str(v) for v in row] for row in j.tolist()]
    elif joints == "booleans":
        j = [[True, False, True]] * NUM_JOINTS
    elif joints == "huge_int":
        j = j.tolist()
        j[3][0] = 10**400
    with pytest.raises(FrameRejected) as info:
        validator.validate(t, j, confidence)
    assert info.value.reason == reason
    assert validator.counters[f"rejected_{reason}"] == 1 and validator.counters["rejected"] == 1
    # a list of plain numbers and a confidence on the threshold are fine
    frame = validator.validate(2, _pose().tolist(), [0.3] + [0.0] * (NUM_JOINTS - 1))
    assert frame.t == 2.0 and validator.counters["accepted"] == 1


def test_reset_counters_keeps_the_last_timestamp(validator: FrameValidator) -> None:
    validator.validate(1.0, _pose())
    with pytest.raises(FrameRejected):
        validator.validate(1.0, _pose())
    validator.reset_counters()
    assert validator.counters["rejected"] == 0 and validator.counters["accepted"] == 0
    with pytest.raises(FrameRejected, match="backwards"):  # a new trial on the same stream: still ordered
        validator.validate(0.5, _pose())
