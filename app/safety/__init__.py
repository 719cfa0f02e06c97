"""ISO/TS 15066 speed and separation monitoring, the one address of the safety function.

- :mod:`app.safety.ssm`: the protective separation distance ``S_p``, its parameters (:class:`SSMParams`),
  the planner's forecast clearance and the speed scaling of the standard's constant-speed form;
- :mod:`app.safety.stopping`: the robot's one stopping model and the system's reaction time ``T_r``;
- :mod:`app.safety.governor`: the speed governor's separation model and braking envelope, and the
  standard's speed-scaling law;
- :mod:`app.safety.monitor`: the ground-truth monitor, the judge of a trial;
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
