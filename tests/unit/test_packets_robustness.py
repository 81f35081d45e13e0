"""The robustness bench on the real-radio worlds (issue 20): ble, ble-dynamic, ble-recorded, and
the oracle on BLE advertisements."""

from __future__ import annotations

import pytest

from ra2vipas.services.orchestrator import robustness
from ra2vipas.services.orchestrator.oracle import oracle_choice
from ra2vipas.services.protocol.scenario import build_scenario


def test_the_bench_has_the_real_radio_worlds():
    for name in ("ble", "ble-dynamic", "ble-recorded"):
        assert robustness.SCENARIOS[name] == (name, {})


def test_the_bench_runs_them_with_an_oracle_where_a_model_exists():
    report = robustness.run(tests=3, seed=2, scenarios=["ble", "ble-recorded"], workers=1)
    ble, recorded = report["scenarios"]["ble"], report["scenarios"]["ble-recorded"]
    assert set(ble["dr"]) == {*robustness.ALGORITHMS, "oracle"} and ble["ra2vipas_over_oracle"] is not None
    assert set(recorded["dr"]) == set(robustness.ALGORITHMS) and recorded["ra2vipas_over_oracle"] is None
    assert all(0.0 <= v <= 1.0 for s in (ble, recorded) for v in s["dr"].values())


def test_the_packet_oracle_finds_the_tx_from_a_sweeps_packets():
    """The Bayes-MAP over the packets' joint Gaussian with the true model: on the ble world it
    names the Tx in nearly every test (a sweep's ~50 packets, channel offsets and rounding
    modelled); with the radio's spread made huge it is near chance."""
    scenario = build_scenario("ble")
    right = sum(c == tx for c, tx in (oracle_choice(scenario, 1, k) for k in range(10)))
    assert right >= 9
    noisy = build_scenario("ble", {"rf_noise_db": 30.0, "channel_offset_db": 30.0})
    assert sum(c == tx for c, tx in (oracle_choice(noisy, 1, k) for k in range(10))) <= 5


def test_the_oracle_refuses_a_recorded_channel():
    with pytest.raises(ValueError, match="recorded"):
        oracle_choice(build_scenario("ble-recorded"), 1, 0)
