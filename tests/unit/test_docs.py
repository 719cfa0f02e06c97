"""The README stays a page for users and the docs site stays true to the code: the settings page is the one
generated from ``Settings``, every page the site names exists, no measurement history sits in the README."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_the_settings_page_is_generated_from_the_settings() -> None:
    out = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "settings_doc.py"), "--check"], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    page = (ROOT / "docs" / "settings.md").read_text()
    from app.config import Settings

    for name in Settings.model_fields:
        assert f"`HRC_{name.upper()}`" in page


def test_the_readme_is_short_and_for_users() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) < 300
    for phrase in ("this round", "last round"):
        assert phrase not in text.lower()
    # every local link of the README points to a file that exists
    for target in re.findall(r"\]\(((?!https?://|#)[^)]+)\)", text):
        assert (ROOT / target.split("#")[0]).exists(), target


def test_every_page_of_the_site_exists() -> None:
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    pages = [next(iter(item.values())) for item in config["nav"]]
    for page in pages:
        assert (ROOT / "docs" / page).is_file(), page
