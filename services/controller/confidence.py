"""The controllers' confidence maps: named coefficients in a data file (issue 19).

Each built-in reports a raw confidence, the posterior of the target it names under its own
model, and passes it through a Platt map with covariates the controller measures itself
(``Confidence``, the confidence part of a composition)::

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

RAW_CONFIDENCE_CLIP = 0.01
"""The raw posterior enters the confidence map clipped to [0.01, 0.99]: beyond, it says more about
the model's own assumptions than about the world (a posterior of 1 - 1e-9 is wrong a few percent
of the time in a crowd), and a map linear in an unbounded logit would have to flatten every
confidence to tame those few."""

ADVERTS_MAP_SUFFIX = "-adverts"
"""A built-in's map for a rig of BLE advertisements (``SensorConfig.radio`` "adverts") is named
ALGORITHM-adverts (``bench calibrate --adverts``: fitted on the BLE worlds, whose raw confidences
the RSSI-pair worlds' map does not describe); without one, the algorithm's own map."""

CROWDING_SCALE_RAD = math.radians(1.0)
"""Scale of the crowding covariate exp(-d / scale) of the confidence map (see ``Confidence``)."""


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


@dataclass(slots=True)
class Covariates:
    """What the confidence map conditions on, all measured by the policy itself (see
    ``Confidence``)."""

    tx_walks: float = 0.0
    noise_correlation: float = 0.0
    clutter_density: float = 0.0
    crowding: float = 0.0


class Confidence:
    """The confidence part: the raw posterior of the target named, through a ``ConfidenceMap``.

    sigmoid((A + G tx_walks) logit(raw) + B + C tx_walks + D rho + E clutter + F crowding), raw
    clipped to [0.01, 0.99] (``RAW_CONFIDENCE_CLIP``; G: a walking Tx's posterior is worth less
    per unit of logit). The covariates stand for what the policy's model leaves out: a walking
    Tx may have moved off the answer by the time it is scored (tx_walks: from Rx(dir) when the
    policy listens; for the camera alone, the share of targets seen walking); correlated fading
    leaves fewer independent RF samples than the AR(1) model credits (rho, from Rx(iso)); false
    boxes make tracks that are not people (the tracker's clutter density); another target within
    a degree or so of the answer may be the one the association rule names (crowding,
    exp(-d / 1 deg) for the gap d to the nearest other track). Identity (clipped to [0, 1]) when
    no map is set.

    Parameters
    ----------
    confidence_map : ConfidenceMap or None
        The fitted map (the built-ins': ``shipped_maps()``).
    walk_prior : float
        Prior of the share of walkers, for the camera-alone covariate.
    """

    def __init__(self, confidence_map: ConfidenceMap | None = None, walk_prior: float = 0.3) -> None:
        self.map, self.walk_prior = confidence_map, walk_prior

    def covariates(self, estimate_rad: float, rf, vision, iso) -> Covariates:
        """The covariates of an answer at ``estimate_rad`` given the RF and vision beliefs and
        the Rx(iso) statistics (``rf_belief``, ``vision_belief``)."""
        walks = rf.tx_walks if rf.listens or not vision.sees else float(vision.tracks.walking_share(self.walk_prior))
        rho = iso.noise_correlation() if iso.n else 0.0
        return Covariates(walks, rho, vision.clutter_density(), vision.crowding(estimate_rad, CROWDING_SCALE_RAD))

    def __call__(self, raw: float, covariates: Covariates) -> float:
        """The confidence reported for a raw posterior ``raw``."""
        if self.map is None:
            return float(min(max(raw, 0.0), 1.0))
        p = min(max(raw, RAW_CONFIDENCE_CLIP), 1.0 - RAW_CONFIDENCE_CLIP)
        logit = math.log(p / (1.0 - p))
        c = covariates
        return self.map(logit, c.tx_walks, c.noise_correlation, c.clutter_density, c.crowding)


@lru_cache(maxsize=1)
def _file() -> dict[str, Any]:
    return json.loads(MAPS_FILE.read_text())


@lru_cache(maxsize=1)
def shipped_maps() -> dict[str, ConfidenceMap]:
    """{algorithm: its map} as shipped in ``data/confidence_maps.json``."""
    return {name: ConfidenceMap(**{k: entry["map"][k] for k in ConfidenceMap.FIELDS}) for name, entry in _file()["maps"].items()}


def shipped_map(name: str, radio: str = "pair") -> ConfidenceMap | None:
    """The shipped map ``name`` for a rig whose ``SensorConfig.radio`` is ``radio``: on BLE
    advertisements ``name`` + ``ADVERTS_MAP_SUFFIX`` where one ships, else ``name`` (None: neither)."""
    maps = shipped_maps()
    return (maps.get(name + ADVERTS_MAP_SUFFIX) if radio == "adverts" else None) or maps.get(name)


def shipped_entry(algorithm: str) -> dict[str, Any]:
    """Everything the file says of one algorithm's map (its fit: from_s, samples, ECE)."""
    return _file()["maps"][algorithm]


def write_maps(report: dict[str, Any], path: Path = MAPS_FILE) -> None:
    """Write the maps of a ``calibration.calibrate`` report (merged into the file's other maps),
    with the command that made them."""
    data = json.loads(path.read_text()) if path.exists() else {"maps": {}}
    joint, adverts = bool(report.get("joint")), bool(report.get("adverts"))
    flag = ("--joint " if joint else "") + ("--adverts " if adverts else "")
    for name, a in report["algorithms"].items():
        algorithm = name.removesuffix(ADVERTS_MAP_SUFFIX if adverts else "").removesuffix("-joint" if joint else "")
        data["maps"][name] = {"map": asdict(ConfidenceMap.from_vector(a["map"])),
                              "command": f"ra2vipas bench calibrate {flag}-a {algorithm} --tests {report['tests_per_scenario']} "
                                         f"--seed {report['seed']} --from-s {report['from_s']:g} --write",
                              "from_s": report["from_s"], "samples": a["samples"], "ece_raw": a["ece_raw"],
                              "ece_fitted": a["ece_fitted"]}
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    _file.cache_clear()
    shipped_maps.cache_clear()
