"""The JSON message format of pushed skeleton frames (``/api/ingest``), shared by the server and the clients.

One message = one capture of the tracker, a JSON object (see ``docs/stream-protocol.md`` for the full
description) with every body the tracker reports, each with its tracker id::

    {"t": 12.345, "format": "zed34", "frame": "camera", "units": "m",
     "bodies": [{"id": 3, "joints": [[x, y, z], ..., null, ...], "confidence": [0.9, ...]},
                {"id": 7, "joints": [...], "confidence": [...]}]}

``"bodies": []`` is a capture with nobody in view (a valid, person-free frame). The single-body message of
earlier clients stays valid: ``joints`` and ``confidence`` at the top level (and an optional ``body_id``,
default 0) are one body.

- ``format``: ``"canonical"`` (the app's 19 joints, :data:`~app.prediction.skeleton.JOINTS` order),
  ``"zed34"`` or ``"zed38"`` (ZED SDK ``BODY_34`` / ``BODY_38`` keypoint order), for every body.
- ``id``: the tracker's id of the body, an integer >= 0, distinct within the message.
- ``joints``: one ``[x, y, z]`` per keypoint; ``null`` (or a triple of ``null``) marks a keypoint the tracker
  did not see. ``NaN``/``Infinity`` literals are invalid (the frame is rejected), never "missing".
- ``t`` (optional): the sender's timestamp (s); the receiver maps it onto its own clock. Without it the
  receive time is used.
- ``confidence`` (optional): one value per keypoint in [0, 1] (ZED reports 0..100: divide by 100).
- ``frame`` (optional, default ``"world"``): ``"camera"`` coordinates are mapped by the camera pose of the
  receiving app's settings (``HRC_CAMERA_POSE``).
- ``units`` (optional, default ``"m"``): ``"m"`` or ``"mm"``; joints that cannot be a person in the units
  named (metres sent as ``"mm"``) are refused (``wrong_units``).

Every value is checked as sent, never coerced: strings and booleans are not numbers, a confidence outside
[0, 1] is refused (``bad_confidence``), not clipped. A rejection caused by one body names it (its index in
``bodies`` and its id).

Pure functions, no I/O, except :func:`send_messages` (an asyncio WebSocket client for the example scripts).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from collections.abc import AsyncIterator, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from app.cell.validation import FrameRejected, checked_timestamp, is_number, short_repr
from app.prediction.skeleton import NUM_JOINTS

__all__ = [
    "FORMATS",
    "MAX_BODIES",
    "StreamBody",
    "StreamMessage",
    "canonical_bodies",
    "make_bodies_message",
    "make_message",
    "message_from_zed_bodies",
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
class StreamBody:
    """One body of a parsed message, before conversion to the canonical skeleton.

    Attributes:
        id: The tracker's id of the body (>= 0; 0 for a single-body message without ``body_id``).
        joints: Keypoints (N, 3) in metres (units applied), NaN where not seen.
        confidence: Per-keypoint confidence (N,) in [0, 1], or ``None`` (not sent).
    """

    id: int
    joints: np.ndarray
    confidence: np.ndarray | None


@dataclass(frozen=True)
class StreamMessage:
    """A parsed message (one capture), before conversion to the canonical skeleton.

    Attributes:
        t: Sender's timestamp (s) or ``None``.
        format: Joint format (of every body).
        frame: ``"world"`` or ``"camera"``.
        bodies: The bodies, in the order sent (ids distinct); empty for a capture with nobody in view.
    """

    t: float | None
    format: Format
    frame: Literal["world", "camera"]
    bodies: tuple[StreamBody, ...]

    def _only(self) -> StreamBody:
        if len(self.bodies) != 1:
            raise ValueError(f"the message has {len(self.bodies)} bodies, not one")
        return self.bodies[0]

    @property
    def joints(self) -> np.ndarray:
        """The keypoints (N, 3) of a one-body message (ValueError for another count)."""
        return self._only().joints

    @property
    def confidence(self) -> np.ndarray | None:
        """The confidences (N,) of a one-body message, or ``None`` (not sent)."""
        return self._only().confidence

    @property
    def body_id(self) -> int:
        """The id of a one-body message's body."""
        return self._only().id

    @property
    def body_ids(self) -> tuple[int, ...]:
        return tuple(b.id for b in self.bodies)


#: Deepest nesting a message may have (a frame needs 3: object > joints > [x, y, z]; the rest is room for a
#: tracker's own fields); deeper text is refused unparsed.
MAX_DEPTH = 16
#: A skeleton whose seen joints span less than this, read in the units the message names, is not a person
#: in those units: metres sent as ``"mm"`` (a person of 1.7 "mm"). Read as ``"m"``, more than
#: ``MAX_SPAN`` (a person 100 m tall) is millimetres sent as metres.
MIN_SPAN = {"mm": 10.0}
MAX_SPAN = {"m": 100.0}


def _nesting_depth(text: str) -> int:
    """The deepest nesting of brackets in JSON text (brackets inside strings not counted), stopping once it
    passes :data:`MAX_DEPTH`: bounded work and no recursion whatever the text."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > MAX_DEPTH:
                    return deepest
        elif ch in "]}":
            depth -= 1
    return deepest


def _loads(message: str | bytes) -> Any:
    """A message's JSON, refused (``malformed``) when it is not UTF-8 JSON or nests deeper than a frame."""
    try:
        text = message.decode("utf-8") if isinstance(message, bytes) else message
    except UnicodeDecodeError:
        raise FrameRejected("malformed", "messages must be UTF-8 JSON text") from None
    if _nesting_depth(text) > MAX_DEPTH:
        raise FrameRejected("malformed", f"the JSON nests deeper than a frame message ({MAX_DEPTH} levels)")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise FrameRejected("malformed", f"not JSON: {short_repr(str(exc))}") from None


def _coordinate(v: Any, i: int) -> float:
    if not is_number(v):
        raise FrameRejected("malformed", f"joint {i} has a non-number coordinate {short_repr(v)}")
    try:
        x = float(v)
    except OverflowError:
        raise FrameRejected(
            "out_of_range", f"joint {i} has a coordinate too large: {short_repr(v)}"
        ) from None
    if not math.isfinite(x):
        raise FrameRejected("non_finite", f"joint {i} has a NaN/inf coordinate (use null for 'not seen')")
    return x


def _point(p: Any, i: int) -> list[float]:
    if p is None:
        return [math.nan] * 3
    if not isinstance(p, list | tuple) or len(p) != 3:
        raise FrameRejected("malformed", f"joint {i} must be [x, y, z] or null, got {short_repr(p)}")
    if all(v is None for v in p):
        return [math.nan] * 3
    return [_coordinate(v, i) for v in p]


def _confidence(c: Any, i: int) -> float:
    if c is None:
        return math.nan  # not seen
    if not is_number(c):
        raise FrameRejected("malformed", f"confidence {i} must be a number in [0, 1], got {short_repr(c)}")
    try:
        x = float(c)
    except OverflowError:
        raise FrameRejected("bad_confidence", f"confidence {i} is {short_repr(c)}, not in [0, 1]") from None
    if not math.isfinite(x):
        raise FrameRejected("non_finite", f"confidence {i} is {x}")
    if not 0.0 <= x <= 1.0:
        raise FrameRejected(
            "bad_confidence", f"confidence {i} is {x:g}, not in [0, 1] (ZED's 0..100: divide by 100)"
        )
    return x


def _choice(message: dict[str, Any], key: str, default: str, allowed: Iterable[str]) -> str:
    value = message.get(key, default)
    if not isinstance(value, str) or value not in allowed:
        raise FrameRejected(
            "unknown_format", f"{key} must be one of {sorted(allowed)}, got {short_repr(value)}"
        )
    return value


def _check_units(pts: np.ndarray, units: str) -> None:
    """Refuse joints that cannot be a person in ``units`` (see :data:`MIN_SPAN`)."""
    seen = pts[np.all(np.isfinite(pts), axis=1)]
    if len(seen) < 2:
        return
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 - (-1e308) is inf: refused as well
        span = float(np.max(np.ptp(seen, axis=0)))
    if span < MIN_SPAN.get(units, 0.0):
        raise FrameRejected(
            "wrong_units",
            f'units "{units}" but the joints span {span:.3g} {units}: they look like metres; send units "m"',
        )
    if span > MAX_SPAN.get(units, math.inf):
        raise FrameRejected(
            "wrong_units",
            f'units "{units}" but the joints span {span:.3g} {units}: they look like millimetres; '
            'send units "mm"',
        )


#: Most bodies one message may carry (a tracker reporting more is refused: ``malformed``).
MAX_BODIES = 16


def _body_id(v: Any, k: int) -> int:
    if not isinstance(v, int) or isinstance(v, bool):
        raise FrameRejected("malformed", f"body {k}: id must be an integer >= 0, got {short_repr(v)}")
    if v < 0:
        raise FrameRejected("malformed", f"body {k}: id must be >= 0, got {v}")
    return int(v)


def _parse_body(obj: dict[str, Any], fmt: str, units: str, body_id: int, label: str | None) -> StreamBody:
    """One body's ``joints`` and ``confidence``; a rejection's detail starts with ``label`` (which body)."""
    try:
        joints = obj.get("joints")
        if not isinstance(joints, list):
            raise FrameRejected("malformed", "joints must be a list of [x, y, z]")
        n = FORMATS[fmt]
        if len(joints) != n:
            raise FrameRejected("joint_count", f"format {fmt!r} needs {n} joints, got {len(joints)}")
        pts = np.array([_point(p, i) for i, p in enumerate(joints)], dtype=np.float64)
        _check_units(pts, units)
        pts *= UNITS[units]
        conf = obj.get("confidence")
        conf_arr = None
        if conf is not None:
            if not isinstance(conf, list) or len(conf) != n:
                raise FrameRejected("joint_count", f"confidence must be a list of {n} numbers")
            conf_arr = np.array([_confidence(c, i) for i, c in enumerate(conf)], dtype=np.float64)
            conf_arr = np.nan_to_num(conf_arr, nan=0.0)
    except FrameRejected as exc:
        if label is None:
            raise
        raise FrameRejected(exc.reason, f"{label}: {exc.detail}") from None
    return StreamBody(id=body_id, joints=pts, confidence=conf_arr)


def parse_message(message: dict[str, Any] | str | bytes) -> StreamMessage:
    """Parse and check one message (a dict or its JSON text): every input gives a message or a
    :class:`FrameRejected` with its reason, never another exception. A rejection caused by one body names
    it: ``body 1 (id 7): joint 4 ...``.

    Raises:
        FrameRejected: ``malformed`` (not JSON, nested too deeply, wrong types, both ``bodies`` and
            top-level ``joints``, a body id that is not an integer >= 0 or not distinct, more than
            :data:`MAX_BODIES` bodies), ``unknown_format`` (format/frame/units), ``joint_count`` (joints do
            not match the format), ``non_finite`` (NaN/inf values), ``bad_timestamp``, ``bad_confidence``,
            ``out_of_range`` (a number too large for a float), ``wrong_units`` (the joints cannot be a
            person in the units named).
    """
    if isinstance(message, bytes | str):
        message = _loads(message)
    if not isinstance(message, dict):
        raise FrameRejected("malformed", "a frame message must be a JSON object")
    kind = message.get("type", "frame")
    if kind != "frame":
        raise FrameRejected("malformed", f"unknown message type {short_repr(kind)}")
    fmt = _choice(message, "format", "canonical", FORMATS)
    frame = _choice(message, "frame", "world", FRAMES)
    units = _choice(message, "units", "m", UNITS)
    t = message.get("t")
    if t is not None:
        t = checked_timestamp(t)
    if "bodies" not in message:  # the single-body message
        body_id = message.get("body_id")
        bid = 0 if body_id is None else _body_id(body_id, 0)
        body = _parse_body(message, fmt, units, bid, None)
        return StreamMessage(t=t, format=fmt, frame=frame, bodies=(body,))  # type: ignore[arg-type]
    if "joints" in message or "confidence" in message:
        raise FrameRejected(
            "malformed", "a message has either bodies or top-level joints/confidence (one body), not both"
        )
    raw = message["bodies"]
    if not isinstance(raw, list):
        raise FrameRejected("malformed", 'bodies must be a list of {"id": ..., "joints": [...]}')
    if len(raw) > MAX_BODIES:
        raise FrameRejected("malformed", f"{len(raw)} bodies; at most {MAX_BODIES} per message")
    bodies: list[StreamBody] = []
    seen: dict[int, int] = {}
    for k, obj in enumerate(raw):
        if not isinstance(obj, dict):
            raise FrameRejected("malformed", f"body {k} must be a JSON object, got {short_repr(obj)}")
        if "id" not in obj:
            raise FrameRejected("malformed", f"body {k} has no id (the tracker's id of the body)")
        bid = _body_id(obj["id"], k)
        if bid in seen:
            raise FrameRejected(
                "malformed", f"body {k} has the id {bid} of body {seen[bid]}: ids must differ"
            )
        seen[bid] = k
        bodies.append(_parse_body(obj, fmt, units, bid, f"body {k} (id {bid})"))
    return StreamMessage(t=t, format=fmt, frame=frame, bodies=tuple(bodies))  # type: ignore[arg-type]


def to_canonical(
    msg: StreamMessage, *, T_world_camera: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Canonical joints (J, 3) in the world frame (NaN where not seen) and confidences (J,) of a one-body
    message (:func:`canonical_bodies` for any number of bodies).

    A canonical joint derived from a keypoint that was not seen is itself not seen (NaN, confidence 0).

    Raises:
        FrameRejected: ``no_camera_pose`` for a camera-frame message without ``T_world_camera``.
        ValueError: the message has not exactly one body.
    """
    return _body_to_canonical(msg, msg._only(), T_world_camera)


def canonical_bodies(
    msg: StreamMessage, *, T_world_camera: np.ndarray | None = None
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Every body of ``msg`` as ``(id, joints (J, 3), confidence (J,))``, canonical, in the world frame (NaN
    where not seen); see :func:`to_canonical`. A message with no body gives an empty list.

    Raises:
        FrameRejected: ``no_camera_pose`` for a camera-frame message without ``T_world_camera``.
    """
    return [(b.id, *_body_to_canonical(msg, b, T_world_camera)) for b in msg.bodies]


def _body_to_canonical(
    msg: StreamMessage, body: StreamBody, T_world_camera: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    from app.prediction import adapters

    pts = body.joints
    seen = np.all(np.isfinite(pts), axis=1)
    conf = body.confidence if body.confidence is not None else np.ones(len(pts))
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


def _encode_body(
    joints: np.ndarray, confidence: np.ndarray | None, format: Format, ndigits: int
) -> dict[str, Any]:
    j = np.asarray(joints, dtype=np.float64)
    n = FORMATS[format]
    if j.shape != (n, 3):
        raise ValueError(f"format {format!r} needs joints of shape ({n}, 3), got {j.shape}")
    pts: list[list[float | None] | None] = [
        None if not np.all(np.isfinite(p)) else [_num(v, ndigits) for v in p] for p in j
    ]
    out: dict[str, Any] = {"joints": pts}
    if confidence is not None:
        c = np.asarray(confidence, dtype=np.float64)
        if c.shape != (n,):
            raise ValueError(f"confidence must have shape ({n},), got {c.shape}")
        out["confidence"] = [0.0 if not math.isfinite(v) else round(float(v), 3) for v in c]
    return out


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
    """Build one single-body message (a JSON-ready dict); NaN keypoints become ``null`` ("not seen").
    :func:`make_bodies_message` builds a message of any number of bodies.

    Args:
        joints: Keypoints (N, 3) in ``units``, N given by ``format``.
        format: Joint format.
        t: Sender's timestamp (s), or ``None`` to let the receiver use its receive time.
        confidence: Per-keypoint confidence (N,) in [0, 1].
        frame: Coordinate frame of ``joints``.
        units: Length unit of ``joints``.
        body_id: The tracker's body id (the receiver takes 0 without it).
        ndigits: Decimals kept (4 in metres = 0.1 mm).
    """
    msg: dict[str, Any] = {"format": format, "frame": frame, "units": units}
    msg.update(_encode_body(joints, confidence, format, ndigits))
    if t is not None:
        msg["t"] = float(t)
    if body_id is not None:
        msg["body_id"] = int(body_id)
    return msg


def make_bodies_message(
    bodies: Sequence[tuple[int, np.ndarray, np.ndarray | None]],
    *,
    format: Format = "canonical",
    t: float | None = None,
    frame: Literal["world", "camera"] = "world",
    units: Literal["m", "mm"] = "m",
    ndigits: int = 4,
) -> dict[str, Any]:
    """Build one message of every body of a capture (a JSON-ready dict), the inverse of
    :func:`parse_message`: ``bodies`` are ``(id, joints (N, 3), confidence (N,) or None)``, ids distinct
    and >= 0; none is a capture with nobody in view. See :func:`make_message` for the other arguments.

    Raises:
        ValueError: an id repeated or negative, or joints/confidences of the wrong shape.
    """
    ids = [int(b[0]) for b in bodies]
    if len(set(ids)) != len(ids) or any(i < 0 for i in ids):
        raise ValueError(f"body ids must be distinct and >= 0, got {ids}")
    encoded = [
        {"id": i, **_encode_body(j, c, format, ndigits)} for i, (_, j, c) in zip(ids, bodies, strict=True)
    ]
    msg: dict[str, Any] = {"format": format, "frame": frame, "units": units, "bodies": encoded}
    if t is not None:
        msg["t"] = float(t)
    return msg


def _zed_confidence(keypoint_confidence: np.ndarray | None) -> np.ndarray | None:
    if keypoint_confidence is None:
        return None
    conf = np.nan_to_num(np.asarray(keypoint_confidence, dtype=np.float64), nan=0.0) / 100.0
    return np.clip(conf, 0.0, 1.0)


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
    """A single-body message from one ZED ``BodyData``: ``keypoint`` (N, 3) (NaN where not detected) and
    ``keypoint_confidence`` (N,) in ZED's 0..100 scale (NaN where not detected)."""
    return make_message(
        np.asarray(keypoint, dtype=np.float64),
        format=body_format,
        t=t,
        confidence=_zed_confidence(keypoint_confidence),
        frame=frame,
        units=units,
        body_id=body_id,
    )


def message_from_zed_bodies(
    bodies: Sequence[tuple[int, np.ndarray, np.ndarray | None]],
    *,
    t: float | None,
    body_format: Literal["zed34", "zed38"],
    frame: Literal["world", "camera"] = "camera",
    units: Literal["m", "mm"] = "m",
) -> dict[str, Any]:
    """One message of every body of a ZED capture: ``bodies`` are ``(BodyData.id, keypoint (N, 3),
    keypoint_confidence (N,) in 0..100)`` (NaN where not detected); none: nobody in view."""
    return make_bodies_message(
        [(int(i), np.asarray(kp, dtype=np.float64), _zed_confidence(c)) for i, kp, c in bodies],
        format=body_format,
        t=t,
        frame=frame,
        units=units,
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
