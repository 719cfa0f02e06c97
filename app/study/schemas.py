"""Pydantic models of the study records: ``*Create`` (input), ``*Update`` (partial input), ``*Read`` (output).

The repository returns ``*Read`` models (never ORM objects), so that the API can return them directly and no
database session escapes the repository.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, computed_field, field_validator

Method = Literal["proactive", "reactive"]
TrialStatus = Literal["running", "completed", "aborted"]
FinalStatus = Literal["completed", "aborted"]

ParticipantCode = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")]


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True)


class _ApiIn(_In):
    """The bodies of the API's requests: strict types (``age: true`` or ``"30"`` is a 422, not 1 or 30)."""

    model_config = ConfigDict(strict=True)


class _Out(BaseModel):
    model_config = ConfigDict(from_attributes=True)


# --- participants -------------------------------------------------------------------------------------


class ParticipantCreate(_ApiIn):
    """A new participant. ``code`` is a pseudonym (letters, digits, ``.``, ``_``, ``-``), unique."""

    code: ParticipantCode
    age: int | None = Field(None, ge=0, lt=150)
    sex: str | None = Field(None, max_length=32)
    experience: str | None = Field(None, max_length=200, description="experience with robots, free text")
    notes: str = Field("", max_length=10_000)


class ParticipantUpdate(_ApiIn):
    """A partial update: only the fields that are set are changed."""

    code: ParticipantCode | None = None
    age: int | None = Field(None, ge=0, lt=150)
    sex: str | None = Field(None, max_length=32)
    experience: str | None = Field(None, max_length=200)
    notes: str | None = Field(None, max_length=10_000)


class ParticipantRead(_Out):
    id: int
    code: str
    age: int | None
    sex: str | None
    experience: str | None
    notes: str
    created: datetime


# --- study sessions -----------------------------------------------------------------------------------


class StudySessionCreate(_ApiIn):
    name: str = Field(min_length=1, max_length=200)
    notes: str = Field("", max_length=10_000)


class StudySessionUpdate(_ApiIn):
    name: str | None = Field(None, min_length=1, max_length=200)
    notes: str | None = Field(None, max_length=10_000)


class StudySessionRead(_Out):
    id: int
    name: str
    notes: str
    created: datetime


# --- trials -------------------------------------------------------------------------------------------


class TrialCreate(_In):
    """A trial about to start (status ``running``). ``order_index`` None: the next free position of the
    participant within the session. ``settings``: a JSON snapshot of the settings it runs with."""

    participant_id: int
    method: Method
    session_id: int | None = None
    order_index: int | None = Field(None, ge=0)
    seed: int = Field(0, ge=0, lt=2**63)
    duration_s: float | None = Field(None, gt=0)
    settings: dict[str, Any] = Field(default_factory=dict)


class TrialMetricsRead(_Out):
    """Stored metrics of one trial (see :class:`app.control.metrics.TrialMetrics`) plus the per-task rates.
    ``min_separation_m`` is None when no person was seen during the trial; the time budget and the arrivals
    are None for a trial stored before they were recorded, the arrival errors also without arrivals."""

    trial_id: int
    duration_s: float
    completed_tasks: int
    plans_computed: int
    avg_planning_time_s: float
    p95_planning_time_s: float
    stop_replans: int
    stop_replans_moving: int | None = None
    online_replans: int
    deadline_misses: int
    emergency_plans: int
    plan_failures: int
    min_separation_m: float | None
    violations: int
    contacts: int = 0
    violation_time_s: float = 0.0
    violations_iso: int = 0
    violations_person_faster: int | None = None
    harmful_contacts: int | None = None
    violations_measured_vh: int | None = None
    exceedance_s: float | None = None
    max_approach_mps: float | None = None
    intrusions: int = 0
    min_separation_moving_m: float | None = None
    time_stopped_s: float
    time_nominal_s: float
    time_collision_avoidance_s: float
    time_moving_s: float
    mean_speed_scale: float
    budget_moving_full_s: float | None = None
    budget_moving_scaled_s: float | None = None
    budget_braking_s: float | None = None
    budget_stopped_s: float | None = None
    budget_planned_wait_s: float | None = None
    budget_gripper_s: float | None = None
    budget_waiting_for_person_s: float | None = None
    budget_waiting_for_plan_s: float | None = None
    budget_idle_s: float | None = None
    arrivals: int | None = None
    arrival_error_median_abs_s: float | None = None
    arrival_error_bias_s: float | None = None
    median_plan_s: float | None = None
    plans_forecast: int | None = None
    plans_reactive: int | None = None
    plans_reactive_only: int | None = None
    reactive_gain_s: float | None = None
    stale_stops: int
    frames_received: int
    frames_rejected: int

    @computed_field  # type: ignore[prop-decorator]
    @property
    def stop_replans_per_task(self) -> float:
        return self.stop_replans / max(self.completed_tasks, 1)

    @computed_field  # type: ignore[prop-decorator]
    @property
    def online_replans_per_task(self) -> float:
        return self.online_replans / max(self.completed_tasks, 1)

    @field_validator("min_separation_m", "min_separation_moving_m")
    @classmethod
    def _finite_or_none(cls, v: float | None) -> float | None:
        return v if v is not None and math.isfinite(v) else None


class TrialRead(_Out):
    id: int
    participant_id: int
    participant_code: str
    session_id: int | None
    method: Method
    order_index: int
    seed: int
    duration_s: float | None
    settings: dict[str, Any]
    started_at: datetime
    ended_at: datetime | None
    status: TrialStatus
    abort_reason: str | None
    metrics: TrialMetricsRead | None = None


class TrialEventRead(_Out):
    id: int
    trial_id: int
    t: float
    kind: str
    payload: dict[str, Any]
