from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from app.cli import app as cli_app
from app.prediction.adapters import CMU38_NAMES
from app.prediction.data import (
    Augmentation,
    Clip,
    ClipError,
    WindowSampler,
    load_clip,
    load_clip_dir,
    mirror,
    resample,
    rotate_z,
    windows,
)
from app.prediction.evaluate import HORIZONS_MS, error_quantiles, mpjpe_at_horizons
from app.prediction.graphmixer import GraphMixerConfig
from app.prediction.predictor import MotionPredictor, load_graphmixer
from app.prediction.skeleton import JOINT_INDEX, JOINTS, NUM_JOINTS, bone_lengths
from app.prediction.train import TrainConfig, train

torch.set_num_threads(1)
TINY = GraphMixerConfig(channels=8, blocks=1, embed_dim=4)


def _synthetic(seed: int, frames: int = 90) -> np.ndarray:
    """A person walking in a straight line at 0.5-1.5 m/s with a swinging arm: (T, J, 3) at 30 Hz."""
    rng = np.random.default_rng(seed)
    base = rng.normal(scale=0.15, size=(NUM_JOINTS, 3)) + np.array([0.0, 0.0, 1.0])
    base[JOINT_INDEX["l_hip"]] = [0.0, 0.1, 0.9]
    base[JOINT_INDEX["r_hip"]] = [0.0, -0.1, 0.9]
    heading = rng.uniform(-np.pi, np.pi)
    speed = rng.uniform(0.5, 1.5)
    t = np.arange(frames) / 30.0
    pos = np.repeat(base[None], frames, axis=0)
    pos[:, JOINT_INDEX["r_hand"], 2] += 0.2 * np.sin(4.0 * t)
    pos = rotate_z(pos[None], np.array([heading]))[0]
    pos += speed * t[:, None, None] * np.array([np.cos(heading), np.sin(heading), 0.0])
    return pos


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("clips")
    for split, seeds in (("train", range(6)), ("test", range(10, 12))):
        (root / split).mkdir()
        for s in seeds:
            np.savez(
                root / split / f"walk_{s}.npz",
                positions=_synthetic(s),
                fps=30.0,
                joint_names=np.array(JOINTS),
            )
    return root


def _cfg(**kw) -> TrainConfig:
    base = {
        "steps": 40,
        "batch": 8,
        "lr": 5e-3,
        "warmup": 5,
        "eval_every": 10,
        "patience": 10,
        "max_minutes": None,
    }
    base.update(kw)
    return TrainConfig(model=TINY, augmentation=Augmentation(translate_m=1.0), **base)


def _split(clip_dir: Path):
    clips = load_clip_dir(clip_dir, split="train")
    return clips[:5], clips[5:]


# ------------------------------------------------------------------------------------------------ data


def test_load_clip_formats(tmp_path: Path) -> None:
    pos = _synthetic(0, frames=60)
    np.savez(tmp_path / "c60.npz", positions=pos[::1], fps=60.0, joint_names=np.array(JOINTS))
    clip = load_clip(tmp_path / "c60.npz")
    assert clip.frames == 30  # 60 frames at 60 Hz -> 30 frames at 30 Hz
    np.testing.assert_allclose(clip.positions[1], pos[2])
    cmu = np.zeros((5, 38, 3))
    cmu[:, 0] = [1.0, 2.0, 1.0]
    np.savez(tmp_path / "cmu.npz", positions=cmu, fps=30.0, joint_names=np.array(CMU38_NAMES))
    assert load_clip(tmp_path / "cmu.npz").positions.shape == (5, NUM_JOINTS, 3)
    np.savez(
        tmp_path / "odd.npz", positions=np.zeros((5, 7, 3)), fps=30.0, joint_names=np.array(list("abcdefg"))
    )
    with pytest.raises(ClipError, match="unknown joint set"):
        load_clip(tmp_path / "odd.npz")
    bad = pos.copy()
    bad[3, 2, 1] = np.nan
    np.savez(tmp_path / "nan.npz", positions=bad, fps=30.0, joint_names=np.array(JOINTS))
    with pytest.raises(ClipError, match="NaN"):
        load_clip(tmp_path / "nan.npz")
    with pytest.raises(ClipError, match="does not exist"):
        load_clip_dir(tmp_path / "nowhere")


def test_one_reader_for_every_clip_file(tmp_path: Path) -> None:
    """Training and replay read clip files with one reader: a canonical recording with its own frame times
    (the app's recordings) trains at 30 Hz, interpolated; the replay loader sees the same joints at the
    recorded times; a recording of another skeleton is refused by both, naming the file."""
    from app.cell.human import load_replay_clip
    from app.prediction.data import read_clip_file

    pos = _synthetic(1, frames=31)  # 30 Hz, 1 s
    t = np.sort(np.random.default_rng(0).uniform(0.0, 1.0, 29))
    t = np.concatenate([[0.0], t, [1.0]]) + 5.0  # irregular frame times, as a tracker delivers them
    rec = np.stack(
        [np.interp(t - 5.0, np.arange(31) / 30, pos[:, j, a]) for j in range(NUM_JOINTS) for a in range(3)]
    )
    rec = rec.T.reshape(31, NUM_JOINTS, 3)
    np.savez(tmp_path / "rec.npz", t=t, joints=rec, joint_names=np.array(JOINTS))
    f = read_clip_file(tmp_path / "rec.npz")
    assert f.source == "canonical" and not f.uniform
    np.testing.assert_allclose(f.times, t - 5.0)
    replay = load_replay_clip(tmp_path / "rec.npz")
    np.testing.assert_allclose(replay.times, f.times)
    np.testing.assert_allclose(replay.joints, rec)
    train_clip = load_clip(tmp_path / "rec.npz")
    assert train_clip.frames == 31  # 0 .. 1 s at 30 Hz
    np.testing.assert_allclose(
        train_clip.positions, pos, atol=0.05
    )  # linear interpolation of a smooth motion
    np.testing.assert_allclose(train_clip.positions[0], rec[0])
    np.testing.assert_allclose(train_clip.positions[-1], rec[-1])
    np.savez(tmp_path / "other.npz", t=np.arange(3) / 30, joints=np.zeros((3, 38, 3)))
    for loader in (load_clip, load_replay_clip, read_clip_file):
        with pytest.raises(ClipError, match=r"other\.npz: unknown joint set"):
            loader(tmp_path / "other.npz")
    np.savez(tmp_path / "back.npz", t=np.array([0.0, 0.1, 0.05]), joints=np.zeros((3, NUM_JOINTS, 3)))
    with pytest.raises(ClipError, match="strictly increasing"):
        load_clip(tmp_path / "back.npz")


def test_a_clip_in_millimetres_is_refused_by_the_one_reader(tmp_path: Path) -> None:
    from app.cell.human import load_replay_clip
    from app.prediction.data import read_clip_file

    pos = _synthetic(2, frames=30)
    np.savez(tmp_path / "mm.npz", positions=pos * 1000.0, fps=30.0, joint_names=np.array(JOINTS))
    for loader in (load_clip, load_replay_clip, read_clip_file):
        with pytest.raises(ClipError, match=r"mm\.npz.*millimetres"):
            loader(tmp_path / "mm.npz")
    np.savez(tmp_path / "m.npz", positions=pos, fps=30.0, joint_names=np.array(JOINTS))
    assert read_clip_file(tmp_path / "m.npz").joints.shape == pos.shape


def test_clip_dir_splits(clip_dir: Path) -> None:
    assert [c.name for c in load_clip_dir(clip_dir, split="test")] == ["walk_10", "walk_11"]
    assert len(load_clip_dir(clip_dir)) == 8


def test_augmentations_keep_bone_lengths() -> None:
    pos = _synthetic(3)[None]
    lengths = bone_lengths(pos)
    np.testing.assert_allclose(mirror(mirror(pos)), pos)
    # the same bones, left and right swapped
    np.testing.assert_allclose(np.sort(bone_lengths(mirror(pos)), -1), np.sort(lengths, -1), atol=1e-12)
    rotated = rotate_z(pos, np.array([0.7]))
    np.testing.assert_allclose(bone_lengths(rotated), lengths, atol=1e-12)
    np.testing.assert_allclose(rotated[..., 2], pos[..., 2])
    # mirroring swaps the sides: the mirrored left hip is the reflected right hip
    m = mirror(pos)
    np.testing.assert_allclose(m[0, 0, JOINT_INDEX["l_hip"]], pos[0, 0, JOINT_INDEX["r_hip"]] * [1, -1, 1])


def test_resample_speed() -> None:
    pos = _synthetic(1, frames=61)
    fast = resample(pos, 2.0)
    assert fast.shape[0] == 31
    np.testing.assert_allclose(fast[5], pos[10])
    slow = resample(pos, 0.5)
    np.testing.assert_allclose(slow[1], 0.5 * (pos[0] + pos[1]))


def test_work_cell_augmentation_slows_and_pauses_the_motion() -> None:
    # a clip moving at exactly 1 m/s along x: the sampled window's speed is the playback rate
    pos = np.zeros((400, NUM_JOINTS, 3))
    pos[..., 0] = (np.arange(400) / 30.0)[:, None]
    clips = [Clip(name="line", positions=pos, action="walk")]
    plain = {"rotate": False, "translate_m": 0.0, "mirror_p": 0.0}

    def speeds(aug: Augmentation) -> np.ndarray:  # (windows, frames - 1) m/s of the pelvis
        w = WindowSampler(clips, 40, augmentation=aug, seed=0).sample(64)
        return np.diff(w[:, :, 0, 0], axis=1) * 30.0

    slow = speeds(Augmentation(**plain, slow_p=1.0, pause_p=0.0))
    assert np.all(slow > 0.3 - 1e-9) and np.all(slow < 0.8 + 1e-9)
    assert np.ptp(slow, axis=1).max() < 1e-9  # one rate per window
    paused = speeds(Augmentation(**plain, slow_p=0.0, pause_p=1.0))
    at_rest = paused < 1e-9
    # every window slows down; most come to rest (a pause drawn near the window's end is cut before it)
    assert np.all(paused.min(axis=1) < paused.max(axis=1) - 1e-9) and at_rest.any(axis=1).mean() > 0.8
    runs = [np.flatnonzero(r) for r in at_rest if r.any()]
    assert all(np.all(np.diff(r) == 1) for r in runs)  # one pause per window
    assert max(r.size for r in runs) >= 20  # pauses of up to 30 frames at rest
    # it slows down smoothly: no step changes the speed by more than 0.31 of the playback rate (9.3 m/s^2
    # at 1 m/s, within the 12 m/s^2 a person's speed may change by)
    assert np.abs(np.diff(paused, axis=1)).max() <= 0.31 * 1.25 + 1e-9
    plain_rate = speeds(Augmentation(**plain, slow_p=0.0, pause_p=0.0))
    assert np.all(plain_rate > 0.8 - 1e-9) and np.all(plain_rate < 1.25 + 1e-9)


def test_window_sampler_is_seeded(clip_dir: Path) -> None:
    clips = load_clip_dir(clip_dir, split="train")
    a = WindowSampler(clips, 40, augmentation=Augmentation(), seed=3).sample(4)
    b = WindowSampler(clips, 40, augmentation=Augmentation(), seed=3).sample(4)
    c = WindowSampler(clips, 40, augmentation=Augmentation(), seed=4).sample(4)
    assert a.shape == (4, 40, NUM_JOINTS, 3)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    # rotation and translation are horizontal: the heights stay those of the synthetic clips
    assert a[..., 2].min() > 0.0 and a[..., 2].max() < 2.0
    assert windows(clips, 40, stride=10).shape == (6 * 6, 40, NUM_JOINTS, 3)


# ------------------------------------------------------------------------------------------------ eval


def test_mpjpe_at_horizons_interpolates() -> None:
    N, H = 3, 30
    last = np.zeros((N, NUM_JOINTS, 3))
    target = np.zeros((N, H, NUM_JOINTS, 3))
    # the error grows linearly, 1 m per second, along x
    pred = target.copy()
    pred[..., 0] = (np.arange(1, H + 1) / 30.0)[None, :, None]
    res = mpjpe_at_horizons(last, pred, target, fps=30.0)
    assert list(res) == [str(ms) for ms in HORIZONS_MS]
    for ms in HORIZONS_MS:
        assert res[str(ms)] == pytest.approx(ms, abs=1e-6)
    q = error_quantiles(pred, target)
    assert len(q["p95"]) == H + 1 and q["p95"][0] == 0.0
    assert q["p95"][30] == pytest.approx(1.0)


# ------------------------------------------------------------------------------------------------ train


def test_training_writes_weights_card_and_quantiles(clip_dir: Path, tmp_path: Path) -> None:
    tr, val = _split(clip_dir)
    res = train(
        tr,
        val,
        _cfg(),
        out=tmp_path / "m.pt",
        test_clips=load_clip_dir(clip_dir, split="test"),
        progress=False,
    )
    assert res.weights.is_file() and res.card.is_file() and res.quantiles.is_file()
    assert res.steps == 40 and res.stopped == "steps"
    # learned to walk: better than holding the last pose over the whole horizon on held-out clips
    gm = res.metrics["validation"]["graphmixer"]["mpjpe_mm"]["1000"]
    zv = res.metrics["validation"]["zero_velocity"]["mpjpe_mm"]["1000"]
    assert gm < 0.8 * zv
    q = json.loads(res.quantiles.read_text())
    assert set(q["kinds"]) == {"graphmixer", "constant_velocity", "zero_velocity"}
    assert len(q["kinds"]["graphmixer"]["p95"]) == 31
    card = res.card.read_text()
    assert "| graphmixer |" in card and "Test" in card and "seed 0" in card
    p = MotionPredictor(weights=res.weights)
    assert p.effective_kind == "graphmixer"
    np.testing.assert_allclose(p.margins_for("graphmixer"), q["kinds"]["graphmixer"]["p95"])
    assert (tmp_path / "checkpoints" / "last.pt").is_file()


def test_training_is_seeded(clip_dir: Path, tmp_path: Path) -> None:
    tr, val = _split(clip_dir)
    cfg = _cfg(steps=12, eval_every=6)
    a = train(tr, val, cfg, out=tmp_path / "a.pt", progress=False)
    b = train(tr, val, cfg, out=tmp_path / "b.pt", progress=False)
    sa, sb = load_graphmixer(a.weights).model.state_dict(), load_graphmixer(b.weights).model.state_dict()
    for k in sa:
        torch.testing.assert_close(sa[k], sb[k], rtol=0, atol=0)


def test_early_stopping_and_resume(clip_dir: Path, tmp_path: Path) -> None:
    tr, val = _split(clip_dir)
    stuck = train(tr, val, _cfg(lr=0.0, patience=2, eval_every=5), out=tmp_path / "s.pt", progress=False)
    assert stuck.stopped == "early_stopping" and stuck.steps == 15
    first = train(
        tr, val, _cfg(steps=10), out=tmp_path / "r.pt", checkpoint_dir=tmp_path / "ck", progress=False
    )
    assert first.steps == 10
    second = train(
        tr,
        val,
        _cfg(steps=10),
        out=tmp_path / "r.pt",
        checkpoint_dir=tmp_path / "ck",
        resume=True,
        progress=False,
    )
    assert second.steps == 10  # already done: nothing left to train
    with pytest.raises(ValueError, match="other settings"):
        train(
            tr,
            val,
            _cfg(steps=10, batch=4),
            out=tmp_path / "r.pt",
            checkpoint_dir=tmp_path / "ck",
            resume=True,
        )


# ------------------------------------------------------------------------------------------------ cli


def test_cli_train_and_eval(clip_dir: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "cli.pt"
    r = runner.invoke(
        cli_app,
        ["hmp", "train", "--clips", str(clip_dir), "--val-clips", "walk_5", "--steps", "6",
         "--eval-every", "3", "--channels", "8", "--blocks", "1", "--out", str(out),
         "--sim-train-operators", "1", "--sim-train-duration", "3",
         "--checkpoint-dir", str(tmp_path / "ck"), "--no-progress"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    assert out.is_file() and out.with_suffix(".md").is_file()
    # one network on every source: the clips and simulated operators, each validated on its own held-out part
    info = load_graphmixer(out).meta["info"]
    assert info["sources"] == ["cmu", "sim"] and info["left_out"] is None
    assert "sim_train/sim_operator_2000" in info["train_clips"]
    assert {"sim_val/sim_operator_2001", "sim_val/sim_operator_2002"} <= set(info["val_clips"])
    r = runner.invoke(cli_app, ["hmp", "eval", "--clips", str(clip_dir), "--weights", str(out), "--json"])
    assert r.exit_code == 0, r.output
    report = json.loads(r.output)
    assert set(report["mpjpe_mm"]) == {"graphmixer", "constant_velocity", "zero_velocity"}
    assert report["windows"] == 2 * (90 - 40 + 1)
    # the model card gets the same numbers as a section of its own, replaced (not repeated) on a new run
    card = out.with_suffix(".md")
    args = ["hmp", "eval", "--clips", str(clip_dir), "--weights", str(out), "--json", "--card", str(card)]
    for _ in range(2):
        assert runner.invoke(cli_app, args).exit_code == 0
    text = card.read_text()
    assert (
        text.startswith("# Model card") and text.count(f"<!-- hrc hmp eval: {clip_dir.name} (test) -->") == 1
    )
    cv = report["mpjpe_mm"]["constant_velocity"]["1000"]
    assert "| constant_velocity | " in text and f"{cv:.1f} |" in text and "| coverage (target 0.95) |" in text
    r = runner.invoke(cli_app, [*args[:-1], str(tmp_path / "no" / "card.md")])
    assert r.exit_code == 2 and "does not exist" in r.output
    # constant velocity is exact on straight walking, except for the swinging hand
    assert report["mpjpe_mm"]["constant_velocity"]["1000"] < report["mpjpe_mm"]["zero_velocity"]["1000"]
    r = runner.invoke(cli_app, ["hmp", "eval", "--clips", str(tmp_path / "missing")])
    assert r.exit_code == 2 and "does not exist" in r.output
    # wrong weights are refused, never silently replaced by constant velocity
    wrong = tmp_path / "wrong.pt"
    r = runner.invoke(cli_app, ["hmp", "eval", "--clips", str(clip_dir), "--weights", str(wrong), "--json"])
    assert r.exit_code != 0 and "wrong.pt" in r.output and "not found" in r.output
    wrong.write_bytes(b"not a checkpoint")
    r = runner.invoke(cli_app, ["hmp", "eval", "--clips", str(clip_dir), "--weights", str(wrong), "--json"])
    assert r.exit_code != 0 and "cannot read Graph-Mixer weights" in r.output


def test_cli_leave_one_source_out(clip_dir: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "no_cmu.pt"
    r = runner.invoke(
        cli_app,
        ["hmp", "train", "--leave-out", "cmu", "--sim-train-operators", "1", "--sim-train-duration", "3",
         "--steps", "4", "--eval-every", "2", "--channels", "8", "--blocks", "1", "--out", str(out),
         "--checkpoint-dir", str(tmp_path / "ck"), "--no-progress"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    info = load_graphmixer(out).meta["info"]
    assert info["left_out"] == "cmu" and info["sources"] == ["sim"]
    assert all(c.startswith("sim_train/") for c in info["train_clips"]) and info["test_clips"] == []
    assert info["val_clips"] == ["sim_val/sim_operator_2001", "sim_val/sim_operator_2002"]
    args = ["hmp", "eval", "--leave-out", "cmu", "--clips", str(clip_dir), "--weights", str(out), "--json"]
    r = runner.invoke(cli_app, args)
    assert r.exit_code == 0, r.output
    report = json.loads(r.output)
    assert report["left_out"] == "cmu" and report["trained_on"] == ["sim"]
    assert report["clips"].endswith("(test)") and set(report["forecast"]["margin_mm"]) == set(
        report["forecast"]["coverage"]
    )
    # weights that may have seen the source are refused, and so are unknown sources and missing weights
    r = runner.invoke(cli_app, ["hmp", "eval", "--leave-out", "sim", "--weights", str(out)])
    assert r.exit_code == 2 and "was not trained with --leave-out sim" in r.output
    r = runner.invoke(cli_app, ["hmp", "eval", "--leave-out", "mocap"])
    assert r.exit_code == 2 and "unknown source 'mocap'" in r.output
    r = runner.invoke(cli_app, ["hmp", "eval", "--leave-out", "cmu", "--weights", str(tmp_path / "none.pt")])
    assert r.exit_code == 2 and "none.pt" in r.output and "hrc hmp train --leave-out cmu" in r.output
    r = runner.invoke(cli_app, ["hmp", "train", "--leave-out", "cmu", "--sim-train-seed", "1990"])
    assert r.exit_code == 2 and "tuning seeds" in r.output


def test_cli_eval_without_clips_says_what_to_do(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HRC_CMU_DIR", str(tmp_path / "no_cmu_here"))
    r = CliRunner().invoke(cli_app, ["hmp", "eval"])
    assert r.exit_code == 2
    assert "CMU clips were not found" in r.output and "--clips" in r.output
