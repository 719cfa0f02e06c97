"""Example 1: replay a recorded clip to the app's skeleton stream (``/api/ingest``).

Start the app with the stream source, then replay a clip as if a tracker saw it::

    HRC_HUMAN_SOURCE=stream hrc serve
    python examples/stream_replay_client.py ../shared/data/cmu_mocap/test/washwindow_1.npz \\
        --url ws://127.0.0.1:8000/api/ingest --token "$HRC_API_TOKEN" --loops 3

The clip (the CMU npz format or a recording of the app) is placed into the operator's area of the work cell
exactly as ``ReplaySource`` does, and sent in the canonical format, world frame, at the clip's frame rate,
with the clip's own timestamps (the app maps them onto its clock), as body id 0. Several clips are several
people: clip ``k`` is body id ``k``, placed ``--spacing`` metres beside the one before, on the first clip's
frame times. See ``docs/stream-protocol.md``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any


def messages(
    clip: Path | Sequence[Path], *, loops: int, place: bool, spacing_m: float = 0.8
) -> tuple[Iterator[dict[str, Any]], float, int]:
    """The clips' frames as messages (clip ``k``: body id ``k``, shifted ``k * spacing_m`` along y), the
    first clip's frame rate (Hz) and the number of messages."""
    import numpy as np

    from app.cell.human import ReplaySource
    from app.cell.stream_protocol import make_bodies_message
    from app.config import load_workcell

    clips = [clip] if isinstance(clip, str | Path) else list(clip)
    cell = load_workcell()
    sources = [ReplaySource(c, cell, place=place) for c in clips]
    lead = sources[0]
    times = lead.clip.times
    fps = (len(times) - 1) / times[-1] if len(times) > 1 else 30.0
    total = loops * len(times)

    def generate() -> Iterator[dict[str, Any]]:
        for k in range(total):
            t = (k // len(times)) * lead.clip.period_s + float(times[k % len(times)])
            frames = [s.frame_at(t + 1e-6) for s in sources]
            bodies = []
            for i, frame in enumerate(frames):
                assert frame is not None
                bodies.append((i, frame.joints + np.array([0.0, i * spacing_m, 0.0]), frame.confidence))
            yield make_bodies_message(bodies, t=frames[0].t)  # type: ignore[union-attr]

    return generate(), fps, total


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "clip",
        type=Path,
        nargs="+",
        help="an .npz clip (CMU format or an app recording); several: several people",
    )
    parser.add_argument("--url", default="ws://127.0.0.1:8000/api/ingest", help="the app's ingest WebSocket")
    parser.add_argument("--token", default=os.environ.get("HRC_API_TOKEN"), help="operator token")
    parser.add_argument("--loops", type=int, default=1, help="how many times to play the clip")
    parser.add_argument("--rate", type=float, default=None, help="send rate (Hz); default: the clip's")
    parser.add_argument("--no-place", action="store_true", help="send the clip's coordinates as they are")
    parser.add_argument(
        "--spacing", type=float, default=0.8, help="metres between the people of several clips"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if not args.token:
        parser.error("no token: pass --token or set HRC_API_TOKEN")

    from app.cell.stream_protocol import send_messages

    msgs, fps, total = messages(args.clip, loops=args.loops, place=not args.no_place, spacing_m=args.spacing)
    rate = args.rate or fps
    names = ", ".join(str(c) for c in args.clip)
    logging.info("sending %d frames of %s at %.1f Hz to %s", total, names, rate, args.url)
    counts = asyncio.run(send_messages(args.url, msgs, token=args.token, rate_hz=rate))
    logging.info("sent %d frames, %d rejected by the server", counts["sent"], counts["errors"])
    return 0 if counts["errors"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
