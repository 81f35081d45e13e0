"""API schemas of parameter studies (``/studies``): ``StudyCreate`` (what a client sends),
``StudyPublic`` / ``StudyPage`` (what the API shows), ``StudyResults`` (the results object,
the same as ``ra2vipas simulate --vary ... --json`` prints)."""

from __future__ import annotations

from typing import Annotated, Any, Optional

from pydantic import BaseModel, ConfigDict, Field

from ra2vipas.services.orchestrator.api.schemas import (
    CampaignCreate,
    CampaignStatus,
    OverrideValue,
    PairedComparison,
    ParameterName,
    PODSummary,
    Progress,
)
from ra2vipas.services.orchestrator.study import MAX_POINTS, MAX_STUDY_EPISODES, MAX_VARIED

VaryValues = Annotated[list[OverrideValue], Field(min_length=1, max_length=MAX_POINTS)]


class StudyCreate(CampaignCreate):
    """Body of ``POST /studies``: a campaign's fields (the base scenario, the algorithms, the
    tests per point, the seed and the campaign options) and the parameters to vary."""

    vary: dict[ParameterName, VaryValues] = Field(
        min_length=1, max_length=MAX_VARIED,
        description=f"NAME: [values] for each varied scenario parameter (GET /presets/{{name}} lists them with their ranges); "
                    f"several parameters give the product of their values, at most {MAX_POINTS} points and "
                    f"{MAX_STUDY_EPISODES} episodes (points x tests x algorithms)")


class StudyPoint(BaseModel):
    point: int = Field(description="index in the grid (the first varied parameter varies slowest)")
    values: dict[str, Any] = Field(description="the varied parameters' values at this point")
    campaign_id: str = Field(description="the point's campaign (GET /campaigns/{id})")
    status: CampaignStatus
    progress: Progress
    pod: PODSummary


class StudyPublic(BaseModel):
    """A study: its grid and options, its status and progress over every point, and (in
    ``GET /studies/{id}``) its points."""

    id: str
    name: Optional[str]
    status: CampaignStatus = Field(description="queued, training, running, then done, failed (a point failed) or cancelled")
    progress: Progress = Field(description="episodes over every point")
    preset: str
    overrides: dict[str, Any]
    vary: dict[str, list[Any]]
    parameters: list[str] = Field(description="the varied parameters, in grid order")
    points_total: int
    algorithms: list[str]
    tests: int = Field(description="tests per point and algorithm")
    seed: int
    mode: str
    stop_confidence: float
    created_at: float
    started_at: Optional[float]
    finished_at: Optional[float]
    elapsed_s: Optional[float]
    error: Optional[str] = Field(description="the first failed point's error")
    points: Optional[list[StudyPoint]] = Field(None, description="GET /studies/{id} only")


class StudyPage(BaseModel):
    items: list[StudyPublic]
    total: int
    limit: int
    offset: int


class StudyRow(BaseModel):
    """One point x algorithm: the point, its varied values (one field per varied parameter),
    and every scalar field of the algorithm's block in the point's campaign results (nested
    objects flattened with ``_``, e.g. ``calibration_ece_final``, ``decision_accuracy``)."""

    model_config = ConfigDict(extra="allow")

    point: int
    algorithm: str
    tests: int = Field(description="tests this row rests on (fewer than the study's in a partial result)")
    dr_final: float
    ci95_lo: float
    ci95_hi: float
    time_to_dr90_s: Optional[float]
    in_fov_final: float
    pod_r2: Optional[float]
    campaign_id: Optional[str]


class StudyResultPoint(BaseModel):
    point: int
    values: dict[str, Any]
    campaign_id: Optional[str]
    status: CampaignStatus
    pod: Optional[PODSummary]
    steps_per_second: Optional[float]
    paired: Optional[list[PairedComparison]] = Field(None, description="the point's algorithms compared test by test (McNemar)")


class StudyResults(BaseModel):
    """The results object of a study: one row per point x algorithm."""

    id: Optional[str]
    name: Optional[str]
    status: CampaignStatus
    partial: bool = Field(description="true when read before the study was done (rows of the tests recorded so far)")
    preset: str
    overrides: dict[str, Any]
    vary: dict[str, list[Any]]
    parameters: list[str]
    algorithms: list[str]
    tests: int
    seed: int
    mode: str
    stop_confidence: float
    points: list[StudyResultPoint]
    rows: list[StudyRow]
    steps_per_second: Optional[float]
    policies: Optional[dict[str, dict[str, str]]] = Field(None, description="policies outside the built-ins: the package and version "
                                                                            "each came from ({name: {package, version}})")
