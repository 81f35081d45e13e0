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
