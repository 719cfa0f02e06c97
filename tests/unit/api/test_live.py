"""Live WebSockets: snapshot fan-out with bounded per-client queues, and the ingest socket's token, size, rate
and format checks, none of which can harm the runtime."""

from __future__ import annotations

import asyncio
import json
from dataclasses import replace
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.api.live_hub import (
    WS_MESSAGE_TOO_BIG,
    WS_POLICY_VIOLATION,
    WS_TRY_AGAIN_LATER,
    ClientQueue,
    LiveHub,
    LiveLimits,
    RateLimiter,
    dumps_strict,
)
from app.config import Settings

FRAME = {"t": 1.0, "format": "canonical", "joints": [[0.0, 0.0, 1.0]] * 19}


def _closed_code(ws: Any) -> int:
    """Read until the server closes; returns the close code."""
    for _ in range(1000):
        msg = ws.receive()
        if msg["type"] == "websocket.close":
            return msg["code"]
    raise AssertionError("the server did not close the socket")


# ---- pieces -------------------------------------------------------------------------------------------


def test_client_queue_drops_the_oldest() -> None:
    async def scenario() -> tuple[list[str | None], int]:
        q = ClientQueue(3)
        for k in range(10):
            q.put(str(k))
        got = [await q.get(timeout_s=0.01) for _ in range(4)]
        return got, q.dropped

    got, dropped = asyncio.run(scenario())
    assert got == ["7", "8", "9", None]
    assert dropped == 7


def test_rate_limiter_token_bucket(fake_clock: Any) -> None:
    rl = RateLimiter(rate_hz=10.0, burst=5, clock=fake_clock)
    assert [rl.allow() for _ in range(7)] == [True] * 5 + [False] * 2
    assert rl.rejected_in_window == 2
    fake_clock.t += 0.25  # 2.5 tokens back
    assert [rl.allow() for _ in range(3)] == [True, True, False]
    fake_clock.t += 1.0  # a new window
    assert rl.allow() and rl.rejected_in_window == 0 and rl.rejected_total == 3


def test_strict_json_has_no_nan() -> None:
    text = dumps_strict({"a": float("inf"), "b": [1.0, float("nan")], "c": 2})
    assert json.loads(text) == {"a": None, "b": [1.0, None], "c": 2}


def test_limits_are_validated() -> None:
    with pytest.raises(ValueError, match="queue"):
        LiveLimits(live_queue=0)
    with pytest.raises(ValueError, match="rate"):
        LiveLimits(ingest_rate_hz=0)


def test_hub_never_lets_a_client_hold_more_than_its_queue(runtime: Any) -> None:
    """Clients that never read: the runtime's publishes and the hub's fan-out stay bounded."""

    async def scenario() -> tuple[list[int], int]:
        hub = LiveHub(runtime, limits=LiveLimits(live_queue=4))
        hub.start(asyncio.get_running_loop())
        try:
            clients = [hub.register() for _ in range(3)]
            for k in range(500):
                runtime.publish(replace(runtime.snapshot(), t=float(k)))  # never blocks
                hub._fanout(dumps_strict({"k": k}))
            return [len(c) for c in clients if c is not None], max(
                s._q.qsize() for s in runtime.subscriptions
            )
        finally:
            hub.stop()

    sizes, sub_size = asyncio.run(scenario())
    assert sizes == [4, 4, 4]
    assert sub_size <= LiveLimits().subscription_size


def test_a_new_clients_first_snapshot_is_fresh(runtime: Any) -> None:
    """Nothing is broadcast while no client listens: a client who connects 10 s after the last one left gets
    the runtime's newest snapshot, not the text broadcast then; a text of the newest snapshot is reused."""

    async def scenario() -> tuple[dict[str, Any], dict[str, Any]]:
        hub = LiveHub(runtime, limits=LiveLimits(live_rate_hz=30.0))
        hub.start(asyncio.get_running_loop())
        try:
            q = hub.register()  # an earlier client
            assert q is not None
            runtime.publish(replace(runtime.snapshot(), t=1.0, state="nominal"))
            for _ in range(200):
                await asyncio.sleep(0.01)
                if hub.latest_text is not None and json.loads(hub.latest_text)["t"] == 1.0:
                    break
            reused = json.loads(hub.current_text())
            hub.unregister(q)  # it leaves; 10 s later, nobody listening, the runtime moved on
            runtime.publish(replace(runtime.snapshot(), t=11.0, state="idle"))
            await asyncio.sleep(0.1)
            return reused, json.loads(hub.current_text())
        finally:
            hub.stop()

    reused, first = asyncio.run(scenario())
    assert reused["t"] == 1.0 and reused["state"] == "nominal"
    assert first["t"] == 11.0 and first["state"] == "idle"


# ---- /api/live ----------------------------------------------------------------------------------------


def test_live_streams_snapshots_with_token_in_query(
    client: TestClient, settings: Settings, runtime: Any
) -> None:
    with client.websocket_connect(f"/api/live?token={settings.api_token}") as ws:
        first = ws.receive_json()
        assert first["type"] == "snapshot" and first["state"] == "idle"
        assert first["separation_m"] is None  # inf -> null: valid JSON for a browser
        runtime.publish(replace(runtime.snapshot(), state="nominal", t=12.5, speed_scale=0.5))
        for _ in range(50):
            msg = ws.receive_json()
            if msg["t"] == 12.5:
                break
        assert msg["state"] == "nominal" and msg["speed_scale"] == 0.5


def test_live_token_in_header_or_first_message(client: TestClient, settings: Settings) -> None:
    with client.websocket_connect(
        "/api/live", headers={"Authorization": f"Bearer {settings.api_token}"}
    ) as ws:
        assert ws.receive_json()["type"] == "snapshot"
    with client.websocket_connect("/api/live") as ws:
        ws.send_text(json.dumps({"token": settings.api_token}))
        assert ws.receive_json()["type"] == "snapshot"


def test_live_rejects_bad_tokens(client: TestClient) -> None:
    with (
        pytest.raises(WebSocketDisconnect) as exc,
        client.websocket_connect("/api/live?token=wrong-token-123456"),
    ):
        pass
    assert exc.value.code == WS_POLICY_VIOLATION
    with client.websocket_connect("/api/live") as ws:
        ws.send_text(json.dumps({"token": "wrong"}))
        err = ws.receive_json()
        assert err["type"] == "error" and err["code"] == "unauthorized"
        assert _closed_code(ws) == WS_POLICY_VIOLATION
    with client.websocket_connect("/api/live") as ws:
        ws.send_text("x" * 10_000)  # an oversized first message is not parsed
        assert ws.receive_json()["code"] == "unauthorized"
        assert _closed_code(ws) == WS_POLICY_VIOLATION


def test_live_auth_times_out(make_client: Any, settings: Settings) -> None:
    c = make_client(settings, auth_timeout_s=0.05)
    with c.websocket_connect("/api/live") as ws:
        assert ws.receive_json()["code"] == "unauthorized"
        assert _closed_code(ws) == WS_POLICY_VIOLATION


def test_live_is_open_with_read_only_open(make_client: Any, settings: Settings) -> None:
    c = make_client(settings.model_copy(update={"read_only_open": True}))
    with c.websocket_connect("/api/live") as ws:
        assert ws.receive_json()["type"] == "snapshot"


def test_live_client_limit(make_client: Any, settings: Settings) -> None:
    c = make_client(settings, max_live_clients=1)
    url = f"/api/live?token={settings.api_token}"
    with c.websocket_connect(url) as first:
        assert first.receive_json()["type"] == "snapshot"
        with c.websocket_connect(url) as second:
            assert second.receive_json()["code"] == "too_many_clients"
            assert _closed_code(second) == WS_TRY_AGAIN_LATER


# ---- /api/ingest --------------------------------------------------------------------------------------


def _ingest(c: TestClient, settings: Settings) -> Any:
    ws = c.websocket_connect(f"/api/ingest?token={settings.api_token}")
    return ws


def test_ingest_accepts_frames_and_answers_errors(
    client: TestClient, settings: Settings, runtime: Any
) -> None:
    with _ingest(client, settings) as ws:
        ready = ws.receive_json()
        assert ready["type"] == "ready" and ready["max_rate_hz"] == 120.0
        ws.send_text(json.dumps(FRAME))
        for bad in ("{not json", "[1, 2, 3]", b"\xff\xfe"):
            (ws.send_bytes if isinstance(bad, bytes) else ws.send_text)(bad)
            err = ws.receive_json()
            assert (err["code"], err["reason"]) == ("rejected", "malformed")
        ws.send_text(json.dumps({"t": 2.0}))  # the runtime rejects it
        err = ws.receive_json()
        assert err["code"] == "rejected" and "joints" in err["detail"]
        ws.send_bytes(json.dumps(FRAME).encode())  # UTF-8 bytes are fine too
        ws.send_text(json.dumps(FRAME))
    assert len(runtime.ingested) == 3
    assert client.get("/api/health").json()["status"] == "ok"  # the runtime is unharmed


def test_ingest_needs_the_token_even_when_reads_are_open(make_client: Any, settings: Settings) -> None:
    c = make_client(settings.model_copy(update={"read_only_open": True}))
    with (
        pytest.raises(WebSocketDisconnect) as exc,
        c.websocket_connect("/api/ingest?token=nope-nope-nope-nope"),
    ):
        pass
    assert exc.value.code == WS_POLICY_VIOLATION
    with c.websocket_connect("/api/ingest") as ws:
        ws.send_text(json.dumps(FRAME))  # a frame is not a token
        assert ws.receive_json()["code"] == "unauthorized"
        assert _closed_code(ws) == WS_POLICY_VIOLATION
    with c.websocket_connect("/api/ingest") as ws:
        ws.send_text(json.dumps({"token": settings.api_token}))
        assert ws.receive_json()["type"] == "ready"


def test_ingest_oversized_message_closes(make_client: Any, settings: Settings, runtime: Any) -> None:
    c = make_client(settings, ingest_max_bytes=1024)
    with _ingest(c, settings) as ws:
        ws.receive_json()
        ws.send_text(json.dumps({**FRAME, "pad": "x" * 2000}))
        err = ws.receive_json()
        assert err["code"] == "too_large" and "1024" in err["detail"]
        assert _closed_code(ws) == WS_MESSAGE_TOO_BIG
    assert runtime.ingested == []
    with _ingest(c, settings) as ws:  # the server still takes new trackers
        ws.receive_json()
        ws.send_text(json.dumps(FRAME))
        ws.send_text("{}")
        assert ws.receive_json()["code"] == "rejected"
    assert len(runtime.ingested) == 1


def test_ingest_too_fast_is_rejected_then_closed(
    make_client: Any, settings: Settings, runtime: Any, fake_clock: Any
) -> None:
    """The fake clock stands still: the bucket (burst 10) empties, further messages are rejected, and after
    ``ingest_close_after`` rejections within a second the tracker is closed."""
    c = make_client(settings, ingest_rate_hz=10.0, ingest_burst=10, ingest_close_after=5)
    with _ingest(c, settings) as ws:
        ws.receive_json()
        for _ in range(10):
            ws.send_text(json.dumps(FRAME))
        for _ in range(5):
            ws.send_text(json.dumps(FRAME))
            assert ws.receive_json()["code"] == "rate_limited"
        fake_clock.t += 0.5  # 5 tokens back
        for _ in range(5):
            ws.send_text(json.dumps(FRAME))
        ws.send_text(json.dumps(FRAME))  # 6th rejection in this window -> closed
        assert ws.receive_json()["code"] == "rate_limited"
        assert _closed_code(ws) == WS_POLICY_VIOLATION
    assert len(runtime.ingested) == 15
    assert c.get("/api/health").json()["status"] == "ok"


def test_ingest_survives_a_runtime_failure(client: TestClient, settings: Settings, runtime: Any) -> None:
    calls = []

    def broken(message: Any) -> None:
        calls.append(message)
        raise ZeroDivisionError("bug")

    runtime.ingest = broken
    with _ingest(client, settings) as ws:
        ws.receive_json()
        ws.send_text(json.dumps(FRAME))
        assert ws.receive_json()["code"] == "internal"
        ws.send_text(json.dumps(FRAME))
        assert ws.receive_json()["code"] == "internal"
    assert len(calls) == 2


def test_ingest_answers_hostile_messages_with_a_reason_and_the_state_counts_them(
    client: TestClient, settings: Settings, runtime: Any
) -> None:
    """Deep nesting, huge integers and wrong types reach the stream source's one parser: each gets an error
    reply with its reason code and a count in ``/api/state``, never a dropped connection."""
    from app.cell.human import StreamSource
    from app.cell.validation import REJECT_REASONS

    stream = StreamSource()
    runtime.ingest = lambda message: stream.push(message, t_received=1.0)

    def frame_counts() -> dict[str, Any]:  # what Runtime.frame_counts makes of its source's counters
        c = stream.counters
        return {
            "frames_received": c["accepted"] + c["rejected"],
            "frames_rejected": {
                "total": c["rejected"],
                "by_reason": {r: c[f"rejected_{r}"] for r in REJECT_REASONS},
            },
            "servo_overruns": 0,
        }

    runtime.frame_counts = frame_counts
    hostile = [
        ("[" * 20_000 + "]" * 20_000, "malformed"),  # 40 kB of nested lists
        ('{"t": 1' + "0" * 400 + ', "joints": []}', "bad_timestamp"),  # an integer of 10^400
        ('{"format": [1], "joints": []}', "unknown_format"),
        ('{"joints": [[0, 0, 1]], "confidence": ["0.5"]}', "joint_count"),
    ]
    with _ingest(client, settings) as ws:
        ws.receive_json()
        for text, reason in hostile:
            ws.send_text(text)
            err = ws.receive_json()
            assert (err["code"], err["reason"]) == ("rejected", reason), err
        ws.send_text(json.dumps(FRAME))  # the connection is still open and frames still go in
    assert stream.frame_at(1e9) is not None
    state = client.get("/api/state", headers={"Authorization": f"Bearer {settings.api_token}"}).json()
    by_reason = state["frames_rejected"]["by_reason"]
    assert state["frames_rejected"]["total"] == 4 and state["frames_received"] == 5
    assert (by_reason["malformed"], by_reason["bad_timestamp"], by_reason["unknown_format"]) == (1, 1, 1)
    assert state["servo_overruns"] == 0
