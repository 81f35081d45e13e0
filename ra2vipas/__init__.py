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

from ra2vipas.api import Client, ClientError, paired_test, simulate, study, to_dataframe  # noqa: E402
from ra2vipas.services.controller.contract import EpisodeContext, Policy, PolicyDecision, RigDescription  # noqa: E402

__all__ = ["Client", "ClientError", "EpisodeContext", "Policy", "PolicyDecision", "RigDescription", "paired_test", "simulate",
           "study", "to_dataframe", "__version__"]

try:
    from importlib.metadata import version as _version

    __version__ = _version("ra2vipas")
except Exception:  # not installed (a bare checkout)
    __version__ = "0+unknown"
