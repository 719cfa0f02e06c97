"""Clips are identified by split and name (app.prediction.data): names repeat across split folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.prediction.data import Clip, ClipError, check_disjoint, load_clip_dir, split_clips
from app.prediction.skeleton import JOINTS, NUM_JOINTS


def _write(path: Path, offset: float, frames: int = 50) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    positions = np.full((frames, NUM_JOINTS, 3), offset)
    np.savez(path, positions=positions, fps=30.0, joint_names=np.array(JOINTS))


@pytest.fixture
def repeated_names(tmp_path: Path) -> Path:
    """``train/walk_1`` and ``test/walk_1``: different recordings under one name."""
    _write(tmp_path / "train" / "walk_1.npz", 0.0)
    _write(tmp_path / "train" / "walk_2.npz", 1.0)
    _write(tmp_path / "test" / "walk_1.npz", 2.0)
    return tmp_path


def test_clips_are_keyed_by_split_and_name(repeated_names: Path) -> None:
    clips = load_clip_dir(repeated_names)
    assert [c.key for c in clips] == [("test", "walk_1"), ("train", "walk_1"), ("train", "walk_2")]
    assert [c.label for c in clips] == ["test/walk_1", "train/walk_1", "train/walk_2"]
    by_key = {c.key: c for c in clips}
    assert by_key["test", "walk_1"].positions[0, 0, 0] == 2.0  # each key its own recording
    assert by_key["train", "walk_1"].positions[0, 0, 0] == 0.0
    assert [c.key for c in load_clip_dir(repeated_names, split="test")] == [("test", "walk_1")]


def test_the_index_file_gives_the_split_too(repeated_names: Path) -> None:
    (repeated_names / "index.json").write_text(
        '[{"file": "train/walk_1.npz", "action": "walk"}, {"file": "test/walk_1.npz", "action": "walk"}]'
    )
    assert [c.key for c in load_clip_dir(repeated_names)] == [("test", "walk_1"), ("train", "walk_1")]


def test_validation_clips_are_chosen_by_key(repeated_names: Path) -> None:
    clips = load_clip_dir(repeated_names)
    train, val = split_clips(clips, ["train/walk_1"])
    assert [c.key for c in val] == [("train", "walk_1")]
    assert ("test", "walk_1") in [c.key for c in train]
    # a bare name that several splits share is refused, not silently applied to both
    with pytest.raises(ClipError, match=r"walk_1.*split/name"):
        split_clips(clips, ["walk_1"])
    # a unique bare name still works (the shipped validation list)
    assert [c.key for c in split_clips(clips, ["walk_2"])[1]] == [("train", "walk_2")]


def test_training_and_evaluation_never_share_a_clip(repeated_names: Path) -> None:
    train_set = load_clip_dir(repeated_names, split="train")
    test_set = load_clip_dir(repeated_names, split="test")
    check_disjoint(train=train_set, test=test_set)  # same name, different splits: distinct clips
    with pytest.raises(ClipError, match="train/walk_1 is in train and test"):
        check_disjoint(train=train_set, test=[*test_set, train_set[0]])
    same = Clip(name="walk_1", positions=np.zeros((5, NUM_JOINTS, 3)), split="train")
    with pytest.raises(ClipError, match="in train and train"):
        check_disjoint(train=[*train_set, same])


def test_train_refuses_a_clip_in_two_sets(repeated_names: Path, tmp_path: Path) -> None:
    from app.prediction.train import TrainConfig, train

    clips = load_clip_dir(repeated_names, split="train")
    with pytest.raises(ClipError, match="must not share"):
        train(clips, clips[:1], TrainConfig(steps=1), out=tmp_path / "w.pt")
