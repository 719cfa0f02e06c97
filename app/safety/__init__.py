"""ISO/TS 15066 speed and separation monitoring, the one address of the safety function.

- :mod:`app.safety.ssm`: the protective separation distance ``S_p``, its parameters (:class:`SSMParams`),
  the planner's forecast clearance and the speed scaling of the standard's constant-speed form;
- :mod:`app.safety._kernels`: the speed governor's compiled inner loops (per servo tick).

Pure computation over numpy arrays: nothing here imports the runtime, the cell, the database or the web.
"""

from __future__ import annotations

from app.safety.ssm import (
    SSMParams,
    forecast_clearance,
    max_safe_speed,
    protective_separation,
    speed_scale,
)

__all__ = ["SSMParams", "forecast_clearance", "max_safe_speed", "protective_separation", "speed_scale"]
