"""Recordings of simulated operators at work, as clips for training and calibrating the motion predictor.

The simulated operator is part of the simulated *world*: the predictor never imports it, it only gets the
frames (``hrc hmp record-sim`` writes them as clips, ``hrc hmp calibrate`` takes them as data).
"""

from __future__ import annotations

import math

import numpy as np

from app.cell.operator_sim import OperatorParams, SimulatedOperator
from app.config import WorkCell
from app.prediction.skeleton import NUM_JOINTS

__all__ = ["simulated_operator_sequences"]


def simulated_operator_sequences(
    cell: WorkCell,
    *,
    participants: int,
    duration_s: float,
    seed: int,
    fps: float = 30.0,
    block_every_s: tuple[float, float] = (12.0, 25.0),
) -> list[np.ndarray]:
    """Frames (T, J, 3) of simulated operators (participant seeds ``seed``, ``seed + 1``, ...) at work: a
    block is placed at a random drop station every ``block_every_s`` seconds (the robot's cadence), so the
    motion includes their fetches as well as assembling and spontaneous reaches."""
    if participants < 1 or not duration_s > 0:
        raise ValueError("need at least one participant and a positive duration")
    stations = [s.name for s in cell.drop_stations]
    out = []
    for i in range(participants):
        pseed = int(seed) + i
        rng = np.random.default_rng([pseed, 0xCA1])
        op = SimulatedOperator(cell, OperatorParams.draw(pseed), seed=pseed, fps=fps)
        n = math.floor(duration_s * fps)
        t_next = float(rng.uniform(*block_every_s))
        frames = np.empty((n, NUM_JOINTS, 3))
        for k in range(n):
            t = k / fps
            if t >= t_next:
                op.notify_block_placed(str(rng.choice(stations)), t)
                t_next += float(rng.uniform(*block_every_s))
            frame = op.frame_at(t)
            assert frame is not None
            frames[k] = frame.joints
        out.append(frames)
    return out
