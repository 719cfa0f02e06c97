"""The lifecycle of a viser server with one worker thread, shared by the live scene and the replay.

:class:`ViserServerThread` starts a viser server on a host and port, places the initial camera, lets the
caller draw into it, then runs the caller's worker on a daemon thread until :meth:`ViserServerThread.stop`
sets the stop event, joins the thread and shuts the server down. Usage::

    srv = ViserServerThread(host="127.0.0.1", port=8080, name="hrc-scene", token="...")
    srv.start(build=lambda server: ..., worker=lambda stop: ...)
    print(srv.port)
    srv.stop()

With a ``token``, a viewer's WebSocket must carry it (``?token=`` in the socket's URL, ``Authorization:
Bearer``, or the cookie ``hrc_token``); one without it is closed (1008) before it receives anything of the
scene or the GUI. The page itself (viser's client application, the same for every server) is served to
anyone. In a browser: ``http://HOST:PORT/?websocket=ws://HOST:PORT/%3Ftoken%3D<token>`` (viser's client
connects to the URL given in ``websocket``).

A requested port that another program holds is an error (:class:`PortInUse`), not a move to the next one.
"""

from __future__ import annotations

import hmac
import logging
import socket
import threading
from collections.abc import Callable
from http.cookies import CookieError, SimpleCookie
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, urlsplit

if TYPE_CHECKING:  # viser is imported at start(): importing the UI must not import the web server
    import viser

logger = logging.getLogger(__name__)

#: Initial camera of every view of the cell (world frame, m): behind and beside the robot, looking at it.
CAMERA_POSITION = (2.3, -2.0, 1.6)
CAMERA_LOOK_AT = (0.45, 0.0, 0.1)
#: How long :meth:`ViserServerThread.stop` waits for the worker thread (s).
JOIN_TIMEOUT_S = 5.0
#: WebSocket close code of a viewer without the token (policy violation, as the API's sockets).
WS_POLICY_VIOLATION = 1008
#: The cookie a page may set to pass the token to the viewer's socket (cookies are per host, not per port).
TOKEN_COOKIE = "hrc_token"


class PortInUse(OSError):  # noqa: N818 (reads as the condition it reports)
    """The requested port of a viser server is held by another program.

    Attributes:
        host: The interface.
        port: The port.
    """

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.port = int(port)
        super().__init__(f"port {port} on {host} is in use by another program")


def check_port_free(host: str, port: int) -> None:
    """Raise :class:`PortInUse` when nothing can listen on ``host:port`` now (port 0 is always free).

    A check before a server starts, to report a taken port before anything else starts; the server
    itself checks again (:meth:`ViserServerThread.start`)."""
    if int(port) == 0:
        return
    try:
        infos = socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
    except socket.gaierror:
        return  # the server will report an unknown host itself
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
        except OSError as exc:
            raise PortInUse(host, int(port)) from exc


def request_token(path: str, headers: Any) -> str | None:
    """The token a viewer's WebSocket handshake carries: ``?token=`` in its URL, a bearer token, or the
    :data:`TOKEN_COOKIE` cookie (in that order); None without one."""
    query = parse_qs(urlsplit(path).query)
    if query.get("token"):
        return query["token"][0]
    auth = headers.get("Authorization") or ""
    if auth[:7].lower() == "bearer " and auth[7:].strip():
        return auth[7:].strip()
    raw = headers.get("Cookie")
    if raw:
        cookie = SimpleCookie()
        try:
            cookie.load(raw)
        except CookieError:
            return None
        if TOKEN_COOKIE in cookie:
            return cookie[TOKEN_COOKIE].value
    return None


def require_token(server: viser.ViserServer, token: str) -> None:
    """Close every viewer's WebSocket that does not carry ``token`` before it receives anything.

    viser has no authentication of its own: this hooks the connection callback of its WebSocket server
    (``_websock_server``, run for each new connection before any message is sent to it) and reads the
    handshake of the connection (``_live_connections``). Both are viser internals, checked by the tests."""
    if not token:
        raise ValueError("require_token needs a non-empty token")
    ws_server = server._websock_server
    expected = token.encode()

    async def check(conn: Any) -> None:
        connection = ws_server._live_connections.get(conn.client_id)
        if connection is None:
            return
        request = connection.request
        given = None if request is None else request_token(request.path, request.headers)
        if given is not None and hmac.compare_digest(given.encode(), expected):
            return
        logger.warning("3D view: a viewer without the operator token was refused")
        await connection.close(WS_POLICY_VIOLATION, "operator token needed (?token= in the socket's URL)")

    ws_server._client_connect_cb.insert(0, check)  # before viser's own: nothing is queued for it


class ViserServerThread:
    """One viser server and the worker thread that updates it.

    Args:
        host: Interface to bind.
        port: TCP port (0 picks a free one: read :attr:`port` after :meth:`start`; a taken port is an
            error).
        name: Name of the worker thread, also used in error messages.
        token: The token a viewer must send (see the module docstring); None: open to anyone who reaches
            the port.
    """

    def __init__(self, *, host: str, port: int, name: str, token: str | None = None) -> None:
        self._host = host
        self._requested_port = int(port)
        self._name = name
        self._token = token
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
            PortInUse: another program holds the requested port (viser would have moved to the next one).
        """
        if self._server is not None:
            raise RuntimeError(f"{self._name}: start() called twice; call stop() first")
        import viser

        check_port_free(self._host, self._requested_port)
        server = viser.ViserServer(host=self._host, port=self._requested_port, verbose=False)
        if self._requested_port != 0 and server.get_port() != self._requested_port:
            server.stop()  # taken between the check and the start
            raise PortInUse(self._host, self._requested_port)
        try:
            if self._token is not None:
                require_token(server, self._token)
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
