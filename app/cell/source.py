"""The protocol of every human source: where the person's skeleton comes from.

Kept apart from the sources themselves (:mod:`app.cell.human`) so that the frame validation, which wraps
any source, and the sources, which validate what they receive, do not import each other.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from app.prediction.skeleton import HumanFrame

__all__ = ["HumanSource"]


@runtime_checkable
class HumanSource(Protocol):
    """Where skeleton frames come from.

    Only :meth:`frame_at` is required; the sources subclass this protocol for the defaults of the optional
    capabilities, so that whoever uses a source asks it directly instead of probing for them.

    Attributes:
        validates_frames: The source validates every frame itself (the stream source, which must answer
            the sender) and keeps the validation ``counters``: validation does not check them again.
    """

    validates_frames: bool = False

    def frame_at(self, t: float) -> HumanFrame | None:
        """The newest frame at or before ``t`` (s), or ``None`` if there is none yet."""
        ...

    def notify_block_placed(self, station: str, t: float) -> None:
        """The robot placed a block at ``station`` at ``t`` (s): the simulated operator goes and fetches it;
        a source that does not react to the task ignores it (the default)."""

    def reset_counters(self) -> None:
        """Zero the validation counters of a source that :attr:`validates_frames` (the default: it has
        none)."""

    def ground_truth(self) -> Callable[[float], np.ndarray | HumanFrame] | None:
        """The person's true pose at any instant, ``t -> (J, 3)`` (m), or every person's, ``t ->``
        :class:`~app.prediction.skeleton.HumanFrame` (their bodies with their ids), for the ground-truth
        monitor: a simulated or recorded person's own ``pose_at``; None (the default) where the source knows
        the person only as a tracker reports them."""
        return None
