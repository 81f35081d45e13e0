"""The learner service's node logic: train the POD model once per (scenario, seed), serve it.

``model/pod`` is a queryable. A ``PODRequest`` names a scenario and a seed; the learner
looks up its cache, or asks a rig's sensors to run the training episode
(``data/*/training`` query), fits ``p_hat_D(r)`` (``ra2vipas.services.learner.pod``) and caches
the result. Concurrent requests for the same model wait for one training. Training is
deterministic in (scenario, seed), so a restarted learner retrains the identical model; with
``cache_dir`` set, models also survive restarts on disk.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from ra2vipas.services.learner.model_cache import CachedPOD, PODCache, fingerprint
from ra2vipas.services.learner.pod import LearnerSettings, TrainingDataError, fit_pod
from ra2vipas.services.learner.trained import NO_SENSORS, TRAINING_DATA_ERROR
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import (
    ErrorReply,
    PODRequest,
    PODResponse,
    TrainingRequest,
    TrainingStream,
    decode,
    dump,
    training_job_id,
)
from ra2vipas.services.transport.bus import Bus, QueryError, Reply, undeclare_all
from ra2vipas.services.transport.runtime import first_valid_reply

log = logging.getLogger(__name__)

TRAINING_TIMEOUT_S = 600.0


class LearnerNode:
    """Serves POD models; each model is trained at most once per process (and per cache dir)."""

    def __init__(self, bus: Bus, name: str = "learner", cache_dir: str | None = None, settings: LearnerSettings | None = None) -> None:
        self.bus = bus
        self.name = keys.check_chunk(name, "name")
        self.settings = settings or LearnerSettings()
        self.cache_dir = Path(cache_dir) if cache_dir else None
        if self.cache_dir:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
        # the models kept there are named by what decides them besides (scenario, seed): this
        # code, these settings, the numerical libraries and their kernels (model_cache.py), so a
        # changed learner trains again instead of serving a stale model
        self._disk = PODCache(self.cache_dir, fingerprint(self.settings)) if self.cache_dir else None
        self._cache: dict[str, PODResponse] = {}
        self._locks: dict[str, threading.Lock] = {}
        self._guard = threading.Lock()
        self._handles = [
            bus.serve(keys.pod_model(), self._on_request),
            bus.announce(keys.alive("learner", self.name)),
        ]

    def _on_request(self, _key: str, payload: bytes) -> bytes:
        req, reason = decode(PODRequest, payload)
        if req is None:
            raise QueryError(dump(ErrorReply(error=f"malformed PODRequest: {reason}")).decode())
        return dump(self.model_for(req), version=req.protocol)  # nothing newer than the asker speaks

    def model_for(self, req: PODRequest) -> PODResponse:
        """The cached model of (scenario, seed), training it first if needed (blocking)."""
        job = training_job_id(req.scenario, req.seed)
        with self._guard:
            lock = self._locks.setdefault(job, threading.Lock())
        with lock:
            cached = self._cache.get(job) or self._load(job)
            if cached is not None:
                self._cache[job] = cached
                return cached
            stream = self._run_training(TrainingRequest(job_id=job, scenario=req.scenario, seed=req.seed))
            try:
                learned = fit_pod(list(stream.samples), LearnerSettings.for_scenario(req.scenario, self.settings))
            except TrainingDataError as err:  # the asker is told why (its campaign fails with it: TRAINING_DATA_ERROR)
                log.warning("cannot learn the POD model %s: %s", job, err)
                raise QueryError(dump(ErrorReply(error=f"{TRAINING_DATA_ERROR}: {err} (n_train = "
                                                       f"{req.scenario.n_train}: raise it)")).decode()) from None
            response = PODResponse(job_id=job, model=learned.model, train_seconds=round(learned.train_seconds, 6))
            self._cache[job] = response
            self._store(job, response)
            log.info("trained POD model %s in %.2f s", job, learned.train_seconds)
            return response

    def _run_training(self, request: TrainingRequest) -> TrainingStream:
        done = threading.Event()
        box: dict[str, list[Reply]] = {}

        def got(replies: list[Reply]) -> None:
            box["replies"] = replies
            done.set()

        self.bus.query(keys.training_any(), dump(request), TRAINING_TIMEOUT_S, got)
        done.wait(TRAINING_TIMEOUT_S + 5.0)
        stream, passed_over = first_valid_reply(box.get("replies", []), TrainingStream, "TrainingStream",
                                                accept=lambda s: s.job_id == request.job_id)
        if stream is None:
            error = ("no training stream: " + "; ".join(passed_over)) if passed_over else NO_SENSORS
            raise QueryError(dump(ErrorReply(error=error)).decode())
        return stream

    # -- optional disk cache ----------------------------------------------------------------
    def _load(self, job: str) -> PODResponse | None:
        hit = self._disk.load(job) if self._disk is not None else None
        return None if hit is None else PODResponse(job_id=job, model=hit.model, train_seconds=hit.train_seconds)

    def _store(self, job: str, response: PODResponse) -> None:
        if self._disk is not None:
            self._disk.store(job, CachedPOD(model=response.model, r2=None, train_seconds=response.train_seconds))

    def close(self) -> None:
        undeclare_all(self._handles)
