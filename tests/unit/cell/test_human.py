"""Human sources: the simulated operator (determinism, realism, reactions), replayed clips, pushed streams."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path

import numpy as np
import pytest

from app.cell.human import (
    HumanSource,
    OperatorParams,
    ReplaySource,
    SimulatedOperator,
    StreamSource,
    load_replay_clip,
    make_human_source,
    place_clip,
    save_clip,
)
from app.cell.operator_sim import OracleForecaster
from app.cell.population import DEFAULT_POPULATION_PATH
from app.cell.stream_protocol import make_message, message_from_zed_body, parse_message, send_messages
from app.cell.validation import CellVolume, FrameRejected, FrameValidator
from app.config import Settings, load_workcell
from app.prediction import adapters
from app.prediction.profiles import min_jerk
from app.prediction.skeleton import JOINT_INDEX, JOINTS, NUM_JOINTS, bone_lengths

CELL = load_workcell()
FPS = 30.0


def _run_operator(op: SimulatedOperator, seconds: float, notify: dict[int, str]) -> np.ndarray:
    """Frames (K, J, 3) at every frame time, notifying ``{frame index: station}``."""
    out = []
    for k in range(round(seconds * FPS)):
        if k in notify:
            op.notify_block_placed(notify[k], k / FPS)
        out.append(op.frame_at(k / FPS).joints)
    return np.stack(out)


# -- operator parameters ----------------------------------------------------------------------------------
def test_params_are_reproducible_and_vary_between_participants() -> None:
    assert OperatorParams.draw(7) == OperatorParams.draw(7)
    drawn = [OperatorParams.draw(s) for s in range(40)]
    heights = [p.height_m for p in drawn]
    assert min(heights) >= 1.5 and max(heights) <= 1.95 and np.std(heights) > 0.04
    assert {p.handedness for p in drawn} == {"left", "right"}
    assert all(1.0 <= p.hand_speed_mps <= 1.5 for p in drawn)
    assert len({round(p.reach_rate_hz, 6) for p in drawn}) == 40
    with pytest.raises(ValueError, match="height_m"):
        OperatorParams(height_m=3.0)
    with pytest.raises(ValueError, match="handedness"):
        OperatorParams(handedness="both")  # type: ignore[arg-type]


def test_min_jerk_profile() -> None:
    assert min_jerk(0.0) == 0.0 and min_jerk(1.0) == 1.0 and min_jerk(0.5) == pytest.approx(0.5)
    assert min_jerk(-1.0) == 0.0 and min_jerk(2.0) == 1.0


# -- simulated operator -----------------------------------------------------------------------------------
def test_simulated_operator_is_deterministic_under_a_seed_however_it_is_queried() -> None:
    notify = {30: "B", 200: "C", 330: "A"}
    a = SimulatedOperator(CELL, OperatorParams.draw(3), seed=3)
    frames_a = _run_operator(a, 15.0, notify)
    # the same participant queried at irregular times (100 Hz here, with gaps), same notifications
    b = SimulatedOperator(CELL, OperatorParams.draw(3), seed=3)
    got = {}
    t = 0.0
    pending = dict(notify)
    while t < 15.0:
        for k in [k for k in pending if k / FPS <= t]:
            b.notify_block_placed(pending.pop(k), k / FPS)
        f = b.frame_at(t)
        got[round(f.t * FPS)] = f.joints
        t += 0.01 if int(t * 10) % 3 else 0.137
    assert len(got) > 200
    for k, joints in got.items():
        if k < len(frames_a):
            np.testing.assert_array_equal(joints, frames_a[k])
    # another seed is another person
    c = SimulatedOperator(CELL, OperatorParams.draw(4), seed=4)
    assert not np.allclose(_run_operator(c, 15.0, notify), frames_a)


def test_the_oracle_forecast_is_the_operators_own_future_and_leaves_it_as_it_was() -> None:
    notify = {30: "B", 200: "C"}
    op = SimulatedOperator(CELL, OperatorParams.draw(5), seed=5)
    oracle = OracleForecaster(op, horizon=30, margin_m=0.02)
    forecasts = {}
    for k in range(round(10.0 * FPS)):
        if k in notify:
            op.notify_block_placed(notify[k], k / FPS)
        f = op.frame_at(k / FPS)
        if k % 7 == 0:
            forecasts[k] = oracle.update(f)
    # the operator, asked for its future ahead of time, still gives the frames of one that never was
    reference = _run_operator(SimulatedOperator(CELL, OperatorParams.draw(5), seed=5), 10.0, notify)
    np.testing.assert_array_equal(_run_operator(op, 10.0, {}), reference)
    exact = 0
    for k, fc in forecasts.items():
        assert fc.t0 == k / FPS and fc.joints.shape == (31, NUM_JOINTS, 3)
        np.testing.assert_allclose(fc.times - fc.t0, np.arange(31) / FPS, atol=1e-12)
        assert np.all(fc.margins == 0.02) and fc.growth_mps == 1.6
        upto = min(k + 31, len(reference))
        if not any(k < n <= upto for n in notify):  # no block placed within the horizon: exact
            np.testing.assert_array_equal(fc.joints[: upto - k], reference[k:upto])
            exact += 1
    assert exact == 34  # all but the 9 forecasts made less than a horizon before a placement
    with pytest.raises(ValueError, match="horizon"):
        OracleForecaster(op, horizon=0)
    with pytest.raises(ValueError, match="margin_m"):
        OracleForecaster(op, margin_m=math.nan)


def test_the_compiled_body_pose_equals_the_numpy_reference() -> None:
    """The operator's compiled pose function gives the NumPy reference's joints, for bodies of several
    heights, postures from upright to a deep twisted lean, and hands near and out of reach (protraction and
    the clamped two-link chains)."""
    from app.cell.operator_sim import _Body
    from app.cell.reference import body_pose_reference

    rng = np.random.default_rng(6)
    for i in range(400):
        body = _Body(float(rng.uniform(1.4, 2.1)))
        posture = np.array([rng.uniform(0.0, 1.35), rng.uniform(-0.5, 0.5), rng.uniform(0, 0.12), 0.0])
        lh = rng.uniform([-0.2, -0.6, 0.3], [1.2, 0.8, 1.6])
        rh = rng.uniform([-0.2, -0.8, 0.3], [1.2, 0.6, 1.6])
        if i % 50 == 0:
            lh = rh = np.array([0.0, 0.0, 5.0])  # far out of reach, straight up
        sway = rng.normal(0.0, 0.01, 3)
        np.testing.assert_allclose(
            body.pose(posture, lh, rh, sway),
            body_pose_reference(body, posture, lh, rh, sway),
            rtol=0,
            atol=1e-12,
        )


def test_frames_lie_on_the_30_hz_grid() -> None:
    op = SimulatedOperator(CELL, seed=1, t0=2.0)
    assert op.frame_at(1.99) is None
    f = op.frame_at(2.05)
    assert f.t == pytest.approx(2.0 + 1 / 30)
    assert op.frame_at(2.06) is f  # same frame until the next grid point
    assert op.frame_at(2.0 + 2 / 30).t == pytest.approx(2.0 + 2 / 30)
    assert isinstance(op, HumanSource)


@pytest.mark.parametrize("seed", [0, 5])
def test_simulated_motion_is_human_like(seed: int) -> None:
    op = SimulatedOperator(CELL, seed=seed, noise=False)
    notify = {k: "ABCD"[i % 4] for i, k in enumerate(range(15, 1200, 150))}
    joints = _run_operator(op, 40.0, notify)
    # a rigid skeleton (protraction of the shoulder on long reaches moves it by a few cm at most)
    bl = bone_lengths(joints)
    assert np.max(bl.max(axis=0) - bl.min(axis=0)) < 0.06
    # hands move like a person reaching: peaks of about 1-1.5 m/s, never jumps
    hands = joints[:, [JOINT_INDEX["l_hand"], JOINT_INDEX["r_hand"]]]
    speed = np.linalg.norm(np.diff(hands, axis=0), axis=-1) * FPS
    assert 0.9 < speed.max() < 1.8
    assert np.percentile(speed, 50) < 0.4  # mostly small assembling motions
    # the person stays standing in the operator area, feet on the floor, head up
    op_area = CELL.operator
    pelvis = joints[:, JOINT_INDEX["pelvis"]]
    assert np.all(np.abs(pelvis[:, :2] - op_area.center_xy) < np.asarray(op_area.size_xy) / 2 + 0.15)
    ankles = joints[:, [JOINT_INDEX["l_ankle"], JOINT_INDEX["r_ankle"]], 2]
    assert np.allclose(ankles, op_area.floor_z + ankles.min() - op_area.floor_z)  # planted
    assert np.all(joints[:, JOINT_INDEX["head"], 2] > CELL.table.center[2] + 0.3)
    # every frame passes the cell's validation
    v = FrameValidator.for_workcell(CELL)
    for k, j in enumerate(joints):
        v.validate(k / FPS, j)
    # it reaches into the shared area: a hand gets within 6 cm of every station it was called to
    for a in [a for a in op.actions if a.kind == "fetch"]:
        name = "l_hand" if a.hand == "left" else "r_hand"
        window = joints[math.ceil(a.t_start * FPS) : math.floor(a.t_end * FPS), JOINT_INDEX[name]]
        assert np.min(np.linalg.norm(window - np.array(a.target_world), axis=-1)) < 0.06


def test_operator_fetches_the_blocks_the_robot_placed() -> None:
    params = OperatorParams(reaction_s=0.5, assemble_s=1.0, reach_rate_hz=0.0)
    op = SimulatedOperator(CELL, params, seed=11, noise=False)
    _run_operator(op, 3.0, {})
    assert not [a for a in op.actions if a.kind == "fetch"]
    op.notify_block_placed("C", 3.0)
    assert op.pending_blocks() == []  # not seen before the operator's time reaches it
    for k in range(90, 300):
        op.frame_at(k / FPS)
    fetches = [a for a in op.actions if a.kind == "fetch"]
    assert [a.station for a in fetches] == ["C"]
    assert 3.5 <= fetches[0].t_start < 3.5 + 1.3  # after the reaction time, at the next decision point
    station = next(s for s in CELL.drop_stations if s.name == "C")
    np.testing.assert_allclose(fetches[0].target_world[:2], station.xyz[:2])
    assert fetches[0].hand == "right" if station.xyz[1] > 0 else "left"  # facing the robot: +y is their right
    with pytest.raises(ValueError, match="unknown drop station"):
        op.notify_block_placed("Z", 5.0)


def test_reach_depth_and_rate_shape_spontaneous_reaches() -> None:
    deep = SimulatedOperator(CELL, OperatorParams(reach_rate_hz=0.5, reach_depth=1.0), seed=2, noise=False)
    shallow = SimulatedOperator(CELL, OperatorParams(reach_rate_hz=0.5, reach_depth=0.0), seed=2, noise=False)
    never = SimulatedOperator(CELL, OperatorParams(reach_rate_hz=0.0), seed=2, noise=False)
    for op in (deep, shallow, never):
        op.hand_positions(40.0)  # plans the behaviour up to 40 s without building frames

    def reach_x(op: SimulatedOperator) -> list[float]:
        return [a.target_world[0] for a in op.actions if a.kind == "reach_across"]

    assert not reach_x(never)
    assert len(reach_x(deep)) >= 5 and len(reach_x(shallow)) >= 5
    # the robot is at x = 0, the person at x ~ 1.4: deeper reaches get closer to the robot
    assert np.mean(reach_x(deep)) < np.mean(reach_x(shallow)) - 0.1


# -- clips and replay -------------------------------------------------------------------------------------
def _sim_clip(tmp_path: Path, seconds: float = 2.0) -> Path:
    op = SimulatedOperator(CELL, seed=9, noise=False)
    frames = [op.frame_at(k / FPS) for k in range(round(seconds * FPS))]
    return save_clip(tmp_path / "rec.npz", frames)


def test_recordings_round_trip_and_replay_forth_and_back_without_a_jump(tmp_path: Path) -> None:
    path = _sim_clip(tmp_path)
    clip = load_replay_clip(path)
    assert clip.source == "canonical" and clip.joints.shape == (60, NUM_JOINTS, 3)
    assert clip.period_s == pytest.approx(2.0)
    src = ReplaySource(path, CELL, t0=10.0, place=False)
    span = 59 / 30  # first to last frame
    assert src.duration_s == pytest.approx(span)
    assert src.frame_at(9.9) is None
    f0 = src.frame_at(10.0)
    np.testing.assert_allclose(f0.joints, clip.joints[0], atol=1e-6)
    # after the last frame the clip plays backwards: the frame just after the turn is the one before the last
    back = src.frame_at(10.0 + span + 1 / 30 + 1e-6)
    assert back.t == pytest.approx(10.0 + span + 1 / 30)
    np.testing.assert_allclose(back.joints, clip.joints[-2])
    # and forwards again from the first frame after the second pass
    fwd = src.frame_at(10.0 + 2 * span + 1e-6)
    np.testing.assert_allclose(fwd.joints, clip.joints[0])
    # over many passes: timestamps increase and no frame-to-frame jump exceeds the clip's own largest step
    frames = [src.frame_at(10.0 + k / 30 + 1e-6) for k in range(400)]
    ts = np.array([f.t for f in frames])
    assert np.all(np.diff(ts) > 0) and ts[-1] > 10.0 + 6 * span
    step = lambda j: np.linalg.norm(np.diff(j, axis=0), axis=-1).max()  # noqa: E731
    assert step(np.stack([f.joints for f in frames])) <= step(clip.joints) + 1e-12
    held = ReplaySource(path, CELL, place=False, loop=False)
    assert held.frame_at(100.0).t == pytest.approx(59 / 30)  # the last frame, held: the stream goes stale


def test_placement_faces_the_robot_with_feet_on_the_floor(tmp_path: Path) -> None:
    path = _sim_clip(tmp_path)
    clip = load_replay_clip(path)
    # turn and move the recording somewhere else, then place it back
    c, s = math.cos(1.0), math.sin(1.0)
    moved = clip.joints @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T + np.array([5.0, -3.0, 0.4])
    placed = place_clip(moved, CELL)
    op = CELL.operator
    pelvis = placed[:, JOINT_INDEX["pelvis"]]
    np.testing.assert_allclose(pelvis[:, :2].mean(axis=0), op.center_xy, atol=1e-9)
    lr = placed[:, JOINT_INDEX["l_hip"]] - placed[:, JOINT_INDEX["r_hip"]]
    fwd = np.arctan2(-lr[:, 0], lr[:, 1]).mean()
    assert math.cos(fwd - op.facing_yaw) > 0.95
    ankles = placed[:, [JOINT_INDEX["l_ankle"], JOINT_INDEX["r_ankle"]], 2]
    assert np.percentile(ankles, 1) == pytest.approx(op.floor_z + 0.08)
    np.testing.assert_allclose(bone_lengths(placed), bone_lengths(clip.joints), atol=1e-9)


def test_cmu_clip_replays_in_the_operator_area(cmu_dir: Path) -> None:
    src = ReplaySource(cmu_dir / "test" / "washwindow_1.npz", CELL)
    assert src.clip.source == "cmu38"
    v = FrameValidator(volume=CellVolume.from_workcell(CELL))
    accepted = 0
    for k in range(0, 600, 3):
        f = src.frame_at(k / FPS)
        v.check(f)
        accepted += 1
    assert accepted == 200
    f = src.frame_at(src.duration_s + 0.001)
    assert f.t == pytest.approx(src.duration_s)  # the last frame, then backwards


def test_exported_clips_replay_as_recorded(tmp_path: Path) -> None:
    """The clips of ``hrc export --clips`` (canonical ``positions`` named in ``joint_names``) are read as the
    canonical recording they are, not as the CMU format (the replay source and ``hrc cell check``)."""
    rec = load_replay_clip(_sim_clip(tmp_path))
    np.savez_compressed(
        tmp_path / "exported.npz",
        positions=rec.joints.astype(np.float32),
        fps=np.float64(30.0),
        joint_names=np.array(JOINTS),
    )
    clip = load_replay_clip(tmp_path / "exported.npz")
    assert clip.source == "canonical" and clip.joints.shape == rec.joints.shape
    np.testing.assert_allclose(clip.joints, rec.joints, atol=1e-6)
    np.testing.assert_allclose(clip.times, rec.times)


def test_bad_clip_files_are_explained(tmp_path: Path) -> None:
    np.savez(tmp_path / "x.npz", foo=np.zeros(3))
    with pytest.raises(ValueError, match="neither 'positions'"):
        load_replay_clip(tmp_path / "x.npz")
    np.savez(tmp_path / "y.npz", positions=np.zeros((5, 20, 3)))
    with pytest.raises(ValueError, match=r"\(T, 38, 3\) or the canonical joints \(T, 19, 3\)"):
        load_replay_clip(tmp_path / "y.npz")
    np.savez(tmp_path / "z.npz", positions=np.zeros((5, 19, 3)), joint_names=np.array(["a"] * 19))
    with pytest.raises(ValueError, match="named in joint_names"):
        load_replay_clip(tmp_path / "z.npz")  # 19 joints of another skeleton
    with pytest.raises(ValueError, match="cannot read"):
        load_replay_clip(tmp_path / "missing.npz")


# -- stream -----------------------------------------------------------------------------------------------
def _canonical_pose() -> np.ndarray:
    op = SimulatedOperator(CELL, seed=0, noise=False)
    return op.frame_at(0.0).joints


def test_stream_accepts_canonical_messages_and_maps_sender_time() -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    pose = _canonical_pose()
    # the sender's clock is 1000 s ahead; delays vary between 5 and 20 ms
    for k, delay in enumerate([0.02, 0.005, 0.01, 0.015]):
        t_sender = 1000.0 + k / FPS
        frame = src.push(json.dumps(make_message(pose, t=t_sender)), t_received=t_sender - 1000.0 + delay)
    assert frame.t == pytest.approx(3 / FPS + 0.005)  # the least-delayed message sets the offset
    np.testing.assert_allclose(frame.joints, pose, atol=1e-4)
    assert src.frame_at(0.0) is None
    assert src.frame_at(0.06).t == pytest.approx(1 / FPS + 0.005)
    assert len(src.frames_after(0.05)) == 2
    # without t, the receive time is the frame time
    f = src.push(make_message(pose), t_received=5.0)
    assert f.t == 5.0
    assert src.counters["accepted"] == 5 and src.counters["received"] == 5


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda m: "{not json", "malformed"),
        (lambda m: json.dumps([1, 2]), "malformed"),
        (lambda m: {**m, "format": "kinect"}, "unknown_format"),
        (lambda m: {**m, "frame": "robot"}, "unknown_format"),
        (lambda m: {**m, "joints": m["joints"][:-1]}, "joint_count"),
        (lambda m: {**m, "confidence": [1.0] * 3}, "joint_count"),
        (lambda m: json.dumps(m).replace(str(m["joints"][3][0]), "NaN", 1), "non_finite"),
        (lambda m: json.dumps(m).replace(str(m["joints"][3][0]), "Infinity", 1), "non_finite"),
        (lambda m: {**m, "t": "yesterday"}, "bad_timestamp"),
        (lambda m: {**m, "joints": [[9.0, 0.0, 0.0]] * NUM_JOINTS}, "out_of_range"),
        (lambda m: {**m, "frame": "camera"}, "no_camera_pose"),
        (lambda m: {**m, "joints": [None] * NUM_JOINTS}, "missing_joints"),
    ],
)
def test_stream_rejects_bad_messages_with_a_reason(mutate: object, reason: str) -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    msg = make_message(_canonical_pose(), t=1.0)
    with pytest.raises(FrameRejected) as info:
        src.push(mutate(msg), t_received=1.0)  # type: ignore[operator]
    assert info.value.reason == reason
    assert src.counters[f"rejected_{reason}"] == 1
    assert src.frame_at(10.0) is None


def test_stream_rejects_duplicated_and_backwards_timestamps() -> None:
    src = StreamSource()
    pose = _canonical_pose()
    src.push(make_message(pose), t_received=1.0)
    with pytest.raises(FrameRejected, match="duplicate_timestamp"):
        src.push(make_message(pose), t_received=1.0)
    with pytest.raises(FrameRejected, match="backwards_timestamp"):
        src.push(make_message(pose), t_received=0.5)


def test_stream_fills_a_few_missing_joints_from_the_previous_frame() -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    pose = _canonical_pose()
    src.push(make_message(pose, t=0.0), t_received=0.0)
    moved = pose + np.array([0.05, 0.0, 0.0])
    moved[[14, 15, 17, 18]] = np.nan  # knees and ankles hidden behind the table
    f = src.push(make_message(moved, t=1 / FPS), t_received=1 / FPS)
    np.testing.assert_allclose(f.joints[14], pose[14], atol=1e-4)
    np.testing.assert_allclose(f.joints[0], moved[0], atol=1e-4)
    assert f.confidence[14] == 0.0 and f.confidence[0] == 1.0
    too_many = pose.copy()
    too_many[:8] = np.nan
    with pytest.raises(FrameRejected, match="missing_joints"):
        src.push(make_message(too_many, t=2 / FPS), t_received=2 / FPS)


def test_stream_converts_zed_bodies_in_the_camera_frame() -> None:
    rng = np.random.default_rng(0)
    kp = np.array([0.0, 2.0, 0.0]) + rng.normal(0.0, 0.3, size=(34, 3))  # camera frame, metres
    conf = rng.uniform(40, 100, size=34)
    kp[20] = np.nan  # a keypoint ZED did not detect
    conf[20] = np.nan
    T = np.eye(4)
    T[:3, 3] = [1.4, 0.0, 0.2]
    src = StreamSource(T_world_camera=T, max_missing_joints=NUM_JOINTS)
    src.push(make_message(_canonical_pose(), t=0.0), t_received=0.0)  # something to fill from
    msg = message_from_zed_body(kp, conf, t=1.0, body_format="zed34", units="m")
    assert msg["joints"][20] is None and msg["confidence"][20] == 0.0
    frame = src.push(json.dumps(msg), t_received=1.0)
    filled = np.nan_to_num(kp, nan=0.0)
    expected = adapters.from_zed34(filled) + T[:3, 3]
    missing = np.any((adapters.W_ZED34 > 0) & np.isnan(kp[:, 0])[None, :], axis=1)
    assert missing.any()
    np.testing.assert_allclose(frame.joints[~missing], expected[~missing], atol=2e-4)
    assert np.all(frame.confidence[missing] == 0.0)
    assert np.all(frame.confidence[~missing] > 0.39)
    # millimetres are scaled (a body 1.7 m tall, in mm)
    body_mm = np.full((38, 3), 1000.0)
    body_mm[:, 2] = np.linspace(0.0, 1700.0, 38)
    parsed = parse_message(make_message(body_mm, format="zed38", units="mm"))
    np.testing.assert_allclose(parsed.joints, body_mm / 1000.0, atol=1e-6)


def test_stream_queue_is_bounded_and_drops_the_oldest() -> None:
    src = StreamSource(max_queue=4)
    pose = _canonical_pose()
    for k in range(10):
        src.push(make_message(pose), t_received=float(k))
    assert src.counters["dropped"] == 6
    assert [f.t for f in src.frames_after(-1.0)] == [6.0, 7.0, 8.0, 9.0]
    src.reset()
    assert src.frame_at(100.0) is None and src.counters["accepted"] == 0


def test_make_human_source_follows_settings(tmp_path: Path) -> None:
    sim = make_human_source(Settings(human_source="sim"), CELL, seed=2)
    assert isinstance(sim, SimulatedOperator) and sim.params == OperatorParams.draw(2)
    population = tmp_path / "tall.toml"  # the participant is one of the settings' population
    population.write_text(
        DEFAULT_POPULATION_PATH.read_text().replace(
            "normal = { mean = 1.72, sd = 0.09, lo = 1.52, hi = 1.95 }", "uniform = { lo = 1.9, hi = 2.0 }"
        )
    )
    tall = make_human_source(Settings(human_source="sim", population=population), CELL, seed=2)
    assert tall.params == OperatorParams.draw(2, OperatorParams.population(population))
    assert 1.9 <= tall.params.height_m <= 2.0
    clip = _sim_clip(tmp_path, 0.5)
    src = make_human_source(Settings(human_source="replay", replay_clip=clip), CELL)
    assert isinstance(src, ReplaySource)
    assert isinstance(make_human_source(Settings(human_source="stream"), CELL), StreamSource)
    cam = make_human_source(Settings(human_source="stream", camera_pose=[1.4, 0.0, 0.2, 0.0, 0.0, 0.0]), CELL)
    assert isinstance(cam, StreamSource)
    msg = make_message(_canonical_pose() - np.array([1.4, 0.0, 0.2]), frame="camera", t=0.0)
    np.testing.assert_allclose(cam.push(msg, t_received=0.0).joints, _canonical_pose(), atol=2e-4)
    with pytest.raises(ValueError, match="HRC_REPLAY_CLIP"):
        make_human_source(Settings(human_source="replay"), CELL)


def test_send_messages_streams_to_a_websocket_with_the_token() -> None:
    from websockets.asyncio.server import serve

    received: list[dict] = []
    headers: list[str | None] = []

    async def handler(ws: object) -> None:
        headers.append(ws.request.headers.get("Authorization"))  # type: ignore[attr-defined]
        await ws.send(json.dumps({"type": "ready"}))  # type: ignore[attr-defined]
        async for raw in ws:  # type: ignore[attr-defined]
            msg = json.loads(raw)
            received.append(msg)
            if len(received) == 2:
                await ws.send(json.dumps({"type": "error", "code": "rejected", "detail": "x"}))  # type: ignore[attr-defined]

    async def main() -> dict[str, int]:
        async with serve(handler, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            msgs = [make_message(_canonical_pose(), t=k / FPS) for k in range(5)]
            return await send_messages(
                f"ws://127.0.0.1:{port}/api/ingest", msgs, token="secret-token", rate_hz=200.0
            )

    counts = asyncio.run(main())
    assert counts == {"sent": 5, "errors": 1}
    assert headers == ["Bearer secret-token"]
    assert [m["t"] for m in received] == pytest.approx([k / FPS for k in range(5)])
    assert parse_message(received[0]).format == "canonical"


def test_replay_client_example_builds_placed_timed_messages(tmp_path: Path) -> None:
    import importlib.util

    script = Path(__file__).resolve().parents[3] / "examples" / "stream_replay_client.py"
    spec = importlib.util.spec_from_file_location("stream_replay_client", script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    clip = _sim_clip(tmp_path, 1.0)
    msgs, fps, total = module.messages(clip, loops=2, place=False)
    msgs = list(msgs)
    assert fps == pytest.approx(30.0) and total == len(msgs) == 60
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    for k, m in enumerate(msgs):
        src.push(json.dumps(m), t_received=100.0 + k / FPS)  # every message is valid, in order
    assert src.counters["accepted"] == 60
    assert [m["t"] for m in msgs[28:32]] == pytest.approx([28 / 30, 29 / 30, 1.0, 31 / 30])


def test_a_validated_stream_is_not_checked_twice() -> None:
    from app.cell.validation import StaleWatchdog, ValidatedSource

    stream = StreamSource(validator=FrameValidator.for_workcell(CELL))
    wrapped = ValidatedSource(stream, validator=FrameValidator.for_workcell(CELL), watchdog=StaleWatchdog())
    pose = _canonical_pose()
    assert wrapped.poll(0.0) is None and wrapped.is_stale(0.0)
    stream.push(make_message(pose), t_received=0.0)
    with pytest.raises(FrameRejected):
        stream.push(make_message(pose + 10.0), t_received=0.01)
    assert wrapped.poll(0.02).t == 0.0
    assert wrapped.poll(0.03) is None  # nothing new
    assert not wrapped.is_stale(0.1) and wrapped.is_stale(0.2)
    counters = wrapped.counters
    assert counters["accepted"] == 1 and counters["rejected_out_of_range"] == 1 and counters["received"] == 2


def _nested(depth: int) -> str:
    return "[" * depth + "]" * depth


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda m: {**m, "confidence": [5.0] * NUM_JOINTS}, "bad_confidence"),
        (lambda m: {**m, "confidence": [93] * NUM_JOINTS}, "bad_confidence"),  # ZED's 0..100, not divided
        (lambda m: {**m, "confidence": [-3] * NUM_JOINTS}, "bad_confidence"),
        (lambda m: {**m, "confidence": ["0.5"] * NUM_JOINTS}, "malformed"),
        (lambda m: {**m, "confidence": [True] * NUM_JOINTS}, "malformed"),
        (lambda m: {**m, "confidence": [0.1] * NUM_JOINTS}, "no_valid_joint"),
        (lambda m: {**m, "t": True}, "bad_timestamp"),
        (lambda m: {**m, "t": 1e308}, "bad_timestamp"),
        (lambda m: {**m, "t": 10**400}, "bad_timestamp"),
        (lambda m: json.dumps(m).replace('"t": 1.0', '"t": 1' + "0" * 400), "bad_timestamp"),
        (lambda m: {**m, "joints": [[10**400, 0, 0], *m["joints"][1:]]}, "out_of_range"),
        (lambda m: {**m, "confidence": [10**400] * NUM_JOINTS}, "bad_confidence"),
        (lambda m: {**m, "format": [1]}, "unknown_format"),
        (lambda m: {**m, "frame": {"a": 1}}, "unknown_format"),
        (lambda m: {**m, "units": "mm"}, "wrong_units"),  # metres sent as millimetres
        (lambda m: {**m, "joints": [[1000 * v for v in p] for p in m["joints"]]}, "wrong_units"),  # mm as m
        (lambda m: {**m, "joints": [[True, 0.0, 1.0]] * NUM_JOINTS}, "malformed"),
        (lambda m: _nested(20_000), "malformed"),  # 40 kB of nested lists: refused before parsing
        (lambda m: '{"joints": ' + _nested(5_000) + "}", "malformed"),
        (lambda m: {**m, "type": ["frame"]}, "malformed"),
    ],
)
def test_stream_checks_every_value_as_sent_and_counts_the_rejection(mutate: object, reason: str) -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    msg = make_message(_canonical_pose(), t=1.0)
    with pytest.raises(FrameRejected) as info:
        src.push(mutate(msg), t_received=1.0)  # type: ignore[operator]
    assert info.value.reason == reason, info.value
    counters = src.counters
    assert (counters["rejected"], counters[f"rejected_{reason}"], counters["received"]) == (1, 1, 1)
    assert src.push(msg, t_received=1.0).t == 1.0  # the stream goes on


def test_stream_rejects_a_sender_clock_that_goes_back_until_it_stays_back() -> None:
    src = StreamSource(validator=FrameValidator.for_workcell(CELL))
    pose = _canonical_pose()
    src.push(make_message(pose, t=100.0), t_received=10.0)
    src.push(make_message(pose, t=100.1), t_received=10.1)
    for k, back_s in enumerate((1.5, 10.0, 1000.0)):  # not a "clock jump" to re-estimate: rejected
        with pytest.raises(FrameRejected) as info:
            src.push(make_message(pose, t=100.1 - back_s), t_received=10.2 + 0.1 * k)
        assert info.value.reason == "backwards_timestamp" and "before the previous" in info.value.detail
    assert src.counters["rejected_backwards_timestamp"] == 3
    assert src.frame_at(1e9).t == pytest.approx(10.1)
    # a sender whose clock restarted (it stays back for REBASE_AFTER_S): the offset is estimated again
    frame = src.push(make_message(pose, t=5.0), t_received=10.2 + src.REBASE_AFTER_S)
    assert frame.t == pytest.approx(10.2 + src.REBASE_AFTER_S)
    assert src.push(make_message(pose, t=5.1), t_received=11.3).t == pytest.approx(frame.t + 0.1)
