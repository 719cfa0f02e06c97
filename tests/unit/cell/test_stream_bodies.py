"""Several tracked bodies per capture: the stream message, the stream source and per-id validation."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from app.cell.human import StreamSource
from app.cell.operator_sim import SimulatedOperator
from app.cell.stream_protocol import (
    MAX_BODIES,
    canonical_bodies,
    make_bodies_message,
    make_message,
    message_from_zed_bodies,
    parse_message,
)
from app.cell.validation import FrameRejected, FrameValidator, StaleWatchdog, ValidatedSource
from app.config import load_workcell
from app.prediction.skeleton import NUM_JOINTS, HumanFrame

CELL = load_workcell()
FPS = 30.0


def _pose() -> np.ndarray:
    return SimulatedOperator(CELL, seed=0, noise=False).frame_at(0.0).joints


def _two(pose: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
    return [
        (3, pose, np.full(NUM_JOINTS, 0.9)),
        (7, pose + np.array([0.5, 0.0, 0.0]), np.full(NUM_JOINTS, 0.8)),
    ]


# --- the message ------------------------------------------------------------------------------------------
def test_a_multi_body_message_round_trips_through_json() -> None:
    pose = _pose()
    msg = make_bodies_message(_two(pose), t=2.5)
    assert [b["id"] for b in msg["bodies"]] == [3, 7]
    parsed = parse_message(json.dumps(msg))
    assert parsed.t == 2.5 and parsed.body_ids == (3, 7)
    np.testing.assert_allclose(parsed.bodies[1].joints, pose + np.array([0.5, 0.0, 0.0]), atol=1e-4)
    np.testing.assert_allclose(parsed.bodies[0].confidence, 0.9)
    out = canonical_bodies(parsed)
    assert [i for i, _, _ in out] == [3, 7]
    np.testing.assert_allclose(out[0][1], pose, atol=1e-4)


def test_zed_bodies_message_carries_each_id() -> None:
    kp = np.zeros((34, 3))
    kp[:, 2] = np.linspace(0.0, 1.7, 34)
    msg = message_from_zed_bodies(
        [(4, kp, np.full(34, 90.0)), (9, kp + 1.0, None)], t=1.0, body_format="zed34", frame="world"
    )
    parsed = parse_message(msg)
    assert parsed.format == "zed34" and parsed.body_ids == (4, 9)
    np.testing.assert_allclose(parsed.bodies[0].confidence, 0.9)
    assert parsed.bodies[1].confidence is None


def test_the_single_body_message_is_one_body_id_0_or_its_body_id() -> None:
    pose = _pose()
    parsed = parse_message(make_message(pose, t=1.0))
    assert parsed.body_ids == (0,) and parsed.body_id == 0
    np.testing.assert_allclose(parsed.joints, pose, atol=1e-4)
    assert parse_message(make_message(pose, body_id=5)).body_ids == (5,)


def test_zero_bodies_is_a_person_free_frame() -> None:
    parsed = parse_message('{"t": 1.0, "bodies": []}')
    assert parsed.bodies == () and canonical_bodies(parsed) == []
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    frame = src.push('{"bodies": []}', t_received=1.0)
    assert frame.bodies == 0 and frame.joints.shape == (0, 3)
    assert src.frame_at(1.0) is frame and src.counters["accepted"] == 1


@pytest.mark.parametrize(
    ("bodies", "reason", "words"),
    [
        ([{"id": 1, "joints": "P"}, {"id": 1, "joints": "P"}], "malformed", "body 1 has the id 1 of body 0"),
        ([{"id": -2, "joints": "P"}], "malformed", "body 0: id must be >= 0"),
        ([{"id": True, "joints": "P"}], "malformed", "body 0: id must be an integer"),
        ([{"id": "4", "joints": "P"}], "malformed", "body 0: id must be an integer"),
        ([{"joints": "P"}], "malformed", "body 0 has no id"),
        ([{"id": 1, "joints": "P"}, [1, 2]], "malformed", "body 1 must be a JSON object"),
        ([{"id": 1, "joints": "P"}, {"id": 6, "joints": "SHORT"}], "joint_count", "body 1 (id 6): format"),
        ([{"id": 2, "joints": "P", "confidence": "C2"}], "bad_confidence", "body 0 (id 2): confidence 0"),
        ([{"id": 8, "joints": "BAD"}], "malformed", "body 0 (id 8): joint 0 has a non-number"),
    ],
)
def test_a_bad_body_is_rejected_naming_it(bodies: list, reason: str, words: str) -> None:
    pose = np.round(_pose(), 4).tolist()
    subs = {"P": pose, "SHORT": pose[:-1], "BAD": [["x", 0, 0], *pose[1:]], "C2": [2.0] * NUM_JOINTS}
    for b in bodies:
        if isinstance(b, dict):
            for key in ("joints", "confidence"):
                if key in b:
                    b[key] = subs[b[key]]
    with pytest.raises(FrameRejected) as exc:
        parse_message({"bodies": bodies})
    assert exc.value.reason == reason
    assert words in str(exc.value)


def test_bodies_and_top_level_joints_together_are_malformed() -> None:
    pose = np.round(_pose(), 4).tolist()
    with pytest.raises(FrameRejected, match="not both"):
        parse_message({"joints": pose, "bodies": []})
    with pytest.raises(FrameRejected, match="bodies must be a list"):
        parse_message({"bodies": {"id": 1}})
    with pytest.raises(FrameRejected, match=f"at most {MAX_BODIES}"):
        parse_message({"bodies": [{"id": i, "joints": pose} for i in range(MAX_BODIES + 1)]})


def test_make_bodies_message_refuses_repeated_ids() -> None:
    pose = _pose()
    with pytest.raises(ValueError, match="distinct"):
        make_bodies_message([(1, pose, None), (1, pose, None)])


# --- the stream source ------------------------------------------------------------------------------------
def test_stream_source_queues_every_body_with_its_id() -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    pose = _pose()
    frame = src.push(json.dumps(make_bodies_message(_two(pose), t=0.0)), t_received=0.0)
    assert frame.body_ids == (3, 7) and frame.joints.shape == (2 * NUM_JOINTS, 3)
    np.testing.assert_allclose(frame.body(1).joints, pose + np.array([0.5, 0.0, 0.0]), atol=1e-4)
    np.testing.assert_allclose(frame.confidence[:NUM_JOINTS], 0.9)


def test_stream_source_fills_unseen_joints_from_the_same_id() -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    pose = _pose()
    src.push(make_bodies_message(_two(pose), t=0.0), t_received=0.0)
    seen = pose.copy()
    seen[14] = np.nan  # body 7's knee is not seen: filled from body 7's last pose, not body 3's
    bodies = [(3, pose + 0.01, None), (7, seen + np.array([0.5, 0.0, 0.0]), None)]
    frame = src.push(make_bodies_message(bodies, t=1 / FPS), t_received=1 / FPS)
    np.testing.assert_allclose(frame.body(1).joints[14], pose[14] + np.array([0.5, 0.0, 0.0]), atol=1e-4)
    assert frame.body(1).confidence[14] == 0.0 and frame.body(0).confidence[14] == 1.0
    # a new id with an unseen joint has nothing to fill from: rejected, naming the body
    with pytest.raises(FrameRejected, match=r"missing_joints.*body 12"):
        src.push(make_bodies_message([(12, seen, None)], t=2 / FPS), t_received=2 / FPS)


# --- validation per id ------------------------------------------------------------------------------------
def test_validator_names_the_body_of_a_bad_frame() -> None:
    v = FrameValidator.for_workcell(CELL)
    pose = _pose()
    far = pose + np.array([50.0, 0.0, 0.0])
    with pytest.raises(FrameRejected, match=r"out_of_range.*body 7: joint 0"):
        v.validate(0.0, np.concatenate([pose, far]), None, [3, 7])
    with pytest.raises(FrameRejected, match="body 1: id 3 is repeated"):
        v.validate(0.0, np.concatenate([pose, pose]), None, [3, 3])
    with pytest.raises(FrameRejected, match="joint_count"):
        v.validate(0.0, pose, None, [3, 7])
    conf = np.concatenate([np.ones(NUM_JOINTS), np.zeros(NUM_JOINTS)])
    with pytest.raises(FrameRejected, match=r"no_valid_joint.*body 7"):
        v.validate(0.0, np.concatenate([pose, pose + 0.5]), conf, [3, 7])
    assert v.counters["rejected"] == 4 and v.counters["accepted"] == 0


def test_a_jump_is_measured_against_the_same_id_and_a_new_id_is_no_jump() -> None:
    v = FrameValidator()
    pose = _pose()
    a, b = pose, pose + np.array([0.6, 0.0, 0.0])
    v.validate(0.0, np.concatenate([a, b]), None, [3, 7])
    assert set(v.last_changes.appeared) == {3, 7} and not v.last_changes.jumps
    # the two bodies swap places in the list: matched by id, no jump
    v.validate(1 / FPS, np.concatenate([b + 0.001, a + 0.001]), None, [7, 3])
    assert v.last_changes.jumps == {} and v.last_changes.appeared == ()
    # body 7 jumps 1 m in one frame (30 m/s); body 3 stays; body 9 is new
    frame = v.validate(
        2 / FPS,
        np.concatenate([a, b + np.array([1.0, 0.0, 0.0]), a - np.array([0.8, 0, 0])]),
        None,
        [3, 7, 9],
    )
    assert set(v.last_changes.jumps) == {7} and v.last_changes.jumps[7] == pytest.approx(30.0, rel=0.01)
    assert v.last_changes.appeared == (9,) and frame.body_ids == (3, 7, 9)
    # body 3 vanishes: its state is dropped, and it comes back as new (no jump however far it went)
    v.validate(3 / FPS, np.concatenate([b + np.array([1.0, 0.0, 0.0])]), None, [7])
    assert set(v.last_changes.vanished) == {3, 9}
    v.validate(
        4 / FPS, np.concatenate([b + np.array([1.0, 0.0, 0.0]), a + np.array([0.0, 1.0, 0.0])]), None, [7, 3]
    )
    assert v.last_changes.appeared == (3,) and v.last_changes.jumps == {}
    assert v.tracks.jumps == 1


def test_validated_source_reports_body_changes_and_an_empty_cell_keeps_the_stream_alive() -> None:
    pose = _pose()

    class Frames:
        def __init__(self) -> None:
            self.frame: HumanFrame | None = None

        def frame_at(self, t: float) -> HumanFrame | None:
            return self.frame

        def notify_block_placed(self, station: str, t: float) -> None:
            pass

    inner = Frames()
    src = ValidatedSource(inner, validator=FrameValidator.for_workcell(CELL), watchdog=StaleWatchdog(0.1))
    inner.frame = HumanFrame(0.0, np.concatenate([pose, pose + 0.6]), np.ones(2 * NUM_JOINTS), (1, 2))
    first = src.poll(0.0)
    assert first is not None and first.body_ids == (1, 2)
    assert src.last_changes.appeared == (1, 2)
    inner.frame = HumanFrame(0.05, pose.copy(), np.ones(NUM_JOINTS), (2,))  # id 2 jumped 0.6 m
    assert src.poll(0.05) is not None
    assert set(src.last_changes.jumps) == {2} and src.last_changes.vanished == (1,)
    for k in range(1, 6):  # the cell empties: 0-body frames keep the watchdog fed
        inner.frame = HumanFrame.stack(0.05 + 0.05 * k, [])
        frame = src.poll(0.05 + 0.05 * k)
        assert frame is not None and frame.bodies == 0
    assert not src.is_stale(0.3)
    assert src.last_changes.vanished == ()
    assert src.is_stale(0.5)  # and no frame at all is stale


# --- the example clients ----------------------------------------------------------------------------------
def _example(name: str) -> Any:
    import importlib.util

    script = Path(__file__).resolve().parents[3] / "examples" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_zed_client_sends_every_tracked_body_with_its_id_and_empty_captures() -> None:
    zed = _example("zed_client")
    sl = SimpleNamespace(OBJECT_TRACKING_STATE=SimpleNamespace(OK="ok", SEARCHING="searching"))
    kp = np.zeros((34, 3))
    kp[:, 0] = 1.5
    kp[:, 2] = np.linspace(0.0, 1.7, 34)

    def body(i: int, state: str) -> SimpleNamespace:
        return SimpleNamespace(id=i, tracking_state=state, keypoint=kp, keypoint_confidence=np.full(34, 80.0))

    stamp = SimpleNamespace(get_nanoseconds=lambda: 2_000_000_000)
    capture = SimpleNamespace(body_list=[body(4, "ok"), body(5, "searching"), body(9, "ok")], timestamp=stamp)
    msg = zed.capture_message(sl, capture, "zed34")
    parsed = parse_message(json.dumps(msg))
    assert parsed.body_ids == (4, 9) and parsed.t == 2.0 and parsed.frame == "camera"
    empty = parse_message(zed.capture_message(sl, SimpleNamespace(body_list=[], timestamp=stamp), "zed34"))
    assert empty.bodies == ()


def test_the_replay_client_sends_several_clips_as_several_bodies(tmp_path: Path) -> None:
    from app.cell.human import save_clip

    client = _example("stream_replay_client")
    op = SimulatedOperator(CELL, seed=0, noise=False)
    clip = save_clip(tmp_path / "a.npz", [op.frame_at(k / FPS) for k in range(15)])
    msgs, fps, total = client.messages([clip, clip], loops=1, place=False, spacing_m=0.8)
    msgs = list(msgs)
    assert total == len(msgs) == 15 and fps == pytest.approx(30.0)
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    for k, m in enumerate(msgs):
        frame = src.push(json.dumps(m), t_received=k / FPS)
        assert frame.body_ids == (0, 1)
        np.testing.assert_allclose(
            frame.body(1).joints - frame.body(0).joints, [[0.0, 0.8, 0.0]] * 19, atol=1e-3
        )
    one, _, _ = client.messages(clip, loops=1, place=False)
    assert parse_message(next(iter(one))).body_ids == (0,)
