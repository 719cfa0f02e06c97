"""The lifecycle of a viser server with one worker thread, shared by the live scene and the replay.

:class:`ViserServerThread` starts a viser server on a host and port, places the initial camera, lets the
caller draw into it, then runs the caller's worker on a daemon thread until :meth:`ViserServerThread.stop`
sets the stop event, joins the thread and shuts the server down. Usage::

    srv = ViserServerThread(host="127.0.0.1", port=8080, name="hrc-scene")
    srv.start(build=lambda server: ..., worker=lambda stop: ...)
    print(srv.port)
    srv.stop()
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # viser is imported at start(): importing the UI must not import the web server
    import viser

logger = logging.getLogger(__name__)

#: Initial camera of every view of the cell (world frame, m): behind and beside the robot, looking at it.
CAMERA_POSITION = (2.3, -2.0, 1.6)
CAMERA_LOOK_AT = (0.45, 0.0, 0.1)
#: How long :meth:`ViserServerThread.stop` waits for the worker thread (s).
JOIN_TIMEOUT_S = 5.0


class ViserServerThread:
    """One viser server and the worker thread that updates it.

    Args:
        host: Interface to bind.
        port: TCP port (0 picks a free one; viser moves to the next free port when the port is taken: read
            :attr:`port` after :meth:`start`).
        name: Name of the worker thread, also used in error messages.
    """

    def __init__(self, *, host: str, port: int, name: str) -> None:
        self._host = host
        self._requested_port = int(port)
        self._name = name
        self._server: viser.ViserServer | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(
        self,
        build: Callable[[viser.ViserServer], None],
        worker: Callable[[threading.Event], None],
    ) -> viser.ViserServer:
        """Start the server, place the camera, call ``build(server)``, then run ``worker(stop_event)``.

        Args:
            build: Draws the scene and the GUI into the new server; when it raises, the server is stopped
                and the exception propagates (nothing keeps running).
            worker: The thread's body; it must return soon after the event it receives is set.

        Returns:
            The running server.

        Raises:
            RuntimeError: already started.
        """
        if self._server is not None:
            raise RuntimeError(f"{self._name}: start() called twice; call stop() first")
        import viser

        server = viser.ViserServer(host=self._host, port=self._requested_port, verbose=False)
        try:
            server.initial_camera.position = CAMERA_POSITION
            server.initial_camera.look_at = CAMERA_LOOK_AT
            build(server)
        except BaseException:
            server.stop()
            raise
        self._server = server
        self._stop.clear()
        self._thread = threading.Thread(target=worker, args=(self._stop,), name=self._name, daemon=True)
        self._thread.start()
        return server

    def stop(self) -> None:
        """Stop the worker thread (waiting up to :data:`JOIN_TIMEOUT_S`), then the server (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=JOIN_TIMEOUT_S)
            if self._thread.is_alive():
                logger.warning("%s thread did not stop within %.0f s", self._name, JOIN_TIMEOUT_S)
            self._thread = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    @property
    def port(self) -> int:
        """The port the server is bound to (the requested one until :meth:`start`)."""
        return self._server.get_port() if self._server is not None else self._requested_port

    @property
    def host(self) -> str:
        return self._host

    @property
    def running(self) -> bool:
        """The worker thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def server(self) -> viser.ViserServer | None:
        """The running server, None before :meth:`start` and after :meth:`stop`."""
        return self._server
