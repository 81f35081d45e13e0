"""A node's control loop runs under SCHED_FIFO while realtime episodes only are in flight
(services/transport/realtime.py): the rule on a recording stand-in for the system call, and the
system call on a real worker thread (the rule as a rig's nodes drive it through a campaign:
tests/nodes/test_realtime_rig.py)."""

from __future__ import annotations

import errno
import logging
import os
import threading

import pytest

from ra2vipas.services.transport.realtime import RealtimeClass, check_priority, parse_priority, priority_from_env
from ra2vipas.services.transport.runtime import EventLoop


class Calls:
    """A stand-in for ``set_thread_policy`` that records each call; ``refuse``: raise EPERM for FIFO."""

    def __init__(self, refuse: bool = False) -> None:
        self.calls: list[tuple[int, bool, int]] = []
        self.refuse = refuse
        self.lock = threading.Lock()

    def __call__(self, tid: int, realtime: bool, priority: int) -> None:
        with self.lock:
            self.calls.append((tid, realtime, priority))
        if realtime and self.refuse:
            raise PermissionError(errno.EPERM, "Operation not permitted")

    def take(self) -> list[tuple[int, bool, int]]:
        with self.lock:
            got, self.calls = self.calls, []
        return got


def test_fifo_only_while_every_episode_in_flight_is_realtime():
    calls = Calls()
    rt = RealtimeClass(10, calls)
    rt.add_thread(101)
    rt.add_thread(102)
    assert calls.take() == [] and not rt.active
    rt.began("a", True)
    assert rt.active and calls.take() == [(101, True, 10), (102, True, 10)]
    rt.began("a", True)  # a duplicate start changes nothing
    rt.began("b", True)
    assert calls.take() == []
    rt.began("f", False)  # a fast episode: its lockstep never sleeps, so back to the ordinary class
    assert not rt.active and calls.take() == [(101, False, 10), (102, False, 10)]
    rt.ended("a")
    assert calls.take() == []  # b (realtime) and f (fast) still in flight
    rt.ended("f")
    assert rt.active and calls.take() == [(101, True, 10), (102, True, 10)]
    rt.add_thread(103)  # a thread that joins while it is on gets it at once
    assert calls.take() == [(103, True, 10)]
    rt.ended("b")
    assert not rt.active and calls.take() == [(101, False, 10), (102, False, 10), (103, False, 10)]
    rt.ended("b")  # unknown keys are ignored
    rt.began("g", False)
    rt.ended("g")
    assert calls.take() == [] and not rt.active


def test_priority_zero_never_asks():
    calls = Calls()
    rt = RealtimeClass(0, calls)
    rt.add_thread(1)
    rt.began("a", True)
    assert calls.take() == [] and not rt.active


def test_a_refusal_is_said_once_undone_and_never_asked_again(caplog):
    calls = Calls(refuse=True)
    rt = RealtimeClass(10, calls)
    rt.add_thread(7)
    with caplog.at_level(logging.INFO, logger="ra2vipas"):
        rt.began("a", True)
        rt.ended("a")
        rt.began("b", True)
    assert not rt.active and rt.refused
    assert calls.take() == [(7, True, 10), (7, False, 0)]  # tried once, put back, not again
    said = [r.getMessage() for r in caplog.records if "SCHED_FIFO" in r.getMessage()]
    assert len(said) == 1 and "RA2VIPAS_REALTIME_PRIORITY=0" in said[0]


def test_the_priority_is_checked_from_flags_and_environment(monkeypatch):
    assert check_priority(0) == 0 and check_priority(49) == 49
    assert parse_priority("12") == 12
    with pytest.raises(ValueError, match="--realtime-priority must be an integer 0-49, got 'x'"):
        parse_priority("x")
    with pytest.raises(ValueError, match="--realtime-priority must be 0-49"):
        parse_priority("-1")
    with pytest.raises(ValueError, match="0-49"):
        check_priority(50)
    monkeypatch.setenv("RA2VIPAS_REALTIME_PRIORITY", "12")
    assert priority_from_env() == 12
    monkeypatch.setenv("RA2VIPAS_REALTIME_PRIORITY", "twelve")
    with pytest.raises(ValueError, match="RA2VIPAS_REALTIME_PRIORITY must be an integer"):
        priority_from_env()
    monkeypatch.delenv("RA2VIPAS_REALTIME_PRIORITY")
    assert priority_from_env(7) == 7


def test_the_worker_thread_really_runs_under_sched_fifo_and_goes_back_with_its_nice_value():
    """The system call on a real loop's worker: SCHED_FIFO at the priority where the process may
    (root here, as in CI); where it may not, the loop says so and stays in the ordinary class."""
    loop = EventLoop("rt-test", realtime_priority=10)
    try:
        tid = loop._thread.native_id
        os.setpriority(os.PRIO_PROCESS, tid, 3)  # a thread's own nice value (Linux: per thread)
        loop.post(loop.realtime.began, "a", True)
        assert loop.wait_idle()
        if loop.realtime.refused:
            assert os.sched_getscheduler(tid) == os.SCHED_OTHER
            return
        assert os.sched_getscheduler(tid) == os.SCHED_FIFO and os.sched_getparam(tid).sched_priority == 10
        loop.post(loop.realtime.began, "f", False)
        assert loop.wait_idle()
        assert os.sched_getscheduler(tid) == os.SCHED_OTHER
        assert os.getpriority(os.PRIO_PROCESS, tid) == 3  # the nice value it had, not 0
    finally:
        loop.stop()
