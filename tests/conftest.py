"""Shared fixtures: where the optional shared data lives, skip helpers, and a fixed terminal.

Every test sees the same plain, wide terminal (``COLUMNS=200``, no colour), whatever the terminal of whoever
runs them: the command-line tests assert exit codes and short tokens, never how rich wraps a line. A test
about a narrow terminal sets its own ``COLUMNS``.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = REPO_ROOT.parent / "shared"
CMU_DIR = SHARED_DIR / "data" / "cmu_mocap"

#: The terminal every test runs in (set before any test module imports rich).
FIXED_TERMINAL = {"COLUMNS": "200", "LINES": "50", "NO_COLOR": "1", "TERM": "dumb"}


def pytest_configure(config: pytest.Config) -> None:
    os.environ.update(FIXED_TERMINAL)
    for name in ("FORCE_COLOR", "CLICOLOR_FORCE"):
        os.environ.pop(name, None)


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    """The recorded CMU clips; tests that use them skip cleanly where ``../shared`` is absent."""
    if not (CMU_DIR / "index.json").is_file():
        pytest.skip(f"recorded CMU clips not found at {CMU_DIR}")
    return CMU_DIR
