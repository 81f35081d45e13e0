"""Everywhere a built-in runs, a user's policy runs (issue 19): the example policy, installed as a
user would, in a study and in the robustness bench, and results that name it; a campaign of a
policy outside the built-ins drawn and shown with its own colour; and no list of the built-ins'
names kept outside the registry and the wire protocol."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ra2vipas.services.benchmarks.dashboard import seed_campaign
from ra2vipas.services.controller import registry
from ra2vipas.services.controller.registry import BUILTINS
from ra2vipas.services.orchestrator import names, plots, robustness
from ra2vipas.services.orchestrator.dashboard import data
from ra2vipas.services.orchestrator.storage import Store
from tests.api.live import LiveAPI
from tests.policies.test_example_policy import PROVENANCE, ROOT, SMALL, _run, installed  # noqa: F401  (a fixture)

# -- a study and the robustness bench run the installed example -----------------------------------

def test_a_study_runs_an_installed_policy_and_its_rows_name_it(installed):  # noqa: F811
    out = _run(["simulate", "--vary", "n_targets=4,8", "-a", "greedy,ra2vipas", "--tests", "2", "--seed", "3", *SMALL,
                "--workers", "1", "--json"], installed)
    assert out.returncode == 0, out.stderr[-2000:]
    study = json.loads(out.stdout.strip().splitlines()[-1])
    assert study["algorithms"] == ["greedy", "ra2vipas"]
    assert {(r["point"], r["algorithm"]) for r in study["rows"]} == {(p, a) for p in (0, 1) for a in ("greedy", "ra2vipas")}
    assert study["policies"] == PROVENANCE
    # the Python API: the same study, the same rows
    code = ("import json, ra2vipas; print(json.dumps(ra2vipas.study({'n_targets': [4, 8]}, overrides={'steps': 30, 'n_train': 300}, "
            "tests=2, seed=3, algorithms=['greedy', 'ra2vipas'])))")
    api = subprocess.run([sys.executable, "-c", code], env=installed, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert api.returncode == 0, api.stderr[-2000:]
    in_python = json.loads(api.stdout.strip().splitlines()[-1])
    assert in_python["policies"] == PROVENANCE
    strip = ("steps_per_second",)
    assert [{k: v for k, v in r.items() if k not in strip} for r in in_python["rows"]] == \
           [{k: v for k, v in r.items() if k not in strip} for r in study["rows"]]


@pytest.fixture()
def importable(installed):  # noqa: F811
    """The installed example importable in this process too (its folder on sys.path), for an
    API server and its in-memory mesh of controller nodes running here; undone afterwards."""
    site = installed["PYTHONPATH"]
    sys.path.insert(0, site)
    registry.refresh()
    try:
        yield
    finally:
        sys.path.remove(site)
        for module in [m for m in sys.modules if m == "my_policy" or m.startswith("my_policy.")]:
            del sys.modules[module]
        registry.refresh()


def test_a_study_through_the_api_runs_an_installed_policy_and_shows_it(importable, tmp_path):
    from tests.api.test_studies_api import BODY, wait_study

    server = LiveAPI(tmp_path / "s.db").start()
    try:
        with server.client() as http:
            r = http.post("/studies", json={**BODY, "algorithms": ["greedy", "ra2vipas"], "tests": 2})
            assert r.status_code == 201, r.text
            s = wait_study(server, r.json()["id"])
            assert s["status"] == "done", s
            results = http.get(f"/studies/{s['id']}/results").json()
            csv = http.get(f"/studies/{s['id']}/results", params={"format": "csv"}).text
            svg = http.get(f"/studies/{s['id']}/plots/dr_final", params={"format": "svg"})
            page = http.get(f"/ui/studies/{s['id']}")
    finally:
        server.stop()
    assert {(r["point"], r["algorithm"]) for r in results["rows"]} == {(p, a) for p in (0, 1) for a in ("greedy", "ra2vipas")}
    assert results["policies"] == PROVENANCE
    assert sum(line.split(",").count("greedy") for line in csv.splitlines()[1:]) == 2
    assert svg.status_code == 200 and "greedy" in svg.text
    assert page.status_code == 200
    chart = json.loads(re.search(r'<script type="application/json" id="study-data">(.*?)</script>', page.text, re.S).group(1))
    assert chart["colors"] == names.web_colours(["greedy", "ra2vipas"])


def test_the_robustness_bench_adds_an_installed_policy_and_its_paired_difference(installed):  # noqa: F811
    out = _run(["bench", "robustness", "--tests", "3", "--scenario", "paper", "--workers", "1", "-a", "greedy", "--json"], installed)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["algorithms"] == [*BUILTINS, "greedy"] and report["policies"] == PROVENANCE
    paper = report["scenarios"]["paper"]
    assert list(paper["dr"]) == [*BUILTINS, "greedy", "oracle"]
    versus = paper["versus_ra2vipas"]["greedy"]
    assert versus["difference"] == pytest.approx(paper["dr"]["ra2vipas"] - paper["dr"]["greedy"], abs=1e-4)
    assert versus["difference_ci95"][0] <= versus["difference"] <= versus["difference_ci95"][1]
    assert 0.0 <= versus["p_value"] <= 1.0
    table = _run(["bench", "robustness", "--tests", "2", "--scenario", "paper", "--workers", "1", "-a", "greedy"], installed)
    assert table.returncode == 0 and "greedy" in table.stdout and "ra2vipas-my-policy 0.1.0" in table.stdout
    missing = _run(["bench", "robustness", "--tests", "2", "--scenario", "paper", "-a", "greedy"],
                   {k: v for k, v in installed.items() if k != "PYTHONPATH"})
    assert missing.returncode == 2 and "unknown policy 'greedy'" in missing.stderr


def test_another_policy_leaves_the_builtins_robustness_numbers_as_they_were():
    rng = np.random.default_rng(5)
    hits = {a: rng.integers(0, 2, 40).tolist() for a in (*BUILTINS, "oracle")}
    alone = robustness.summarize_scenario("paper", hits)
    beside = robustness.summarize_scenario("paper", {**{a: hits[a] for a in BUILTINS}, "greedy": rng.integers(0, 2, 40).tolist(),
                                                     "oracle": hits["oracle"]})
    extra = beside.pop("versus_ra2vipas")
    for key in ("dr", "ci95"):
        beside[key].pop("greedy")
    assert beside == alone and json.dumps(beside) == json.dumps(alone)  # the same keys in the same order
    # Ra²ViPAS against itself (a policy that chose the same) is a zero difference
    same = robustness.summarize_scenario("paper", {**hits, "twin": hits["ra2vipas"]})["versus_ra2vipas"]["twin"]
    assert same["difference"] == 0.0 and same["not_worse"] and same["p_value"] == 1.0
    assert set(extra["greedy"]) == {"difference", "difference_ci95", "not_worse", "only_ra2vipas", "only_other", "p_value"}


# -- figures and the dashboard with a name outside the built-ins --------------------------------

def test_a_policy_has_one_colour_whatever_is_drawn_beside_it():
    assert names.colours(BUILTINS) == dict(zip(BUILTINS, names.PLOT_COLOURS))  # what a four-algorithm figure always drew
    alone, beside = names.colours(["greedy"]), names.colours(["ra2vipas", "greedy", "rapas"])
    assert alone["greedy"] == beside["greedy"] and alone["greedy"] not in names.PLOT_COLOURS
    many = names.web_colours([f"p{i}" for i in range(len(names.WEB_EXTRA))])
    assert sorted(many.values()) == sorted(names.WEB_EXTRA)  # no two share a colour while the palette lasts
    assert names.label("greedy") == "greedy" and names.label("ra2vipas") == "Ra²ViPAS"


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """A finished campaign of "greedy" and "ra2vipas", written through the storage API, served."""
    db = tmp_path_factory.mktemp("everywhere") / "r.db"
    store = Store(str(db))
    cid = seed_campaign(store, tests=6, seed=4, algorithms=["greedy", "ra2vipas"])
    store.close()
    server = LiveAPI(db).start()
    yield server, cid
    server.stop()


def test_figures_draw_a_campaign_of_a_policy_outside_the_builtins(stored):
    server, cid = stored
    with server.client() as http:
        results = http.get(f"/campaigns/{cid}/results").json()
        assert list(results["algorithms"]) == ["greedy", "ra2vipas"]
        for kind in ("dr", "reliability"):
            for fmt, magic in (("png", b"\x89PNG"), ("svg", b"<?xml")):
                r = http.get(f"/campaigns/{cid}/plots/{kind}", params={"format": fmt})
                assert r.status_code == 200 and r.content.startswith(magic), (kind, fmt, r.text[:200])
        svg = http.get(f"/campaigns/{cid}/plots/dr", params={"format": "svg"}).text
    assert "greedy (final" in svg
    from matplotlib.colors import to_hex

    fig = plots.dr_figure(results)
    drawn = {line.get_label().split(" (")[0]: to_hex(line.get_color()) for line in fig.axes[0].get_lines() if "(final" in line.get_label()}
    want = {plots.LABELS.get(a, a): to_hex(c) for a, c in names.colours(["greedy", "ra2vipas"]).items()}
    assert drawn == want
    only = {a: b for a, b in results["algorithms"].items() if a == "greedy"}
    fig = plots.dr_figure({**results, "algorithms": only})
    assert to_hex(fig.axes[0].get_lines()[0].get_color()) == want["greedy"]  # the same colour alone


def test_the_dashboard_shows_a_policy_outside_the_builtins_in_the_servers_colour(stored):
    server, cid = stored
    with server.client() as http:
        page = http.get(f"/ui/campaigns/{cid}")
        assert page.status_code == 200 and "greedy" in page.text
        curves = json.loads(re.search(r'<script type="application/json" id="dr-data">(.*?)</script>', page.text, re.S).group(1))
        episode = http.get(f"/ui/campaigns/{cid}/tests/0/greedy")
        assert episode.status_code == 200 and "Test 0, greedy" in episode.text
        assert http.get(f"/ui/campaigns/{cid}/tests/0/ravipas").status_code == 404  # not one of its algorithms
        tests = http.get(f"/ui/campaigns/{cid}/tests", params={"sort_algorithm": "greedy"})
        assert tests.status_code == 200
        results = http.get(f"/campaigns/{cid}/results").json()
    colour = names.web_colours(["greedy", "ra2vipas"])
    assert {a: (c["label"], c["color"]) for a, c in curves["algorithms"].items()} == \
           {"greedy": ("greedy", colour["greedy"]), "ra2vipas": ("Ra²ViPAS", colour["ra2vipas"])}
    reliability = data.reliability_series(results)
    assert reliability["algorithms"]["greedy"]["color"] == colour["greedy"]
    chart = data.study_chart({"parameters": ["n_targets"], "vary": {"n_targets": [4]}, "partial": False, "status": "done",
                              "algorithms": ["greedy", "ra2vipas"], "rows": []})
    assert chart["colors"] == colour


# -- one list of the built-ins' names ---------------------------------------------------------------

ALLOWED = {"services/controller/registry.py",  # registry.BUILTINS
           "services/protocol/messages.py", "services/protocol/versions.py"}  # the names protocol 1.0 froze
PRODUCT = ("services", "cli", "ra2vipas", "tools")


def _lists_of_the_builtins(path: Path) -> list[int]:
    """Lines of tuples, lists and sets of string literals that hold every built-in's name."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            strings = {e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)}
            if set(BUILTINS) <= strings:
                found.append(node.lineno)
    return found


def test_no_list_of_the_builtins_names_outside_the_registry_and_the_protocol():
    offenders = []
    for top in PRODUCT:
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel not in ALLOWED and ".venv" not in rel:
                offenders += [f"{rel}:{line}" for line in _lists_of_the_builtins(path)]
    for path in sorted((ROOT / "services").rglob("*.js")):  # the dashboard's colours come from the server
        text = path.read_text()
        if all(re.search(rf"\b{name}\b\s*:", text) for name in BUILTINS):
            offenders.append(path.relative_to(ROOT).as_posix())
    assert not offenders, f"lists of the built-ins' names: derive them from registry.BUILTINS / names(): {offenders}"


def test_the_radio_warning_counts_the_builtins_that_read_rx_dir_never_a_policy_whose_cues_are_unknown():
    from ra2vipas.services.orchestrator.rigcheck import dr_warnings, radio_algorithms

    assert radio_algorithms() == tuple(a for a in BUILTINS if a != "ravipas")  # RaViPAS: the camera and Rx(iso) only
    assert radio_algorithms() == tuple(a for a in BUILTINS if registry.load(a).reads_rx_dir)  # what their classes say
    scenario = {"n_targets": 20, "antenna_model": "paper"}
    far_below = {"dr_final": 0.0}
    assert dr_warnings({"scenario": scenario, "tests": 200, "algorithms": {"greedy": far_below, "ravipas": far_below}}) == []
    warned = dr_warnings({"scenario": scenario, "tests": 200, "algorithms": {"greedy": far_below, "rapas": far_below}})
    assert len(warned) == 1 and "rapas 0.00" in warned[0] and "greedy" not in warned[0]
