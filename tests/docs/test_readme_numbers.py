"""The README's result tables are what the code prints (issue 13): its generated blocks equal
``tools/docs.py``'s rendering of docs/results.json, and the JSON's small check campaign, rerun
now, equals what the JSON recorded (a change to the controller that moves any number fails
here until `make docs` is run)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

import ra2vipas
from tests.conftest import differences, untimed

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


def test_the_recorded_check_campaign_is_what_the_code_prints_now(data):
    check = data["check"]
    now = ra2vipas.simulate(preset=check["preset"], overrides=check["overrides"], tests=check["tests"], seed=check["seed"])
    assert not differences(untimed(now), check["results"]), differences(untimed(now), check["results"])


def test_the_documented_tables_agree_with_the_recorded_campaigns(data):
    """The rendered numbers come from the recorded results: e.g. the paper table's 12 s column
    is each algorithm's final DR, and seeds 1-3 are all there."""
    for preset in ("paper", "dynamic"):
        assert sorted(data[preset]) == ["1", "2", "3"]
        for seed, campaign in data[preset].items():
            for name, a in campaign["algorithms"].items():
                assert a["dr_at_s"]["12"] == a["dr_final"]
                assert a["ci95"][0] <= a["dr_final"] <= a["ci95"][1]
    assert len(data["robustness"]["scenarios"]) >= 12
