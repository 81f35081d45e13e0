"""Slow clients cannot take the API down (issue 18). Connections that trickle one header line
every 10 s once exhausted the orchestrator's file descriptors: /health timed out for the whole
attack and asyncio logged hundreds of thousands of ``socket.accept() out of system resource``
tracebacks. Here the attack (``tests/integration/slowloris.py``, bounded in count and time,
loopback only) runs against a stack whose descriptor limit it would exhaust (4096, as a
smaller machine has; the attack holds up to 5 000 connections from another loopback address),
and /health must keep answering within a second, the log stay small and the stack serve
afterwards."""

from __future__ import annotations

import resource

from tests import http
from tests.integration.conftest import start_stack, stop_stack
from tests.integration.slowloris import attack

FD_LIMIT = 4096


def _low_fd_limit() -> None:  # in the child before exec: soft and hard, so nothing can raise it
    resource.setrlimit(resource.RLIMIT_NOFILE, (FD_LIMIT, FD_LIMIT))


def test_a_slow_client_attack_leaves_health_answering_and_the_log_bounded(procs, tmp_path):
    state = start_stack(procs, tmp_path, rigs=1, preexec_fn=_low_fd_limit)
    log = state["logs"] / "orchestrator.log"
    before = log.stat().st_size
    report = attack(state["api"], sockets=5000, seconds=15.0, line_every_s=10.0, open_per_s=1000.0, source="127.0.0.2")
    summary = report.summary()
    assert report.opened >= 5000 and report.closed_by_server > 0, summary  # it did attack, and the server let go of it
    assert len(report.probes) >= 20 and all(status == 200 for _, _, status in report.probes), summary
    assert report.worst_probe_s < 1.0, summary
    grown = log.stat().st_size - before
    text = log.read_text(errors="replace")
    assert grown < 64_000 and "out of system resource" not in text and "Too many open files" not in text, (grown, text[-2000:])
    r = http.get(f"{state['api']}/health", timeout=2)
    assert r.status_code == 200, r.text
    stop_stack(procs, state["up"])
