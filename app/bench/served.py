"""``hrc bench served``: the planning of a served trial, with the operator's dashboard open and without it.

A real server (``hrc serve`` in a subprocess: the simulated cell, SQLite in a temporary directory) runs two
proactive trials started over REST, one after the other with the same seed: the first with no page open, the
second with the dashboard open in a headless Chromium (Debian's, ``HRC_CHROMIUM`` or ``/usr/bin/chromium``;
the 3D view in it renders with software WebGL where the machine has no GPU). During each trial the plans'
compute times are read from ``/api/state`` twice a second; at its end the trial's metrics give the missed
deadlines. On Linux the CPU seconds of the server process and of the browser's processes over the trial
say where the machine's time went.

Prints ``deadline_ms`` and per condition (``no_page``, ``dashboard``): ``plan_ms`` (``p50``, ``p95``,
``n``), ``deadline_misses`` and per minute, ``completed_tasks``, and ``cpu_s`` (``server``, ``browser``).
Without Chromium or Playwright the dashboard condition says why it was not run.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: The trial's seed (not a tuning seed).
SEED = 11
TOKEN_BYTES = 24
SERVER_START_TIMEOUT_S = 240.0
#: Headless Chromium as the benchmarks and the end-to-end tests run it.
CHROMIUM_ARGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    # WebGL in software (SwiftShader) for the viser 3D view on machines without a GPU.
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
)


def free_port() -> int:
    """A free TCP port on the loopback address."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def chromium_path() -> str | None:
    """Debian's Chromium: ``HRC_CHROMIUM`` where set (None if no file is there), else the system's."""
    configured = os.environ.get("HRC_CHROMIUM")
    if configured:
        return configured if Path(configured).is_file() else None
    for candidate in ("/usr/bin/chromium", "/usr/bin/chromium-browser"):
        if Path(candidate).is_file():
            return candidate
    return shutil.which("chromium")


def _clock_ticks() -> float:
    return float(os.sysconf("SC_CLK_TCK"))


def _proc_cpu_s(pid: int | str) -> float:
    """User + system CPU seconds of process ``pid`` (all its threads), 0 where it cannot be read."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _clock_ticks()


def _browser_cpu_s() -> float:
    """CPU seconds of every Chromium process on the machine."""
    total = 0.0
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        with contextlib.suppress(OSError):
            if "chrom" in Path(f"/proc/{pid}/comm").read_text():
                total += _proc_cpu_s(pid)
    return total


def serve_env(*, token: str, data_dir: Path, port: int, viser_port: int) -> dict[str, str]:
    """The environment of an ``hrc serve`` subprocess on loopback ``port`` (and ``viser_port``) with the
    simulated cell, ``token`` and ``data_dir``: this process's environment without its ``HRC_`` settings."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HRC_")}
    env.update(
        HRC_API_TOKEN=token,
        HRC_DATA_DIR=str(data_dir),
        HRC_HOST="127.0.0.1",
        HRC_PORT=str(port),
        HRC_VISER_PORT=str(viser_port),
        HRC_ROBOT="sim",
        HRC_HUMAN_SOURCE="sim",
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
        PYTHONUNBUFFERED="1",
    )
    return env


class ServeProcess:
    """``hrc serve`` in a subprocess on free loopback ports with the simulated cell, its data and its log
    in ``work`` (also its working directory, so that no ``.env`` of the caller's leaks in); the benchmark's
    and the end-to-end tests' server.

    Args:
        work: A directory of its own.
        token: The operator token (default: a random one).
        log_level: ``hrc serve --log-level``.
    """

    def __init__(self, work: Path, *, token: str | None = None, log_level: str = "info") -> None:
        import secrets

        self.token = secrets.token_hex(TOKEN_BYTES) if token is None else token
        self.port, self.viser_port = free_port(), free_port()
        self.data_dir = work / "data"
        env = serve_env(token=self.token, data_dir=self.data_dir, port=self.port, viser_port=self.viser_port)
        self.base_url = f"http://127.0.0.1:{self.port}"
        self.log_path = work / "server.log"
        self._log = self.log_path.open("wb")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "serve", "--log-level", log_level],
            cwd=work,
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )

    def wait_healthy(self, timeout_s: float = SERVER_START_TIMEOUT_S) -> None:
        """Return once ``/api/health`` answers 200.

        Raises:
            RuntimeError: the server exited first, or did not answer within ``timeout_s`` (with its log's
                tail).
        """
        import httpx

        deadline = time.monotonic() + timeout_s
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(
                    f"hrc serve exited ({self.process.returncode}) before it was healthy:\n{self.log_tail()}"
                )
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{self.base_url}/api/health", timeout=2.0).status_code == 200:
                    return
            if time.monotonic() > deadline:
                raise RuntimeError(f"hrc serve was not healthy within {timeout_s:.0f} s:\n{self.log_tail()}")
            time.sleep(0.5)

    def log_tail(self, n: int = 60) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return "<no log>"

    def stop(self) -> None:
        """Stop the server (SIGTERM, then a kill after 30 s) and close its log."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        self._log.close()


def _trial(server: ServeProcess, client: Any, participant_id: int, duration_s: float) -> dict[str, Any]:
    """A proactive trial of ``duration_s`` over REST; its plans' compute times and CPU use."""
    r = client.post(
        "/api/trials",
        json={
            "participant_id": participant_id,
            "method": "proactive",
            "duration_s": duration_s,
            "seed": SEED,
        },
    )
    if r.status_code not in (200, 201):
        raise RuntimeError(f"starting the trial failed: {r.status_code} {r.text}")
    trial_id = r.json()["id"]
    cpu0 = (_proc_cpu_s(server.process.pid), _browser_cpu_s())
    plans: list[float] = []
    counted = 0
    t_end = time.monotonic() + duration_s + 3.0
    while time.monotonic() < t_end:
        state = client.get("/api/state").json()
        recent = list(state.get("planning_ms") or [])
        computed = int((state.get("counters") or {}).get("plans_computed", 0))
        new = computed - counted
        if new > 0 and recent:  # the newest plans (the snapshot keeps the last 20)
            plans.extend(recent[-min(new, len(recent)) :])
            counted = computed
        time.sleep(0.5)
    cpu1 = (_proc_cpu_s(server.process.pid), _browser_cpu_s())
    for _ in range(40):  # the trial's end is recorded a moment later
        trial = client.get(f"/api/trials/{trial_id}").json()
        if trial.get("status") != "running":
            break
        time.sleep(0.5)
    metrics = trial.get("metrics") or {}
    arr = np.asarray(plans, dtype=np.float64)
    misses = int(metrics.get("deadline_misses") or 0)
    return {
        "plan_ms": {
            "p50": round(float(np.percentile(arr, 50)), 1) if arr.size else None,
            "p95": round(float(np.percentile(arr, 95)), 1) if arr.size else None,
            "n": int(arr.size),
        },
        "deadline_misses": misses,
        "deadline_misses_per_min": round(60.0 * misses / duration_s, 2),
        "completed_tasks": metrics.get("completed_tasks"),
        "status": trial.get("status"),
        "cpu_s": {
            "server": round(cpu1[0] - cpu0[0], 1),
            "browser": round(cpu1[1] - cpu0[1], 1),
        },
    }


def run(*, quick: bool = False, progress: bool = True) -> dict[str, Any]:
    """Two served proactive trials (15 s each with ``quick``, 120 s otherwise): without a page, then with
    the dashboard open."""
    duration = 15.0 if quick else 120.0
    out: dict[str, Any] = {"duration_s": duration, "seed": SEED, "cores": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="hrc-bench-served-") as tmp:
        import httpx

        server = ServeProcess(Path(tmp))
        client = httpx.Client(
            base_url=server.base_url, headers={"Authorization": f"Bearer {server.token}"}, timeout=10.0
        )
        try:
            server.wait_healthy()
            info = client.get("/api/info").json()
            deadline_s = info.get("deadline_s")
            out["deadline_ms"] = None if deadline_s is None else round(1e3 * float(deadline_s), 3)
            participant = client.post("/api/participants", json={"code": "BENCH-SERVED"}).json()
            if progress:
                log.info("bench served: a %.0f-s trial with no page open", duration)
            out["no_page"] = _trial(server, client, participant["id"], duration)
            chromium = chromium_path()
            try:
                from playwright.sync_api import sync_playwright
            except ImportError:
                sync_playwright = None  # type: ignore[assignment]
            if chromium is None or sync_playwright is None:
                why = "Chromium not found" if chromium is None else "playwright is not installed"
                out["dashboard"] = {"skipped": why}
                return out
            if progress:
                log.info("bench served: a %.0f-s trial with the dashboard open", duration)
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=chromium, args=list(CHROMIUM_ARGS))
                try:
                    page = browser.new_page(viewport={"width": 1440, "height": 900})
                    page.goto(f"{server.base_url}/")
                    page.get_by_test_id("login-token").fill(server.token)
                    page.get_by_test_id("login-submit").click()
                    page.get_by_test_id("app-view").wait_for()
                    time.sleep(3.0)  # the 3D view loads its scene
                    out["dashboard"] = _trial(server, client, participant["id"], duration)
                finally:
                    browser.close()
        finally:
            client.close()
            server.stop()
    return out
