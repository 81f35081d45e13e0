"""``ra2vipas bench plots``: a small run through the real processes prints both numbers the
issue sets as targets and leaves no process behind (stack, renderers, plot clients)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def processes_with(marker: str) -> list[int]:
    """Processes whose environment carries ``marker`` (every process the benchmark started
    inherits it)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit() and int(entry) != os.getpid():
            try:
                with open(f"/proc/{entry}/environ", "rb") as f:
                    if marker.encode() in f.read():
                        found.append(int(entry))
            except OSError:
                pass
    return found


def test_bench_plots_reports_read_p99_and_slowdown_and_leaves_nothing_behind():
    marker = f"PLOTS_BENCH_TEST={uuid.uuid4().hex}"
    env = {**os.environ, "PYTHONPATH": str(ROOT), marker.split("=")[0]: marker.split("=")[1]}
    proc = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "bench", "plots", "--clients", "6", "--readers", "1", "--tests", "2",
                           "--fixtures", "1", "--fixture-tests", "2", "--repeats", "1", "--rigs", "1", "--json"],
                          capture_output=True, text=True, timeout=600, env=env, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["benchmark"] == "plots" and report["plot_clients"] == 6
    assert report["targets"] == {"read_p99_ms": 200.0, "slowdown_pct": 10.0}
    assert report["read_p99_ms"] > 0 and isinstance(report["slowdown_pct"], float)
    assert set(report["met"]) == {"read_p99_ms", "slowdown_pct"}
    assert report["figures"] == {"dr": 2, "pod": 2, "episode": 2 * 3 * 2}
    assert report["renderer_processes"] >= 1
    loaded = report["with_plots"]["runs"][0]
    assert loaded["plots"]["requests"] > 0 and "200" in loaded["plots"]["status"]
    assert report["without_plots"]["runs"][0]["read_errors"] == 0 == loaded["read_errors"]
    assert report["without_plots"]["steps_per_second"] > 0 and report["with_plots"]["steps_per_second"] > 0
    assert processes_with(marker) == [], "the benchmark left processes behind"
