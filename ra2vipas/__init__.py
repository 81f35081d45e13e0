"""ra2vipas: find which target around a pan camera carries the radio transmitter.

The Python API (the CLI and the REST API do the same things):

>>> import ra2vipas
>>> results = ra2vipas.simulate(preset="paper", overrides={"n_targets": 30}, tests=50, seed=1)
>>> results["algorithms"]["ra2vipas"]["dr_final"]
>>> with ra2vipas.Client("http://127.0.0.1:8080") as client:      # a running orchestrator
...     campaign = client.start_campaign(preset="paper", tests=50, seed=1)
...     results = client.wait(campaign["id"])

The services and the command line live in the subpackages ``ra2vipas.services`` (the wire
protocol, the simulated sensors, the learner, the controller, the orchestrator) and
``ra2vipas.cli``. In a source checkout they are the repository's ``services/`` and ``cli/``
folders, mapped to these names by the editable install (``pip install -e .``, pyproject's
package-dir); an installed wheel has them inside this package.
"""

from __future__ import annotations

import os as _os
import sys as _sys

# One BLAS/OpenMP thread. The linear algebra here is on matrices of a few hundred entries:
# worker threads only spin and steal the cores the services need, and, worse, a threaded
# BLAS sums in another order, so a campaign's confidences would differ in the last digit
# between a process with 1 thread (every service) and one with many (a notebook): results
# must be equal value for value wherever they are computed. The variables work if numpy is
# not loaded yet; if it is, threadpoolctl (a scikit-learn dependency) limits the loaded
# libraries.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
if "numpy" in _sys.modules:
    from threadpoolctl import threadpool_limits as _threadpool_limits

    _threadpool_limits(1)

# The public names load on first use (PEP 562), so that ``import ra2vipas`` (which every
# service and the ``ra2vipas`` command do first) costs nothing, and a Ctrl-C while the command line
# loads its libraries reaches its entry (``ra2vipas.cli.launch``), which ends it in one line.
_EXPORTS = {
    "Client": "ra2vipas.api", "ClientError": "ra2vipas.api", "paired_test": "ra2vipas.api", "simulate": "ra2vipas.api",
    "study": "ra2vipas.api", "to_dataframe": "ra2vipas.api",
    "EpisodeContext": "ra2vipas.services.controller.contract", "Policy": "ra2vipas.services.controller.contract",
    "PolicyDecision": "ra2vipas.services.controller.contract", "RigDescription": "ra2vipas.services.controller.contract",
}

__all__ = [*_EXPORTS, "__version__"]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'ra2vipas' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})


try:
    from importlib.metadata import version as _version

    __version__ = _version("ra2vipas")
except Exception:  # not installed (a bare checkout)
    __version__ = "0+unknown"
