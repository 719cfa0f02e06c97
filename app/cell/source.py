"""The protocol of every human source: where the person's skeleton comes from.

Kept apart from the sources themselves (:mod:`app.cell.human`) so that the frame validation, which wraps
any source, and the sources, which validate what they receive, do not import each other.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from app.prediction.skeleton import HumanFrame

__all__ = ["HumanSource"]


@runtime_checkable
class HumanSource(Protocol):
    """Where skeleton frames come from. Sources may also have ``notify_block_placed(station, t)``."""

    def frame_at(self, t: float) -> HumanFrame | None:
        """The newest frame at or before ``t`` (s), or ``None`` if there is none yet."""
        ...
