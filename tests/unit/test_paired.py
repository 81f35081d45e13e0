"""Per-test outcomes and the paired test between two algorithms (issue 23, point 8): every test
k meets the same world for each algorithm, so two algorithms are compared on their discordant
tests with McNemar's exact test; checked on hand-made cases with known p-values."""

from __future__ import annotations

import json

import numpy as np
import pytest

import ra2vipas
from ra2vipas.services.orchestrator.metrics import mcnemar_exact, paired_comparison
from ra2vipas.services.orchestrator.reduce import AlgorithmTally
from tests.api.live import SMALL
from tests.cli.conftest import ra2vipas as cli


@pytest.mark.parametrize("only_a, only_b, p", [
    (8, 2, 112 / 1024),   # 2 P(X <= 2), X ~ Bin(10, 1/2) = 2 (1 + 10 + 45) / 2^10
    (5, 0, 2 / 32),       # 2 P(X = 0), X ~ Bin(5, 1/2)
    (3, 3, 1.0),
    (0, 0, 1.0),          # no discordant test: no evidence either way
    (0, 12, 2 / 4096),
])
def test_the_exact_mcnemar_p_value(only_a, only_b, p):
    assert mcnemar_exact(only_a, only_b) == pytest.approx(p, rel=1e-12)


def test_the_p_value_is_scipys_binomtest_to_its_rounding_without_importing_scipy_stats():
    """The integer tail equals ``scipy.stats.binomtest(a, n, 1/2)`` to the 6 decimals results keep,
    over every split of 1..40 discordant tests, and larger ones, and scoring a campaign
    no longer imports scipy.stats (~1 s of CPU in every process that did)."""
    import subprocess
    import sys

    from scipy.stats import binomtest

    from ra2vipas.services.orchestrator.metrics import _rounded

    cases = [(a, n - a) for n in range(1, 41) for a in range(n + 1)]
    cases += [(a, n - a) for n in (99, 150) for a in range(0, n + 1, 7)]
    cases += [(a, 3000 - a) for a in range(0, 3001, 197)] + [(1450, 1550), (9000, 1000)]
    for a, b in cases:
        assert _rounded(mcnemar_exact(a, b)) == _rounded(float(binomtest(a, a + b, 0.5).pvalue)), (a, b)
    probe = ("import sys; from ra2vipas.services.orchestrator.metrics import paired_comparison; "
             "paired_comparison('a', [1, 0, 1] * 40, 'b', [0, 1, 0] * 40); print('scipy.stats' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.strip() == "False"


def test_a_hand_made_pair_of_algorithms():
    # tests 0-7: only a hits; 8-9: only b; 10-11: both; 12: neither; 13: b not recorded
    a = [1] * 8 + [0, 0] + [1, 1] + [0] + [1]
    b = [0] * 8 + [1, 1] + [1, 1] + [0] + [None]
    got = ra2vipas.paired_test(a, b, "ra2vipas", "rapas")
    assert got == {"a": "ra2vipas", "b": "rapas", "tests": 13, "both": 2, "only_a": 8, "only_b": 2, "neither": 1,
                   "dr_difference": round(6 / 13, 6), "p_value": round(112 / 1024, 6)}
    assert paired_comparison("x", [], "y", [])["p_value"] is None


def test_tallies_keep_each_tests_outcome_by_index_and_results_pair_only_shared_tests():
    steps = 3
    a, b = AlgorithmTally(steps, 0.1), AlgorithmTally(steps, 0.1)
    for k, hit in ((2, 1), (0, 1), (1, 1)):  # out of order, as a mesh records them
        a.add([0, 0, hit], [0, 0, hit], test_index=k)
    for k, hit in ((0, 0), (2, 0)):  # test 1 of b never recorded (a cancelled campaign)
        b.add([0, 0, hit], [0, 0, hit], test_index=k)
    assert a.outcomes(3) == [1, 1, 1] and b.outcomes(3) == [0, None, 0]
    got = paired_comparison("a", a.outcomes(3), "b", b.outcomes(3))
    assert got["tests"] == 2 and got["only_a"] == 2 and got["p_value"] == 0.5


def test_simulate_returns_per_test_outcomes_and_the_paired_tests():
    res = ra2vipas.simulate(overrides={**SMALL, "rf_noise_db": 6.0, "n_targets": 12}, tests=8, seed=3,
                            algorithms=["ra2vipas", "rapas", "ravipas"])
    assert set(res["outcomes"]) == {"ra2vipas", "rapas", "ravipas"}
    for name, hits in res["outcomes"].items():
        assert len(hits) == 8 and set(hits) <= {0, 1}
        assert np.mean(hits) == pytest.approx(res["algorithms"][name]["dr_final"])
    assert [(p["a"], p["b"]) for p in res["paired"]] == [("ra2vipas", "rapas"), ("ra2vipas", "ravipas"), ("rapas", "ravipas")]
    first = res["paired"][0]
    assert first == ra2vipas.paired_test(res["outcomes"]["ra2vipas"], res["outcomes"]["rapas"], "ra2vipas", "rapas")


def test_the_simulate_table_and_json_offer_the_paired_test():
    args = ["simulate", "--tests", "4", "--seed", "2", "-a", "ra2vipas,rapas", "--workers", "1", *[f"--set={k}={v}" for k, v in SMALL.items()]]
    table = cli(*args, env={"COLUMNS": "200"})
    assert table.returncode == 0, table.stderr
    assert "Paired comparison of the final answers" in table.stdout and "ra2vipas vs rapas" in table.stdout
    res = json.loads(cli(*args, "--json").stdout.splitlines()[-1])
    assert res["paired"][0]["a"] == "ra2vipas" and res["paired"][0]["tests"] == 4 and len(res["outcomes"]["rapas"]) == 4
