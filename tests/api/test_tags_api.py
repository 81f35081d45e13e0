"""A campaign with several tags (protocol 1.4, docs/tags.md) is refused, at creation, to a rig
whose sensors speak 1.3: a node written from the 1.3 page rejects every EpisodeStart whose
scenario carries ``n_tags``."""

from __future__ import annotations

from ra2vipas.services.sensors.node import simulated_descriptor
from tests.api.live import SMALL, LiveAPI


def test_a_campaign_with_several_tags_is_refused_to_a_1_3_rig(tmp_path):
    server = LiveAPI(tmp_path / "tags.db", rigs=("ble-13",), window=2,
                     sensors={"ble-13": {"descriptor": simulated_descriptor("ble-13", protocol="1.3")}}).start()
    try:
        server.settle()
        with server.client() as http:
            r = http.post("/campaigns", json={"preset": "ward", "overrides": SMALL, "tests": 2, "seed": 1, "rigs": ["ble-13"]})
            assert r.status_code == 422, r.text
            assert "rig ble-13 speaks protocol 1.3; scenario parameter 'n_tags' needs protocol 1.4" in r.json()["detail"], r.text
            assert http.get("/campaigns").json()["items"] == []  # nothing stored
            single = http.post("/campaigns", json={"preset": "dynamic", "overrides": SMALL, "tests": 1, "seed": 1,
                                                   "rigs": ["ble-13"], "algorithms": ["rapas"]})
            assert single.status_code == 201, single.text  # the same rig runs a one-tag campaign
    finally:
        server.stop()


def test_a_campaign_that_searches_for_more_tags_than_a_rig_hears_is_refused_or_takes_the_rigs_tags(tmp_path):
    """Protocol 1.5: two-1 says it hears 2 tags. A 3-tag campaign targeting it is a 422 naming the
    rig and both numbers (before: episodes whose third tag was never heard, rerun until they failed);
    with the rig's values it searches for 2 and runs there; untargeted, it runs on the rig that
    takes any number of tags."""
    server = LiveAPI(tmp_path / "tags15.db", rigs=("two-1", "any-1"), window=2,
                     sensors={"two-1": {"descriptor": simulated_descriptor("two-1", tags=2)}}).start()
    try:
        server.settle()
        body = {"preset": "ward", "overrides": SMALL, "tests": 1, "seed": 1, "algorithms": ["ra2vipas"]}
        with server.client() as http:
            rigs = {r["name"]: r for r in http.get("/rigs").json()["rigs"]}
            assert rigs["two-1"]["descriptor"]["tags"] == 2 and rigs["any-1"]["descriptor"].get("tags") is None
            r = http.post("/campaigns", json={**body, "rigs": ["two-1"]})
            assert r.status_code == 422, r.text
            assert r.json()["detail"] == ("scenario.n_tags: rig two-1 hears at most 2, the campaign says 3 "
                                          "(use_rig_values takes the rig's)"), r.text
            assert http.get("/campaigns").json()["items"] == []
            taken = http.post("/campaigns", json={**body, "rigs": ["two-1"], "use_rig_values": True})
            assert taken.status_code == 201, taken.text
            assert taken.json()["targeting"]["rig_values"] == {"n_tags": 2} and taken.json()["overrides"]["n_tags"] == 2
        assert server.wait(taken.json()["id"])["status"] == "done"
        with server.client() as http:  # both rigs idle: the scheduler gives two-1 none of its episodes
            untargeted = http.post("/campaigns", json={**body, "tests": 4})
            assert untargeted.status_code == 201, untargeted.text
        for created, rig, n_tags in ((taken, "two-1", 2), (untargeted, "any-1", 3)):
            done = server.wait(created.json()["id"])
            assert done["status"] == "done", done["error"]
            assert done["scenario"]["n_tags"] == n_tags
            with server.client() as http:
                tests = http.get(f"/campaigns/{done['id']}/tests", params={"limit": 10}).json()["items"]
                results = http.get(f"/campaigns/{done['id']}/results").json()
            assert tests and {t["rig"] for t in tests} == {rig}
            assert all(t["attempt"] == 1 for t in tests), tests  # no episode tried on a rig that hears fewer tags, then rerun
            assert len(results["algorithms"]["ra2vipas"]["tags"]["per_tag"]) == n_tags
    finally:
        server.stop()
