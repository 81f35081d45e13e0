"""Compile the numba kernels into their on-disk cache once, before the test suite (``make test``).

The controller's, the tracker's and the learner's inner loops are numba functions cached on disk
(``cache=True``, beside their source): the first process that calls one compiles it (~25-35 s of
CPU for all of them) and later processes load it. In a fresh clone the suite starts many
processes at once (two pytest workers, the services and the engine's worker processes they
start), and each that calls a kernel before the cache holds it compiles it again. One short
campaign per world with every built-in (and a POD model trained, not loaded) compiles each
kernel once. ``make test`` runs it twice side by side: for this CPU, and with
``NUMBA_CPU_NAME=generic`` for tests/docs/test_other_cpus.py's child (numba keys its cache by
the CPU it compiles for).

    python tools/warm_kernels.py
"""

from __future__ import annotations

import os
import time

WORLDS = ("paper", "dynamic", "ble-dynamic", "ble-recorded", "ward")


def main() -> None:
    os.environ["RA2VIPAS_POD_CACHE"] = "off"  # train: the learner's kernels compile too
    started = time.process_time()
    from ra2vipas.services.orchestrator.simulate import run_campaign
    from ra2vipas.services.protocol.scenario import build_scenario

    for preset in WORLDS:
        run_campaign(preset, build_scenario(preset, {"steps": 12, "n_train": 150}), 1, 1, workers=1)
    cpu = os.environ.get("NUMBA_CPU_NAME") or "this CPU"
    print(f"numba kernels compiled or loaded for {cpu} in {time.process_time() - started:.1f} s of CPU")


if __name__ == "__main__":
    main()
