"""API schemas (request and response bodies), distinct from wire messages and database rows."""

from __future__ import annotations

from typing import Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field

from services.controller.policy import ALGORITHMS

MAX_TESTS = 10000

AlgorithmName = Literal["ra2vipas", "rapas", "ravipas", "sweep"]


class CampaignCreate(BaseModel):
    """Body of ``POST /campaigns``."""

    model_config = ConfigDict(extra="forbid")

    preset: str = Field("paper", description="scenario preset (GET /presets)", max_length=64)
    overrides: dict[str, Any] = Field(default_factory=dict, description="scenario parameters to override, NAME: value", max_length=64)
    algorithms: list[AlgorithmName] = Field(default_factory=lambda: list(ALGORITHMS), min_length=1, max_length=4)
    tests: int = Field(50, ge=1, le=MAX_TESTS, description="Monte Carlo tests per algorithm")
    seed: int = Field(1, ge=0, le=2**63 - 1, description="campaign seed; fixes every random draw")
    mode: Literal["fast", "realtime"] = Field("fast", description="fast: lockstep as fast as possible; realtime: one sample every T_RF")
    name: Optional[str] = Field(None, max_length=100)


class Progress(BaseModel):
    done: int
    running: int
    pending: int
    total: int


class PODSummary(BaseModel):
    r2: Optional[float] = None
    train_seconds: Optional[float] = None


class CampaignPublic(BaseModel):
    """A campaign as the API shows it."""

    id: str
    name: Optional[str]
    status: Literal["queued", "training", "running", "done", "failed", "cancelled"]
    preset: str
    overrides: dict[str, Any]
    scenario: dict[str, Any]
    algorithms: list[str]
    tests: int
    seed: int
    mode: str
    progress: Progress
    created_at: float
    started_at: Optional[float]
    finished_at: Optional[float]
    pod: PODSummary
    steps_per_second: Optional[float]
    error: Optional[str]


def campaign_public(row: dict[str, Any]) -> CampaignPublic:
    return CampaignPublic(
        id=row["id"], name=row["name"], status=row["status"], preset=row["preset"], overrides=row["overrides"],
        scenario=row["scenario"], algorithms=row["algorithms"], tests=row["tests"], seed=row["seed"], mode=row["mode"],
        progress=Progress(**row["progress"]), created_at=row["created_at"], started_at=row["started_at"],
        finished_at=row["finished_at"], pod=PODSummary(r2=row["pod_r2"], train_seconds=row["pod_train_seconds"]),
        steps_per_second=row["steps_per_second"], error=row["error"],
    )


class Health(BaseModel):
    status: Literal["ok", "starting", "degraded"]
    ready: bool
    database: bool
    zenoh: bool
    rigs: list[str]
    expected_rigs: int
    learners: list[str]
