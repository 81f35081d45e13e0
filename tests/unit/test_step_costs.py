"""A node's per-step cost clock (services/transport/costs.py, issue 22), on a scripted clock."""

import pytest

from ra2vipas.services.transport import costs
from ra2vipas.services.transport.costs import CostClock, step_breakdown


@pytest.fixture
def clock(monkeypatch):
    """``costs.now_ns`` reads ``t[0]``: a test moves time by hand."""
    t = [0]
    monkeypatch.setattr(costs, "now_ns", lambda: t[0])
    return t


def _handle(c: CostClock, t: list[int], posted: int, started: int, work: int) -> None:
    c.mark_arrival(posted, started)
    t[0] = started + work
    c.lap("compute")
    t[0] += 1
    c.lap("publish")
    c.replied()


def test_the_wait_for_an_episodes_first_step_message_is_in_no_stage(clock):
    """The first message waited on the wire and in the queue (behind the episode's set-up): the
    span starts as its handling does; later waits are ``outside`` and ``queued``, and the stages
    cover the span exactly."""
    c = CostClock()
    _handle(c, clock, posted=1_000_000, started=9_000_000, work=100_000)  # queued 8 ms behind the set-up: no step's
    _handle(c, clock, posted=9_150_001, started=9_170_001, work=100_000)  # 50 us outside, 20 us queued
    r = c.report()
    assert c.steps == 2 and c.first == 9_000_000 and c.outside == 50_000 and c.queued == 20_000
    assert c.outside + c.queued + c.compute + c.publish == c.last - c.first == 9_270_002 - 9_000_000
    assert r.span_ms == 0.27 and r.queued_ms == 0.02 and r.outside_ms == 0.05  # [ms], to 4 decimals


def test_both_views_of_the_transport_agree_when_the_first_command_waited_long(clock):
    """Lockstep, 100 steps: the controller's first command overtook the sensors' episode start
    and waited 5 ms for it; every message then takes 30 us on the wire. Both nodes' views of the
    transport read the 60 us round trip (short by their edges, one step each), not the first
    wait spread over the steps (+50 us a step)."""
    ctl, sen = CostClock(), CostClock()
    wire, sensors_work, controller_work = 30_000, 200_000, 100_000
    posted, started = wire, 5_000_000  # command 0, published at 0
    for _ in range(100):
        _handle(sen, clock, posted=posted, started=started, work=sensors_work)
        arrives = clock[0] + wire  # the measurement
        _handle(ctl, clock, posted=arrives, started=arrives, work=controller_work)
        posted = started = clock[0] + wire  # the next command
    b = step_breakdown([ctl.report()], [sen.report()])
    assert b["transport_ms"] == pytest.approx(0.060, rel=0.05) and b["transport_ms_sensors_view"] == pytest.approx(0.060, rel=0.05), b
    assert b["parts_sum_ms"] == pytest.approx(b["step_ms"], rel=1e-3)
    assert b["step_ms"] == pytest.approx(0.060 + 0.200 + 0.100, rel=0.01)  # transport, sensors, controller
