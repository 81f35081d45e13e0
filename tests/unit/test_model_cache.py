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
