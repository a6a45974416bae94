"""Request and response models of the REST API (pydantic); units mm, rad, degC, s unless named."""

from __future__ import annotations

import re
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StringConstraints

from driftlab.api.strict import MAX_ID
from driftlab.campaigns.campaign_repo import CampaignSummary, MachineInfo

Condition = Literal["spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b"]
JobKind = Literal["fit", "diagnose"]
JobState = Literal["queued", "running", "done", "failed"]
ModelStatus = Literal["current", "retired"]

#: identifiers in paths and queries (machine ids, channel names): no spaces, no control characters
ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,63}$"
ChannelName = Annotated[str, StringConstraints(pattern=ID_PATTERN)]
TemperatureC = Annotated[float, Field(ge=-100.0, le=1000.0)]


def _json_integer(value: object) -> object:
    """Read a JSON number without a fraction as the integer it is (JSON Schema's "integer": 3.0 is 3).

    JSON has one number type; only text ("3") and booleans (true) stay refused by the strict models.
    """
    if isinstance(value, float) and value.is_integer() and abs(value) <= 2**53:
        return int(value)
    return value


RowId = Annotated[int, Field(ge=1, le=MAX_ID), BeforeValidator(_json_integer)]
#: the bounds of a diagnosis' held-out fraction (below 1 % a campaign's last rows round to none held out)
HOLDOUT_FRACTION = (0.01, 0.9)


_ISO_DATE = re.compile(r"[0-9]{4}-[0-9]{2}-[0-9]{2}")


def _iso_text(value: object) -> object:
    """Refuse a date-time that is not ISO 8601 text (pydantic would read a number, or digits, as a Unix time)."""
    if value is not None and not (isinstance(value, str) and _ISO_DATE.match(value)):
        raise ValueError("must be an ISO 8601 date-time string")
    return value


#: a date-time in a strict body: ISO 8601 text only (parsed by pydantic's lax rules, a number refused)
IsoDateTime = Annotated[datetime, Field(strict=False), BeforeValidator(_iso_text)]


class _Out(BaseModel):
    """Base of responses."""

    model_config = ConfigDict(extra="forbid")


class _In(BaseModel):
    """Base of request bodies: unknown keys, non-finite numbers and coercions ("0.5" as a number, true as 1)
    are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


# ----------------------------------------------------------------------------- machines


class MachineOut(_Out, MachineInfo):
    """A machine tool with the size of its history and its current model version."""


class MachineList(_Out):
    """A page of machines."""

    items: list[MachineOut]
    limit: int
    offset: int


# ----------------------------------------------------------------------------- campaigns


class CampaignOut(_Out, CampaignSummary):
    """One line of the campaign list."""


class CampaignList(_Out):
    """A page of campaigns, oldest first."""

    items: list[CampaignOut]
    limit: int
    offset: int


class StageOut(_Out):
    """One stage of a campaign's plan as run."""

    ordinal: int
    name: str
    heat_source: str
    axis: str | None
    spindle_rpm: float
    feed_mm_min: float
    start_s: float
    end_s: float | None
    status: str


class ChannelOut(_Out):
    """A thermocouple site of a campaign."""

    ordinal: int
    name: str
    location: str
    structure: str
    is_room: bool
    calibration_slope: float
    calibration_offset: float


class CampaignDetail(CampaignOut):
    """A campaign with its stages, channels and campaign.json document."""

    stage_list: list[StageOut]
    channel_list: list[ChannelOut]
    meta: dict[str, Any] | None


# ----------------------------------------------------------------------------- histories


class TemperaturePoint(_Out):
    """One reading (degC); null = a missing reading."""

    time_s: float
    value: float | None


class Bucket(_Out):
    """Min/mean/max of the readings in [time_s, t_end_s) (the last bucket includes its end)."""

    time_s: float
    t_end_s: float
    n: int
    min: float | None
    mean: float | None
    max: float | None


class TemperatureHistory(_Out):
    """A channel's readings (``points``, paged) or its downsampled buckets (``buckets``)."""

    campaign_id: int
    channel: str
    points: list[TemperaturePoint] | None = None
    buckets: list[Bucket] | None = None
    next_cursor: str | None = None


class LatestTemperatures(_Out):
    """A machine's latest thermocouple scan (what a streaming compensator reads); null = missing."""

    machine_id: str
    campaign_id: int
    time_s: float
    time: datetime
    temperatures: dict[str, float | None]


class ConditionRow(_Out):
    """One line of the machine-state log (only the requested columns are present)."""

    time_s: float
    spindle_rpm: float | None = None
    feed_mm_min: float | None = None
    x: float | None = None
    y: float | None = None
    z: float | None = None
    a: float | None = None
    b: float | None = None


class ConditionBucket(_Out):
    """Min/mean/max of each requested machine-state column in one time bucket."""

    time_s: float
    t_end_s: float
    n: int
    values: dict[str, Bucket]


class ConditionHistory(_Out):
    """Machine-state rows (``points``, paged) or downsampled buckets (``buckets``)."""

    campaign_id: int
    columns: list[str]
    points: list[ConditionRow] | None = None
    buckets: list[ConditionBucket] | None = None
    next_cursor: str | None = None


class ErrorSampleOut(_Out):
    """One measured work-space error (rad or mm) at a position of the moved axis."""

    seq: int
    time_s: float
    axis: str
    term: str
    position: float
    direction: int
    sweep: int
    flags: int
    value: float


class ErrorHistory(_Out):
    """A page of a campaign's error samples in measurement order."""

    campaign_id: int
    items: list[ErrorSampleOut]
    next_cursor: str | None = None


class DriftPoint(_Out):
    """One point of the drift of (axis, term) across a machine's campaigns."""

    campaign_id: int
    time: datetime
    time_s: float
    position: float
    direction: int
    sweep: int
    value: float


class DriftOut(_Out):
    """The error history of (axis, term) in wall-clock time."""

    machine_id: str
    axis: str
    term: str
    position: float | None
    direction: int | None
    interpolate: bool
    points: list[DriftPoint]


# ----------------------------------------------------------------------------- models


class ModelSummary(_Out):
    """A model registry entry without its document."""

    machine_id: str
    version: int
    status: str
    created_at: datetime
    retired_at: datetime | None
    source_campaigns: list[int]
    terms: int


class ModelVersionOut(ModelSummary):
    """A model registry entry with its document (what compensators load)."""

    document: dict[str, Any]


class ModelList(_Out):
    """A page of model versions."""

    items: list[ModelSummary]
    limit: int
    offset: int


class ModelRegisterIn(_In):
    """A new model document to store as the machine's next (and current) version."""

    document: dict[str, Any] = Field(description="a driftlab-model/1 document; its machine must match the path")
    source_campaigns: list[RowId] = Field(default_factory=list, max_length=1000)


# ----------------------------------------------------------------------------- jobs


class JobSubmit(_In):
    """A fit (of a machine from its campaigns, registering a new model version) or a diagnosis (of one
    campaign) to run in the background."""

    kind: JobKind
    machine_id: str | None = Field(default=None, pattern=ID_PATTERN)
    campaign_ids: list[RowId] = Field(
        default_factory=list,
        max_length=200,
        description="fit: the campaigns (default every campaign of the machine); diagnose: exactly one",
    )
    holdout_fraction: float = Field(
        default=0.25,
        ge=HOLDOUT_FRACTION[0],
        lt=HOLDOUT_FRACTION[1],
        description="diagnose: fraction of each (axis, term)'s rows held out",
    )


class JobOut(_Out):
    """A job's state and, once done, its result (failed: a one-line error)."""

    id: int
    kind: str
    state: str
    params: dict[str, Any]
    result: dict[str, Any] | None
    error: str | None
    machine_id: str | None
    campaign_id: int | None
    attempts: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobList(_Out):
    """A page of jobs, newest first."""

    items: list[JobOut]
    limit: int
    offset: int


# ----------------------------------------------------------------------------- on-line update


class ProbeIn(_In):
    """A touch-probe sphere-centre measurement: pose, temperatures and the measured deviation (mm)."""

    measured_at: IsoDateTime | None = Field(
        default=None, description="ISO 8601, between 1970 and 2200, UTC when naive; default now"
    )
    x: float = Field(ge=-1e4, le=1e4)
    y: float = Field(ge=-1e4, le=1e4)
    z: float = Field(ge=-1e4, le=1e4)
    a_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    b_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    dx: float = Field(ge=-10.0, le=10.0)
    dy: float = Field(ge=-10.0, le=10.0)
    dz: float = Field(ge=-10.0, le=10.0)
    # patternProperties alone would let any other key through in the schema: close it
    temperatures: dict[ChannelName, TemperatureC] = Field(
        default_factory=dict,
        max_length=200,
        json_schema_extra={"additionalProperties": False},
        description="degC per channel: at least the model's inputs",
    )
    forgetting: float | None = Field(
        default=None, gt=0.5, le=1.0, description="forgetting factor lambda (only when the state starts)"
    )


class Vector3(_Out):
    """A translation error (mm)."""

    dx: float
    dy: float
    dz: float


class OnlineOut(_Out):
    """The machine's on-line (RLS) state and the correction it gives at the last probed pose."""

    machine_id: str
    model_version: int
    forgetting: float
    n_updates: int
    theta: dict[str, list[float]]
    update_id: int | None = None
    offline_prediction: Vector3 | None = None
    prior_error: Vector3 | None = None
    online_prediction: Vector3 | None = None
    correction: Vector3 | None = Field(
        default=None, description="to add to the commanded position: minus (off-line + on-line prediction)"
    )


class Health(_Out):
    """Liveness and database reachability."""

    status: str
    database: str
