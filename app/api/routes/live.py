"""``/api/live`` (runtime snapshots at up to 30 Hz) and ``/api/ingest`` (skeleton frames from a tracker).

See :mod:`app.api.live_hub` for the fan-out, the bounds and the message formats.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from typing import Any

from fastapi import APIRouter, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from app.api.auth import bearer_token, tokens_match
from app.api.deps import ApiContext
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
from app.cell.stream_protocol import MAX_BODIES
from app.cell.validation import FrameRejected
from app.control.runtime import IngestUnavailable, Runtime

logger = logging.getLogger(__name__)

#: Exceptions of ``Runtime.ingest`` and the code of the error message ``/api/ingest`` answers each with
#: (an open WebSocket has no HTTP status; the frame is dropped and the socket stays open).
INGEST_ERROR_CODES: dict[type[Exception], str] = {
    FrameRejected: "rejected",
    IngestUnavailable: "unavailable",
}
_INGEST_ERRORS = tuple(INGEST_ERROR_CODES)


def _ingest_error_code(exc: Exception) -> str:
    """The code of ``exc`` in :data:`INGEST_ERROR_CODES` (a subclass takes its base class's code)."""
    return next(code for cls, code in INGEST_ERROR_CODES.items() if isinstance(exc, cls))


# ---------------------------------------------------------------------------------------------------------
# authentication of a WebSocket


def _ctx(websocket: WebSocket) -> ApiContext | None:
    return getattr(websocket.app.state, "hrc", None)


async def authenticate(websocket: WebSocket, *, token: str, allow_open: bool, limits: LiveLimits) -> bool:
    """Accept ``websocket`` if it is authorised; close it (1008) and return False if not.

    A token in the ``Authorization`` header or ``?token=`` is checked before accepting (a wrong one is denied
    during the handshake). Without either, the socket is accepted and the first message must be
    ``{"token": "..."}`` within ``limits.auth_timeout_s``.
    """
    given = bearer_token(websocket.headers.get("authorization")) or websocket.query_params.get("token")
    if given is not None:
        if not tokens_match(given, token):
            await websocket.close(code=WS_POLICY_VIOLATION, reason="invalid operator token")
            return False
        await websocket.accept()
        return True
    await websocket.accept()
    if allow_open:
        return True
    try:
        message = await asyncio.wait_for(websocket.receive(), limits.auth_timeout_s)
    except TimeoutError:
        await _send_error(websocket, "unauthorized", 'no token: send {"token": "..."} first')
        await websocket.close(code=WS_POLICY_VIOLATION, reason="authentication timed out")
        return False
    if message["type"] == "websocket.disconnect":
        return False
    text = _message_text(message)
    presented = None
    if text is not None and len(text) <= limits.max_auth_bytes:
        with contextlib.suppress(ValueError):
            obj = json.loads(text)
            if isinstance(obj, dict) and isinstance(obj.get("token"), str):
                presented = obj["token"]
    if not tokens_match(presented, token):
        await _send_error(websocket, "unauthorized", "missing or invalid operator token")
        await websocket.close(code=WS_POLICY_VIOLATION, reason="invalid operator token")
        return False
    return True


def _message_text(message: dict[str, Any]) -> str | None:
    """The text of a received ASGI WebSocket message (UTF-8 decoded bytes), None if undecodable/empty."""
    text = message.get("text")
    if text is not None:
        return text
    data = message.get("bytes")
    if data is None:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


async def _send_error(websocket: WebSocket, code: str, detail: str, *, reason: str | None = None) -> None:
    """``{"type": "error", "code": ..., "detail": ...}``, with the frame's rejection ``reason`` (one of
    :data:`~app.cell.validation.REJECT_REASONS`) when a frame was rejected."""
    if websocket.application_state == WebSocketState.CONNECTED:
        msg: dict[str, Any] = {"type": "error", "code": code, "detail": detail}
        if reason is not None:
            msg["reason"] = reason
        with contextlib.suppress(WebSocketDisconnect, RuntimeError, OSError):
            await websocket.send_text(dumps_strict(msg))


router = APIRouter(tags=["live"])


@router.websocket("/live")
async def live_socket(websocket: WebSocket) -> None:
    """Snapshots of the runtime as JSON text messages (``{"type": "snapshot", ...}``) at up to 30 Hz."""
    ctx = _ctx(websocket)
    if ctx is None:
        await websocket.close(code=WS_TRY_AGAIN_LATER, reason="server starting or stopping")
        return
    hub: LiveHub = ctx.hub
    if not await authenticate(
        websocket, token=ctx.token, allow_open=ctx.settings.read_only_open, limits=hub.limits
    ):
        return
    q = hub.register()
    if q is None:
        await _send_error(
            websocket, "too_many_clients", f"at most {hub.limits.max_live_clients} live clients"
        )
        await websocket.close(code=WS_TRY_AGAIN_LATER, reason="too many live clients")
        return
    try:
        q.put(hub.current_text())
        sender = asyncio.create_task(_live_sender(websocket, q))
        receiver = asyncio.create_task(_drain_until_disconnect(websocket))
        done, pending = await asyncio.wait({sender, receiver}, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
        for task in pending:
            with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError, OSError):
                await task
        for task in done:
            exc = task.exception()
            if exc is not None and not isinstance(exc, WebSocketDisconnect | OSError | RuntimeError):
                logger.warning("live client ended with %r", exc)
    finally:
        hub.unregister(q)
        if q.dropped:
            logger.info("live client disconnected; %d snapshots dropped for it (slow client)", q.dropped)


async def _live_sender(websocket: WebSocket, q: ClientQueue) -> None:
    while True:
        text = await q.get(timeout_s=1.0)
        if text is None:
            continue
        await websocket.send_text(text)
        q.sent += 1


async def _drain_until_disconnect(websocket: WebSocket) -> None:
    """Read (and ignore) client messages until the client disconnects."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return


@router.websocket("/ingest")
async def ingest_socket(websocket: WebSocket) -> None:
    """Skeleton frames from an external tracker into the runtime's ``StreamSource`` (one JSON text each: one
    capture with every tracked body, :mod:`app.cell.stream_protocol`)."""
    ctx = _ctx(websocket)
    if ctx is None:
        await websocket.close(code=WS_TRY_AGAIN_LATER, reason="server starting or stopping")
        return
    hub: LiveHub = ctx.hub
    limits = hub.limits
    if not await authenticate(websocket, token=ctx.token, allow_open=False, limits=limits):
        return
    if hub.ingest_clients >= limits.max_ingest_clients:
        await _send_error(websocket, "too_many_clients", f"at most {limits.max_ingest_clients} trackers")
        await websocket.close(code=WS_TRY_AGAIN_LATER, reason="too many ingest clients")
        return
    hub.ingest_clients += 1
    try:
        await websocket.send_text(
            dumps_strict(
                {
                    "type": "ready",
                    "max_message_bytes": limits.ingest_max_bytes,
                    "max_rate_hz": limits.ingest_rate_hz,
                    "max_bodies": MAX_BODIES,
                    "human_source": ctx.settings.human_source,
                }
            )
        )
        await _ingest_loop(websocket, ctx.runtime, limits)
    except WebSocketDisconnect:
        pass
    finally:
        hub.ingest_clients -= 1


async def _ingest_loop(websocket: WebSocket, runtime: Runtime, limits: LiveLimits) -> None:
    limiter = RateLimiter(limits.ingest_rate_hz, limits.ingest_burst, limits.clock)
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        raw_len = len(message["text"].encode("utf-8")) if message.get("text") is not None else None
        if raw_len is None:
            raw_len = len(message.get("bytes") or b"")
        if raw_len > limits.ingest_max_bytes:
            await _send_error(
                websocket, "too_large", f"message of {raw_len} bytes exceeds {limits.ingest_max_bytes} bytes"
            )
            await websocket.close(code=WS_MESSAGE_TOO_BIG, reason="message too big")
            return
        if not limiter.allow():
            if limiter.rejected_in_window > limits.ingest_close_after:
                await _send_error(
                    websocket, "rate_limited", "closing: the rate limit was exceeded repeatedly"
                )
                await websocket.close(code=WS_POLICY_VIOLATION, reason="rate limit exceeded")
                return
            await _send_error(
                websocket, "rate_limited", f"more than {limits.ingest_rate_hz:g} messages/s; message dropped"
            )
            continue
        # the text as received: the stream source parses it (one validation, every rejection counted)
        raw = message.get("text")
        if raw is None:
            raw = message.get("bytes") or b""
        try:
            runtime.ingest(raw)
        except _INGEST_ERRORS as exc:
            reason = exc.reason if isinstance(exc, FrameRejected) else None
            await _send_error(websocket, _ingest_error_code(exc), str(exc), reason=reason)
        except Exception:
            logger.exception("ingest: the runtime failed on a frame; the frame is dropped")
            await _send_error(websocket, "internal", "the frame could not be processed; it was dropped")
