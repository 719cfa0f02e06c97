"""The machinery of the live WebSockets (``app.api.routes.live``): snapshot fan-out, bounds, rate limiting.

``/api/live`` streams runtime snapshots, ``/api/ingest`` takes skeleton frames in.

Fan-out (``/api/live``): one broadcaster thread holds a single bounded runtime subscription, keeps only the
newest snapshot, serialises it to JSON once per tick (at most ``live_rate_hz``, 30 Hz) and hands the text
to the event loop, where every client has its own bounded queue that drops the oldest text when the client
is slow. The runtime's control loop only ever pushes into its own bounded subscription: no client can block
it, and the JSON encoding happens off the control thread, once for all clients.

Ingest (``/api/ingest``): a tracker sends one JSON capture (every body it tracks) per text message (the
``StreamSource`` format); each message is checked for size, rate (token bucket) and JSON syntax before it
reaches ``Runtime.ingest``; every rejected message is answered with
``{"type": "error", "code": ..., "detail": ...}`` and a client that keeps flooding (or sends an oversized
message) is closed. Nothing a client sends can raise into the runtime.

Authentication on both sockets: ``Authorization: Bearer <token>`` header, ``?token=`` query parameter, or a
first message ``{"token": "..."}`` within ``auth_timeout_s``. With ``HRC_READ_ONLY_OPEN`` ``/api/live`` is
open; ``/api/ingest`` always needs the token.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from app.control.runtime import Runtime, Subscription

logger = logging.getLogger(__name__)

# WebSocket close codes (RFC 6455 section 7.4.1).
WS_NORMAL = 1000
WS_GOING_AWAY = 1001
WS_UNSUPPORTED_DATA = 1003
WS_POLICY_VIOLATION = 1008
WS_MESSAGE_TOO_BIG = 1009
WS_INTERNAL_ERROR = 1011
WS_TRY_AGAIN_LATER = 1013


@dataclass(frozen=True, slots=True)
class LiveLimits:
    """Bounds of the live sockets.

    Attributes:
        live_rate_hz: Most snapshots per second sent to each ``/api/live`` client.
        live_queue: Texts queued per live client before the oldest is dropped.
        max_live_clients: Live clients at once (more are closed with 1013).
        subscription_size: Size of the broadcaster's runtime subscription (drops the oldest).
        ingest_max_bytes: Largest accepted ``/api/ingest`` message (UTF-8 bytes); larger closes with 1009.
        ingest_rate_hz: Sustained ingest messages per second (token bucket refill rate).
        ingest_burst: Token bucket capacity (messages that may arrive back to back).
        ingest_close_after: Rate-rejected messages within one second after which the client is closed.
        max_ingest_clients: Trackers connected at once.
        auth_timeout_s: How long a client without header/query token has to send ``{"token": ...}``.
        max_auth_bytes: Largest first (authentication) message.
        clock: Monotonic clock (s) for the rate limits; tests pass a fake one.
    """

    live_rate_hz: float = 30.0
    live_queue: int = 8
    max_live_clients: int = 256
    subscription_size: int = 4
    ingest_max_bytes: int = 64 * 1024
    ingest_rate_hz: float = 120.0
    ingest_burst: int = 120
    ingest_close_after: int = 120
    max_ingest_clients: int = 4
    auth_timeout_s: float = 5.0
    max_auth_bytes: int = 4096
    clock: Callable[[], float] = time.monotonic

    def __post_init__(self) -> None:
        if not (0 < self.live_rate_hz <= 1000 and 0 < self.ingest_rate_hz <= 10_000):
            raise ValueError("live_rate_hz and ingest_rate_hz must be positive (and sane)")
        if min(self.live_queue, self.subscription_size, self.ingest_burst, self.ingest_max_bytes) < 1:
            raise ValueError("queue sizes, the ingest burst and the message size limit must be >= 1")


def finite_json(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (strict JSON has no NaN or Infinity)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite_json(v) for v in obj]
    return obj


def dumps_strict(obj: Any) -> str:
    """Compact, strict JSON (non-finite floats become null, so browsers can ``JSON.parse`` it)."""
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False)
    except ValueError:
        return json.dumps(finite_json(obj), separators=(",", ":"), allow_nan=False)


def snapshot_json(snapshot: Any) -> dict[str, Any]:
    """``{"type": "snapshot", **snapshot.to_json()}`` (the message of ``/api/live``)."""
    return {"type": "snapshot", **snapshot.to_json()}


class ClientQueue:
    """A bounded queue of texts for one WebSocket client that drops the oldest when full.

    Lives on the event loop thread (no locking): :meth:`put` is called by the hub, :meth:`get` by the client's
    sender task.
    """

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"client queue size must be >= 1, got {maxsize}")
        self._items: deque[str] = deque(maxlen=maxsize)
        self._ready = asyncio.Event()
        self.dropped = 0
        self.sent = 0

    def put(self, text: str) -> None:
        if len(self._items) == self._items.maxlen:
            self.dropped += 1
        self._items.append(text)
        self._ready.set()

    async def get(self, timeout_s: float) -> str | None:
        """The oldest queued text, waiting at most ``timeout_s``; None on timeout."""
        if not self._items:
            self._ready.clear()
            try:
                await asyncio.wait_for(self._ready.wait(), timeout_s)
            except TimeoutError:
                return None
            if not self._items:
                return None
        return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)


class LiveHub:
    """Fans runtime snapshots out to the ``/api/live`` clients (see the module docstring).

    Args:
        runtime: The runtime; only ``subscribe(maxsize)`` and ``snapshot()`` are used (tests pass a double).
        limits: Rate and queue bounds.
    """

    def __init__(self, runtime: Runtime, *, limits: LiveLimits | None = None) -> None:
        self._runtime = runtime
        self.limits = limits or LiveLimits()
        self._clients: set[ClientQueue] = set()
        self._n_clients = 0  # read by the broadcaster thread (an int read is atomic)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._subscription: Subscription | None = None
        self.published = 0
        self.latest_text: str | None = None
        self._latest_t = -math.inf  # runtime time of the snapshot in latest_text
        self.ingest_clients = 0

    # ---- lifecycle (called from the lifespan) -------------------------------------------------------
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Subscribe to the runtime and start the broadcaster thread, posting into ``loop``."""
        if self._thread is not None:
            raise RuntimeError("LiveHub already started")
        self._loop = loop
        self._stop.clear()
        self._subscription = self._runtime.subscribe(maxsize=self.limits.subscription_size)
        self._thread = threading.Thread(target=self._run, name="hrc-live-broadcaster", daemon=True)
        self._thread.start()

    def stop(self, *, timeout_s: float = 2.0) -> None:
        """Stop the broadcaster and close the subscription (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                logger.warning("live broadcaster did not stop within %.1f s", timeout_s)
            self._thread = None
        if self._subscription is not None:
            with contextlib.suppress(Exception):
                self._subscription.close()
            self._subscription = None

    # ---- clients (event loop thread) ----------------------------------------------------------------
    def register(self) -> ClientQueue | None:
        """A new client queue, or None when ``max_live_clients`` are already connected."""
        if len(self._clients) >= self.limits.max_live_clients:
            return None
        q = ClientQueue(self.limits.live_queue)
        self._clients.add(q)
        self._n_clients = len(self._clients)
        return q

    def unregister(self, q: ClientQueue) -> None:
        self._clients.discard(q)
        self._n_clients = len(self._clients)

    @property
    def client_count(self) -> int:
        return len(self._clients)

    def _fanout(self, text: str, t: float = -math.inf) -> None:
        self.latest_text = text
        self._latest_t = t
        self.published += 1
        for q in self._clients:
            q.put(text)

    def current_text(self) -> str:
        """The newest snapshot as JSON text, for a new client's first message: the broadcast text when it
        is at most one live period older than the runtime's newest snapshot, else that snapshot serialised
        now (nothing is broadcast while no client listens, so the broadcast text may be old)."""
        snap = self._runtime.snapshot()
        text = self.latest_text
        t = _snapshot_t(snap)
        if text is not None and t - self._latest_t <= 1.0 / self.limits.live_rate_hz:
            return text
        return dumps_strict(snapshot_json(snap))

    # ---- broadcaster thread -------------------------------------------------------------------------
    def _newest(self, first: Any) -> Any:
        """``first`` or a newer snapshot already waiting in the subscription."""
        newest = first
        for _ in range(self.limits.subscription_size + 1):
            nxt = self._subscription.get(timeout=0.0)
            if nxt is None:
                break
            newest = nxt
        return newest

    def _run(self) -> None:
        period_s = 1.0 / self.limits.live_rate_hz
        clock = time.monotonic
        next_t = clock()
        while not self._stop.is_set():
            try:
                snap = self._subscription.get(timeout=0.25)
                if snap is None:
                    continue
                wait_s = next_t - clock()
                if wait_s > 0 and self._stop.wait(wait_s):
                    break
                now = clock()
                next_t = max(next_t + period_s, now)
                if self._n_clients == 0:
                    continue  # nobody listens: do not serialise
                newest = self._newest(snap)
                text = dumps_strict(snapshot_json(newest))
                loop = self._loop
                if loop is None or loop.is_closed():
                    break
                loop.call_soon_threadsafe(self._fanout, text, _snapshot_t(newest))
            except RuntimeError as exc:  # the loop closed under us during shutdown
                if self._stop.is_set():
                    break
                logger.warning("live broadcaster: %s", exc)
            except Exception:
                logger.exception("live broadcaster: a snapshot could not be published; continuing")
                self._stop.wait(period_s)


def _snapshot_t(snapshot: Any) -> float:
    """A snapshot's runtime time (s); ``inf`` when it has none (never older than a cached text)."""
    try:
        t = float(snapshot.t)
    except (AttributeError, TypeError, ValueError):
        return math.inf
    return t if math.isfinite(t) else math.inf


# ---------------------------------------------------------------------------------------------------------
# rate limiting


class RateLimiter:
    """Token bucket: ``rate_hz`` sustained, ``burst`` back to back; counts rejections per one-second window.

    Args:
        rate_hz: Refill rate (messages per second).
        burst: Bucket capacity.
        clock: Monotonic time source (s).
    """

    def __init__(self, rate_hz: float, burst: int, clock: Callable[[], float]) -> None:
        self.rate_hz = rate_hz
        self.burst = burst
        self._clock = clock
        self._tokens = float(burst)
        self._t_last = clock()
        self._window_start = self._t_last
        self.rejected_in_window = 0
        self.rejected_total = 0

    def allow(self) -> bool:
        now = self._clock()
        dt_s = max(0.0, now - self._t_last)
        self._t_last = now
        self._tokens = min(float(self.burst), self._tokens + dt_s * self.rate_hz)
        if now - self._window_start >= 1.0:
            self._window_start = now
            self.rejected_in_window = 0
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        self.rejected_in_window += 1
        self.rejected_total += 1
        return False
