"""``campaign start --embedded`` says where its campaign's dashboard page is (``ra2vipas up``: in
test_browser.py, which has a stack)."""

from __future__ import annotations

import re
import subprocess
import sys

from tests.integration.conftest import ROOT


def test_an_embedded_campaign_prints_its_dashboard_page(tmp_path):
    out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "campaign", "start", "--embedded", "--rigs", "1", "--tests", "1",
                          "-a", "rapas", "--set", "steps=10", "--set", "n_train=100", "--set", "n_targets=5", "--db", str(tmp_path / "e.db"),
                          "--json"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    match = re.search(r"^dashboard: (http://127\.0\.0\.1:\d+/ui/campaigns/([0-9a-f]{12}))$", out.stderr, re.MULTILINE)
    assert match, out.stderr
    assert match.group(2) in out.stderr.split("campaign ", 1)[1]
