"""Surveys: the format, the survey rig, and the benchmark it makes. A survey recorded from our
simulator (tests/rigs/data/sim-survey.json) and served back as a rig gives a campaign, scored
from the survey's layout, whose DR is within the Wilson interval of the live simulator on the
same static scene."""

from __future__ import annotations

import json
import math
import os
import time

import numpy as np
import pytest

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.controller.policy import Controller, sensor_config_from_scenario
from ra2vipas.services.orchestrator.metrics import score_episode, wilson_interval
from ra2vipas.services.orchestrator.reproducibility import canonical, differences
from ra2vipas.services.orchestrator.simulate import train_pod
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.rigs.conformance import check_rig
from ra2vipas.services.rigs.survey import Survey, SurveyNode, load
from ra2vipas.services.transport.bus import MemoryBus
from tests.api.live import LiveAPI
from tests.conftest import make_platform, polar_positions
from tests.rigs.make_survey import SCENE, SEED, make

DATA = __import__("pathlib").Path(__file__).resolve().parent / "data" / "sim-survey.json"
TESTS = 30
STEPS = 60
ALGORITHMS = ("ra2vipas", "rapas", "ravipas")  # ravipas (camera only) is the one far from 1.0 on this scene


@pytest.fixture(scope="module")
def survey() -> Survey:
    return load(DATA)


def test_the_checked_in_survey_is_what_the_recorder_makes(tmp_path, survey):
    """Made again now, the survey's draws are the checked-in ones; floats rounded as every draw
    recorded on another machine is compared (services/orchestrator/reproducibility.py)."""
    make(tmp_path / "again.json")
    again, recorded = json.loads((tmp_path / "again.json").read_text()), json.loads(DATA.read_text())
    assert canonical(again) == canonical(recorded), differences(canonical(again), canonical(recorded))
    assert len(survey.passes) == 3 and len(survey.pans_rad) == 180 and len(survey.training) == 300
    assert survey.rig.kind == "hardware" and survey.rig.rx_dir.model == "paper"
    assert len(survey.layout.bearings_rad) == SCENE["n_targets"]


def test_the_survey_rig_passes_the_conformance_kit_where_it_applies(survey):
    bus = MemoryBus()
    node = SurveyNode(bus, "survey-1", survey)
    try:
        results = {r.rule: r.status for r in check_rig(bus, "survey-1", timeout=3.0)}
    finally:
        node.close()
        bus.close()
    realtime = {k: v for k, v in results.items() if k.startswith("realtime")}
    assert set(realtime.values()) == {"skip"}  # a survey runs fast episodes only (its descriptor says so)
    # pans are answered from the nearest surveyed pan (2 degrees apart): pan-wrapped tolerates 0.05 rad
    assert {k: v for k, v in results.items() if not k.startswith("realtime")} == {**dict.fromkeys(
        [k for k in results if not k.startswith("realtime")], "pass"), "tags": "skip"}, results  # it says no number of tags


def test_passes_are_drawn_without_replacement_and_the_nearest_pan_serves(survey):
    bus = MemoryBus()
    node = SurveyNode(bus, "survey-1", survey)
    try:
        assert node.nearest(math.radians(2.9)) == node.nearest(math.radians(1.2)) == 91  # -180 + 2 * 91 = 2 degrees
        assert node.nearest(math.radians(179.5)) == 0  # the circle: 179.5 degrees is nearest to -180
        ep = {"rng": np.random.default_rng(0), "orders": {}}
        drawn = [node._draw(ep, 5) for _ in range(3)]
        assert sorted(id(d) for d in drawn) == sorted(id(p[5]) for p in survey.passes)  # each pass once
    finally:
        node.close()
        bus.close()


def _live_simulator_dr(survey: Survey, algorithm: str) -> tuple[int, int]:
    """Final hits of the live simulator on the survey's static scene (the same layout, fresh
    noise per test), with the POD model of the same training episode."""
    sc = build_scenario("paper", {**SCENE, "steps": STEPS})
    lay = survey.layout
    positions = polar_positions(lay.ranges_m, np.degrees(lay.bearings_rad))
    pod = train_pod(build_scenario("paper", {**SCENE, "n_train": 300}), SEED).model
    hits = 0
    for k in range(TESTS):
        platform = make_platform(sc, positions, lay.tx_index, seed=SEED, test_index=k)
        ctl = Controller(algorithm, sensor_config_from_scenario(sc), pod)
        pan, estimates = ctl.first_pan(), []
        for t in range(STEPS):
            d = ctl.step(platform.sense(t, pan))
            pan = d.next_pan_rad
            estimates.append(d.estimate_rad)
        h, _, _ = score_episode(np.array(estimates), platform.truth.step_bearings_rad(), lay.tx_index, sc.fov_half_angle_rad, STEPS)
        hits += bool(h[-1])
    return hits, TESTS


def test_a_campaign_on_the_survey_rig_matches_the_live_simulator(tmp_path, survey):
    server = LiveAPI(tmp_path / "survey.db", rigs=())
    server.nodes += [SurveyNode(server.bus, "survey-1", survey), ControllerNode(server.bus, "survey-1")]
    server.start()
    try:
        server.settle()
        with server.client() as http:
            rigs = {r["name"]: r for r in http.get("/rigs").json()["rigs"]}
            assert rigs["survey-1"]["descriptor"]["kind"] == "survey"
            body = {"preset": "paper", "overrides": {**SCENE, "steps": STEPS, "n_train": 300}, "tests": TESTS, "seed": SEED,
                    "algorithms": list(ALGORITHMS), "rig_kind": "survey"}
            refused = http.post("/campaigns", json={**body, "mode": "realtime"})
            assert refused.status_code == 422 and refused.json()["errors"][0]["loc"] == ["body", "mode"]
            r = http.post("/campaigns", json={**body, "use_rig_values": True})
            assert r.status_code == 201, r.text
        done = server.wait(r.json()["id"], timeout=600)
        assert done["status"] == "done", done["error"]
        with server.client() as http:
            results = http.get(f"/campaigns/{done['id']}/results").json()
        assert "warnings" not in results and "assumptions" not in results
        assert results["pod"]["r2"] is None and "no rig served the training truth" in results["pod"]["note"]
    finally:
        server.stop()
    for algorithm in ALGORITHMS:
        hits, n = _live_simulator_dr(survey, algorithm)
        lo, hi = wilson_interval(hits, n)
        survey_dr = results["algorithms"][algorithm]["dr_final"]
        print(f"{algorithm}: survey rig final DR {survey_dr:.3f} {results['algorithms'][algorithm]['ci95']}, live simulator {hits}/{n} = {hits / n:.3f} ({lo:.3f}-{hi:.3f})")
        assert lo <= survey_dr <= hi, (algorithm, survey_dr, hits / n, (lo, hi))
        s_lo, s_hi = results["algorithms"][algorithm]["ci95"]
        assert s_lo <= hits / n <= s_hi, (algorithm, hits / n, (s_lo, s_hi))


def test_survey_record_with_an_operators_layout_then_serve_it_as_a_rig(local_stack, tmp_path):
    """The commands as an operator runs them on a local stack: `survey record` drives the stack's
    rig through a small sweep with the scene's layout from a file (`--layout`, as for a real
    scene), `survey serve` serves the file as rig survey-1 (with `ra2vipas controller` for it),
    and a campaign on survey-1 is scored from that layout. A layout that is not one is a usage
    error."""
    import signal

    import httpx

    from tests.integration.conftest import wait_for_line
    from tests.rigs.conftest import cli

    api, env, registry = local_stack["api"], local_stack["env"], local_stack["registry"]
    bad = tmp_path / "bad-layout.json"
    bad.write_text(json.dumps({"bearings_rad": [0.5], "tx_index": 3}))
    refused = cli("survey", "record", "--rig", "rig-1", "-o", str(tmp_path / "never.json"), "--layout", str(bad), env=env)
    assert refused.returncode == 2 and refused.stderr.startswith(f"error: cannot read the layout {bad}"), refused.stderr
    layout = {"bearings_rad": [-2.0, -0.4, 1.1, 2.6], "ranges_m": [3.0, 2.0, 4.5, 1.5], "tx_index": 2}
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    file = tmp_path / "scene.json"
    recorded = cli("survey", "record", "--rig", "rig-1", "-o", str(file), "--pans", "12", "--passes", "2", "--n-train", "40",
                   "--layout", str(tmp_path / "layout.json"), "--set", "n_targets=4", env=env)
    assert recorded.returncode == 0, recorded.stderr
    assert recorded.stdout.strip() == f"wrote a survey of 4 targets, 2 passes of 12 pans, 40 training samples to {file}"
    survey = load(file)
    assert survey.layout.model_dump() == {**layout, "bearings_rad": tuple(layout["bearings_rad"]), "ranges_m": tuple(layout["ranges_m"]),
                                          "tx_indices": (), "tag_addresses": ()}  # one tag: no carriers of others
    assert b"tx_indices" not in file.read_bytes() and b"rf_tags" not in file.read_bytes()  # a single-tag survey is written as before
    assert len(survey.pans_rad) == 12 and len(survey.passes) == 2 and survey.rig.kind == "hardware"

    served = registry.start("survey", "serve", str(file), "--rig", "survey-1", env=env)
    controller = registry.start("controller", "--rig", "survey-1", env=env)
    wait_for_line(served, "survey[survey-1] up", 60)
    with httpx.Client(base_url=api, timeout=30) as http:
        def survey_rig():
            rig = {r["name"]: r for r in http.get("/rigs").json()["rigs"]}.get("survey-1")
            return rig if rig and rig["live"] and rig["descriptor"] else None

        deadline = time.monotonic() + 60
        while (rig := survey_rig()) is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert rig is not None, http.get("/rigs").json()
        assert rig["descriptor"]["kind"] == "survey" and rig["descriptor"]["modes"] == ["fast"]
        r = http.post("/campaigns", json={"overrides": {"steps": 12, "n_train": 40, "n_targets": 4}, "tests": 2, "seed": 1,
                                          "algorithms": ["rapas"], "rigs": ["survey-1"], "use_rig_values": True})
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        deadline = time.monotonic() + 120
        while (c := http.get(f"/campaigns/{cid}").json())["status"] not in ("done", "failed", "cancelled") and time.monotonic() < deadline:
            time.sleep(0.2)
        assert c["status"] == "done", c
        for k in range(2):
            trace = http.get(f"/campaigns/{cid}/tests/{k}/rapas").json()
            assert trace["rig"] == "survey-1" and trace["tx_index"] == layout["tx_index"]
            assert [t["bearing_rad"] for t in trace["targets"]] == pytest.approx(layout["bearings_rad"])
            assert [t["range_m"] for t in trace["targets"]] == pytest.approx(layout["ranges_m"])
    for proc in (served, controller):
        os.killpg(proc.pid, signal.SIGTERM)
        assert proc.wait(30) == 0
