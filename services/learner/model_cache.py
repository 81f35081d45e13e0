"""Trained POD models kept on disk between runs: a run that needs the model of a (scenario, seed)
this machine already trained, with this code and these numerical libraries, loads it instead of
training again (the training episode and the fit take seconds of CPU per model).

A model is the same bytes whether it is trained or loaded: what decides it besides the scenario
and the seed (``training_job_id``, the learner's own cache key) is in the file's name, so any
change to it misses the cache instead of reading a stale model —

* the code of the training world and the learner: every file of ``services/learner``,
  ``services/sensors`` (with its data files) and ``services/protocol``, and
  ``services/orchestrator/simulate.py`` (``train_pod``, which scores the model);
* the learner's settings;
* the numerical libraries' versions (numpy, SciPy, scikit-learn, numba) and Python's;
* the kernels they run: the machine's architecture, numpy's dispatched CPU features, and every
  ``NPY_*``, ``OPENBLAS_*``, ``NUMBA_*``, ``OMP_*`` and ``MKL_*`` variable (they move a float's
  last bits, as another CPU does).

Where: ``$RA2VIPAS_POD_CACHE`` if set (``off`` turns the cache off), else
``$XDG_CACHE_HOME/ra2vipas/pod-models`` (``~/.cache/ra2vipas/pod-models``). A file is written
whole or not at all (a temporary file renamed into place), an unreadable or malformed one is
trained again, and a folder that cannot be written only costs the training: the cache never
fails a run. Used by the in-process engine (``simulate``, studies, benchmarks, calibration),
and by the learner service for its ``--cache-dir`` (off by default, so a stack trains what its
sensors stream; a model it keeps has no R², and the in-process engine never takes one of those).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import platform
import sys
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Mapping

from ra2vipas.services.protocol.pod import PODModel

log = logging.getLogger("ra2vipas")

ENV = "RA2VIPAS_POD_CACHE"
OFF = frozenset({"off", "0", "no", "false", "none"})
LIBRARIES = ("numpy", "scipy", "scikit-learn", "numba")
KERNEL_VARIABLES = ("NPY_", "OPENBLAS_", "NUMBA_", "OMP_", "MKL_")
_SERVICES = Path(__file__).resolve().parents[1]
CODE = ("learner", "sensors", "protocol", "orchestrator/simulate.py")  # under services/: what trains and scores a model


@dataclass(frozen=True)
class CachedPOD:
    """A trained model with its score (R² against its training episode's truth) and the seconds
    its training took when it was trained."""

    model: PODModel
    r2: float | None  # None: trained by the learner service from a rig's stream (no truth to score it)
    train_seconds: float


def cache_folder(environ: Mapping[str, str] = os.environ) -> Path | None:
    """The folder models are kept in, or None when ``RA2VIPAS_POD_CACHE`` turns the cache off."""
    value = environ.get(ENV, "").strip()
    if value.lower() in OFF:
        return None
    if value:
        return Path(value).expanduser()
    base = environ.get("XDG_CACHE_HOME", "").strip() or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ra2vipas" / "pod-models"


@lru_cache(maxsize=1)
def _code_digest() -> str:
    digest = hashlib.sha256()
    for part in CODE:
        path = _SERVICES / part
        for file in sorted(path.rglob("*") if path.is_dir() else [path]):
            if file.is_file() and "__pycache__" not in file.parts:
                digest.update(file.relative_to(_SERVICES).as_posix().encode() + b"\0" + file.read_bytes() + b"\0")
    return digest.hexdigest()


def _versions() -> list[str]:
    out = [sys.version]
    for name in LIBRARIES:
        try:
            out.append(f"{name}=={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            out.append(f"{name} missing")
    return out


def _kernels(environ: Mapping[str, str]) -> list[str]:
    from numpy._core import _multiarray_umath as umath

    features = sorted(f for f in umath.__cpu_dispatch__ if umath.__cpu_features__.get(f))
    variables = sorted(f"{k}={v}" for k, v in environ.items() if k.startswith(KERNEL_VARIABLES))
    return [platform.machine(), *features, *variables]


def fingerprint(settings: object | None = None, environ: Mapping[str, str] = os.environ) -> str:
    """What decides a trained model besides (scenario, seed), as 16 hex digits (module docstring)."""
    learner = json.dumps(dataclasses.asdict(settings), sort_keys=True, default=str) if dataclasses.is_dataclass(settings) else repr(settings)
    parts = [_code_digest(), learner, *_versions(), *_kernels(environ)]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


class PODCache:
    """The models of one folder, under this code's fingerprint (``fingerprint``)."""

    def __init__(self, folder: Path, fingerprint: str) -> None:
        self.folder, self.fingerprint = folder, fingerprint

    @classmethod
    def from_environment(cls, settings: object | None = None, environ: Mapping[str, str] = os.environ) -> PODCache | None:
        folder = cache_folder(environ)
        return None if folder is None else cls(folder, fingerprint(settings, environ))

    def path(self, job_id: str) -> Path:
        return self.folder / f"{job_id}-{self.fingerprint}.json"

    def load(self, job_id: str) -> CachedPOD | None:
        """The model of ``job_id`` (``training_job_id``) if this cache has it, else None."""
        path = self.path(job_id)
        try:
            data = json.loads(path.read_bytes())
            return CachedPOD(model=PODModel.model_validate(data["model"]), r2=None if data["r2"] is None else float(data["r2"]),
                             train_seconds=float(data["train_seconds"]))
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as err:  # unreadable or malformed: train again
            log.warning("ignoring the cached POD model %s (%s)", path, err)
            return None

    def store(self, job_id: str, pod: CachedPOD) -> None:
        """Keep ``pod`` (a file written whole: a temporary file renamed into place); a folder that
        cannot be written is logged and otherwise ignored."""
        body = json.dumps({"job_id": job_id, "fingerprint": self.fingerprint, "r2": pod.r2, "train_seconds": pod.train_seconds,
                           "model": pod.model.model_dump(mode="json")}).encode()
        tmp = None
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{job_id}-", suffix=".tmp", dir=self.folder)
            with os.fdopen(fd, "wb") as f:
                f.write(body)
            os.replace(tmp, self.path(job_id))
            tmp = None
        except OSError as err:
            log.debug("cannot keep the POD model %s in %s: %s", job_id, self.folder, err)
        finally:
            if tmp is not None:
                try:
                    os.unlink(tmp)
                except OSError:
                    pass
