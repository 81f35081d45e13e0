"""When the Tx walks, the episode figure (``campaign plot --kind episode``, the dashboard's
figure link: one renderer) draws its bearing over time, and ``campaign trace`` says where it
went, as the interactive episode page does (issue 23, point 2)."""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.orchestrator import plots
from ra2vipas.services.protocol.scenario import build_scenario
from tests.api.live import SMALL
from tests.cli.conftest import ra2vipas

STEPS = 30


def walking_episode() -> dict:
    """Target 1, the Tx, walks from 51.6° to -5.5°; target 2 walks too; target 0 stands."""
    tx_path = np.linspace(math.radians(51.6), math.radians(-5.5), STEPS)
    other = np.linspace(-2.0, -2.5, STEPS)
    return {"test_index": 0, "algorithm": "ra2vipas", "tx_index": 1, "bearings": [0.5, float(tx_path[0]), -2.0],
            "ranges": [3.0, 1.29, 5.5], "pans": np.zeros(STEPS).tolist(), "estimates": tx_path.tolist(),
            "hits": [True] * STEPS,
            "trajectories": [{"index": 1, "bearings_rad": tx_path.tolist(), "ranges_m": np.linspace(1.29, 2.0, STEPS).tolist()},
                             {"index": 2, "bearings_rad": other.tolist(), "ranges_m": [5.5] * STEPS}]}


def test_the_episode_figure_draws_a_walking_tx_where_it_was_at_each_step():
    ep = walking_episode()
    fig = plots.episode_figure(build_scenario("paper", {"steps": STEPS}), ep)
    ax = fig.axes[1]
    tx_lines = [line for line in ax.get_lines() if line.get_label().startswith("Tx bearing")]
    assert len(tx_lines) == 1
    y = np.asarray(tx_lines[0].get_ydata(), dtype=float)
    assert np.allclose(y[~np.isnan(y)], np.degrees(ep["trajectories"][0]["bearings_rad"]))
    flat = [line for line in ax.get_lines() if np.allclose(np.asarray(line.get_ydata(), float), 51.6)]
    assert not flat, "no flat line at the Tx's starting bearing"
    polar = fig.axes[0]
    star = next(c for c in polar.collections if c.get_label() == "Tx")
    assert np.allclose(star.get_offsets()[0], [math.radians(-5.5), 2.0])  # drawn where it ended


def test_campaign_trace_and_plot_follow_a_walking_tx(live, tmp_path):
    body = {"preset": "paper", "overrides": {**SMALL, "walking_fraction": 1.0, "walk_speed_mps": 3.0}, "algorithms": ["rapas"],
            "tests": 1, "seed": 2}
    with live.client() as http:
        r = http.post("/campaigns", json=body)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    assert live.wait(cid)["status"] == "done"
    with live.client() as http:
        trace = http.get(f"/campaigns/{cid}/tests/0/rapas").json()
    tx = trace["targets"][trace["tx_index"]]
    assert tx["bearings_rad"], "the Tx walks"
    end = math.degrees(tx["bearings_rad"][len(trace["steps"]) - 1])
    text = ra2vipas("campaign", "trace", cid, "--api", live.url, "--test", "0", "--algorithm", "rapas", env={"COLUMNS": "200"})
    assert text.returncode == 0, text.stderr
    assert "walking from" in text.stdout and f"to {end:.1f}°" in text.stdout and "Tx bearing" in text.stdout
    out = tmp_path / "ep.svg"
    proc = ra2vipas("campaign", "plot", cid, "--api", live.url, "--kind", "episode", "--test", "0", "--algorithm", "rapas",
                    "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "Tx bearing (walking)" in out.read_text()
