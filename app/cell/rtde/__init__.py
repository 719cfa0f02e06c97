"""A real UR arm over RTDE (``ur_rtde``), driven from its own worker process.

Why a process: ``rtde_receive.RTDEReceiveInterface(...)`` and ``rtde_control.RTDEControlInterface(...)``
block inside their constructors *while holding the GIL* when a peer accepts the TCP connection but never
answers (measured with ur_rtde 1.6.5: every Python thread of the process freezes). In a separate
process such a hang costs nothing but that process, which the parent kills after its timeout.

Layers, one module each:

- :mod:`app.cell.rtde.wire`: :func:`~app.cell.rtde.wire.probe_rtde`, a pure-Python RTDE handshake
  (protocol version + controller version) with socket timeouts: tells "nothing listening", "listening but
  silent" and "a UR controller" apart before ur_rtde is touched.
- :mod:`app.cell.rtde.worker`: the worker process (:func:`~app.cell.rtde.worker.worker_main`), which
  connects, runs the fixed-rate servo loop and its watchdog, and reconnects.
- :mod:`app.cell.rtde.backend`: :class:`~app.cell.rtde.backend.RtdeRobot`, the parent-side
  :class:`~app.cell.robot.RobotBackend` that starts the worker and talks to it.

Times in the worker are ``time.monotonic`` (system-wide, so comparable with
:class:`~app.cell.clock.WallClock`).
"""
