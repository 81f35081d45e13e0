"""The eq. 6 trap is said where a user looks (issue 23, point 7): under the paper's antenna model
Rx(dir)'s dBm reading is scaled by ϱ, so it dips when aligned; ``presets show``, the API's
preset, the README and the policy's docs say so, with numbers the physics gives."""

from __future__ import annotations

import numpy as np

import ra2vipas.services.controller.policy as policy
from ra2vipas.services.orchestrator.presets import ANTENNA_NOTE, preset_object
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.physics import directional_rssi_dbm
from tests.cli.conftest import ROOT, ra2vipas


def test_the_numbers_quoted_are_the_physics():
    for model, quoted in (("paper", (-36.0, -24.9, 0.0)), ("db-gain", (-36.0, -37.6, -56.0))):
        sc = build_scenario("paper", {"antenna_model": model})
        got = [round(float(directional_rssi_dbm(sc, 2.0, np.radians(a))), 1) + 0.0 for a in (0, 45, 90)]
        assert got == list(quoted), (model, got)
    paper = build_scenario("paper")
    assert directional_rssi_dbm(paper, 2.0, 0.0) < directional_rssi_dbm(paper, 2.0, np.radians(90))  # the dip


def test_presets_show_the_api_the_readme_and_the_policy_docs_say_it():
    shown = " ".join(ra2vipas("presets", "show", "paper", env={"COLUMNS": "200"}).stdout.split())
    assert "Rx(dir) dips where it is aligned under antenna_model=paper" in shown
    assert "LOWEST when it points at the Tx" in preset_object("paper")["parameters"]["antenna_model"]["description"]
    assert "LOWEST when it points at the Tx" in ANTENNA_NOTE
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "under `paper` Rx(dir) reads *lowest* when it points at the Tx" in readme
    assert "*dips* where the antenna points at the Tx" in " ".join(policy.__doc__.split())
