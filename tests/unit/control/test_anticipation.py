"""The expected fetch of a placed block in the proactive method's forecast (app.control.anticipation)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.cell.operator_sim import OperatorParams, SimulatedOperator
from app.config import load_workcell
from app.control.anticipation import FetchAnticipation, FetchAnticipationParams
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import JOINT_INDEX, HumanFrame

CELL = load_workcell()
STATIONS = {s.name: np.asarray(s.xyz, dtype=np.float64) for s in CELL.drop_stations}
FPS = 30.0
H = 30
ARM = {side: [JOINT_INDEX[f"{side}_{j}"] for j in ("elbow", "wrist", "hand")] for side in ("l", "r")}


def _frame(t: float = 0.0) -> HumanFrame:
    """A person standing at their work spot (the simulated operator's first frame), at time ``t``."""
    op = SimulatedOperator(CELL, OperatorParams(), seed=1)
    return HumanFrame(t, op.frame_at(0.0).joints)


def _forecast(frame: HumanFrame, drift: float = 0.0) -> HumanForecast:
    """A predictor's forecast from ``frame``: the pose drifting along +y at ``drift`` m/s."""
    times = frame.t + np.arange(H + 1) / FPS
    joints = frame.joints[None] + (times - frame.t)[:, None, None] * np.array([0.0, drift, 0.0])
    return HumanForecast(
        t0=frame.t, times=times, joints=joints, margins=np.linspace(0.02, 0.05, H + 1), growth_mps=0.1
    )


def _moved(frame: HumanFrame, side: str, station: np.ndarray, fraction: float, t: float) -> HumanFrame:
    """``frame`` with the ``side`` arm's hand (and wrist, elbow by half) moved ``fraction`` of the way to
    ``station``, at time ``t``."""
    j = np.array(frame.joints, copy=True)
    elbow, wrist, hand = ARM[side]
    d = fraction * (station - j[hand])
    j[hand] += d
    j[wrist] += d
    j[elbow] += 0.5 * d
    return HumanFrame(t, j)


def test_nothing_expected_leaves_the_forecast_as_it_is() -> None:
    ant = FetchAnticipation(STATIONS)
    frame = _frame()
    fc = _forecast(frame)
    assert ant.apply(frame, fc) is fc
    assert ant.expected() == []


def test_the_nearer_hand_reaches_the_station_on_a_minimum_jerk_profile() -> None:
    p = FetchAnticipationParams(hand_speed_mps=2.0)  # a fast reach: over within the horizon
    ant = FetchAnticipation(STATIONS, p)
    frame = _frame(10.0)
    fc = _forecast(frame, drift=0.05)
    ant.expect("D", t_release=9.5)  # D (+y) is on the person's right: they face -x
    out = ant.apply(frame, fc)
    station = STATIONS["D"]
    elbow, wrist, hand = ARM["r"]
    # the reach could have started at the release + the reaction time: it starts now
    t_on = max(frame.t, 9.5 + p.reaction_s)
    length = float(np.linalg.norm(station - frame.joints[hand]))
    duration = max(p.min_reach_s, 1.875 * length / p.hand_speed_mps)
    before = out.times <= t_on + 1e-9
    np.testing.assert_allclose(out.joints[before], fc.joints[before])
    # then the hand heads for the station, never moving away from it, and is there once the reach is over
    d = np.linalg.norm(out.joints[:, hand] - station, axis=1)
    assert np.all(np.diff(d) <= 1e-9)
    after = out.times >= t_on + duration - 1e-9
    assert after.any()
    np.testing.assert_allclose(out.joints[after, hand], np.broadcast_to(station, (after.sum(), 3)))
    # the wrist moves with the hand, the elbow half as much; every other joint keeps the predictor's forecast
    np.testing.assert_allclose(
        out.joints[:, wrist] - fc.joints[:, wrist], out.joints[:, hand] - fc.joints[:, hand]
    )
    np.testing.assert_allclose(
        out.joints[:, elbow] - fc.joints[:, elbow], 0.5 * (out.joints[:, hand] - fc.joints[:, hand])
    )
    others = [j for j in range(fc.joints.shape[1]) if j not in ARM["r"]]
    np.testing.assert_array_equal(out.joints[:, others], fc.joints[:, others])
    # times, margins and the growth beyond the horizon are the predictor's
    np.testing.assert_array_equal(out.times, fc.times)
    np.testing.assert_array_equal(out.margins, fc.margins)
    assert out.growth_mps == fc.growth_mps and out.max_margin_m == fc.max_margin_m
    # the station on the person's left is reached with the left hand
    ant2 = FetchAnticipation(STATIONS, p)
    ant2.expect("A", t_release=9.5)
    out2 = ant2.apply(frame, fc)
    changed = np.any(out2.joints != fc.joints, axis=(0, 2))
    assert set(np.flatnonzero(changed)) == set(ARM["l"])


def test_a_reach_expected_later_starts_later() -> None:
    ant = FetchAnticipation(STATIONS, FetchAnticipationParams(reaction_s=0.3))
    frame = _frame(10.0)
    fc = _forecast(frame)
    ant.expect("C", t_release=10.5)  # the robot is still releasing: the hand is expected from 10.8 s on
    out = ant.apply(frame, fc)
    moved = np.any(out.joints != fc.poses_at(out.times)[0], axis=(1, 2))
    assert not moved[out.times <= 10.8 + 1e-9].any()
    assert moved[-1]


def test_a_reach_that_ends_beyond_the_horizon_extends_the_forecast_to_the_station() -> None:
    """Held halfway at the horizon's end, the hand would seem to stop short of the station for good: the
    forecast goes on, at its step, until the expected reach is over, with the margin grown as beyond the
    horizon."""
    p = FetchAnticipationParams(reaction_s=0.8, hand_speed_mps=0.6)
    ant = FetchAnticipation(STATIONS, p)
    frame = _frame(10.0)
    fc = _forecast(frame, drift=0.05)
    ant.expect("D", t_release=10.0)
    out = ant.apply(frame, fc)
    hand = ARM["r"][2]
    station = STATIONS["D"]
    length = float(np.linalg.norm(station - frame.joints[hand]))
    t_done = 10.0 + p.reaction_s + max(p.min_reach_s, 1.875 * length / p.hand_speed_mps)
    assert t_done > fc.times[-1] + 0.5
    # the forecast's own samples keep their times and margins; the new ones follow at its step
    n = fc.times.shape[0]
    np.testing.assert_array_equal(out.times[:n], fc.times)
    np.testing.assert_array_equal(out.margins[:n], fc.margins)
    np.testing.assert_allclose(np.diff(out.times[n - 1 :]), 1.0 / FPS)
    assert out.times[-2] < t_done <= out.times[-1] + 1e-9
    # beyond the horizon: the last predicted pose held, its margin grown, the hand arriving at the station
    held, grown = fc.poses_at(out.times[n:])
    np.testing.assert_allclose(out.margins[n:], grown)
    others = [j for j in range(fc.joints.shape[1]) if j not in ARM["r"]]
    np.testing.assert_array_equal(out.joints[n:, others], held[:, others])
    np.testing.assert_allclose(out.joints[-1, hand], station)
    d = np.linalg.norm(out.joints[:, hand] - station, axis=1)
    assert np.all(np.diff(d) <= 1e-9)
    # a reach already over by the horizon's end adds nothing
    quick = FetchAnticipation(STATIONS, FetchAnticipationParams(reaction_s=0.0, hand_speed_mps=3.0))
    quick.expect("D", t_release=10.0)
    np.testing.assert_array_equal(quick.apply(frame, fc).times, fc.times)


def test_over_an_exact_horizon_only_the_reach_beyond_it_is_added() -> None:
    """With a forecast that is exact over its horizon (the oracle), the forecast's own samples are kept as
    they are. Where it brings no hand to the station, the fetch comes after the horizon: the hand goes on
    from where the forecast leaves it to the station, on the expected reach of that length, starting at the
    horizon's end (or at the reach's expected start, if later). Where the forecast brings a hand to the
    station, or a hand has reached it, nothing is added."""
    p = FetchAnticipationParams(reaction_s=0.8, hand_speed_mps=0.6)
    frame = _frame(10.0)
    fc = _forecast(frame, drift=0.05)
    hand = ARM["r"][2]
    station = STATIONS["D"]
    n = fc.times.shape[0]
    for reaction_s, start in ((0.8, fc.times[-1]), (1.5, 11.5)):
        ant = FetchAnticipation(STATIONS, replace(p, reaction_s=reaction_s), exact_horizon=True)
        ant.expect("D", t_release=10.0)
        out = ant.apply(frame, fc)
        length = float(np.linalg.norm(station - fc.joints[-1, hand]))
        t_done = start + max(p.min_reach_s, 1.875 * length / p.hand_speed_mps)
        assert out.times[-2] < t_done <= out.times[-1] + 1e-9
        np.testing.assert_array_equal(out.joints[:n], fc.joints)  # the known part untouched
        np.testing.assert_array_equal(out.margins[:n], fc.margins)
        held, grown = fc.poses_at(out.times[n:])
        np.testing.assert_allclose(out.margins[n:], grown)
        others = [j for j in range(fc.joints.shape[1]) if j not in ARM["r"]]
        np.testing.assert_array_equal(out.joints[n:, others], held[:, others])
        # the hand waits at the forecast's last pose until the reach starts, then goes to the station
        d = np.linalg.norm(out.joints[n - 1 :, hand] - station, axis=1)
        waiting = out.times[n - 1 :] <= start + 1e-9
        np.testing.assert_allclose(d[waiting], d[0])
        assert np.all(np.diff(d) <= 1e-9) and d[-1] < 1e-9
    # a forecast that brings the hand to the station shows the fetch itself
    ant = FetchAnticipation(STATIONS, p, exact_horizon=True)
    ant.expect("D", t_release=10.0)
    reaching = HumanForecast(
        t0=fc.t0,
        times=fc.times,
        joints=np.stack([_moved(frame, "r", station, k / H, t).joints for k, t in enumerate(fc.times)]),
        margins=fc.margins,
        growth_mps=0.1,
    )
    assert ant.apply(frame, reaching) is reaching
    # a hand at the station: the exact forecast shows where it goes from there
    at = FetchAnticipation(STATIONS, p, exact_horizon=True)
    at.expect("D", t_release=10.0)
    there = _moved(frame, "r", station, 1.0, 11.0)
    at.apply(there, _forecast(there))
    later = _moved(frame, "r", station, 1.0, 11.1)
    fc_later = _forecast(later)
    assert at.apply(later, fc_later) is fc_later


def test_a_fetch_is_over_once_the_hand_came_and_withdrew_then_the_next_one_counts() -> None:
    p = FetchAnticipationParams()
    ant = FetchAnticipation(STATIONS, p)
    f0 = _frame(10.0)
    ant.expect("D", 9.0)
    ant.expect("B", 9.5)
    # the hand at the station: the fetch is under way, the forecast holds the hand there
    at = _moved(f0, "r", STATIONS["D"], 0.97, 11.0)
    assert np.linalg.norm(at.joints[ARM["r"][2]] - STATIONS["D"]) <= p.reached_radius_m
    out = ant.apply(at, _forecast(at, drift=-0.3))
    np.testing.assert_allclose(out.joints[:, ARM["r"][2]], np.broadcast_to(STATIONS["D"], (H + 1, 3)))
    assert ant.expected() == ["D", "B"]
    # on its way back but still near: still the fetch of D
    near = _moved(f0, "r", STATIONS["D"], 0.85, 11.3)
    assert np.linalg.norm(near.joints[ARM["r"][2]] - STATIONS["D"]) < p.reached_radius_m + p.withdraw_m
    ant.apply(near, _forecast(near))
    assert ant.expected() == ["D", "B"]
    # withdrawn: D is over, the next forecast reaches for B
    back = _frame(11.6)
    out = ant.apply(back, _forecast(back))
    assert ant.expected() == ["B"]
    d_end = np.linalg.norm(out.joints[-1][[ARM["l"][2], ARM["r"][2]]] - STATIONS["B"], axis=1).min()
    d_now = np.linalg.norm(back.joints[[ARM["l"][2], ARM["r"][2]]] - STATIONS["B"], axis=1).min()
    assert d_end < d_now - 0.1


def test_an_overdue_fetch_is_forgotten_and_reset_forgets_all() -> None:
    p = FetchAnticipationParams(timeout_s=2.0)
    ant = FetchAnticipation(STATIONS, p)
    ant.expect("A", 10.0)
    f = _frame(11.9)
    fc0 = _forecast(f)
    assert ant.apply(f, fc0) is not fc0 and ant.expected() == ["A"]  # still expected: the hand reaches
    late = _frame(12.1)
    fc = _forecast(late)
    assert ant.apply(late, fc) is fc and ant.expected() == []
    ant.expect("B", 12.0)
    ant.reset()
    assert ant.expected() == []


def test_bad_input_is_refused_with_a_message() -> None:
    ant = FetchAnticipation(STATIONS)
    with pytest.raises(ValueError, match="unknown drop station 'E'"):
        ant.expect("E", 1.0)
    with pytest.raises(ValueError, match="t_release must be finite"):
        ant.expect("A", float("nan"))
    with pytest.raises(ValueError, match=r"station 'X': expected a finite \(3,\) position"):
        FetchAnticipation({"X": [0.0, np.inf, 0.0]})
    with pytest.raises(ValueError, match="hand_speed_mps must be > 0"):
        FetchAnticipationParams(hand_speed_mps=0.0)
    with pytest.raises(ValueError, match="reaction_s must be finite and >= 0"):
        FetchAnticipationParams(reaction_s=-0.1)


def test_one_observed_fetch_gives_back_the_reaction_and_the_hand_speed() -> None:
    from app.control.anticipation import observed_fetch
    from app.prediction.profiles import min_jerk

    reaction, duration, length, radius = 0.45, 0.7, 0.5, 0.12
    t = np.arange(0.0, 3.0, 1 / 240)
    d = length * (1 - min_jerk((t - reaction) / duration))  # the hand's distance to the station
    t10 = t[np.argmax(d <= 0.9 * length)]
    t_reached = t[np.argmax(d <= radius)]
    seen = observed_fetch(0.0, t10, t_reached, length, radius)
    assert seen is not None
    assert seen[0] == pytest.approx(reaction, abs=0.01)
    assert seen[1] == pytest.approx(1.875 * length / duration, rel=0.02)
    assert observed_fetch(0.0, 0.5, 0.4, length, radius) is None  # reached before it started
    assert observed_fetch(0.0, 0.1, 0.4, 0.1, radius) is None  # from within the reached radius


def test_the_fetch_timing_is_learned_from_the_fetches_seen() -> None:
    """A participant who reacts late and reaches slowly: after their fetches the forecast expects that,
    not the prior."""
    from app.prediction.profiles import min_jerk

    base = _frame()
    name, station = next(iter(STATIONS.items()))
    side = (
        "l"
        if np.linalg.norm(base.joints[ARM["l"][2]] - station)
        < np.linalg.norm(base.joints[ARM["r"][2]] - station)
        else "r"
    )
    params = FetchAnticipationParams(reaction_s=0.6, hand_speed_mps=1.2, prior_weight=1.0)
    ant = FetchAnticipation(STATIONS, params)
    assert ant.timing() == (0.6, 1.2)
    reaction, duration = 1.2, 1.0
    t0 = 0.0
    for _ in range(4):  # four fetches: reach, hold, withdraw
        ant.expect(name, t0)
        for k in range(int(4.0 * FPS)):
            t = t0 + k / FPS
            s = float(min_jerk(np.array([(t - t0 - reaction) / duration]))[0])
            back = float(min_jerk(np.array([(t - t0 - reaction - duration - 0.5) / 0.6]))[0])
            frame = _moved(base, side, station, s * (1 - back), t)
            ant.apply(frame, _forecast(frame))
        t0 += 5.0
    assert ant.fetches_seen == 4
    learned_reaction, learned_speed = ant.timing()
    length = float(np.linalg.norm(base.joints[ARM[side][2]] - station))
    # the running mean with the prior counted once: 4 observations of (1.2 s, 1.875 L / 1 s) and the prior
    assert learned_reaction == pytest.approx((0.6 + 4 * reaction) / 5, abs=0.05)
    assert learned_speed == pytest.approx((1.2 + 4 * 1.875 * length / duration) / 5, rel=0.08)
