"""The README's result tables are what the code prints (issue 13): its generated blocks equal
``tools/docs.py``'s rendering of docs/results.json; the JSON's small check campaign, rerun
now, equals what the JSON recorded; and the first tests of every documented campaign (paper
and dynamic seeds, early decisions, every robustness world), rerun now, are the ones the JSON
recorded with it (a change to the code that moves any number fails here until `make docs` is
run)."""

from __future__ import annotations

import importlib.util
import json
from collections import Counter
from pathlib import Path

import pytest

import ra2vipas
from ra2vipas.services.orchestrator import reproducibility
from tests.conftest import untimed

ROOT = Path(__file__).resolve().parents[2]


def _docs():
    spec = importlib.util.spec_from_file_location("ra2vipas_docs_tool", ROOT / "tools" / "docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def docs():
    return _docs()


@pytest.fixture(scope="module")
def data(docs):
    return json.loads(docs.RESULTS.read_text())


def test_the_readme_blocks_are_the_rendered_results(docs, data):
    text = docs.README.read_text()
    shown = docs.blocks_of(text)
    rendered = docs.render(data)
    assert set(shown) == set(rendered), "every generated block is in the README once"
    for name, body in rendered.items():
        assert shown[name] == body, f"README block {name!r} differs from docs/results.json: run `make docs`"
    assert docs.apply(text, rendered) == text


def test_a_hand_edited_number_is_caught(docs, data):
    text = docs.README.read_text()
    edited = text.replace("| 1 | **ra2vipas** |", "| 1 | **ra2vipas** | 0.999 |", 1)
    assert edited != text
    assert docs.apply(edited, docs.render(data)) != edited


def test_the_recorded_check_campaign_is_what_the_code_prints_now(docs, data):
    """The check campaign rerun now: each test's decisions as recorded (but for near-ties another
    CPU may flip), and its results as recorded, numbers that pass through a fit within the
    stated tolerances (services/orchestrator/reproducibility.py)."""
    check = data["check"]
    now_tests = docs.first_tests(check["preset"], check["overrides"], check["seed"], check["tests"])
    problems, flipped = reproducibility.decision_drift([("check", now_tests, check["first_tests"])])
    assert not problems, problems
    now = ra2vipas.simulate(preset=check["preset"], overrides=check["overrides"], tests=check["tests"], seed=check["seed"])
    rule = reproducibility.results_tolerance(Counter(name for _, name, _ in flipped), check["tests"])
    drift = reproducibility.differences(untimed(now), check["results"], rule)
    assert not drift, drift


def test_the_first_tests_of_every_documented_campaign_are_what_the_code_prints_now(docs, data):
    """Every campaign behind a README table reruns its first tests (seconds, not the 20 minutes
    of `make docs`): each test's decisions (the digest of every step's choice) and final hit are
    the recorded ones but for near-ties another CPU may flip, within the bounds of
    services/orchestrator/reproducibility.py, and their POD R² is the whole campaign's (it depends
    on the scenario and seed only) within the tolerance of a fit."""
    assert sorted(data["paper"]) == sorted(data["dynamic"]) == [str(s) for s in data["seeds"]] == ["1", "2", "3"]
    campaigns = docs.documented_campaigns(data)
    assert len(campaigns) == 2 * 3 + 1 + len(data["robustness"]["scenarios"]) and len(data["robustness"]["scenarios"]) >= 12
    problems: list[str] = []
    compared = []
    for label, spec, entry in campaigns:
        recorded = entry.get("first_tests")
        assert recorded is not None, f"{label}: no first_tests record: run `python tools/docs.py --first-tests`"
        assert abs(recorded["pod_r2"] - entry.get("pod_r2", recorded["pod_r2"])) <= reproducibility.POD_R2_TOLERANCE, (
            f"{label}: the record is not of this campaign")
        now = docs.first_tests(**spec)
        if not abs(now["pod_r2"] - recorded["pod_r2"]) <= reproducibility.POD_R2_TOLERANCE:
            problems.append(f"{label}: POD R² {now['pod_r2']} != {recorded['pod_r2']}")
        compared.append((label, now, recorded))
    problems += reproducibility.decision_drift(compared)[0]
    assert not problems, f"{problems}: the code no longer prints the documented numbers: run `make docs`"


def test_first_tests_are_not_added_to_a_campaign_this_code_did_not_print(docs, data):
    """`tools/docs.py --first-tests` only adds records, and refuses when the rerun's POD R² is
    not the recorded campaign's: it cannot paper over a drift that only `make docs` can redo."""
    drifted = {**data, "paper": {"1": {"pod_r2": 0.5}}, "dynamic": {}, "robustness": {"seed": 1, "scenarios": {}}}
    with pytest.raises(SystemExit, match=r"paper seed 1: POD R² 0.98795 now, 0.5 recorded: run `make docs`"):
        docs.fill_first_tests(drifted, progress=lambda _: None)
    kept = {**data, "dynamic": {}, "robustness": {"seed": 1, "scenarios": {}}, "paper": {"1": {"first_tests": {"tests": 0}}}}
    assert docs.fill_first_tests(kept, progress=lambda _: None)["paper"]["1"]["first_tests"] == {"tests": 0}
