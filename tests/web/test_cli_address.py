"""``campaign start --embedded`` says where its campaign's dashboard page is while it runs, on
the port asked for (``--port``), and, since its stack stops with the command, how to open the
page afterwards (issue 23, point 5; ``ra2vipas up``: in test_browser.py, which has a stack)."""

from __future__ import annotations

import re
import subprocess
import sys

from ra2vipas.cli.stack import free_port
from tests.integration.conftest import ROOT


def test_an_embedded_campaign_prints_its_dashboard_page_and_how_to_open_it_afterwards(tmp_path):
    port = free_port()
    db = tmp_path / "e.db"
    out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "campaign", "start", "--embedded", "--rig-count", "1", "--tests", "1",
                          "-a", "rapas", "--set", "steps=10", "--set", "n_train=100", "--set", "n_targets=5", "--db", str(db),
                          "--port", str(port), "--json"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    match = re.search(rf"^dashboard \(while this command runs\): (http://127\.0\.0\.1:{port}/ui/campaigns/([0-9a-f]{{12}}))$", out.stderr,
                      re.MULTILINE)
    assert match, out.stderr
    cid = match.group(2)
    assert f"campaign {cid}" in out.stderr.splitlines()
    said = " ".join(out.stderr.split())
    assert (f"to open campaign {cid} in the dashboard afterwards, run `ra2vipas up --db {db}` and browse "
            f"http://127.0.0.1:8080/ui/campaigns/{cid}") in said


def test_port_without_embedded_is_a_usage_error():
    out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "campaign", "start", "--port", "9999", "--api", "http://127.0.0.1:9"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 2 and out.stderr.startswith("error: --port sets the API port of the --embedded stack")
