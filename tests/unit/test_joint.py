"""The search for K tags at once and one tag at a time (issue 21; services/controller/joint.py):
the compositions of the single-tag parts, driven by the simulated world without a network."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.controller import registry
from ra2vipas.services.controller.builtins import compose, joint_search
from ra2vipas.services.controller.composed import Composition
from ra2vipas.services.controller.contract import episode_context
from ra2vipas.services.controller.joint import JointSearch, SequentialSearch, TagDecision, tag_view
from ra2vipas.services.controller.node import tag_results
from ra2vipas.services.controller.policy import ControllerSettings, sensor_config_from_scenario, tuned_settings
from ra2vipas.services.orchestrator.metrics import summarize_tags
from ra2vipas.services.orchestrator.reduce import TagTally
from ra2vipas.services.orchestrator.simulate import run_campaign, run_test, train_pod
from ra2vipas.services.protocol.measurements import Advertisement, CameraFrame, RFSample, StepMeasurement
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.world import SimulatedPlatform

SMALL = {"n_targets": 8, "steps": 40}


@pytest.fixture(scope="module")
def two_tags():
    scenario = build_scenario("paper", {**SMALL, "n_tags": 2})
    return scenario, train_pod(scenario, 1).model


def _context(scenario, model, stop_confidence=0.0, test=0):
    return episode_context(sensor_config_from_scenario(scenario), model, scenario, 1, test, stop_confidence)


def test_a_tags_view_is_its_own_evidence_as_tag_0_and_nothing_when_it_was_not_heard():
    frames = (CameraFrame(box_bearings_rad=(0.1,)),)
    paired = StepMeasurement(step=3, pan_rad=0.2, rf=RFSample(iso_rssi_dbm=-40.0, dir_rssi_dbm=-41.0), frames=frames,
                             rf_tags=(RFSample(iso_rssi_dbm=-50.0, dir_rssi_dbm=-52.0, tag=2),))
    view = tag_view(paired, 2, step=1)
    assert (view.rf.iso_rssi_dbm, view.rf.tag, view.step, view.frames) == (-50.0, 0, 1, frames)
    assert tag_view(paired, 1).rf is None and not tag_view(paired, 1).advertisements()
    adverts = StepMeasurement(step=0, pan_rad=0.0, frames=frames, adverts=(
        Advertisement(receiver="iso", rssi_dbm=-60.0, tag=1), Advertisement(receiver="dir", rssi_dbm=-61.0, tag=0),
        Advertisement(receiver="dir", rssi_dbm=-62.0, tag=1)))
    assert [a.rssi_dbm for a in tag_view(adverts, 1).advertisements()] == [-60.0, -62.0]
    assert [a.rssi_dbm for a in tag_view(adverts, 0).advertisements()] == [-61.0]



def _state(model) -> tuple:
    """Everything a pydantic model object holds: its fields, which were set, its extra and private."""
    return (type(model), model.__dict__, model.__pydantic_fields_set__, model.__pydantic_extra__, model.__pydantic_private__)


def test_a_tags_view_is_the_object_model_construct_and_model_copy_build():
    frames = (CameraFrame(box_bearings_rad=(0.1,)),)
    paired = StepMeasurement(step=3, pan_rad=0.2, rf=RFSample(iso_rssi_dbm=-40.0, dir_rssi_dbm=-41.0), frames=frames,
                             rf_tags=(RFSample(iso_rssi_dbm=-50.0, dir_rssi_dbm=-52.0, tag=2),
                                      RFSample(iso_rssi_dbm=-51.0, dir_rssi_dbm=-53.0, tag=1)))
    adverts = StepMeasurement(step=5, pan_rad=0.1, frames=frames, adverts=(
        Advertisement(receiver="iso", rssi_dbm=-60.0, tag=1, channel=37, offset_s=0.01),
        Advertisement(receiver="dir", rssi_dbm=-61.0, tag=0), Advertisement(receiver="dir", rssi_dbm=-62.0, tag=1)))
    for m in (paired, adverts):
        for tag in range(3):
            for step in (None, 2):
                t = int(m.step) if step is None else step
                if m.rf is not None:  # what tag_view built with pydantic's own constructors
                    pair = next((p for p in m.pairs() if p.tag == tag), None)
                    rf = None if pair is None else (pair if pair.tag == 0 else pair.model_copy(update={"tag": 0}))
                    want = StepMeasurement.model_construct(step=t, pan_rad=m.pan_rad, rf=rf, frames=m.frames, adverts=(), rf_tags=())
                else:
                    ads = tuple(a if a.tag == 0 else a.model_copy(update={"tag": 0}) for a in m.adverts if a.tag == tag)
                    want = StepMeasurement.model_construct(step=t, pan_rad=m.pan_rad, rf=None, frames=m.frames, adverts=ads, rf_tags=())
                got = tag_view(m, tag, step)
                assert got == want and _state(got)[:1] + _state(got)[2:] == _state(want)[:1] + _state(want)[2:]
                assert {k: v for k, v in got.__dict__.items() if k not in ("rf", "adverts")} == \
                       {k: v for k, v in want.__dict__.items() if k not in ("rf", "adverts")}
                assert (got.rf is None) == (want.rf is None) and (got.rf is None or _state(got.rf) == _state(want.rf))
                assert [_state(a) for a in got.adverts] == [_state(a) for a in want.adverts]

def test_a_joint_search_for_one_tag_is_the_single_tag_search_step_for_step(two_tags):
    scenario = build_scenario("paper", SMALL)
    model = train_pod(scenario, 1).model
    sensors = sensor_config_from_scenario(scenario)
    cfg = tuned_settings("ra2vipas")
    for rule in ("entropy", "neediest"):
        single = Composition(sensors.initial_pan_rad, compose("ra2vipas", sensors, model, cfg))
        joint = JointSearch(sensors.initial_pan_rad, [compose("ra2vipas", sensors, model, cfg)], pan_rule=rule)
        a, b = SimulatedPlatform(scenario, 1, 0), SimulatedPlatform(scenario, 1, 0)
        pan_a, pan_b = single.first_pan(), joint.first_pan()
        for t in range(scenario.steps):
            da, db = single.step(a.sense(t, pan_a)), joint.step(b.sense(t, pan_b))
            assert (db.next_pan_rad, db.estimate_rad, db.confidence) == (da.next_pan_rad, da.estimate_rad, da.confidence)
            assert db.tags[0].estimate_rad == da.estimate_rad
            pan_a, pan_b = da.next_pan_rad, db.next_pan_rad


def test_the_sequential_baseline_with_one_tag_is_ra2vipas_to_the_digit():
    scenario = build_scenario("paper", SMALL)
    model = train_pod(scenario, 1).model
    for test in range(2):
        ours = run_test(scenario, 1, test, "ra2vipas", model)
        seq = run_test(scenario, 1, test, "ra2vipas-seq", model)
        assert (seq.pans, seq.estimates, seq.confidences, seq.hits) == (ours.pans, ours.estimates, ours.confidences, ours.hits)


def test_every_tag_shares_one_camera_belief(two_tags):
    scenario, model = two_tags
    search = joint_search("ra2vipas", _context(scenario, model), 2)
    assert search.parts[0].vision is search.parts[1].vision
    assert search.parts[0].rf is not search.parts[1].rf and search.parts[0].iso is not search.parts[1].iso
    with pytest.raises(ValueError, match="share one vision"):
        JointSearch(0.0, [compose("ra2vipas", _context(scenario, model).sensors, model,
                                  tuned_settings("ra2vipas")) for _ in range(2)])


def _drive(search, platform, steps):
    pan, pans, decisions = search.first_pan(), [], []
    for t in range(steps):
        d = search.step(platform.sense(t, pan))
        pans.append(d.next_pan_rad)
        decisions.append(d)
        pan = d.next_pan_rad
    return pans, decisions


def test_a_decided_tag_stops_steering_the_pan(two_tags):
    """Tag 1 decided from the start: the pans are those of a search for tag 0 alone."""
    scenario, model = two_tags
    scenario = scenario.model_copy(update={"one_tag_per_person": False})  # tag 0's answers then do not read tag 1's
    context = _context(scenario, model)
    alone = joint_search("ra2vipas", context, 1)
    both = joint_search("ra2vipas", context, 2)
    both.decided[1] = TagDecision(tag=1, estimate_rad=0.0, confidence=1.0, raw_confidence=1.0, decided_step=0)
    pans_alone, _ = _drive(alone, SimulatedPlatform(scenario, 1, 0), scenario.steps)
    pans_both, decisions = _drive(both, SimulatedPlatform(scenario, 1, 0), scenario.steps)
    assert pans_both == pans_alone
    assert all(d.lead_tag == 0 for d in decisions)
    undecided = joint_search("ra2vipas", context, 2)
    pans_undecided, decisions = _drive(undecided, SimulatedPlatform(scenario, 1, 0), scenario.steps)
    assert pans_undecided != pans_alone and {d.lead_tag for d in decisions} == {0, 1}  # undecided, tag 1 pulls too


def test_the_episode_ends_when_every_tag_is_decided_and_decided_answers_stand(two_tags):
    scenario, model = two_tags
    scenario = scenario.model_copy(update={"steps": 80})
    outcome = run_test(scenario, 1, 0, "ra2vipas", model, stop_confidence=0.9)
    decided = outcome.tags.decided_steps
    assert all(d is not None for d in decided), decided
    assert outcome.decided_step == max(decided) and len(outcome.estimates) == max(decided) + 1
    estimates = np.asarray(outcome.tags.estimates)
    for k, d in enumerate(decided):
        assert np.all(estimates[d:, k] == estimates[d, k])  # final once decided
    assert outcome.tags.hits.shape == (2, scenario.steps)


def test_one_tag_at_a_time_searches_tag_1_only_after_tag_0(two_tags):
    scenario, model = two_tags
    scenario = scenario.model_copy(update={"steps": 80})
    outcome = run_test(scenario, 1, 0, "ra2vipas-seq", model, stop_confidence=0.9)
    d0, d1 = outcome.tags.decided_steps
    assert d0 is not None and d1 is not None and d1 > d0
    conf = np.asarray(outcome.tags.confidences)
    assert np.all(conf[: d0 + 1, 1] == 0.0) and conf[d0 + 1, 1] > 0.0  # tag 1 untouched while tag 0 was searched


def test_without_a_decision_each_tag_gets_its_share_of_the_horizon(two_tags):
    scenario, model = two_tags
    search = SequentialSearch(0.0, lambda: compose("ra2vipas", sensor_config_from_scenario(scenario), model,
                                                   tuned_settings("ra2vipas")), n_tags=2, steps=scenario.steps)
    _, decisions = _drive(search, SimulatedPlatform(scenario, 1, 0), scenario.steps)
    assert [d.lead_tag for d in decisions] == [0] * 20 + [1] * 20


def test_the_tag_tally_is_summarize_tags_value_for_value():
    rng = np.random.default_rng(5)
    tests, k, steps = 9, 3, 12
    hits = rng.random((tests, k, steps)) < 0.7
    in_fov = rng.random((tests, k, steps)) < 0.8
    conf = np.round(rng.random((tests, k, steps)), 3)
    decided = [[int(rng.integers(0, steps)) if rng.random() < 0.7 else None for _ in range(k)] for _ in range(tests)]
    tally = TagTally(steps, 0.1, k)
    for i in range(tests):
        tally.add(hits[i], in_fov[i], conf[i], decided[i])
    assert tally.summary(decisions=True) == summarize_tags(hits, in_fov, 0.1, conf, decided)


def test_campaign_results_carry_every_tag_and_the_baseline_is_paired_on_the_same_worlds():
    scenario = build_scenario("paper", {**SMALL, "n_tags": 2, "steps": 30})
    results = run_campaign("paper", scenario, tests=2, seed=1, algorithms=["ra2vipas", "ra2vipas-seq"], stop_confidence=0.9)
    for name in ("ra2vipas", "ra2vipas-seq"):
        tags = results["algorithms"][name]["tags"]
        assert [len(b["dr"]) for b in tags["per_tag"]] == [30, 30]
        assert set(tags["all_decided"]) == {"median_s", "p90_s", "undecided"}
        assert results["algorithms"][name]["dr"] == tags["per_tag"][0]["dr"]  # the top-level block is tag 0's
    assert "policies" not in results  # a policy ra2vipas ships: no provenance block
    (pair,) = results["paired_all_found"]  # paired on "every tag found", beside tag 0's
    assert (pair["a"], pair["b"], pair["tests"]) == ("ra2vipas", "ra2vipas-seq", 2)
    finals = [results["algorithms"][n]["tags"]["all_found"]["dr_final"] for n in ("ra2vipas", "ra2vipas-seq")]
    assert pair["both"] + pair["only_a"] + pair["only_b"] + pair["neither"] == 2
    assert pair["dr_difference"] == pytest.approx(finals[0] - finals[1])
    assert "ra2vipas-seq" in registry.names() and registry.info("ra2vipas-seq").package in ("ra2vipas", "?")


def test_the_node_reports_each_tag_with_its_decision():
    steps = [(TagDecision(0, 0.1, 0.5, 0.5), TagDecision(1, 1.0, 0.2, 0.2)),
             (TagDecision(0, 0.2, 0.96, 0.9, decided_step=1), TagDecision(1, 1.1, 0.4, 0.4))]
    out = tag_results(steps)
    assert [(r.tag, r.estimates_rad, r.confidences, r.decided_step) for r in out] == [
        (0, (0.1, 0.2), (0.5, 0.96), 1), (1, (1.0, 1.1), (0.2, 0.4), None)]
    assert tag_results([]) == ()


def test_the_pan_rule_is_a_setting_checked_when_made():
    assert ControllerSettings(tag_pan_rule="neediest").tag_pan_rule == "neediest"
    with pytest.raises(ValueError, match="tag_pan_rule"):
        ControllerSettings(tag_pan_rule="loudest")
    assert math.isfinite(ControllerSettings().beta)


def test_bench_step_times_the_joint_search_on_a_preset_with_several_tags(monkeypatch):
    from ra2vipas.services.benchmarks.step import controller_step
    from ra2vipas.services.protocol import scenario as scenarios

    real = scenarios.build_scenario
    monkeypatch.setattr(scenarios, "build_scenario", lambda preset, overrides=None: real(preset, {"steps": 12, "n_train": 200}))
    report = controller_step("ra2vipas", 1, 1, "ward")
    assert report["n_tags"] == 3 and report["steps"] == 12 and report["median_ms"] > 0
    assert report["target_median_ms"] == 1.5  # issue 21's target for K = 3, not the single tag's 1 ms


def test_the_pan_weighs_each_tag_by_which_person_carries_it_an_undetected_one_by_its_bearing(two_tags, monkeypatch):
    """The joint search hands ``pan_weights`` each tag's posterior over the bearing of an
    undetected carrier (``Fusion.beliefs``' l_missed, normalised), so a tag that no track explains
    is not weighed as if it were decided; ``missed_bearings=False`` gives "which track" alone."""
    from ra2vipas.services.controller import multitag

    scenario, model = two_tags
    seen = []
    real = multitag.pan_weights

    def spy(posteriors, decided, rule="entropy", where_missed=None):
        seen.append(where_missed)
        return real(posteriors, decided, rule, where_missed)

    monkeypatch.setattr(multitag, "pan_weights", spy)
    for missed_bearings in (True, False):
        search = joint_search("ra2vipas", _context(scenario, model), 2)
        search.missed_bearings = missed_bearings
        seen.clear()
        _drive(search, SimulatedPlatform(scenario, 1, 0), 3)
        if missed_bearings:
            assert all(w.shape == (2, search.parts[0].fusion.circle.size) for w in seen)
            assert np.allclose([w.sum(axis=1) for w in seen], 1.0)
        else:
            assert seen == [None] * 3


def test_a_tag_whose_person_is_out_of_view_keeps_its_belief_and_is_named_again(two_tags):
    """Tag 1 found, then the camera is held pointing away from its carrier for 2 s: its answer
    stays on the same person (its RF belief and the shared tracks persist), and it is still that
    person when the search points where it likes again."""
    from ra2vipas.services.orchestrator.metrics import associate
    from ra2vipas.services.protocol.angles import wrap

    scenario, model = two_tags
    scenario = scenario.model_copy(update={"steps": 80})
    search = joint_search("ra2vipas", _context(scenario, model), 2)
    platform = SimulatedPlatform(scenario, 1, 0)
    bearings = platform.truth.bearings_rad
    pan, t = search.first_pan(), 0
    for t in range(40):
        d = search.step(platform.sense(t, pan))
        pan = d.next_pan_rad
    carrier = platform.truth.carriers[1]
    assert associate(np.array([d.tags[1].estimate_rad]), bearings)[0] == carrier  # found
    away = float(wrap(bearings[carrier] + math.pi))
    for t in range(40, 60):  # its carrier far outside the field of view
        d = search.step(platform.sense(t, away))
        assert abs(float(wrap(away - bearings[carrier]))) > 2 * scenario.fov_half_angle_rad
        assert associate(np.array([d.tags[1].estimate_rad]), bearings)[0] == carrier
    pan = d.next_pan_rad
    for t in range(60, 80):
        d = search.step(platform.sense(t, pan))
        pan = d.next_pan_rad
    assert associate(np.array([d.tags[1].estimate_rad]), bearings)[0] == carrier and d.tags[1].confidence > 0.5


def test_with_one_tag_per_person_two_tags_that_want_one_person_are_assigned_jointly(two_tags):
    """Both tags' likelihoods peak on the same track: on their own both name it; one person one
    tag, the pair with the larger joint likelihood wins (tag 0 keeps it, tag 1 takes its second)."""
    scenario, model = two_tags
    search = joint_search("ra2vipas", _context(scenario, model), 2)
    _drive(search, SimulatedPlatform(scenario, 1, 0), 12)  # the camera has seen everyone: tracks exist
    m = len(search.tracks)
    assert m >= 3
    grid = search.parts[0].fusion.circle.size
    l0 = np.full(m, -20.0)
    l0[0], l0[1] = 0.0, -8.0  # tag 0: track 0, by far
    l1 = np.full(m, -20.0)
    l1[0], l1[1] = 0.0, -0.5  # tag 1: track 0, track 1 nearly as likely
    missed = np.full(grid, -60.0)
    scored = [(l0, missed), (l1, missed)]
    where = search.parts[0].fusion.where
    search.one_tag_per_person = False
    own = search._answers(scored, search._which_track(scored))
    assert own[0][0] == own[1][0]  # on their own both name one person
    search.one_tag_per_person = True
    joint = search._answers(scored, search._which_track(scored))
    assert joint[0][0] == pytest.approx(float(where[0])) and joint[1][0] == pytest.approx(float(search.parts[1].fusion.where[1]))
    assert joint[1][1] > 0.5  # tag 1's confidence in track 1 under the constraint
