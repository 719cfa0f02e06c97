"""Example 2: stream a ZED camera's body tracking to the app (``/api/ingest``).

Needs a ZED 2/2i/X camera and the ZED SDK with its Python package ``pyzed`` (installed by the SDK, not by
this project). The camera is static; set its pose in the app (``HRC_CAMERA_POSE='[x, y, z, roll, pitch,
yaw]'``, metres/radians, in the coordinate system below: x forward, y left, z up)::

    python examples/zed_client.py --url ws://<app-host>:8000/api/ingest --token "$HRC_API_TOKEN" \
        --format zed34

Every body the SDK tracks is sent with its tracker id, one message per capture (a capture with nobody in
view too). This script is deliberately thin: everything it shares with the app (building the messages,
sending them) is ``app.cell.stream_protocol`` and is tested there. The message format is
``docs/stream-protocol.md``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys
from collections.abc import AsyncIterator
from typing import Any


def open_camera(sl: Any, body_format: str) -> Any:
    """Open the camera (metres, RIGHT_HANDED_Z_UP_X_FWD, static) and start body tracking."""
    zed = sl.Camera()
    init = sl.InitParameters()
    init.camera_fps = 30
    init.depth_mode = sl.DEPTH_MODE.NEURAL
    init.coordinate_units = sl.UNIT.METER
    init.coordinate_system = sl.COORDINATE_SYSTEM.RIGHT_HANDED_Z_UP_X_FWD
    err = zed.open(init)
    if err != sl.ERROR_CODE.SUCCESS:
        raise RuntimeError(f"cannot open the ZED camera: {err}")
    tracking = sl.PositionalTrackingParameters()
    tracking.set_as_static = True  # the camera does not move: its world frame is its own frame
    zed.enable_positional_tracking(tracking)
    params = sl.BodyTrackingParameters()
    params.detection_model = sl.BODY_TRACKING_MODEL.HUMAN_BODY_ACCURATE
    params.body_format = sl.BODY_FORMAT.BODY_34 if body_format == "zed34" else sl.BODY_FORMAT.BODY_38
    params.enable_tracking = True
    params.enable_body_fitting = True
    err = zed.enable_body_tracking(params)
    if err != sl.ERROR_CODE.SUCCESS:
        zed.close()
        raise RuntimeError(f"cannot start ZED body tracking: {err}")
    return zed


def capture_message(sl: Any, bodies: Any, body_format: str) -> dict[str, Any]:
    """One message of a grabbed capture: every body the SDK tracks (``tracking_state`` OK) with its id;
    none is a person-free capture (sent all the same: the stream stays alive while the cell is empty)."""
    from app.cell.stream_protocol import message_from_zed_bodies

    tracked = [b for b in bodies.body_list if b.tracking_state == sl.OBJECT_TRACKING_STATE.OK]
    return message_from_zed_bodies(
        [(int(b.id), b.keypoint, b.keypoint_confidence) for b in tracked],
        t=bodies.timestamp.get_nanoseconds() * 1e-9,
        body_format=body_format,  # type: ignore[arg-type]
        frame="camera",
    )


async def body_messages(sl: Any, zed: Any, body_format: str) -> AsyncIterator[dict[str, Any]]:
    """One message per grabbed frame (:func:`capture_message`)."""
    bodies = sl.Bodies()
    runtime = sl.BodyTrackingRuntimeParameters()
    runtime.detection_confidence_threshold = 40

    def grab() -> dict[str, Any] | None:
        if zed.grab() != sl.ERROR_CODE.SUCCESS:
            return None
        zed.retrieve_bodies(bodies, runtime)
        return capture_message(sl, bodies, body_format)

    while True:
        msg = await asyncio.to_thread(grab)  # the SDK blocks; keep the WebSocket responsive
        if msg is not None:
            yield msg


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="ws://127.0.0.1:8000/api/ingest", help="the app's ingest WebSocket")
    parser.add_argument("--token", default=os.environ.get("HRC_API_TOKEN"), help="operator token")
    parser.add_argument("--format", choices=["zed34", "zed38"], default="zed34", help="ZED body format")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if not args.token:
        parser.error("no token: pass --token or set HRC_API_TOKEN")
    try:
        import pyzed.sl as sl
    except ImportError:
        logging.error("pyzed is not installed: install the ZED SDK and its Python API (get_python_api.py)")
        return 2

    from app.cell.stream_protocol import send_messages

    zed = open_camera(sl, args.format)
    try:
        asyncio.run(send_messages(args.url, body_messages(sl, zed, args.format), token=args.token))
    except KeyboardInterrupt:
        pass
    finally:
        zed.disable_body_tracking()
        zed.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
