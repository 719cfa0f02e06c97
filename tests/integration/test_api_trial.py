"""The real wiring: a trial started over REST runs the real runtime (simulated cell, wall clock) and ends with
its metrics and events in the database; E-stop and reset; pushed skeleton frames through ``/api/ingest``,
where oversized, malformed and too-fast messages are rejected while the runtime keeps running."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.api.live_hub import WS_MESSAGE_TOO_BIG, WS_POLICY_VIOLATION, LiveLimits
from app.config import Settings

TOKEN = "trial-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Longest wait for a short trial to end and be stored (a wait with a timeout, not a timing assertion).
END_TIMEOUT_S = 120.0


def _settings(tmp_path: Path, **extra: Any) -> Settings:
    return Settings(
        _env_file=None,
        data_dir=tmp_path,
        api_token=TOKEN,
        database_url=f"sqlite:///{(tmp_path / 'study.db').as_posix()}",
        robot="sim",
        **extra,
    )


def _wait_ended(c: TestClient, trial_id: int) -> dict[str, Any]:
    deadline = time.monotonic() + END_TIMEOUT_S
    while time.monotonic() < deadline:
        t = c.get(f"/api/trials/{trial_id}", headers=AUTH).json()
        if t["status"] != "running":
            return t
        time.sleep(0.1)
    raise AssertionError(f"trial {trial_id} did not end within {END_TIMEOUT_S} s")


@pytest.fixture
def sim_client(tmp_path: Path) -> Iterator[TestClient]:
    with TestClient(create_app(_settings(tmp_path, human_source="sim"), scene=False)) as c:
        yield c


def test_trial_over_rest_runs_the_runtime_and_stores_metrics(sim_client: TestClient, tmp_path: Path) -> None:
    c = sim_client
    p = c.post("/api/participants", json={"code": "R1"}, headers=AUTH).json()
    r = c.post(
        "/api/trials",
        json={"participant_id": p["id"], "method": "proactive", "duration_s": 10.0, "seed": 3},
        headers=AUTH,
    )
    assert r.status_code == 201, r.text
    trial_id = r.json()["id"]
    again = c.post(
        "/api/trials",
        json={"participant_id": p["id"], "method": "reactive", "duration_s": 10.0},
        headers=AUTH,
    )
    assert again.status_code == 409 and f"trial {trial_id}" in again.json()["detail"]
    with c.websocket_connect(f"/api/live?token={TOKEN}") as ws:  # the live view follows the trial
        for _ in range(300):
            snap = ws.receive_json()
            if snap["trial_id"] == trial_id:
                break
        assert snap["trial_id"] == trial_id and snap["method"] == "proactive"
        assert len(snap["q"]) == 6
    done = _wait_ended(c, trial_id)
    assert done["status"] == "completed", done
    m = done["metrics"]
    assert m is not None and m["duration_s"] > 0 and m["frames_received"] > 0
    kinds = [e["kind"] for e in done["events"]]
    assert kinds[0] == "trial_started" and kinds.count("trial_ended") == 1, done["events"]
    assert done["events_total"] == len(kinds)
    csv_rows = c.get("/api/export/metrics.csv", headers=AUTH).text.strip().splitlines()
    assert len(csv_rows) == 2  # header + this trial
    repo = c.app.state.hrc.repo
    frames = repo.load_frames(trial_id)  # recorded for replay, at the camera rate
    assert frames is not None and len(frames) > 0 and frames.q.shape == (len(frames), 6)
    assert np.all(np.diff(frames.t) > 0)


def test_stop_estop_and_reset_with_the_real_runtime(sim_client: TestClient) -> None:
    c = sim_client
    p = c.post("/api/participants", json={"code": "R2"}, headers=AUTH).json()
    t = c.post(
        "/api/trials", json={"participant_id": p["id"], "method": "reactive", "duration_s": 600}, headers=AUTH
    ).json()
    stopped = c.post(f"/api/trials/{t['id']}/stop", headers=AUTH)
    assert stopped.status_code == 200
    ended = _wait_ended(c, t["id"])
    assert ended["status"] == "aborted" and ended["abort_reason"] == "operator"
    assert c.post(f"/api/trials/{t['id']}/stop", headers=AUTH).status_code == 409
    estop = c.post("/api/robot/estop", headers=AUTH)
    assert estop.status_code == 200 and estop.json()["estopped"] is True
    reset = c.post("/api/robot/reset", headers=AUTH)
    assert reset.status_code == 200 and reset.json()["estopped"] is False


def _person_messages(times: list[float]) -> list[dict[str, Any]]:
    """Canonical-format messages of the simulated operator's pose at ``times`` (world frame)."""
    from app.cell.operator_sim import SimulatedOperator
    from app.cell.stream_protocol import make_message
    from app.config import load_workcell

    op = SimulatedOperator(load_workcell(), seed=0)
    out = []
    for t in times:
        frame = op.frame_at(t)
        assert frame is not None
        out.append(make_message(np.asarray(frame.joints), t=t))
    return out


def test_ingest_rejects_bad_messages_without_harming_the_runtime(tmp_path: Path) -> None:
    limits = LiveLimits(
        ingest_max_bytes=16 * 1024,
        ingest_rate_hz=120.0,
        ingest_burst=30,
        ingest_close_after=30,
        clock=lambda: 0.0,  # the rate limit's clock stands still: the burst is all there is
    )
    app = create_app(_settings(tmp_path, human_source="stream"), limits=limits, scene=False)
    with TestClient(app) as c:
        runtime = app.state.hrc.runtime
        with c.websocket_connect(f"/api/ingest?token={TOKEN}") as ws:
            assert ws.receive_json()["type"] == "ready"
            good = _person_messages([k / 30 for k in range(102)])
            ws.send_text(json.dumps(good[0]))
            ws.send_text('{"joints": [[0, 0, NaN]' + ", [0.5, -1.2, 0.5]" * 18 + "]}")  # a NaN literal
            err = ws.receive_json()  # the first reply: good[0] was accepted silently
            assert err["code"] == "rejected" and "non_finite" in err["detail"], err
            ws.send_text(json.dumps({"format": "zed34", "joints": [[0.0, 0.0, 1.0]] * 3}))
            err = ws.receive_json()
            assert err["code"] == "rejected" and "joint_count" in err["detail"]
            ws.send_text("not json at all")
            err = ws.receive_json()
            assert (err["code"], err["reason"]) == ("rejected", "malformed")
            ws.send_text(json.dumps(good[1]))
        rejected = c.get("/api/state", headers=AUTH).json()["frames_rejected"]  # each counted by reason
        assert rejected["total"] == 3
        assert [rejected["by_reason"][r] for r in ("non_finite", "joint_count", "malformed")] == [1, 1, 1]
        with c.websocket_connect(f"/api/ingest?token={TOKEN}") as ws:  # too fast: 100 at once
            ws.receive_json()
            codes = []
            for msg in good[2:]:
                ws.send_text(json.dumps(msg))
            while True:
                msg = ws.receive()
                if msg["type"] == "websocket.close":
                    close_code = msg["code"]
                    break
                codes.append(json.loads(msg["text"])["code"])
            # 30 (the burst) accepted without a reply, then rejections until the close
            assert codes == ["rate_limited"] * 31 and close_code == WS_POLICY_VIOLATION
        with c.websocket_connect(f"/api/ingest?token={TOKEN}") as ws:  # oversized
            ws.receive_json()
            ws.send_text(json.dumps({**good[-1], "pad": "x" * 20_000}))
            assert ws.receive_json()["code"] == "too_large"
            assert ws.receive()["code"] == WS_MESSAGE_TOO_BIG
        # the runtime is unharmed: it answers, it is not E-stopped, its snapshots still come
        assert c.get("/api/health").json()["status"] == "ok"
        assert c.get("/api/robot", headers=AUTH).json()["estopped"] is False
        before = runtime.snapshot().t
        with c.websocket_connect(f"/api/live?token={TOKEN}") as live:
            for _ in range(300):
                if live.receive_json()["t"] > before:
                    break
            else:
                raise AssertionError("the runtime stopped publishing snapshots")


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_sigterm_stops_the_robot_first_then_stores_and_closes(tmp_path: Path) -> None:
    """A real ``hrc serve`` process: SIGTERM during a trial stops the runtime (and the robot) at once, the
    trial is stored as aborted with its metrics, then the database is closed and the process exits 0."""
    import os
    import signal
    import subprocess
    import sys

    import httpx

    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("HRC_")}
    env.update(
        HRC_API_TOKEN=TOKEN,
        HRC_DATA_DIR=str(tmp_path / "data"),
        HRC_PORT=str(port),
        HRC_VISER_PORT=str(_free_port()),
        HRC_ROBOT="sim",
        HRC_HUMAN_SOURCE="sim",
    )
    log_path = tmp_path / "serve.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "serve", "--log-level", "info"],
            cwd=tmp_path,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180.0
        while True:
            assert proc.poll() is None, log_path.read_text()
            try:
                if httpx.get(f"{base}/api/health", timeout=2.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "hrc serve did not become healthy:\n" + log_path.read_text()
            time.sleep(0.2)
        with httpx.Client(base_url=base, headers=AUTH, timeout=30.0) as http:
            p = http.post("/api/participants", json={"code": "SIG"}).json()
            t = http.post(
                "/api/trials", json={"participant_id": p["id"], "method": "proactive", "duration_s": 600}
            ).json()
            assert t["status"] == "running"
        proc.send_signal(signal.SIGTERM)
        # uvicorn re-raises the signal after its clean shutdown: the exit status says "ended by SIGTERM"
        assert proc.wait(timeout=90) in (0, -signal.SIGTERM), log_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    log = log_path.read_text()
    order = [
        "stopping the robot first",
        f"trial {t['id']} ended: aborted (shutdown)",
        "runtime stopped",  # threads joined, robot.stop() done
        "operator API stopped",  # recorder drained, database closed
    ]
    positions = [log.find(line) for line in order]
    assert all(pos >= 0 for pos in positions) and positions == sorted(positions), log
    assert positions[1] < log.find(f"trial {t['id']} stored as aborted") < positions[3], log
    from app.study.db import make_engine
    from app.study.repository import StudyRepository

    engine = make_engine(f"sqlite:///{(tmp_path / 'data' / 'hrc.db').as_posix()}")
    try:
        stored = StudyRepository(engine).get_trial(t["id"])
    finally:
        engine.dispose()
    assert stored.status == "aborted" and stored.abort_reason == "shutdown" and stored.metrics is not None
