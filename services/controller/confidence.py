"""The controllers' confidence maps: named coefficients in a data file (issue 19).

Each built-in reports a raw confidence, the posterior of the target it names under its own
model, and passes it through a Platt map with covariates the controller measures itself
(``Controller._calibrated``)::

    z = (logit + logit_x_tx_walks * tx_walks) * logit(raw) + intercept
        + tx_walks * tx_walks + noise_correlation * rho + clutter_density * clutter + crowding * crowding
    confidence = sigmoid(z)

The coefficients live in ``data/confidence_maps.json``, one named field each, written by
``ra2vipas bench calibrate --write`` (``services/orchestrator/calibration.py``), which also
records the command, the samples and the ECE before and after.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

MAPS_FILE = Path(__file__).resolve().parent / "data" / "confidence_maps.json"


@dataclass(frozen=True)
class ConfidenceMap:
    """sigmoid((logit + logit_x_tx_walks tx_walks) logit(raw) + intercept + tx_walks tx_walks +
    noise_correlation rho + clutter_density clutter + crowding crowding)."""

    logit: float = 1.0
    intercept: float = 0.0
    tx_walks: float = 0.0
    noise_correlation: float = 0.0
    clutter_density: float = 0.0
    crowding: float = 0.0
    logit_x_tx_walks: float = 0.0

    FIELDS = ("logit", "intercept", "tx_walks", "noise_correlation", "clutter_density", "crowding", "logit_x_tx_walks")
    """The order of the columns of ``calibration._design`` (and of a coefficient vector)."""

    @classmethod
    def from_vector(cls, values) -> "ConfidenceMap":
        values = [float(v) for v in values] + [0.0] * (len(cls.FIELDS) - len(values))
        return cls(**dict(zip(cls.FIELDS, values[:len(cls.FIELDS)])))

    def vector(self) -> tuple[float, ...]:
        return tuple(getattr(self, name) for name in self.FIELDS)

    def __call__(self, logit: float, tx_walks: float, rho: float, clutter: float, crowding: float) -> float:
        """The confidence of a raw posterior whose clipped logit is ``logit``."""
        z = ((self.logit + self.logit_x_tx_walks * tx_walks) * logit + self.intercept + self.tx_walks * tx_walks
             + self.noise_correlation * rho + self.clutter_density * clutter + self.crowding * crowding)
        return float(1.0 / (1.0 + math.exp(-min(max(z, -50.0), 50.0))))


@lru_cache(maxsize=1)
def _file() -> dict[str, Any]:
    return json.loads(MAPS_FILE.read_text())


@lru_cache(maxsize=1)
def shipped_maps() -> dict[str, ConfidenceMap]:
    """{algorithm: its map} as shipped in ``data/confidence_maps.json``."""
    return {name: ConfidenceMap(**{k: entry["map"][k] for k in ConfidenceMap.FIELDS}) for name, entry in _file()["maps"].items()}


def shipped_entry(algorithm: str) -> dict[str, Any]:
    """Everything the file says of one algorithm's map (its fit: from_s, samples, ECE)."""
    return _file()["maps"][algorithm]


def write_maps(report: dict[str, Any], path: Path = MAPS_FILE) -> None:
    """Write the maps of a ``calibration.calibrate`` report (merged into the file's other maps),
    with the command that made them."""
    data = json.loads(path.read_text()) if path.exists() else {"maps": {}}
    for name, a in report["algorithms"].items():
        data["maps"][name] = {"map": asdict(ConfidenceMap.from_vector(a["map"])),
                              "command": f"ra2vipas bench calibrate -a {name} --tests {report['tests_per_scenario']} "
                                         f"--seed {report['seed']} --from-s {report['from_s']:g} --write",
                              "from_s": report["from_s"], "samples": a["samples"], "ece_raw": a["ece_raw"],
                              "ece_fitted": a["ece_fitted"]}
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    _file.cache_clear()
    shipped_maps.cache_clear()
