"""Every REST route through ``TestClient`` (lifespan running) on a real SQLite database and a runtime double:
success paths and the 404, 409 and 422 paths."""

from __future__ import annotations

import csv
import dataclasses
import io
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api.schemas import MIN_TRIAL_DURATION_S
from app.config import Settings


def _participant(client: TestClient, auth: dict[str, str], code: str = "P01", **extra: Any) -> dict[str, Any]:
    r = client.post("/api/participants", json={"code": code, **extra}, headers=auth)
    assert r.status_code == 201, r.text
    return r.json()


def _start(client: TestClient, auth: dict[str, str], participant_id: int, **extra: Any) -> Any:
    body = {"participant_id": participant_id, "method": "proactive", "duration_s": 10.0, **extra}
    return client.post("/api/trials", json=body, headers=auth)


# ---- lifespan -------------------------------------------------------------------------------------------


def test_lifespan_starts_and_stops_the_runtime(
    make_client: Any, settings: Settings, runtime: Any, auth: dict[str, str]
) -> None:
    c = make_client(settings)
    assert runtime.started == 1 and runtime.stopped == 0
    assert len(runtime.subscriptions) == 1  # the live broadcaster's single subscription
    p = _participant(c, auth)
    assert _start(c, auth, p["id"]).status_code == 201
    c.__exit__(None, None, None)  # shutdown: runtime stops first, then the recorder stores the trial
    assert runtime.stopped == 1
    assert runtime.subscriptions[0].closed


def test_interrupted_trials_are_aborted_at_start(
    make_client: Any, settings: Settings, runtime: Any, auth: dict[str, str]
) -> None:
    from app.study.db import make_engine, upgrade_to_head
    from app.study.repository import StudyRepository
    from app.study.schemas import ParticipantCreate

    url = settings.resolved_database_url()
    upgrade_to_head(url)
    engine = make_engine(url)
    repo = StudyRepository(engine)
    p = repo.create_participant(ParticipantCreate(code="K1"))
    left = repo.create_trial(participant_id=p.id, method="reactive")  # a killed process left it running
    engine.dispose()
    c = make_client(settings)
    t = c.get(f"/api/trials/{left.id}", headers=auth).json()
    assert t["status"] == "aborted" and "interrupted" in t["abort_reason"]


# ---- health and info ----------------------------------------------------------------------------------


def test_info_and_the_trial_record_name_the_predictor_that_runs(
    make_client: Any, settings: Settings, auth: dict[str, str], runtime: Any
) -> None:
    from app.control.world import make_predictor, predictor_info
    from app.prediction.predictor import DEFAULT_WEIGHTS

    runtime.predictor_info = predictor_info(make_predictor("proactive", settings))  # as Runtime.start sets it
    client = make_client(settings)
    got = client.get("/api/info", headers=auth).json()["predictor"]
    import hashlib

    digest = hashlib.sha256(DEFAULT_WEIGHTS.read_bytes()).hexdigest()
    assert got["kind"] == "graphmixer" and got["fallback_reason"] is None
    assert got["weights"] == str(DEFAULT_WEIGHTS) and got["weights_sha256"] == digest
    p = client.post("/api/participants", json={"code": "P1"}, headers=auth).json()
    body = {"participant_id": p["id"], "method": "proactive", "duration_s": 60}
    trial = client.post("/api/trials", json=body, headers=auth).json()
    assert trial["settings"]["predictor"] == got  # the trial record says which predictor ran
    runtime.finish_trial()
    reactive = client.post("/api/trials", json={**body, "method": "reactive"}, headers=auth).json()
    assert reactive["settings"]["predictor"] is None  # the reactive method holds the current pose


def test_health_and_info(client: TestClient, auth: dict[str, str], settings: Settings) -> None:
    h = client.get("/api/health").json()
    assert h == {"status": "ok", "version": h["version"], "runtime": "running", "database": "ok"}
    info = client.get("/api/info", headers=auth).json()
    assert info["viser_port"] == settings.viser_port
    assert info["methods"] == ["proactive", "reactive"]
    assert info["ingest_rate_hz"] == 120.0
    assert info["deadline_s"] == settings.deadline_s
    assert info["anticipate_fetch"] is settings.anticipate_fetch


def test_docs_and_openapi(client: TestClient) -> None:
    assert client.get("/docs").status_code == 200
    schema = client.get("/openapi.json").json()
    assert "/api/trials" in schema["paths"]
    assert "HTTPBearer" in schema["components"]["securitySchemes"]


# ---- participants -------------------------------------------------------------------------------------


def test_participants_crud(client: TestClient, auth: dict[str, str]) -> None:
    p = _participant(client, auth, "P01", age=31, sex="f", experience="none")
    assert p["code"] == "P01" and p["age"] == 31
    assert client.get("/api/participants", headers=auth).json()[0]["id"] == p["id"]
    assert client.get(f"/api/participants/{p['id']}", headers=auth).json() == p
    r = client.patch(f"/api/participants/{p['id']}", json={"notes": "left-handed"}, headers=auth)
    assert r.status_code == 200 and r.json()["notes"] == "left-handed" and r.json()["age"] == 31
    order = client.get(f"/api/participants/{p['id']}/method-order", headers=auth).json()
    assert order == {"participant_id": p["id"], "methods": ["proactive", "reactive"]}
    second = _participant(client, auth, "P02")
    order2 = client.get(f"/api/participants/{second['id']}/method-order", headers=auth).json()
    assert order2["methods"] == ["reactive", "proactive"]
    assert client.delete(f"/api/participants/{p['id']}", headers=auth).status_code == 204
    assert client.get(f"/api/participants/{p['id']}", headers=auth).status_code == 404


def test_participants_errors(client: TestClient, auth: dict[str, str]) -> None:
    p = _participant(client, auth, "P01")
    _participant(client, auth, "P02")
    dup = client.post("/api/participants", json={"code": "P01"}, headers=auth)
    assert dup.status_code == 409 and "P01" in dup.json()["detail"]
    taken = client.patch(f"/api/participants/{p['id']}", json={"code": "P02"}, headers=auth)
    assert taken.status_code == 409
    bad = client.post("/api/participants", json={"code": "bad code!", "age": 200}, headers=auth)
    assert bad.status_code == 422
    detail = bad.json()["detail"]
    assert "body.code" in detail and "body.age" in detail
    assert {tuple(e["loc"]) for e in bad.json()["errors"]} == {("body", "code"), ("body", "age")}
    extra = client.post("/api/participants", json={"code": "P9", "admin": True}, headers=auth)
    assert extra.status_code == 422 and "admin" in extra.json()["detail"]
    null_code = client.patch(f"/api/participants/{p['id']}", json={"code": None}, headers=auth)
    assert null_code.status_code == 422
    not_json = client.post(
        "/api/participants", content=b"{nope", headers={**auth, "Content-Type": "application/json"}
    )
    assert not_json.status_code == 422
    assert client.get("/api/participants/999", headers=auth).status_code == 404
    assert client.patch("/api/participants/999", json={"notes": "x"}, headers=auth).status_code == 404
    assert client.delete("/api/participants/999", headers=auth).status_code == 404
    assert client.get("/api/participants/999/method-order", headers=auth).status_code == 404
    assert client.get("/api/participants/0", headers=auth).status_code == 422
    assert client.get("/api/participants/abc", headers=auth).status_code == 422
    assert client.get("/api/participants?limit=0", headers=auth).status_code == 422


def test_participant_with_trials_needs_with_trials(
    client: TestClient, auth: dict[str, str], runtime: Any
) -> None:
    p = _participant(client, auth)
    assert _start(client, auth, p["id"]).status_code == 201
    runtime.finish_trial("completed")
    r = client.delete(f"/api/participants/{p['id']}", headers=auth)
    assert r.status_code == 409 and "with_trials" in r.json()["detail"]
    # the message names the query as it is written, once
    assert f"DELETE /api/participants/{p['id']}?with_trials=true" in r.json()["detail"]
    assert "with with_trials" not in r.json()["detail"] and "True" not in r.json()["detail"]
    assert client.delete(f"/api/participants/{p['id']}?with_trials=true", headers=auth).status_code == 204
    assert client.get("/api/trials", headers=auth).json() == []


# ---- sessions -----------------------------------------------------------------------------------------


def test_sessions_crud_and_errors(client: TestClient, auth: dict[str, str]) -> None:
    r = client.post("/api/sessions", json={"name": "day 1"}, headers=auth)
    assert r.status_code == 201
    s = r.json()
    assert client.get("/api/sessions", headers=auth).json() == [s]
    assert client.get(f"/api/sessions/{s['id']}", headers=auth).json() == s
    upd = client.patch(f"/api/sessions/{s['id']}", json={"notes": "rainy"}, headers=auth)
    assert upd.status_code == 200 and upd.json()["notes"] == "rainy"
    assert client.patch(f"/api/sessions/{s['id']}", json={"name": None}, headers=auth).status_code == 422
    assert client.post("/api/sessions", json={"name": ""}, headers=auth).status_code == 422
    assert client.get("/api/sessions/77", headers=auth).status_code == 404
    assert client.patch("/api/sessions/77", json={"notes": "x"}, headers=auth).status_code == 404
    assert client.delete("/api/sessions/77", headers=auth).status_code == 404
    assert client.delete(f"/api/sessions/{s['id']}", headers=auth).status_code == 204
    assert client.get(f"/api/sessions/{s['id']}", headers=auth).status_code == 404


# ---- trials -------------------------------------------------------------------------------------------


def test_trial_start_runs_the_runtime_and_its_end_is_stored(
    client: TestClient, auth: dict[str, str], runtime: Any
) -> None:
    p = _participant(client, auth)
    s = client.post("/api/sessions", json={"name": "s"}, headers=auth).json()
    r = _start(client, auth, p["id"], seed=7, session_id=s["id"], method="reactive", duration_s=12.5)
    assert r.status_code == 201, r.text
    trial = r.json()
    assert trial["status"] == "running" and trial["seed"] == 7 and trial["session_id"] == s["id"]
    assert "api_token" not in trial["settings"]
    assert runtime.running_trial_id == trial["id"]
    assert runtime.trial_args == {"method": "reactive", "duration_s": 12.5, "seed": 7}
    runtime.finish_trial("completed", extra_events=2)
    assert client.app.state.hrc.recorder.wait_stored(trial["id"], 10.0)
    got = client.get(f"/api/trials/{trial['id']}", headers=auth).json()
    assert got["status"] == "completed"
    assert got["metrics"]["completed_tasks"] == 2 and got["metrics"]["plans_computed"] == 3
    kinds = [e["kind"] for e in got["events"]]
    assert kinds == ["trial_started", "task_completed", "task_completed", "trial_ended"]  # no duplicates
    assert got["events_total"] == 4
    ev = client.get(f"/api/trials/{trial['id']}/events?kind=task_completed", headers=auth).json()
    assert [e["payload"]["index"] for e in ev] == [0, 1]
    listed = client.get(f"/api/trials?participant_id={p['id']}&status=completed", headers=auth).json()
    assert [t["id"] for t in listed] == [trial["id"]]
    assert client.get("/api/trials?method=proactive", headers=auth).json() == []
    assert client.get("/api/trials?status=bogus", headers=auth).status_code == 422


def test_random_seed_is_stored(client: TestClient, auth: dict[str, str], runtime: Any) -> None:
    p = _participant(client, auth)
    trial = _start(client, auth, p["id"]).json()
    assert trial["seed"] == runtime.trial_args["seed"]


def test_second_start_is_409_naming_the_running_trial(
    client: TestClient, auth: dict[str, str], runtime: Any
) -> None:
    p = _participant(client, auth)
    first = _start(client, auth, p["id"]).json()
    second = _start(client, auth, p["id"], method="reactive")
    assert second.status_code == 409
    assert f"trial {first['id']} is running" in second.json()["detail"]
    assert len(client.get("/api/trials", headers=auth).json()) == 1  # no orphan row


def test_runtime_refusal_is_409_and_the_trial_is_recorded_aborted(
    client: TestClient, auth: dict[str, str], runtime: Any
) -> None:
    p = _participant(client, auth)
    runtime.estopped = True
    r = _start(client, auth, p["id"])
    assert r.status_code == 409 and "reset first" in r.json()["detail"]
    (t,) = client.get("/api/trials", headers=auth).json()
    assert t["status"] == "aborted" and "not started" in t["abort_reason"]


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("participant_id", True),  # was participant 1
        ("participant_id", "1"),
        ("duration_s", True),  # was a 1-s trial
        ("duration_s", "60"),
        ("seed", True),
        ("seed", 7.0),
        ("session_id", "1"),
    ],
)
def test_trial_start_takes_strict_types(
    client: TestClient, auth: dict[str, str], runtime: Any, field: str, value: Any
) -> None:
    p = _participant(client, auth)
    body = {"participant_id": p["id"], "method": "proactive", "duration_s": 60.0, field: value}
    r = client.post("/api/trials", json=body, headers=auth)
    assert r.status_code == 422, r.json()
    assert f"body.{field}" in r.json()["detail"]
    assert runtime.running_trial_id is None


def test_a_trial_too_short_for_one_task_is_refused(
    client: TestClient, auth: dict[str, str], runtime: Any
) -> None:
    p = _participant(client, auth)
    for short in (1e-300, 0.5, 9.99):
        r = _start(client, auth, p["id"], duration_s=short)
        assert r.status_code == 422 and "too short to hold one task" in r.json()["detail"], short
    assert runtime.running_trial_id is None
    assert client.get("/api/info", headers=auth).json()["min_trial_duration_s"] == MIN_TRIAL_DURATION_S
    assert _start(client, auth, p["id"], duration_s=MIN_TRIAL_DURATION_S).status_code == 201


@pytest.mark.parametrize("body", [{"age": True}, {"age": "30"}, {"age": 30.0}, {"code": 12}])
def test_participant_bodies_take_strict_types(client: TestClient, auth: dict[str, str], body: dict) -> None:
    created = client.post("/api/participants", json={"code": "P77", **body}, headers=auth)
    assert created.status_code == 422, created.json()
    p = _participant(client, auth, "P78")
    patched = client.patch(f"/api/participants/{p['id']}", json=body, headers=auth)
    assert patched.status_code == 422, patched.json()


def test_trial_start_validation_and_404(client: TestClient, auth: dict[str, str]) -> None:
    p = _participant(client, auth)
    assert _start(client, auth, 999).status_code == 404
    assert _start(client, auth, p["id"], session_id=999).status_code == 404
    for bad in (
        {"method": "teleport"},
        {"duration_s": 0},
        {"duration_s": -1},
        {"duration_s": 1e9},
        {"seed": -1},
        {"participant_id": 0},
        {"extra": 1},
    ):
        body = {"participant_id": p["id"], "method": "proactive", "duration_s": 10.0, **bad}
        r = client.post("/api/trials", json=body, headers=auth)
        assert r.status_code == 422, bad
        assert r.json()["detail"].startswith("invalid request: body.")
    missing = client.post("/api/trials", json={"participant_id": p["id"]}, headers=auth)
    assert missing.status_code == 422 and "method" in missing.json()["detail"]


def test_stop_trial(client: TestClient, auth: dict[str, str], runtime: Any) -> None:
    p = _participant(client, auth)
    trial = _start(client, auth, p["id"]).json()
    r = client.post(f"/api/trials/{trial['id']}/stop", headers=auth)
    assert r.status_code == 200
    assert runtime.stop_reasons == ["operator"]
    assert r.json()["status"] == "aborted" and r.json()["metrics"] is not None
    again = client.post(f"/api/trials/{trial['id']}/stop", headers=auth)
    assert again.status_code == 409 and "not running" in again.json()["detail"]
    assert client.post("/api/trials/999/stop", headers=auth).status_code == 404


def test_trial_read_errors(client: TestClient, auth: dict[str, str]) -> None:
    assert client.get("/api/trials/5", headers=auth).status_code == 404
    assert client.get("/api/trials/5/events", headers=auth).status_code == 404
    assert client.get("/api/trials/-1", headers=auth).status_code == 422
    assert client.get(f"/api/trials/{2**40}", headers=auth).status_code == 422


# ---- robot --------------------------------------------------------------------------------------------


def test_robot_state_estop_and_reset(client: TestClient, auth: dict[str, str], runtime: Any) -> None:
    r = client.get("/api/robot", headers=auth).json()
    assert r["estopped"] is False and len(r["q"]) == 6 and len(r["p_world_tcp"]) == 3
    assert r["separation_m"] is None  # inf (nobody tracked) becomes null
    state = client.get("/api/state", headers=auth).json()
    assert state["type"] == "snapshot" and state["separation_m"] is None
    p = _participant(client, auth)
    trial = _start(client, auth, p["id"]).json()
    stopped = client.post("/api/robot/estop", headers=auth)
    assert stopped.status_code == 200 and stopped.json()["estopped"] is True
    assert runtime.running_trial_id is None
    assert client.app.state.hrc.recorder.wait_stored(trial["id"], 10.0)
    assert client.get(f"/api/trials/{trial['id']}", headers=auth).json()["status"] == "aborted"
    assert _start(client, auth, p["id"]).status_code == 409  # E-stopped: reset first
    reset = client.post("/api/robot/reset", headers=auth)
    assert reset.status_code == 200 and reset.json()["estopped"] is False
    refused = client.post("/api/robot/reset", headers=auth)
    assert refused.status_code == 409 and "cannot reset" in refused.json()["detail"]


# ---- summary and export -------------------------------------------------------------------------------


def _completed_pair(client: TestClient, auth: dict[str, str], runtime: Any) -> None:
    for code in ("A", "B", "C"):
        p = _participant(client, auth, code)
        for method in ("proactive", "reactive"):
            t = _start(client, auth, p["id"], method=method).json()
            runtime.finish_trial("completed", extra_events=3 if method == "proactive" else 1)
            assert client.app.state.hrc.recorder.wait_stored(t["id"], 10.0)


def test_summary(client: TestClient, auth: dict[str, str], runtime: Any) -> None:
    empty = client.get("/api/summary", headers=auth)
    assert empty.status_code == 200 and empty.json()["n_participants"] == 0
    _completed_pair(client, auth, runtime)
    s = client.get("/api/summary", headers=auth).json()
    assert s["n_participants"] == 3
    assert s["proactive"]["completed_tasks"]["mean"] == 3.0
    assert s["reactive"]["completed_tasks"]["mean"] == 1.0
    assert "completed_tasks" in s["p_values"]
    table = client.get("/api/summary/table.csv", headers=auth)
    assert table.headers["content-type"].startswith("text/csv")
    assert next(csv.reader(io.StringIO(table.text)))[0] == "metric"
    md = client.get("/api/summary/table.md", headers=auth)
    assert md.status_code == 200 and "| proactive |" in md.text
    png = client.get("/api/summary/boxplots.png", headers=auth)
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert client.get("/api/summary?session_id=0", headers=auth).status_code == 422


def test_exports(client: TestClient, auth: dict[str, str], runtime: Any) -> None:
    _completed_pair(client, auth, runtime)
    expected_rows = {"participants": 3, "trials": 6, "metrics": 6, "events": 3 * (5 + 3)}
    for table, n in expected_rows.items():
        r = client.get(f"/api/export/{table}.csv", headers=auth)
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/csv")
        assert f'filename="{table}.csv"' in r.headers["content-disposition"]
        rows = list(csv.DictReader(io.StringIO(r.text)))
        assert len(rows) == n, table
    one = client.get("/api/export/events.csv?trial_id=1", headers=auth)
    assert len(list(csv.DictReader(io.StringIO(one.text)))) == 5
    assert client.get("/api/export/bogus.csv", headers=auth).status_code == 404
    assert client.get("/api/export/events.csv?trial_id=x", headers=auth).status_code == 422


def test_unknown_api_path_is_json_404(client: TestClient, auth: dict[str, str]) -> None:
    r = client.get("/api/nothing-here", headers=auth)
    assert r.status_code == 404 and r.json()["detail"]


def test_health_is_503_when_the_runtime_stops_publishing(client: TestClient, runtime: Any) -> None:
    from dataclasses import replace
    from types import SimpleNamespace

    now = [100.0]
    runtime.clock = SimpleNamespace(now=lambda: now[0])
    runtime.publish(replace(runtime.snapshot(), t=99.5))
    assert client.get("/api/health").json()["runtime"] == "running"
    now[0] = 110.0  # the frame loop has published nothing for 10.5 s
    r = client.get("/api/health")
    assert r.status_code == 503 and r.json() == {**r.json(), "status": "degraded", "runtime": "stopped"}


def test_the_robot_status_carries_the_mode_the_live_snapshot_has() -> None:
    """``GET /api/robot`` and the E-stop's answer carry the mode fields of ``/api/live`` (the page merges an
    answer into the last snapshot: a stale mode must not survive it)."""
    import numpy as np

    from app.api.schemas import robot_status
    from app.control.results import Snapshot
    from app.safety.modes import PartMode

    modes = (
        PartMode("free", "skull_forehead", "skull_forehead", 1.2, 0.5, 1.0, 0.2),
        PartMode("pfl", "hand_fingers", "chest", 0.7, 0.6, 0.675, 1.35),
    )
    snap = Snapshot(
        t=1.0, trial_id=3, state="nominal", method="reactive", speed_scale=0.675, separation_m=0.7,
        required_separation_m=0.6, planning_ms=(), counters={}, q=np.zeros(6), p_world_tcp=np.zeros(3),
        part_modes=modes, part_names=("wrist_3", "tool"),
    )  # fmt: skip
    got = robot_status(snap).model_dump()
    live = snap.to_json()
    for key in ("mode", "mode_text", "limiting_part", "parts"):
        assert got[key] == live[key], key
    assert got["mode"] == "pfl:hand_fingers" and got["mode_text"] == "PFL · hand/fingers"
    assert got["limiting_part"] == "tool" and got["parts"][1]["held_from_text"] == "chest"
    estopped = robot_status(dataclasses.replace(snap, estopped=True, part_modes=(), part_names=()))
    assert estopped.mode == "stopped" and estopped.parts == []
