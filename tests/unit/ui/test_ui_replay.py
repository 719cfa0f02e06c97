"""Replay of a recorded trial: the timeline (pure) and the viser replay driven by it (no browser)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.config import load_workcell
from app.control.metrics import TrialEvent
from app.prediction.skeleton import NUM_JOINTS
from app.ui.replay import ReplayError, ReplayEvent, ReplayTimeline, TrialReplay, load_timeline

T = 31  # one second at 30 Hz


def _capsules(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Toy arm: two vertical links at x = q[:, 0]."""
    pts = np.zeros((q.shape[0], 3, 3))
    pts[:, :, 2] = [0.0, 0.3, 0.6]
    pts[:, :, 0] = q[:, :1]
    return pts[:, :-1], pts[:, 1:], np.array([0.06, 0.05])


def _timeline(*, skeleton: bool = True) -> ReplayTimeline:
    t = np.arange(T) / 30.0
    q = np.zeros((T, 6))
    q[:, 0] = np.linspace(0.0, 1.0, T)
    p = np.stack([q[:, 0], np.zeros(T), np.full(T, 0.3)], axis=1)
    sk = None
    if skeleton:
        sk = np.broadcast_to(np.linspace(0, 1, NUM_JOINTS)[None, :, None], (T, NUM_JOINTS, 3)).copy()
        sk[5:8] = np.nan  # the person was not seen for three frames
    events = [
        ReplayEvent(0.2, "state_changed", {"from": "idle", "to": "nominal"}),
        ReplayEvent(0.5, "state_changed", {"from": "nominal", "to": "collision_avoidance"}),
        ReplayEvent(0.8, "estop", {"source": "api"}),
    ]
    return ReplayTimeline(t=t, q=q, p_world_tcp=p, skeleton=sk, events=events, trial_id=7, method="reactive")


def test_timeline_states_frames_and_estop() -> None:
    tl = _timeline()
    assert len(tl) == T and np.isclose(tl.duration_s, 1.0)
    assert (
        tl.state_at(0.0) == "idle"
        and tl.state_at(0.2) == "nominal"
        and tl.state_at(0.6) == "collision_avoidance"
    )
    assert tl.index_at(-1.0) == 0 and tl.index_at(0.51) == 15 and tl.index_at(5.0) == T - 1
    f = tl.frame_at(0.51)
    assert np.isclose(f.q[0], 0.5) and f.state == "collision_avoidance" and not f.estopped
    assert f.trial_id == 7 and f.method == "reactive" and np.isclose(f.trial_duration_s, 1.0)
    assert tl.frame_at(0.2).skeleton is None  # NaN frame: no person drawn
    assert tl.frame_at(0.9).estopped and tl.frame_at(9.0).t == pytest.approx(1.0)
    assert [e.kind for e in tl.events_until(0.6)] == ["state_changed", "state_changed"]


def test_tool_trace_is_subsampled_but_keeps_both_ends() -> None:
    tl = _timeline()
    full = tl.tool_trace()
    assert full.shape == (T - 1, 2, 3)
    short = tl.tool_trace(max_segments=7)
    assert len(short) <= 8
    assert np.allclose(short[0, 0], tl.p_world_tcp[0]) and np.allclose(short[-1, 1], tl.p_world_tcp[-1])


def test_timeline_rejects_bad_shapes() -> None:
    with pytest.raises(ReplayError, match="non-decreasing"):
        ReplayTimeline(
            t=np.array([0.0, -1.0]),
            q=np.zeros((2, 6)),
            p_world_tcp=np.zeros((2, 3)),
            skeleton=None,
            events=[],
        )
    with pytest.raises(ReplayError, match="skeleton"):
        ReplayTimeline(
            t=np.zeros(2),
            q=np.zeros((2, 6)),
            p_world_tcp=np.zeros((2, 3)),
            skeleton=np.zeros((2, 3, 3)),
            events=[],
        )


def test_replay_slider_play_and_speed() -> None:
    tl = _timeline()
    with TrialReplay(tl, load_workcell(), port=0, robot_capsules=_capsules) as replay:
        assert replay.port > 0
        links = replay.view.handles["robot_links"]
        assert np.allclose(links.batched_positions[:, 0], 0.0, atol=1e-6)
        frame = replay.seek(0.5)
        assert np.allclose(links.batched_positions[:, 0], frame.q[0], atol=1e-5)
        assert replay.view.handles["state_label"].text.startswith("COLLISION AVOIDANCE")
        assert replay._gui["slider"].value == pytest.approx(frame.t)
        replay.pause()
        assert replay.advance(0.1) is None  # paused: nothing moves
        replay.set_speed(2.0)
        replay.play()
        f = replay.advance(0.1)
        assert f is not None and f.t == pytest.approx(0.7, abs=1 / 30)
        replay.advance(10.0)  # past the end: clamps and pauses
        assert replay.t == pytest.approx(1.0) and not replay.playing
        assert replay.view.handles["state_label"].text.startswith("E-STOP")
        with pytest.raises(ValueError, match="speed"):
            replay.set_speed(0.0)


@pytest.fixture()
def repo(tmp_path: Path) -> Iterator[Any]:
    from app.study.db import make_engine, upgrade_to_head
    from app.study.repository import StudyRepository

    url = f"sqlite:///{tmp_path / 'replay.db'}"
    upgrade_to_head(url)
    engine = make_engine(url)
    try:
        yield StudyRepository(engine)
    finally:
        engine.dispose()


def test_load_timeline_from_the_database(repo: Any) -> None:
    from app.study.repository import RecordedFrames
    from app.study.schemas import ParticipantCreate

    cell = load_workcell()
    p = repo.create_participant(ParticipantCreate(code="R01"))
    trial = repo.create_trial(participant_id=p.id, method="proactive", duration_s=1.0)
    with pytest.raises(ReplayError, match="no recorded frames"):
        load_timeline(repo, trial.id, cell)
    q = np.tile(np.asarray(cell.robot.home_q), (T, 1))
    sk = np.zeros((T, NUM_JOINTS, 3)) + np.array([1.3, 0.0, 0.0])
    repo.save_frames(trial.id, RecordedFrames(t=np.arange(T) / 30.0, q=q, skeleton=sk))
    repo.add_events(trial.id, [TrialEvent(0.4, "state_changed", {"from": "idle", "to": "nominal"})])
    tl = load_timeline(repo, trial.id, cell)
    assert len(tl) == T and tl.method == "proactive" and tl.trial_id == trial.id
    assert tl.state_at(0.5) == "nominal"
    # The tool position comes from forward kinematics of the recorded configuration.
    from app.planning.kinematics import UR5e

    expected = UR5e.from_workcell(cell).fk_tcp(q[:1])[0, :3, 3]
    assert np.allclose(tl.frame_at(0.0).p_world_tcp, expected, atol=1e-6)
    assert np.allclose(tl.frame_at(0.0).skeleton, sk[0], atol=1e-6)
