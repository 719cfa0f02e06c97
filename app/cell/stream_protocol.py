"""The JSON message format of pushed skeleton frames (``/api/ingest``), shared by the server and the clients.

One message = one skeleton, a JSON object (see ``docs/stream-protocol.md`` for the full description)::

    {"t": 12.345, "format": "zed34", "frame": "camera", "units": "m",
     "joints": [[x, y, z], ..., null, ...], "confidence": [0.9, ...]}

- ``format``: ``"canonical"`` (the app's 19 joints, :data:`~app.prediction.skeleton.JOINTS` order),
  ``"zed34"`` or ``"zed38"`` (ZED SDK ``BODY_34`` / ``BODY_38`` keypoint order).
- ``joints``: one ``[x, y, z]`` per keypoint; ``null`` (or a triple of ``null``) marks a keypoint the tracker
  did not see. ``NaN``/``Infinity`` literals are invalid (the frame is rejected), never "missing".
- ``t`` (optional): the sender's timestamp (s); the receiver maps it onto its own clock. Without it the
  receive time is used.
- ``confidence`` (optional): one value per keypoint in [0, 1] (ZED reports 0..100: divide by 100).
- ``frame`` (optional, default ``"world"``): ``"camera"`` coordinates are mapped by the camera pose of the
  receiving app's settings (``HRC_CAMERA_POSE``).
- ``units`` (optional, default ``"m"``): ``"m"`` or ``"mm"``.

Pure functions, no I/O, except :func:`send_messages` (an asyncio WebSocket client for the example scripts).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from collections.abc import AsyncIterator, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from app.cell.validation import FrameRejected
from app.prediction.skeleton import NUM_JOINTS

__all__ = [
    "FORMATS",
    "StreamMessage",
    "make_message",
    "message_from_zed_body",
    "parse_message",
    "send_messages",
    "to_canonical",
]

log = logging.getLogger(__name__)

Format = Literal["canonical", "zed34", "zed38"]
#: Joint formats and their keypoint counts.
FORMATS: dict[str, int] = {"canonical": NUM_JOINTS, "zed34": 34, "zed38": 38}
FRAMES = ("world", "camera")
UNITS = {"m": 1.0, "mm": 0.001}


@dataclass(frozen=True)
class StreamMessage:
    """A parsed message, before conversion to the canonical skeleton.

    Attributes:
        t: Sender's timestamp (s) or ``None``.
        format: Joint format.
        joints: Keypoints (N, 3) in metres (units applied), NaN where not seen.
        confidence: Per-keypoint confidence (N,) in [0, 1], or ``None`` (not sent).
        frame: ``"world"`` or ``"camera"``.
        body_id: The tracker's body id, if sent.
    """

    t: float | None
    format: Format
    joints: np.ndarray
    confidence: np.ndarray | None
    frame: Literal["world", "camera"]
    body_id: int | None = None


def _point(p: Any, i: int) -> list[float]:
    if p is None:
        return [math.nan] * 3
    if not isinstance(p, list | tuple) or len(p) != 3:
        raise FrameRejected("malformed", f"joint {i} must be [x, y, z] or null, got {str(p)[:40]}")
    if all(v is None for v in p):
        return [math.nan] * 3
    out = []
    for v in p:
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise FrameRejected("malformed", f"joint {i} has a non-number coordinate {str(v)[:20]}")
        if not math.isfinite(v):
            raise FrameRejected("non_finite", f"joint {i} has a NaN/inf coordinate (use null for 'not seen')")
        out.append(float(v))
    return out


def parse_message(message: dict[str, Any] | str | bytes) -> StreamMessage:
    """Parse and check one message (a dict or its JSON text).

    Raises:
        FrameRejected: ``malformed`` (not JSON, wrong types), ``unknown_format`` (format/frame/units),
            ``joint_count`` (joints do not match the format), ``non_finite`` (NaN/inf values).
    """
    if isinstance(message, bytes | str):
        try:
            message = json.loads(message)
        except (ValueError, UnicodeDecodeError) as exc:
            raise FrameRejected("malformed", f"not JSON: {exc}") from None
    if not isinstance(message, dict):
        raise FrameRejected("malformed", "a frame message must be a JSON object")
    if message.get("type", "frame") != "frame":
        raise FrameRejected("malformed", f"unknown message type {str(message.get('type'))[:30]!r}")
    fmt = message.get("format", "canonical")
    if fmt not in FORMATS:
        raise FrameRejected(
            "unknown_format", f"format must be one of {sorted(FORMATS)}, got {str(fmt)[:30]!r}"
        )
    frame = message.get("frame", "world")
    if frame not in FRAMES:
        raise FrameRejected("unknown_format", f"frame must be 'world' or 'camera', got {str(frame)[:30]!r}")
    units = message.get("units", "m")
    if units not in UNITS:
        raise FrameRejected("unknown_format", f"units must be 'm' or 'mm', got {str(units)[:30]!r}")
    t = message.get("t")
    if t is not None:
        if isinstance(t, bool) or not isinstance(t, int | float):
            raise FrameRejected("malformed", f"t must be a number of seconds, got {str(t)[:30]!r}")
        if not math.isfinite(t):
            raise FrameRejected("non_finite", f"timestamp {t}")
        t = float(t)
    joints = message.get("joints")
    if not isinstance(joints, list):
        raise FrameRejected("malformed", "joints must be a list of [x, y, z]")
    n = FORMATS[fmt]
    if len(joints) != n:
        raise FrameRejected("joint_count", f"format {fmt!r} needs {n} joints, got {len(joints)}")
    pts = np.array([_point(p, i) for i, p in enumerate(joints)], dtype=np.float64)
    pts *= UNITS[units]
    conf = message.get("confidence")
    conf_arr = None
    if conf is not None:
        if not isinstance(conf, list) or len(conf) != n:
            raise FrameRejected("joint_count", f"confidence must be a list of {n} numbers")
        try:
            conf_arr = np.array([math.nan if c is None else float(c) for c in conf], dtype=np.float64)
        except (TypeError, ValueError):
            raise FrameRejected("malformed", "confidence values must be numbers") from None
        if np.any(np.isinf(conf_arr)):
            raise FrameRejected("non_finite", "confidence has inf")
        conf_arr = np.nan_to_num(conf_arr, nan=0.0)
    body_id = message.get("body_id")
    body_id = int(body_id) if isinstance(body_id, int) and not isinstance(body_id, bool) else None
    return StreamMessage(t=t, format=fmt, joints=pts, confidence=conf_arr, frame=frame, body_id=body_id)


def to_canonical(
    msg: StreamMessage, *, T_world_camera: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Canonical joints (J, 3) in the world frame (NaN where not seen) and confidences (J,).

    A canonical joint derived from a keypoint that was not seen is itself not seen (NaN, confidence 0).

    Raises:
        FrameRejected: ``no_camera_pose`` for a camera-frame message without ``T_world_camera``.
    """
    from app.prediction import adapters

    pts = msg.joints
    seen = np.all(np.isfinite(pts), axis=1)
    conf = msg.confidence if msg.confidence is not None else np.ones(len(pts))
    conf = np.where(seen, conf, 0.0)
    if msg.format == "canonical":
        joints, conf_c = pts.copy(), conf
    else:
        W = adapters.W_ZED34 if msg.format == "zed34" else adapters.W_ZED38
        filled = np.where(seen[:, None], pts, 0.0)
        convert = adapters.from_zed34 if msg.format == "zed34" else adapters.from_zed38
        conf_of = adapters.confidence_from_zed34 if msg.format == "zed34" else adapters.confidence_from_zed38
        joints = convert(filled)
        missing = np.any((W > 0) & ~seen[None, :], axis=1)
        joints[missing] = np.nan
        conf_c = np.where(missing, 0.0, conf_of(conf))
    if msg.frame == "camera":
        if T_world_camera is None:
            raise FrameRejected(
                "no_camera_pose",
                "the message is in the camera frame but no camera pose is configured; set HRC_CAMERA_POSE "
                "(x, y, z, roll, pitch, yaw of the camera in the world frame) or send world coordinates",
            )
        T = np.asarray(T_world_camera, dtype=np.float64)
        joints = joints @ T[:3, :3].T + T[:3, 3]
    return joints, np.clip(conf_c, 0.0, 1.0)


def _num(v: float, ndigits: int) -> float | None:
    return round(float(v), ndigits) if math.isfinite(v) else None


def make_message(
    joints: np.ndarray,
    *,
    format: Format = "canonical",
    t: float | None = None,
    confidence: np.ndarray | None = None,
    frame: Literal["world", "camera"] = "world",
    units: Literal["m", "mm"] = "m",
    body_id: int | None = None,
    ndigits: int = 4,
) -> dict[str, Any]:
    """Build one message (a JSON-ready dict); NaN keypoints become ``null`` ("not seen").

    Args:
        joints: Keypoints (N, 3) in ``units``, N given by ``format``.
        format: Joint format.
        t: Sender's timestamp (s), or ``None`` to let the receiver use its receive time.
        confidence: Per-keypoint confidence (N,) in [0, 1].
        frame: Coordinate frame of ``joints``.
        units: Length unit of ``joints``.
        body_id: The tracker's body id.
        ndigits: Decimals kept (4 in metres = 0.1 mm).
    """
    j = np.asarray(joints, dtype=np.float64)
    n = FORMATS[format]
    if j.shape != (n, 3):
        raise ValueError(f"format {format!r} needs joints of shape ({n}, 3), got {j.shape}")
    pts: list[list[float] | None] = []
    for p in j:
        pts.append(None if not np.all(np.isfinite(p)) else [_num(v, ndigits) for v in p])  # type: ignore[misc]
    msg: dict[str, Any] = {"format": format, "frame": frame, "units": units, "joints": pts}
    if t is not None:
        msg["t"] = float(t)
    if confidence is not None:
        c = np.asarray(confidence, dtype=np.float64)
        if c.shape != (n,):
            raise ValueError(f"confidence must have shape ({n},), got {c.shape}")
        msg["confidence"] = [0.0 if not math.isfinite(v) else round(float(v), 3) for v in c]
    if body_id is not None:
        msg["body_id"] = int(body_id)
    return msg


def message_from_zed_body(
    keypoint: np.ndarray,
    keypoint_confidence: np.ndarray | None,
    *,
    t: float | None,
    body_format: Literal["zed34", "zed38"],
    frame: Literal["world", "camera"] = "camera",
    units: Literal["m", "mm"] = "m",
    body_id: int | None = None,
) -> dict[str, Any]:
    """A message from one ZED ``BodyData``: ``keypoint`` (N, 3) (NaN where not detected) and
    ``keypoint_confidence`` (N,) in ZED's 0..100 scale (NaN where not detected)."""
    conf = None
    if keypoint_confidence is not None:
        conf = np.nan_to_num(np.asarray(keypoint_confidence, dtype=np.float64), nan=0.0) / 100.0
        conf = np.clip(conf, 0.0, 1.0)
    return make_message(
        np.asarray(keypoint, dtype=np.float64),
        format=body_format,
        t=t,
        confidence=conf,
        frame=frame,
        units=units,
        body_id=body_id,
    )


async def send_messages(
    url: str,
    messages: Iterable[dict[str, Any]] | AsyncIterator[dict[str, Any]],
    *,
    token: str | None,
    rate_hz: float | None = None,
    open_timeout_s: float = 10.0,
    on_reply: Any = None,
) -> dict[str, int]:
    """Send messages to a WebSocket (``ws://host:8000/api/ingest``) with ``Authorization: Bearer <token>``.

    Paces the messages at ``rate_hz`` (absolute deadlines on the event loop's monotonic clock, no drift)
    when given; replies from the server (``{"type": "ready" | "error", ...}``) are counted, logged and passed
    to ``on_reply(dict)``. Returns ``{"sent": n, "errors": n}``.
    """
    from websockets.asyncio.client import connect

    headers = {"Authorization": f"Bearer {token}"} if token else None
    counts = {"sent": 0, "errors": 0}

    async def _reader(ws: Any) -> None:
        async for raw in ws:
            try:
                reply = json.loads(raw)
            except ValueError:
                continue
            if isinstance(reply, dict) and reply.get("type") == "error":
                counts["errors"] += 1
                log.warning("server rejected a frame: %s %s", reply.get("code"), reply.get("detail"))
            if on_reply is not None:
                on_reply(reply)

    loop = asyncio.get_running_loop()
    async with connect(url, additional_headers=headers, open_timeout=open_timeout_s) as ws:
        reader = asyncio.create_task(_reader(ws))
        try:
            t_next = loop.time()
            async for msg in _aiter(messages):
                if rate_hz:
                    delay = t_next - loop.time()
                    if delay > 0:
                        await asyncio.sleep(delay)
                    t_next = max(t_next + 1.0 / rate_hz, loop.time() - 1.0 / rate_hz)
                await ws.send(json.dumps(msg, allow_nan=False))
                counts["sent"] += 1
            await asyncio.sleep(0.05)  # let the last replies arrive
        finally:
            reader.cancel()
    return counts


async def _aiter(messages: Iterable[dict[str, Any]] | AsyncIterator[dict[str, Any]]) -> AsyncIterator[dict]:
    if hasattr(messages, "__aiter__"):
        async for m in messages:  # type: ignore[union-attr]
            yield m
    else:
        it: Iterator[dict[str, Any]] = iter(messages)  # type: ignore[arg-type]
        for m in it:
            yield m
