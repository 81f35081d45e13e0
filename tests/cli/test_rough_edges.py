"""Everyday mistakes get one line and the right exit code (issue 13): bad settings in the
environment, an --api without its scheme, an unknown preset; and `--version`."""

from __future__ import annotations

import pytest

import ra2vipas
from tests.cli.conftest import one_error_line
from tests.cli.conftest import ra2vipas as run


@pytest.mark.parametrize("variable, value, words", [
    ("RA2VIPAS_PORT", "80a", "valid integer"),
    ("RA2VIPAS_PORT", "70000", "less than or equal to 65535"),
    ("RA2VIPAS_EXPECT_RIGS", "-3", "greater than or equal to 0"),
    ("RA2VIPAS_WINDOW", "0", "greater than or equal to 1"),
    ("RA2VIPAS_PLOT_WORKERS", "two", "valid integer"),
])
def test_a_bad_setting_in_the_environment_is_one_line_and_exit_2(variable, value, words):
    proc = run("orchestrator", env={variable: value}, timeout=60)
    assert proc.returncode == 2, proc
    line = one_error_line(proc)
    assert line.startswith(f"error: {variable}: ") and words in line and repr(value) in line


def test_a_bad_flag_value_names_the_flag():
    from ra2vipas.services.orchestrator.settings import OrchestratorSettings, SettingsError

    with pytest.raises(SettingsError, match=r"^--window: input should be greater than or equal to 1, got 0$"):
        OrchestratorSettings.from_sources(window=0, env={})
    assert OrchestratorSettings.from_sources(env={"RA2VIPAS_PORT": "18300"}).port == 18300


def test_an_api_address_without_its_scheme_is_a_usage_error():
    proc = run("campaign", "list", "--api", "127.0.0.1:18300")
    assert proc.returncode == 2
    assert "expected the API's URL with its scheme, e.g. http://127.0.0.1:18300" in one_error_line(proc)


def test_an_unknown_preset_is_a_usage_error_like_other_bad_input():
    proc = run("presets", "show", "papr")
    assert proc.returncode == 2 and "unknown preset 'papr'" in one_error_line(proc)


def test_version():
    proc = run("--version")
    assert proc.returncode == 0 and proc.stdout.strip() == f"ra2vipas {ra2vipas.__version__}"


def test_results_of_one_algorithm_and_campaigns_by_name(live, done_campaign):
    import json

    cid = done_campaign["id"]
    one = run("campaign", "results", cid, "--algorithm", "rapas", "--json", "--api", live.url)
    assert one.returncode == 0, one.stderr
    assert list(json.loads(one.stdout.strip().splitlines()[-1])["algorithms"]) == ["rapas"]
    bad = run("campaign", "results", cid, "--algorithm", "sweep", "--api", live.url)
    assert bad.returncode == 2 and "no results for 'sweep'" in one_error_line(bad)
    listed = run("campaign", "list", "--name", "fixture", "--json", "--api", live.url)
    items = json.loads(listed.stdout.strip().splitlines()[-1])["items"]
    assert items and {c["name"] for c in items} == {"fixture"}


@pytest.mark.parametrize("seeds, words", [
    ("3-1", "the range '3-1' runs backwards (write 1-3)"),
    ("x", "expected e.g. 1-5 or 1,3,7, got 'x'"),
    ("1-", "expected e.g. 1-5 or 1,3,7, got '1-'"),
    ("-2", "expected e.g. 1-5 or 1,3,7, got '-2'"),
])
def test_benchmark_seeds_that_name_no_seed_are_a_usage_error(seeds, words):
    # before: "3-1" was an empty range, so `bench learner` printed nothing and exited 0
    proc = run("bench", "learner", "--preset", "paper", "--seeds", seeds)
    assert proc.returncode == 2, proc
    assert one_error_line(proc) == f"error: --seeds: {words}"


def test_benchmark_seeds_parse_ranges_and_lists_once_each():
    from cli.bench import parse_seeds

    assert parse_seeds("1-3,7, 2") == [1, 2, 3, 7]
    assert parse_seeds("0") == [0]


def test_bench_walkers_refuses_what_it_cannot_score_in_one_line():
    proc = run("bench", "walkers", "--preset", "ward", "--tests", "2")
    assert proc.returncode == 2 and one_error_line(proc) == "error: bench walkers scores one tag; this scenario has n_tags > 1"
    proc = run("bench", "walkers", "--tests", "2", "--boxed", "30")
    assert proc.returncode == 2 and "boxed <= window" in one_error_line(proc)


def test_a_training_episode_too_short_for_its_radio_is_one_line_naming_n_train():
    """On BLE a 4 s training episode (n_train = 40 samples of 0.1 s) hears ~8 Rx(iso) advertisements, fewer than the
    learner needs: the command says so and which parameter to raise, instead of a traceback."""
    proc = run("simulate", "--preset", "ble", "--set", "n_train=40", "--tests", "1", "-a", "rapas")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        "error: n_train = 40 is too short a training episode for this world: the training stream carries 8 Rx(iso) "
        "advertisements in 40 samples; the POD learner needs at least 10; raise n_train")
