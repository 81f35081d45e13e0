"""Database rows -> API objects (pure functions, no FastAPI): what each endpoint shows."""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import ValidationError

from ra2vipas.services.orchestrator.api.schemas import (
    CampaignProgress,
    CampaignPublic,
    OutcomePublic,
    PODSummary,
    Progress,
    RigPublic,
    RigsPublic,
    SupervisedService,
    TargetPublic,
    TracePublic,
    TraceStep,
)
from ra2vipas.services.orchestrator.metrics import time_to_level
from ra2vipas.services.orchestrator.storage import ACTIVE, Fault

if TYPE_CHECKING:
    from ra2vipas.services.orchestrator.api.study_schemas import StudyPublic


def campaign_progress(row: dict[str, Any], storage_fault: Fault | None = None) -> CampaignProgress:
    """``storage_fault``: the store's current fault; an unfinished campaign shows it in
    ``error`` (it cannot be written to the database, which is what is failing)."""
    error = row["error"]
    if error is None and storage_fault is not None and row["status"] in ACTIVE:
        error = f"database {storage_fault.describe()}; retrying, nothing is lost"
    return CampaignProgress(
        id=row["id"], status=row["status"], progress=Progress(**row["progress"]), started_at=row["started_at"],
        finished_at=row["finished_at"], pod=PODSummary(r2=row["pod_r2"], train_seconds=row["pod_train_seconds"]),
        error=error,
    )


def campaign_public(row: dict[str, Any], now: float | None = None, storage_fault: Fault | None = None) -> CampaignPublic:
    started, finished = row["started_at"], row["finished_at"]
    if started is None:
        elapsed = None
    elif finished is not None:
        elapsed = max(0.0, finished - started)
    else:
        elapsed = max(0.0, (now or time.time()) - started) if row["status"] in ACTIVE else None
    return CampaignPublic(
        **campaign_progress(row, storage_fault).model_dump(), name=row["name"], preset=row["preset"], overrides=row["overrides"],
        scenario=row["scenario"], algorithms=row["algorithms"], tests=row["tests"], seed=row["seed"], mode=row["mode"],
        created_at=row["created_at"], elapsed_s=None if elapsed is None else round(elapsed, 3),
        steps_per_second=row["steps_per_second"], stop_confidence=row.get("stop_confidence") or 0.0,
        targeting=row.get("targeting"),
    )


def outcome_public(row: dict[str, Any], rf_period_s: float) -> OutcomePublic:
    """How one test of one algorithm ended (a ``Store.episode_page`` row); the step-derived
    fields are null until it is done."""
    base = dict(test_index=row["test_index"], algorithm=row["algorithm"], status=row["status"], rig=row["rig"],
                attempt=row["attempt"], tx_index=row["tx_index"])
    hits = row.get("hits")
    if row["status"] != "done" or not hits:
        return OutcomePublic(**base, final_choice=None, final_hit=None, final_in_fov=None, final_estimate_rad=None,
                             hit_rate=None, first_hit_s=None, settled_s=None)
    h = np.asarray(hits, dtype=float)
    first = np.flatnonzero(h > 0)
    decided = row.get("decided_step")
    return OutcomePublic(
        **base, final_choice=row["final_choice"], final_hit=bool(hits[-1]), final_in_fov=bool(row["final_in_fov"]),
        final_estimate_rad=row["final_estimate"], hit_rate=round(float(h.mean()), 6),
        first_hit_s=None if first.size == 0 else round((int(first[0]) + 1) * rf_period_s, 10),
        settled_s=time_to_level(h, 1.0, rf_period_s), final_confidence=row.get("final_confidence"),
        decided_s=None if decided is None else round((decided + 1) * rf_period_s, 10),
    )


def trace_public(row: dict[str, Any], rf_period_s: float) -> TracePublic:
    """Per step of a finished test: pan angle, reward, gamma_hat_t, î_t and whether it hit; the
    targets at step 0 and, for those that walk, their bearing and range at every step."""
    latencies = row.get("latencies") or []
    confidences = row.get("confidences") or []
    steps = [
        TraceStep(step=t, time_s=round((t + 1) * rf_period_s, 10), pan_rad=row["pans"][t], reward=row["rewards"][t],
                  gamma_hat_rad=row["estimates"][t], i_hat=row["chosen"][t], hit=bool(row["hits"][t]), in_fov=bool(row["in_fov"][t]),
                  latency_ms=latencies[t] if t < len(latencies) else None,
                  confidence=confidences[t] if t < len(confidences) else None)
        for t in range(len(row["estimates"]))
    ]
    walks = {t["index"]: t for t in row.get("trajectories") or []}
    targets = [TargetPublic(index=i, bearing_rad=b, range_m=r, is_tx=i == row["tx_index"],
                            bearings_rad=walks[i]["bearings_rad"] if i in walks else None,
                            ranges_m=walks[i]["ranges_m"] if i in walks else None)
               for i, (b, r) in enumerate(zip(row["bearings"], row["ranges"]))]
    return TracePublic(campaign_id=row["campaign_id"], test_index=row["test_index"], algorithm=row["algorithm"], rig=row["rig"],
                       attempt=row["attempt"], tx_index=row["tx_index"], targets=targets, steps=steps,
                       decided_step=row.get("decided_step"), model_check=row.get("model_check"))


def supervised_services(path: str | None) -> list[SupervisedService]:
    """What ``ra2vipas up``'s supervisor says it is restarting (its status file; [] outside
    ``up`` or when the file cannot be read)."""
    if not path:
        return []
    try:
        with open(path, encoding="utf-8") as f:
            items = json.load(f).get("services", [])
        return [SupervisedService.model_validate(item) for item in items]
    except (OSError, ValueError, AttributeError, ValidationError):
        return []


def rigs_public(status: dict[str, Any], services: list[SupervisedService] | None = None) -> RigsPublic:
    """The scheduler's view of the mesh (from Zenoh liveliness) as the API shows it."""
    rigs = [RigPublic(name=name, live=st["sensors"] and st["controller"], sensors=st["sensors"], controller=st["controller"],
                      in_flight=st["in_flight"], described=st.get("described", "unknown"), descriptor=st.get("descriptor"),
                      protocol=st.get("protocol"), announced=st.get("announced", "unknown"), policies=st.get("policies"),
                      controller_protocol=st.get("controller_protocol"))
            for name, st in sorted(status["rigs"].items())]
    return RigsPublic(rigs=rigs, learners=list(status["learners"]), services=services or [])


def study_public(d: dict[str, Any], now: float | None = None) -> StudyPublic:
    """A study (``StudyStore.study``) as the API shows it; ``points`` only if ``d`` has them."""
    from ra2vipas.services.orchestrator.api.study_schemas import StudyPoint, StudyPublic

    started, finished = d["started_at"], d["finished_at"]
    if started is None:
        elapsed = None
    elif finished is not None:
        elapsed = max(0.0, finished - started)
    else:
        elapsed = max(0.0, (now or time.time()) - started) if d["status"] in ACTIVE else None
    points = d.get("points")
    return StudyPublic(
        id=d["id"], name=d["name"], status=d["status"], progress=Progress(**d["progress"]), preset=d["preset"],
        overrides=d["overrides"], vary=d["vary"], parameters=list(d["vary"]), points_total=d["points_total"],
        algorithms=d["algorithms"], tests=d["tests"], seed=d["seed"], mode=d["mode"], stop_confidence=d["stop_confidence"] or 0.0,
        created_at=d["created_at"], started_at=started, finished_at=finished,
        elapsed_s=None if elapsed is None else round(elapsed, 3), error=d["error"],
        points=None if points is None else [StudyPoint(**p) for p in points],
    )
