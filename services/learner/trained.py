"""A trained POD model as a campaign uses it, and how it is scored, without the learner's fitting
code: the orchestrator scores the model a learner sends against the truth of its training
episode (paper eq. 23) and never fits one, so it does not import the fit's numba kernels,
scikit-learn or SciPy (``services/learner/pod.py`` re-exports these)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ra2vipas.services.protocol.pod import PODModel

NO_SENSORS = "no training stream: no sensors answered"
"""The error reply when the training query reached no sensors (none live, or none reachable from
this learner): the orchestrator asks again, with backoff, rather than failing the campaign."""

TRAINING_DATA_ERROR = "cannot learn the POD from the training episode"
"""How the learner's error reply begins when the training stream was too thin to fit p_D from
(``pod.TrainingDataError``: too few samples, or on BLE too few advertisements). A simulated rig's
training episode of (scenario, seed) is the same every time (a survey's is recorded), so when every
live sensors node is simulated or a survey the orchestrator fails the campaign at once with it; a real rig records a new episode
each time (a tag back in range), so it is asked again as for any other failure."""


@dataclass(frozen=True)
class TrainedPOD:
    """The learned model and how it scores against the truth of its training episode."""

    model: PODModel
    r2: float
    train_seconds: float
    cached: bool = False  # loaded from the POD model cache (services/learner/model_cache.py), not trained now


def predict(model: PODModel, rssi_dbm: np.ndarray | float) -> np.ndarray:
    """p_hat_D at ``rssi_dbm`` by linear interpolation of the model's grid (clamped at the ends)."""
    return np.interp(rssi_dbm, model.rssi_grid_dbm, model.mean)


def r2_score(truth: np.ndarray, prediction: np.ndarray) -> float:
    """The coefficient of determination of paper eq. (23)."""
    truth = np.asarray(truth, dtype=float)
    ss_tot = float(np.sum((truth - truth.mean()) ** 2))
    if ss_tot == 0.0:
        return 0.0
    return 1.0 - float(np.sum((truth - np.asarray(prediction)) ** 2)) / ss_tot
