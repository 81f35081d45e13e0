"""``ra2vipas bench dashboard`` runs end to end (small campaign) and reports every page's
server time, size and, in the system's Chromium, first paint and page weight. The numbers are
reported, not asserted (speed targets are checked by running the benchmark, not by tests)."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.integration.conftest import ROOT
from tests.web.conftest import CHROMIUM


def test_bench_dashboard_reports_server_and_browser_numbers():
    out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "bench", "dashboard", "--tests", "60", "--repeats", "2",
                          "--chromium", CHROMIUM, "--json"], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["tests"] == 60 and report["episodes"] == 240
    assert set(report["server"]) >= {"campaigns", "campaign", "campaign_missed_filter", "episode", "new_campaign", "rigs", "studies", "study"}
    for page in report["server"].values():
        assert page["p50_ms"] > 0 and page["bytes"] > 1000 and 0 < page["transferred_bytes"] < page["bytes"]
    assert isinstance(report["campaign_page_under_1s"], bool)
    for name in ("campaigns", "campaign", "episode", "new_campaign", "rigs", "studies", "study"):
        cold = report["browser"][name]["cold"]
        assert cold["first_contentful_paint_ms"] > 0 and cold["load_ms"] > 0
        assert cold["transferred_bytes"] > 10_000 and cold["requests"] >= 5  # the page and its scripts, all from the orchestrator
        assert report["browser"][name]["warm"]["transferred_bytes"] < cold["transferred_bytes"]  # scripts cached


def test_bench_dashboard_without_a_browser_says_so_in_one_line():
    out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "bench", "dashboard", "--chromium", "/nonexistent/chromium"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 2 and out.stderr.startswith("error: no Chromium at") and len(out.stderr.splitlines()) == 1
