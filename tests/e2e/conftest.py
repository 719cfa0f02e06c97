"""End-to-end fixtures: a real ``hrc serve`` subprocess and a real headless Chromium driven by Playwright.

The server runs on free ports with a temporary data directory (its own SQLite database) and a known token;
the browser is Debian's Chromium (``/usr/bin/chromium``, or ``HRC_CHROMIUM``), never a downloaded one. Tests
skip with a clear reason when the browser or Playwright is missing. Screenshots go to ``test-artifacts/``.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.bench.served import CHROMIUM_ARGS, ServeProcess
from app.bench.served import chromium_path as _chromium_path

REPO_ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = REPO_ROOT / "test-artifacts"
TOKEN = "e2e-operator-token-0123456789abcdef"
#: Longest wait for the server's first health answer (migrations, roadmap build or cache load, runtime start).
SERVER_START_TIMEOUT_S = 180.0


class HrcServer(ServeProcess):
    """A running ``hrc serve``: where it listens, its token and its log, and REST calls with the token."""

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}

    def api(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """A REST call with the token (for set-up and for checks beside the browser)."""
        headers = {**self.headers, **kwargs.pop("headers", {})}
        timeout = kwargs.pop("timeout", 30.0)
        return httpx.request(method, f"{self.base_url}{path}", headers=headers, timeout=timeout, **kwargs)


@pytest.fixture(scope="session")
def chromium_path() -> str:
    path = _chromium_path()
    if path is None:
        pytest.skip(
            "Chromium not found at /usr/bin/chromium (install Debian's 'chromium' or set HRC_CHROMIUM)"
        )
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.skip("playwright (python) is not installed; pip install -e '.[dev]'")
    return path


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="session")
def hrc_server(tmp_path_factory: pytest.TempPathFactory, chromium_path: str) -> Iterator[HrcServer]:
    """``hrc serve`` on free ports (simulated robot and person) until the end of the session."""
    server = HrcServer(tmp_path_factory.mktemp("hrc-e2e"), token=TOKEN)
    try:
        try:
            server.wait_healthy(SERVER_START_TIMEOUT_S)
        except RuntimeError as exc:
            pytest.fail(str(exc))
        yield server
    finally:
        server.stop()
        if ARTIFACTS.is_dir():
            with contextlib.suppress(OSError):
                shutil.copy(server.log_path, ARTIFACTS / "e2e-server.log")


@pytest.fixture(scope="module")
def browser(chromium_path: str) -> Iterator[Any]:
    # Module scope: Playwright's sync API keeps an asyncio loop running on the main thread while it is
    # open, which would break every later test that calls asyncio.run().
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path, args=list(CHROMIUM_ARGS))
        try:
            yield b
        finally:
            b.close()


@pytest.fixture()
def page(browser: Any) -> Iterator[Any]:
    """A fresh browser context (empty sessionStorage) with a desktop viewport; page errors fail the test."""
    context = browser.new_context(viewport={"width": 1440, "height": 900}, accept_downloads=True)
    p = context.new_page()
    p.set_default_timeout(30_000)
    errors: list[str] = []
    p.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        yield p
    finally:
        context.close()
    assert not errors, f"JavaScript errors on the page: {errors}"
