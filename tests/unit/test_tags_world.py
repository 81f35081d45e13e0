"""Many tags in the simulated world (issue 21, protocol 1.4; docs/tags.md): K tags, each with its
own address, carrier and advertising schedule (or RF pair per step), drawn from a stream of their
own so that tag 0 is exactly the single-tag world's Tx; truth says who carries which tag."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from jsonschema import Draft202012Validator

from ra2vipas.services.orchestrator.presets import preset_object
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol.messages import EpisodeTruth, Measurement, dump
from ra2vipas.services.protocol.scenario import ScenarioError, build_scenario
from ra2vipas.services.protocol.schemas import schema_documents
from ra2vipas.services.sensors import physics
from ra2vipas.services.sensors.world import GroundTruth, SimulatedPlatform, carrier_pool, episode_truth, tag_address

MAC = re.compile(r"^[0-9A-F]{2}(:[0-9A-F]{2}){5}$")
PANS = np.linspace(-3.0, 3.0, 40)


def _sense_all(platform: SimulatedPlatform, steps: int):
    return [platform.sense(t, float(PANS[t % PANS.size])) for t in range(steps)]


def test_the_ward_preset_is_the_dynamic_world_with_three_tags():
    ward, dynamic = build_scenario("ward"), build_scenario("dynamic")
    assert ward.n_tags == 3 and ward.one_tag_per_person
    assert ward.model_copy(update={"n_tags": 1}) == dynamic
    listed = preset_object("ward")["parameters"]
    assert listed["n_tags"]["value"] == 3 and listed["n_tags"]["allowed"] == "an integer in [1, 64]"
    assert listed["one_tag_per_person"]["allowed"] == "one of true|false"


def test_tags_are_validated_against_the_targets():
    with pytest.raises(ScenarioError, match="n_tags"):
        build_scenario("paper", {"n_targets": 2, "n_tags": 3})
    assert build_scenario("paper", {"n_targets": 2, "n_tags": 3, "one_tag_per_person": False}).n_tags == 3
    with pytest.raises(ScenarioError, match="n_tags"):
        build_scenario("paper", {"n_tags": 0})


@pytest.mark.parametrize("preset", ["paper", "dynamic", "ble", "ble-dynamic"])
def test_tag_0_is_the_single_tag_worlds_tx_draw_for_draw(preset):
    one, three = build_scenario(preset), build_scenario(preset, {"n_tags": 3})
    for test in range(3):
        a, b = SimulatedPlatform(one, 5, test), SimulatedPlatform(three, 5, test)
        assert b.truth.tx_index == a.truth.tx_index and b.truth.carriers[0] == a.truth.tx_index
        np.testing.assert_array_equal(a.truth.positions_m, b.truth.positions_m)
        for ma, mb in zip(_sense_all(a, one.steps), _sense_all(b, three.steps)):
            assert mb.frames == ma.frames and mb.rf == ma.rf
            mine = [(x.receiver, x.rssi_dbm, x.channel, x.offset_s) for x in mb.advertisements(tag=0)]
            assert mine == [(x.receiver, x.rssi_dbm, x.channel, x.offset_s) for x in ma.advertisements()]
            assert {x.address for x in mb.advertisements(tag=0) if mb.rf is None} <= {b.truth.tag_addresses[0]}
            assert all(x.tag == 0 and x.address is None for x in ma.advertisements(tag=None))


def test_each_tag_has_its_own_address_the_same_in_every_test():
    sc = build_scenario("ward")
    addresses = {SimulatedPlatform(sc, 11, test).truth.tag_addresses for test in range(4)}
    assert len(addresses) == 1
    (mine,) = addresses
    assert len(set(mine)) == 3 and all(MAC.match(a) and int(a[:2], 16) >= 0xC0 for a in mine)  # BLE random static
    assert mine == tuple(tag_address(11, k) for k in range(3)) and tag_address(12, 0) != mine[0]


def test_one_tag_per_person_puts_the_tags_on_distinct_targets():
    sc = build_scenario("paper", {"n_targets": 4, "n_tags": 4})
    for test in range(100):
        carriers = SimulatedPlatform(sc, 3, test).truth.carriers
        assert sorted(carriers) == [0, 1, 2, 3]


def test_without_one_tag_per_person_two_tags_may_share_a_person():
    sc = build_scenario("paper", {"n_targets": 5, "n_tags": 3, "one_tag_per_person": False})
    shared, expected = [], []
    for test in range(400):
        truth = SimulatedPlatform(sc, 3, test).truth
        pool = set(carrier_pool(sc, truth.ranges_m, truth.tx_index, 1).tolist()) | {truth.tx_index}
        assert set(truth.carriers) <= pool
        shared.append(len(set(truth.carriers)) < 3)
        m = len(pool)  # each of tags 1, 2 uniform over the m candidates: P(all three distinct) = (m-1)/m * (m-2)/m
        expected.append(1.0 - (m - 1) / m * (m - 2) / m)
    assert abs(np.mean(shared) - np.mean(expected)) < 0.08 and np.mean(shared) > 0.3


def test_each_tag_is_carried_by_someone_the_txs_range_rule_allows():
    """``reference``: tags 1..K-1 go to people within ``tx_max_range_m``, as the Tx is, however
    far the placement pushed the others; ``uniform``: to anyone (docs/tags.md, "Carriers")."""
    sc = build_scenario("paper", {"n_tags": 3})
    near = []
    for test in range(100):
        truth = SimulatedPlatform(sc, 2, test).truth
        ranges = truth.ranges_m
        if np.sum(np.delete(ranges, truth.tx_index) < sc.tx_max_range_m) >= 2:
            assert all(ranges[c] < sc.tx_max_range_m for c in truth.carriers)
        near.append(np.mean(np.delete(ranges, truth.tx_index) < sc.tx_max_range_m))
    assert np.mean(near) < 0.5  # the others mostly lie beyond: a uniform choice among them would mostly be far
    uniform = build_scenario("paper-uniform", {"n_tags": 3})
    truths = [SimulatedPlatform(uniform, 2, t).truth for t in range(100)]
    far = [truth.ranges_m[c] >= 4.0 for truth in truths for c in truth.carriers[1:]]
    assert 0.3 < np.mean(far) < 0.7  # P(range > 4 m) uniform in the 10 m square: 1 - 16 pi / 100 = 0.50


def test_too_few_people_within_range_completes_the_carriers_with_the_nearest():
    layout = GroundTruth(positions_m=np.array([[2.0, 0.0], [0.0, 3.0], [-6.0, 0.0], [4.5, 0.0], [0.0, -5.0]]), tx_index=0)
    sc = build_scenario("paper", {"n_targets": 5, "n_tags": 3})
    for test in range(10):
        carriers = SimulatedPlatform(sc, 1, test, layout=layout).truth.carriers
        assert carriers[0] == 0 and sorted(carriers[1:]) == [1, 3]  # target 1 is within 4 m; 3 (4.5 m) is the nearest other


def test_the_paper_radio_gives_one_pair_per_tag_per_step_at_its_carriers_level():
    sc = build_scenario("paper", {"n_tags": 3})
    platform = SimulatedPlatform(sc, 2, 0)
    ms = _sense_all(platform, sc.steps)
    assert all(m.tags() == (0, 1, 2) and [p.tag for p in m.rf_tags] == [1, 2] for m in ms)
    ranges = platform.truth.ranges_m[list(platform.truth.carriers)]
    for k, d in enumerate(ranges):
        iso = np.array([m.rssi_dbm("iso", tag=k)[0] for m in ms])
        assert abs(iso.mean() - float(physics.path_loss_dbm(sc, d))) < 1.5  # sigma 3 dB over 120 steps: sd 0.27 dB
    noise = [np.array([m.rssi_dbm("iso", tag=k)[0] for m in ms]) for k in range(3)]
    assert abs(np.corrcoef(noise[1], noise[2])[0, 1]) < 0.3  # each tag its own noise


def _ble_quiet(k: int = 3):
    return build_scenario("ble", {"n_tags": k, "shadowing_db": 0.0, "channel_offset_db": 0.0, "steps": 300})


def test_ble_tags_advertise_on_their_own_schedules():
    sc = _ble_quiet()
    platform = SimulatedPlatform(sc, 4, 1)
    ms = _sense_all(platform, sc.steps)
    schedules = [platform._packets] + [t.schedule for t in platform._tags]
    times = [s.times_s for s in schedules]
    assert all(not np.array_equal(times[0][:20], t[:20]) for t in times[1:])  # its own events and advDelay
    assert all(np.array_equal(schedules[0].scan_phases_s, s.scan_phases_s) for s in schedules)  # the rig's scan, shared
    counts = [sum(len(m.advertisements("iso", tag=k)) for m in ms) for k in range(3)]
    expected = sc.steps * sc.rf_period_s / (sc.adv_interval_s + sc.adv_delay_max_s / 2) * (1 - sc.packet_loss_iso)
    assert all(0.7 * expected < c < 1.2 * expected for c in counts), (counts, expected)
    truth = platform.truth
    for k in range(3):
        ads = [a for m in ms for a in m.advertisements(tag=k)]
        assert {a.address for a in ads} == {truth.tag_addresses[k]} and {a.tag for a in ads} == {k}
        level = float(physics.path_loss_dbm(sc, truth.ranges_m[truth.carriers[k]]))
        assert abs(np.mean([a.rssi_dbm for a in ads if a.receiver == "iso"]) - level) < 1.5
    for m in ms:  # one list, in arrival order
        offsets = [a.offset_s for a in m.adverts]
        assert offsets == sorted(offsets)


def test_recorded_tags_share_the_rigs_receivers():
    sc = build_scenario("ble-recorded", {"n_tags": 2, "steps": 100})
    platform = SimulatedPlatform(sc, 1, 0)
    ms = _sense_all(platform, sc.steps)
    other = platform._tags[0].schedule
    assert np.array_equal(other.rx, platform._packets.rx) and other.turn_rad == platform._packets.turn_rad
    assert all(sum(len(m.advertisements(tag=k)) for m in ms) > 0 for k in range(2))


def test_truth_names_each_tags_carrier_and_address_and_a_single_tag_truth_is_unchanged():
    current = Draft202012Validator(schema_documents()["EpisodeTruth.json"])
    sc = build_scenario("ward")
    platform = SimulatedPlatform(sc, 6, 2)
    wire = json.loads(dump(episode_truth(platform.truth, "e")))
    assert wire["tx_indices"] == list(platform.truth.carriers) and wire["tx_indices"][0] == wire["tx_index"]
    assert wire["tag_addresses"] == list(platform.truth.tag_addresses)
    assert list(current.iter_errors(wire)) == []
    assert EpisodeTruth.model_validate(wire).carriers == platform.truth.carriers
    single = json.loads(dump(episode_truth(SimulatedPlatform(build_scenario("dynamic"), 6, 2).truth, "e")))
    assert "tx_indices" not in single and "tag_addresses" not in single


def test_a_scripted_layout_may_name_the_carriers():
    layout = GroundTruth(positions_m=np.array([[2.0, 0.0], [0.0, 3.0], [-4.0, 0.0]]), tx_index=1, tx_indices=(1, 1, 2))
    sc = build_scenario("paper", {"n_targets": 3, "n_tags": 3, "one_tag_per_person": False})
    assert SimulatedPlatform(sc, 1, 0, layout=layout).truth.carriers == (1, 1, 2)
    with pytest.raises(ScenarioError, match="carriers"):
        SimulatedPlatform(build_scenario("paper", {"n_targets": 3, "n_tags": 2}), 1, 0, layout=layout)


def test_measurements_of_several_tags_round_trip_the_wire():
    for preset in ("ward", "ble-dynamic"):
        sc = build_scenario(preset, {"n_tags": 3, "steps": 30})
        for m in _sense_all(SimulatedPlatform(sc, 8, 0), sc.steps):
            wire = Measurement.model_construct(episode_id="e", **{k: getattr(m, k) for k in type(m).model_fields})
            back = Measurement.model_validate_json(dump(wire))
            assert back.tags() == m.tags() and back.rssi_dbm("dir", tag=None) == m.rssi_dbm("dir", tag=None)


def test_simulate_searches_every_tag_of_a_ward_and_reports_each():
    results = run_campaign("ward", build_scenario("ward", {"steps": 20, "n_targets": 8}), tests=2, seed=1, algorithms=["ra2vipas"])
    tags = results["algorithms"]["ra2vipas"]["tags"]
    assert len(tags["per_tag"]) == 3 and len(tags["all_found"]["dr"]) == 20
