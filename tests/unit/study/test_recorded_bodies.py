"""Recorded frames of 1, 2 and 0 tracked bodies: the layout, the study database, the replay and the clips."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import update

from app.cell.bodies import frame_bodies, pad_bodies, recorded_bodies
from app.control.results import TrialFrames
from app.prediction.skeleton import NUM_JOINTS
from app.study.db import make_engine, upgrade_to_head
from app.study.models import RecordedFrame
from app.study.repository import RecordedFrames, StudyRepository
from app.study.schemas import ParticipantCreate
from app.ui.replay import ReplayTimeline

J = NUM_JOINTS


def _body(x: float) -> np.ndarray:
    pose = np.zeros((J, 3))
    pose[:, 0] = x
    pose[:, 2] = np.linspace(0.1, 1.7, J)
    return pose


#: five frames: body 3; bodies 3 and 8; nobody; body 8; bodies 8 and 3 (another order)
JOINTS = [
    _body(1.0),
    np.concatenate([_body(1.1), _body(2.0)]),
    np.zeros((0, 3)),
    _body(2.1),
    np.concatenate([_body(2.2), _body(1.2)]),
]
IDS = [(3,), (3, 8), (), (8,), (8, 3)]


def test_pad_bodies_keeps_each_frames_bodies_and_ids() -> None:
    sk, ids = pad_bodies(JOINTS, IDS)
    assert sk.shape == (5, 2, J, 3) and ids.tolist() == [[3, -1], [3, 8], [-1, -1], [8, -1], [8, 3]]
    assert np.isnan(sk[0, 1]).all() and np.isnan(sk[2]).all()
    for i in range(5):
        joints, got = frame_bodies(sk, ids, i)
        assert got == IDS[i]
        np.testing.assert_allclose(joints, JOINTS[i], atol=1e-6)
    empty, none = pad_bodies([np.zeros((0, 3))], [()])
    assert empty.shape == (1, 0, J, 3) and none.shape == (1, 0)


def test_old_single_body_recordings_read_as_body_0() -> None:
    old = np.stack([_body(1.0), np.full((J, 3), np.nan), _body(1.1)])  # (T, J, 3), a NaN row: nobody
    sk, ids = recorded_bodies(old)
    assert sk.shape == (3, 1, J, 3) and ids.tolist() == [[0], [-1], [0]]
    assert frame_bodies(sk, ids, 1)[1] == ()
    with pytest.raises(ValueError, match="repeats a body id"):
        recorded_bodies(np.zeros((1, 2, J, 3)), np.array([[4, 4]]))
    with pytest.raises(ValueError, match="body_ids must be"):
        recorded_bodies(np.zeros((1, 2, J, 3)), np.array([[4]]))


def test_trial_frames_take_both_layouts() -> None:
    sk, ids = pad_bodies(JOINTS, IDS)
    f = TrialFrames(t=np.arange(5) / 30, q=np.zeros((5, 6)), skeleton=sk, body_ids=ids)
    assert f.bodies(4)[1] == (8, 3) and f.bodies(2)[1] == ()
    old = TrialFrames(t=np.arange(2) / 30, q=np.zeros((2, 6)), skeleton=np.stack([_body(1.0)] * 2))
    assert old.skeleton is not None and old.skeleton.shape == (2, 1, J, 3) and old.bodies(0)[1] == (0,)


@pytest.fixture
def repo(tmp_path: Path) -> Iterator[StudyRepository]:
    url = f"sqlite:///{tmp_path / 'x.db'}"
    upgrade_to_head(url)
    r = StudyRepository(make_engine(url))
    yield r
    r.close()


def _trial(repo: StudyRepository, code: str) -> int:
    p = repo.create_participant(ParticipantCreate(code=code))
    return repo.create_trial(participant_id=p.id, method="proactive").id


def test_the_database_stores_every_body_with_its_id_across_chunks(repo: StudyRepository) -> None:
    tid = _trial(repo, "A01")
    sk, ids = pad_bodies(JOINTS, IDS)
    # chunks of 2 frames: the first holds at most 2 bodies, the third (frame 4) 2, the second... also 2
    repo.save_frames(tid, RecordedFrames(t=np.arange(5) / 30, q=np.zeros((5, 6)), skeleton=sk, body_ids=ids))
    back = repo.load_frames(tid)
    assert back is not None and back.body_ids is not None and back.skeleton is not None
    assert back.body_ids.tolist() == ids.tolist()
    np.testing.assert_allclose(back.skeleton, sk, atol=1e-6)
    # chunks with different numbers of slots are padded to the most
    tid2 = _trial(repo, "A02")
    repo.save_frames(
        tid2,
        RecordedFrames(t=np.arange(5) / 30, q=np.zeros((5, 6)), skeleton=sk, body_ids=ids),
        chunk_frames=1,
    )
    back2 = repo.load_frames(tid2)
    assert back2 is not None and back2.body_ids is not None and back2.body_ids.tolist() == ids.tolist()


def test_the_database_reads_chunks_recorded_before_several_bodies(repo: StudyRepository) -> None:
    tid = _trial(repo, "B01")
    old = np.stack([_body(1.0), np.full((J, 3), np.nan), _body(1.1)])
    repo.save_frames(tid, RecordedFrames(t=np.arange(3) / 30, q=np.zeros((3, 6)), skeleton=old))
    with repo._sessions() as s:  # as revision 0008 wrote them: no body count, no ids
        s.execute(update(RecordedFrame).values(n_bodies=None, body_ids=None))
        s.commit()
    back = repo.load_frames(tid)
    assert back is not None and back.skeleton is not None and back.body_ids is not None
    assert back.skeleton.shape == (3, 1, J, 3) and back.body_ids.tolist() == [[0], [-1], [0]]


def test_the_replay_shows_every_recorded_body_of_each_frame() -> None:
    sk, ids = pad_bodies(JOINTS, IDS)
    tl = ReplayTimeline(
        t=np.arange(5) / 30,
        q=np.zeros((5, 6)),
        p_world_tcp=np.zeros((5, 3)),
        skeleton=sk,
        body_ids=ids,
        events=[],
    )
    for i in range(5):
        frame = tl.frame_at(i / 30)
        assert frame.body_ids == IDS[i]
        if IDS[i]:
            assert frame.skeleton is not None
            np.testing.assert_allclose(frame.skeleton, JOINTS[i], atol=1e-6)
        else:
            assert frame.skeleton is None
    single = ReplayTimeline(
        t=np.arange(2) / 30,
        q=np.zeros((2, 6)),
        p_world_tcp=np.zeros((2, 3)),
        skeleton=np.stack([_body(1.0), np.full((J, 3), np.nan)]),
        events=[],
    )
    assert single.frame_at(0.0).body_ids == (0,) and single.frame_at(1 / 30).skeleton is None


def test_clips_are_exported_per_tracked_body(repo: StudyRepository, tmp_path: Path) -> None:
    from app.study.export import export_clips

    tid = _trial(repo, "C01")
    n = 60
    joints = [np.concatenate([_body(1.0 + 0.001 * k), _body(2.0)]) for k in range(n)]
    sk, ids = pad_bodies(joints, [(0, 5)] * n)
    repo.save_frames(tid, RecordedFrames(t=np.arange(n) / 30, q=np.zeros((n, 6)), skeleton=sk, body_ids=ids))
    paths = export_clips(repo, tmp_path / "clips")
    assert sorted(p.name for p in paths) == [f"trial{tid}_C01_0.npz", f"trial{tid}_C01_b5_0.npz"]
    with np.load(tmp_path / "clips" / f"trial{tid}_C01_b5_0.npz") as z:
        np.testing.assert_allclose(z["positions"][:, 0, 0], 2.0, atol=1e-6)
