"""``hrc serve``: the operator API under uvicorn, one worker, with a safe shutdown order.

On SIGTERM or SIGINT the robot is stopped at once (the runtime's ``stop`` runs on a helper thread as soon as
the signal arrives, before uvicorn drains its connections); then uvicorn shuts down, and the lifespan stores
the aborted trial, flushes the events and closes the database.
"""

from __future__ import annotations

import logging
import re
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

from app.api.live_hub import LiveLimits
from app.config import Settings

logger = logging.getLogger(__name__)

#: Seconds uvicorn waits for open connections at shutdown before closing them.
GRACEFUL_SHUTDOWN_S = 5.0

#: A secret in a URL's query (``?token=...``, ``&access_token=...``): its value is never logged.
_SECRET_QUERY = re.compile(r"(?i)([?&](?:token|access_token|api_token)=)[^&#\s\"']*")
#: The loggers that write request lines: uvicorn's access log and its error log (WebSocket handshakes).
REDACTED_LOGGERS = ("uvicorn.access", "uvicorn.error", "uvicorn")


def redact_secrets(text: str) -> str:
    """``text`` with the value of every ``token`` query parameter replaced by ``***``."""
    return _SECRET_QUERY.sub(r"\1***", text)


class RedactSecrets(logging.Filter):
    """Replaces the operator token in logged URLs (``/api/live?token=...``) before any handler sees it."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact_secrets(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact_secrets(a) if isinstance(a, str) else a for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: redact_secrets(v) if isinstance(v, str) else v for k, v in record.args.items()}
        return True


def install_log_redaction() -> None:
    """Put :class:`RedactSecrets` on the loggers of :data:`REDACTED_LOGGERS` (once each)."""
    for name in REDACTED_LOGGERS:
        logger_ = logging.getLogger(name)
        if not any(isinstance(f, RedactSecrets) for f in logger_.filters):
            logger_.addFilter(RedactSecrets())


def _uvicorn_server_class() -> type:
    import uvicorn

    class _Server(uvicorn.Server):
        """uvicorn's server that stops the robot first when asked to exit."""

        def __init__(self, config: uvicorn.Config, app: Any) -> None:
            super().__init__(config)
            self._app = app
            self._robot_stop_started = False

        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            if not self._robot_stop_started:
                self._robot_stop_started = True
                stop = getattr(self._app.state, "stop_runtime", None)
                if stop is not None:
                    logger.warning("signal %s: stopping the robot first", sig)
                    # not in the signal handler itself: it may interrupt a thread holding a runtime lock
                    threading.Thread(target=stop, name="hrc-stop-robot", daemon=True).start()
            super().handle_exit(sig, frame)

    return _Server


def run_server(
    settings: Settings,
    *,
    log_level: str = "info",
    limits: LiveLimits | None = None,
    echo: Callable[[str], None] | None = None,
) -> None:
    """Serve the operator API on ``settings.host:settings.port`` until SIGTERM/SIGINT.

    Args:
        settings: Application settings (host 127.0.0.1 by default: set ``HRC_HOST=0.0.0.0`` or ``--host`` to
            serve a network, and keep the token secret).
        log_level: uvicorn's log level.
        limits: Live socket bounds (default :class:`LiveLimits`).
        echo: Where to show a newly generated operator token once (the CLI passes ``typer.echo``).
    """
    import uvicorn

    from app.api.app import create_app
    from app.api.auth import ensure_api_token

    limits = limits or LiveLimits()
    token = ensure_api_token(settings)
    if token.source == "generated" and echo is not None:
        echo(
            f"Operator token (generated now, stored in {token.path} with mode 0600):\n\n    {token.value}\n\n"
            "Send it as 'Authorization: Bearer <token>'; set HRC_API_TOKEN to choose your own."
        )
    app = create_app(settings, limits=limits)
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        workers=1,
        log_level=log_level,
        lifespan="on",
        proxy_headers=False,
        server_header=False,
        # a frame larger than this is refused by the protocol layer (1009); smaller oversized ones get a
        # clear error message from /api/ingest
        ws_max_size=4 * limits.ingest_max_bytes,
        ws_max_queue=32,
        limit_concurrency=512,
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
    )
    install_log_redaction()  # after uvicorn.Config, which configures its loggers
    server = _uvicorn_server_class()(config, app)
    if settings.host not in ("127.0.0.1", "localhost", "::1"):
        logger.warning(
            "serving on %s: reachable from the network; every /api route needs the token", settings.host
        )
    server.run()
