"""Regenerate tests/rigs/data/sim-survey.json: a small survey recorded from our simulator through
the survey recorder (the same code path as `ra2vipas survey record`, on the in-memory bus).

    .venv/bin/python -m tests.rigs.make_survey
"""

from pathlib import Path

from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.rigs.survey import record_survey, save
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus

OUT = Path(__file__).resolve().parent / "data" / "sim-survey.json"
SCENE = {"n_targets": 8}
SEED = 11


def make(path: Path = OUT) -> None:
    bus = MemoryBus()
    node = SensorsNode(bus, "sim-1")
    try:
        survey = record_survey(bus, "sim-1", pans=180, passes=3, n_train=300, seed=SEED, scenario=build_scenario("paper", SCENE))
    finally:
        node.close()
        bus.close()
    save(survey, path)


if __name__ == "__main__":
    make()
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes)")
