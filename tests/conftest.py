"""Shared fixtures: where the optional shared data lives, and skip helpers."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = REPO_ROOT.parent / "shared"
CMU_DIR = SHARED_DIR / "data" / "cmu_mocap"


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    """The recorded CMU clips; tests that use them skip cleanly where ``../shared`` is absent."""
    if not (CMU_DIR / "index.json").is_file():
        pytest.skip(f"recorded CMU clips not found at {CMU_DIR}")
    return CMU_DIR
