"""Request and response models of the API that are not study records (those are in ``app.study.schemas``)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Path, Query
from pydantic import BaseModel, ConfigDict, Field, field_validator

from app.study.schemas import TrialEventRead, TrialRead

#: Database ids in paths and bodies: positive, within a signed 32-bit integer.
MAX_ID = 2**31 - 1
Id = Annotated[int, Field(ge=1, le=MAX_ID)]
Method = Literal["proactive", "reactive"]

ParticipantIdPath = Annotated[int, Path(ge=1, le=MAX_ID, description="participant id")]
SessionIdPath = Annotated[int, Path(ge=1, le=MAX_ID, description="study session id")]
TrialIdPath = Annotated[int, Path(ge=1, le=MAX_ID, description="trial id")]
OffsetQuery = Annotated[int, Query(ge=0, le=10**9, description="rows to skip")]
LimitQuery = Annotated[int, Query(ge=1, le=1000, description="most rows to return")]

#: Longest trial the API starts (s).
MAX_TRIAL_DURATION_S = 3600.0
#: Shortest trial the API starts (s): time for one task (the robot fetches a block from the conveyor and
#: places it at a drop station: about 8 s in the shipped cell with nobody in the way), or the trial measures
#: nothing.
MIN_TRIAL_DURATION_S = 10.0


class ErrorRead(BaseModel):
    """Every error response: ``detail`` says what was wrong and what to do."""

    detail: str


class ValidationErrorItem(BaseModel):
    loc: list[str]
    msg: str
    type: str


class ValidationErrorRead(ErrorRead):
    """A 422: ``detail`` lists every invalid field; ``errors`` has them one by one."""

    errors: list[ValidationErrorItem]


class HealthRead(BaseModel):
    status: Literal["ok", "degraded"]
    version: str
    runtime: Literal["running", "stopped"]
    database: Literal["ok", "error"]


class PredictorRead(BaseModel):
    """The proactive method's motion predictor as it runs (``app.control.world.PredictorInfo``)."""

    kind: str = Field(description="what forecasts: graphmixer, or constant_velocity when the weights failed")
    weights: str | None = Field(description="the network's weights file")
    weights_sha256: str | None = Field(description="SHA-256 of the weights file's bytes")
    arbitrated: bool = Field(description="arbitrated online with the baselines (HRC_FORECAST_ARBITRATION)")
    fallback_reason: str | None = Field(
        None, description="why constant velocity runs instead of the network (HRC_HMP_FALLBACK=true)"
    )


class InfoRead(BaseModel):
    """What a client needs to know about this server (no secrets)."""

    version: str
    viser_port: int
    robot: Literal["sim", "rtde"]
    human_source: Literal["sim", "replay", "stream"]
    read_only_open: bool
    methods: list[str]
    min_trial_duration_s: float
    max_trial_duration_s: float
    live_rate_hz: float
    ingest_max_bytes: int
    ingest_rate_hz: float
    deadline_s: float = Field(description="D, the backup-plan deadline (the planning chart's red line)")
    anticipate_fetch: bool = Field(
        description="the proactive forecast expects the person to fetch each block the robot places"
    )
    predictor: PredictorRead | None = Field(
        None, description="the proactive method's predictor as it runs (null: the runtime does not say)"
    )


class TrialStart(BaseModel):
    """Start a trial: the runtime runs ``method`` for ``duration_s`` beside participant ``participant_id``.

    Strict types: ids and the seed are JSON integers, the duration a JSON number (``true`` or ``"60"`` is a
    422, not 1 or 60)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    participant_id: Id
    method: Method
    duration_s: float = Field(
        le=MAX_TRIAL_DURATION_S,
        description=f"trial length (s), {MIN_TRIAL_DURATION_S:g} to {MAX_TRIAL_DURATION_S:g}",
        json_schema_extra={"minimum": MIN_TRIAL_DURATION_S},  # checked below, with a message that says why
    )
    seed: int | None = Field(None, ge=0, le=2**32 - 1, description="default: drawn at random and stored")
    session_id: Id | None = None

    @field_validator("duration_s")
    @classmethod
    def _long_enough_for_a_task(cls, value: float) -> float:
        if not value >= MIN_TRIAL_DURATION_S:
            raise ValueError(
                f"a trial of {value:g} s is too short to hold one task; start one of at least "
                f"{MIN_TRIAL_DURATION_S:g} s"
            )
        return value


class TrialDetail(TrialRead):
    """A trial with its metrics (None while it runs) and its events in time order."""

    events: list[TrialEventRead] = Field(default_factory=list)
    events_total: int = 0


class MethodOrderRead(BaseModel):
    participant_id: int
    methods: list[Method]


class PartModeRead(BaseModel):
    """What limits one robot part now (:class:`app.safety.modes.PartMode`): ``mode`` one of ``free``,
    ``ssm``, ``pfl``, ``stopped``; ``label`` the same with the region (``pfl:hand_fingers``); ``text`` as the
    screens show it; ``region`` the body region of the mode, ``held_from`` the one it keeps ``S_p`` from;
    ``separation_m`` from that region and ``required_m`` the separation the governor holds it to (m; None:
    nobody seen); ``limit_scale`` the largest path scale it allows alone."""

    name: str
    mode: Literal["free", "ssm", "pfl", "stopped"]
    label: str
    text: str
    region: str | None
    held_from: str | None
    held_from_text: str | None = None
    separation_m: float | None
    required_m: float | None
    limit_scale: float


class RobotStatus(BaseModel):
    """The robot and supervisor now (from the runtime's latest snapshot).

    ``q`` (6,) joint positions (rad); ``p_world_tcp`` (3,) tool position in the world frame (m);
    separations in metres (None when no person is tracked): ``separation_m`` of the part that limits the
    robot from the regions it keeps ``S_p`` from, ``required_separation_m`` what the speed governor holds it
    to. ``mode``: that part's mode (``free``, ``ssm``, ``pfl:<region>``, ``stopped``; None without a trial),
    ``mode_text`` as the screens show it, ``parts`` every part's.
    """

    t: float
    state: str
    estopped: bool
    stale: bool
    speed_scale: float
    separation_m: float | None
    required_separation_m: float | None
    q: list[float]
    p_world_tcp: list[float]
    trial_id: int | None
    method: str | None
    trial_elapsed_s: float | None
    trial_duration_s: float | None
    mode: str | None = None
    mode_text: str = "–"
    limiting_part: str | None = None
    parts: list[PartModeRead] = []


def robot_status(snapshot: Any) -> RobotStatus:
    """:class:`RobotStatus` from a runtime ``Snapshot`` (non-finite floats become None)."""
    import math

    def opt(v: Any) -> float | None:
        if v is None:
            return None
        v = float(v)
        return v if math.isfinite(v) else None

    return RobotStatus(
        t=float(snapshot.t),
        state=str(snapshot.state),
        estopped=bool(snapshot.estopped),
        stale=bool(snapshot.stale),
        speed_scale=float(snapshot.speed_scale),
        separation_m=opt(snapshot.separation_m),
        required_separation_m=opt(snapshot.required_separation_m),
        q=[float(v) for v in snapshot.q],
        p_world_tcp=[float(v) for v in snapshot.p_world_tcp],
        trial_id=snapshot.trial_id,
        method=snapshot.method,
        trial_elapsed_s=opt(snapshot.trial_elapsed_s),
        trial_duration_s=opt(snapshot.trial_duration_s),
        **_modes_of(snapshot),
    )


def _modes_of(snapshot: Any) -> dict[str, Any]:
    """The mode fields of a snapshot's JSON (none from a snapshot without them)."""
    to_json = getattr(snapshot, "to_json", None)
    got = to_json() if callable(to_json) else {}
    keys = ("mode", "mode_text", "limiting_part", "parts")
    return {k: got[k] for k in keys if k in got}


#: Responses every authenticated route may give (documented in the OpenAPI schema).
AUTH_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorRead, "description": "missing or invalid operator token"},
    422: {"model": ValidationErrorRead, "description": "invalid request"},
}
NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"model": ErrorRead, "description": "no such record"}}
CONFLICT: dict[int | str, dict[str, Any]] = {409: {"model": ErrorRead, "description": "conflict"}}
