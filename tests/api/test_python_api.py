"""The Python API (``import ra2vipas``): ``simulate`` and ``study`` in this process,
``Client`` against a live orchestrator, ``to_dataframe``; and the README's example, run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import ra2vipas
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol.scenario import build_scenario
from tests.api.conftest import TOKEN
from tests.api.live import SMALL
from tests.conftest import untimed

README = Path(__file__).resolve().parents[2] / "README.md"
BASE = {k: v for k, v in SMALL.items() if k != "n_targets"}  # what a study of n_targets varies on


def test_simulate_is_the_in_process_campaign():
    got = ra2vipas.simulate(preset="paper", overrides=SMALL, tests=3, seed=2, algorithms=["ra2vipas", "rapas"])
    want = run_campaign("paper", build_scenario("paper", SMALL), 3, 2, ["ra2vipas", "rapas"])
    assert untimed(got) == untimed(want)
    assert set(got["algorithms"]) == {"ra2vipas", "rapas"} and "calibration" in got["algorithms"]["ra2vipas"]


def test_simulate_with_two_workers_and_early_decisions():
    one = ra2vipas.simulate(overrides=SMALL, tests=4, seed=3, algorithms=["ra2vipas"], stop_confidence=0.9)
    two = ra2vipas.simulate(overrides=SMALL, tests=4, seed=3, algorithms=["ra2vipas"], stop_confidence=0.9, workers=2)
    assert untimed(one) == untimed(two)
    assert set(one["algorithms"]["ra2vipas"]["decision"]) >= {"accuracy", "median_s", "undecided"}


@pytest.mark.parametrize("kwargs, message", [
    ({"preset": "papr"}, "unknown preset 'papr'"),
    ({"overrides": {"n_target": 30}}, "n_target"),
    ({"overrides": {"n_targets": 0}}, "n_targets"),
    ({"algorithms": ["ra2vipas", "nope"]}, "unknown policy 'nope'"),
    ({"tests": 0}, "tests: expected an integer from 1 to 10000"),
    ({"tests": "10"}, "tests: expected an integer from 1 to 10000"),
    ({"tests": 10001}, "tests: expected an integer from 1 to 10000"),  # the CLI's cap
    ({"seed": -1}, "seed: expected an integer >= 0"),
    ({"stop_confidence": 1.5}, "stop_confidence"),
    ({"workers": 0}, "workers: expected a positive integer"),
])
def test_bad_input_is_a_one_line_value_error(kwargs, message):
    with pytest.raises(ValueError) as err:
        ra2vipas.simulate(**{"overrides": SMALL, "tests": 1, **kwargs})
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_study_point_is_the_campaign_with_that_value():
    study = ra2vipas.study({"n_targets": [4, 8]}, overrides=BASE, tests=3, seed=4, algorithms=["ra2vipas", "rapas"])
    assert [p["values"] for p in study["points"]] == [{"n_targets": 4}, {"n_targets": 8}]
    rows = {(r["n_targets"], r["algorithm"]): r for r in study["rows"]}
    assert len(rows) == 4
    alone = ra2vipas.simulate(overrides={**SMALL, "n_targets": 4}, tests=3, seed=4, algorithms=["ra2vipas", "rapas"])
    for algorithm in ("ra2vipas", "rapas"):
        assert rows[(4, algorithm)]["dr_final"] == alone["algorithms"][algorithm]["dr_final"]
        assert [rows[(4, algorithm)]["ci95_lo"], rows[(4, algorithm)]["ci95_hi"]] == alone["algorithms"][algorithm]["ci95"]
    with pytest.raises(ValueError, match="vary"):
        ra2vipas.study({}, overrides=SMALL, tests=1)
    with pytest.raises(ValueError, match="n_target"):
        ra2vipas.study({"n_target": [4]}, overrides=BASE, tests=1)


def test_to_dataframe_of_a_campaign_and_of_a_study():
    results = ra2vipas.simulate(overrides=SMALL, tests=2, seed=1, algorithms=["ra2vipas", "rapas"])
    curves = ra2vipas.to_dataframe(results)
    assert len(curves) == 2 * SMALL["steps"]
    assert list(curves.columns) == ["preset", "seed", "tests", *SMALL, "algorithm", "step", "time_s", "dr", "ci_lo", "ci_hi"]
    assert set(curves.steps) == {SMALL["steps"]} and set(curves.seed) == {1}  # what was run, on every row
    last = curves[(curves.algorithm == "rapas") & (curves.step == SMALL["steps"])].iloc[0]
    assert last.dr == results["algorithms"]["rapas"]["dr_final"]
    study = ra2vipas.study({"rf_noise_db": [2.0, 4.0]}, overrides=SMALL, tests=2, seed=1, algorithms=["rapas"])
    table = ra2vipas.to_dataframe(study)
    assert list(table["rf_noise_db"]) == [2.0, 4.0] and list(table["algorithm"]) == ["rapas", "rapas"]


def test_the_client_runs_campaigns_and_studies_like_the_process(live):
    with ra2vipas.Client(live.url) as client:
        c = client.start_campaign(preset="paper", overrides=SMALL, tests=2, seed=6, algorithms=["ra2vipas"], name="py")
        results = client.wait(c["id"], timeout=60)
        assert untimed(results) == untimed(ra2vipas.simulate(overrides=SMALL, tests=2, seed=6, algorithms=["ra2vipas"]))
        assert any(item["id"] == c["id"] for item in client.campaigns(status="done"))
        s = client.start_study({"n_targets": [4, 6]}, overrides=BASE, tests=2, seed=6, algorithms=["rapas"])
        got = client.wait_study(s["id"], timeout=60)
        assert [r["dr_final"] for r in got["rows"]] == [
            r["dr_final"] for r in ra2vipas.study({"n_targets": [4, 6]}, overrides=BASE, tests=2, seed=6, algorithms=["rapas"])["rows"]]
        with pytest.raises(ra2vipas.ClientError) as err:
            client.start_campaign(overrides={"n_targets": 0})
        assert err.value.status == 422 and "n_targets" in str(err.value)
        with pytest.raises(ra2vipas.ClientError) as err:
            client.campaign("nope")
        assert err.value.status == 404


def test_the_client_says_when_the_api_is_unreachable_or_refuses_the_token(guarded):
    with pytest.raises(ra2vipas.ClientError) as err:
        with ra2vipas.Client("http://127.0.0.1:9", timeout=2) as client:
            client.campaigns()
    assert err.value.status is None and "cannot reach" in str(err.value)
    with ra2vipas.Client(guarded.url, token="wrong") as client:
        with pytest.raises(ra2vipas.ClientError) as err:
            client.start_campaign(overrides=SMALL, tests=1)
    assert err.value.status == 401
    with ra2vipas.Client(guarded.url, token=TOKEN) as client:
        assert client.start_campaign(overrides=SMALL, tests=1)["status"] in ("queued", "running")


def test_the_readme_example_runs(live, capsys):
    """The README's Python block, with 2 tests instead of 50 and the live server's address."""
    text = README.read_text()
    section = text[text.index("### From Python"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "tests=50" in code and "http://127.0.0.1:8080" in code
    code = code.replace("tests=50", "tests=2").replace("http://127.0.0.1:8080", live.url)
    namespace: dict = {}
    exec(compile(code, "README.md (From Python)", "exec"), namespace)
    assert set(namespace["table"]["n_targets"]) == {10, 20, 40}
    assert len(namespace["noise"]) == 3 * 4 and namespace["curves"]["step"].max() == 120
    assert namespace["results"]["tests"] == 2
