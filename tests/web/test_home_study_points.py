"""The Campaigns home page does not drown in a study's points (issue 23, point 8): they are
hidden by default with a line saying how many and where they are (the study's page, in grid
order), and a filter shows them."""

from __future__ import annotations

import re

from tests.api.live import SMALL, LiveAPI


def test_study_points_are_hidden_from_home_unless_asked_for(tmp_path):
    server = LiveAPI(tmp_path / "h.db", rigs=(), learner=False).start()  # no rig: everything stays queued
    try:
        with server.client() as http:
            r = http.post("/campaigns", json={"preset": "paper", "overrides": SMALL, "tests": 1, "algorithms": ["rapas"], "name": "alone"})
            assert r.status_code == 201, r.text
            alone = r.json()["id"]
            r = http.post("/studies", json={"preset": "paper", "overrides": {k: v for k, v in SMALL.items() if k != "n_targets"},
                                            "vary": {"n_targets": [4, 6, 8]}, "tests": 1, "algorithms": ["rapas"]})
            assert r.status_code == 201, r.text
            points = [p["campaign_id"] for p in http.get(f"/studies/{r.json()['id']}").json()["points"]]
            assert len(points) == 3

            def listed(text: str) -> list[str]:
                return re.findall(r'<tr id="campaign-([0-9a-f]+)"', text)

            home = http.get("/").text
            assert listed(home) == [alone]
            assert "3 campaigns are points of studies, not listed here" in " ".join(home.split())
            shown = http.get("/", params={"points": "show"}).text
            assert set(listed(shown)) == {alone, *points} and "points of studies, not listed" not in shown
            assert 'name="points" value="show" checked' in shown
            assert "&amp;points=show" in shown  # the live table keeps the filter
            assert len(http.get("/campaigns").json()["items"]) == 4  # the API lists every campaign, as before
    finally:
        server.stop()
