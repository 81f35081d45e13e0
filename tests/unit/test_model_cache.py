"""The POD model cache (services/learner/model_cache.py): a loaded model is the trained one to the
last bit, anything that decides a model besides (scenario, seed) misses it, and a bad file or
folder never fails a run."""

from __future__ import annotations

import os

from ra2vipas.services.learner.model_cache import PODCache, cache_folder, fingerprint
from ra2vipas.services.learner.pod import LearnerSettings
from ra2vipas.services.orchestrator.simulate import train_pod
from ra2vipas.services.protocol.messages import training_job_id
from ra2vipas.services.protocol.scenario import build_scenario

SCENARIO = build_scenario("paper", {"n_train": 120, "steps": 5})


def test_a_cached_model_is_the_trained_one_bit_for_bit(tmp_path, monkeypatch):
    monkeypatch.setenv("RA2VIPAS_POD_CACHE", str(tmp_path))
    trained = train_pod(SCENARIO, 3)
    loaded = train_pod(SCENARIO, 3)
    assert not trained.cached and loaded.cached
    assert loaded.model == trained.model and (loaded.r2, loaded.train_seconds) == (trained.r2, trained.train_seconds)
    assert [p.name for p in tmp_path.iterdir()] == [f"{training_job_id(SCENARIO, 3)}-{fingerprint(LearnerSettings())}.json"]
    assert not train_pod(SCENARIO, 4).cached  # another seed is another model
    assert not train_pod(SCENARIO, 3, cache=False).cached


def test_what_decides_a_model_besides_the_scenario_is_in_the_key():
    base = fingerprint(LearnerSettings(), {})
    assert fingerprint(LearnerSettings(), {}) == base
    assert fingerprint(LearnerSettings(grid_points=60), {}) != base
    for variable in ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE", "NUMBA_CPU_NAME"):
        assert fingerprint(LearnerSettings(), {variable: "x"}) != base, variable
    assert fingerprint(LearnerSettings(), {"RA2VIPAS_TOKEN": "x"}) == base  # not a numerical kernel's


def test_where_the_cache_is_and_how_it_is_turned_off(tmp_path):
    assert cache_folder({"RA2VIPAS_POD_CACHE": str(tmp_path)}) == tmp_path
    assert cache_folder({"RA2VIPAS_POD_CACHE": "off"}) is None
    assert cache_folder({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "ra2vipas" / "pod-models"
    assert cache_folder({"HOME": "/home/x"}).parts[-2:] == ("ra2vipas", "pod-models")


def test_a_malformed_file_is_trained_again_and_an_unwritable_folder_only_costs_the_training(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("RA2VIPAS_POD_CACHE", str(tmp_path / "pods"))
    cache = PODCache.from_environment(LearnerSettings())
    path = cache.path(training_job_id(SCENARIO, 5))
    path.parent.mkdir()
    path.write_text('{"model": {"truncated')
    pod = train_pod(SCENARIO, 5)
    assert not pod.cached and "ignoring the cached POD model" in caplog.text
    assert train_pod(SCENARIO, 5).cached  # the malformed file was replaced by the trained model
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    monkeypatch.setenv("RA2VIPAS_POD_CACHE", str(blocked / "pods"))  # a folder that cannot be made
    assert not train_pod(SCENARIO, 5).cached and not train_pod(SCENARIO, 5).cached
    assert not [p for p in (tmp_path / "pods").iterdir() if p.name.endswith(".tmp")]
    assert os.listdir(tmp_path / "pods") == [path.name]


def test_the_learner_services_cache_dir_is_keyed_by_the_code_and_never_feeds_simulate(tmp_path, monkeypatch):
    """``ra2vipas learner --cache-dir``: a second learner on the folder serves the model without a
    training stream (no sensors on its bus); a changed learner (another fingerprint) trains again
    instead of serving a stale model; the in-process engine does not take a model it kept (no R²)."""
    from ra2vipas.services.learner import node as learner_node
    from ra2vipas.services.learner.node import LearnerNode
    from ra2vipas.services.protocol.messages import PODRequest
    from ra2vipas.services.sensors.node import SensorsNode
    from ra2vipas.services.transport.bus import MemoryBus, QueryError

    request = PODRequest(scenario=SCENARIO, seed=5)
    bus = MemoryBus()
    sensors = SensorsNode(bus, "rig-1")
    first = LearnerNode(bus, "l1", cache_dir=str(tmp_path))
    try:
        trained = first.model_for(request)
    finally:
        first.close()
        sensors.close()
    alone = MemoryBus()  # no sensors: a model can only come from the folder
    second = LearnerNode(alone, "l2", cache_dir=str(tmp_path))
    try:
        assert second.model_for(request) == trained
    finally:
        second.close()
    monkeypatch.setattr(learner_node, "fingerprint", lambda settings: "0123456789abcdef")  # another learner's code
    changed = LearnerNode(alone, "l3", cache_dir=str(tmp_path))
    try:
        try:
            changed.model_for(request)
            raise AssertionError("a model kept by another code was served")
        except QueryError as err:
            assert "no training stream" in str(err) or "sensors" in str(err)
    finally:
        changed.close()
        bus.close()
        alone.close()
    monkeypatch.setenv("RA2VIPAS_POD_CACHE", str(tmp_path))
    assert not train_pod(SCENARIO, 5).cached
