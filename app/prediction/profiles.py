"""Motion profiles of human movement, shared by everything that models a reach.

The minimum-jerk profile (Flash & Hogan 1985, *J. Neurosci.* 5(7):1688-1703) describes the hand's path
along a point-to-point reach: the simulated operator moves with it, the planner's reference scenarios
build their reaching person with it, and the task anticipation expects a fetch to follow it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_JERK_PEAK_SPEED", "min_jerk"]

#: Peak speed of a minimum-jerk move over its mean speed (``d/ds`` of the profile at ``s = 1/2``).
MIN_JERK_PEAK_SPEED = 1.875


def min_jerk(s: float | np.ndarray) -> float | np.ndarray:
    """Minimum-jerk phase ``10 s^3 - 15 s^4 + 6 s^5`` for ``s`` in [0, 1] (clipped)."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 + s * (-15.0 + 6.0 * s))
