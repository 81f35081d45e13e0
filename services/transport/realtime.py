"""Realtime scheduling of a node's control loop: ``SCHED_FIFO`` while it runs realtime episodes only.

A realtime episode's latency (sample to command, docs/protocol.md "Realtime") is the controller's
step, about a millisecond, once every T_RF. On a machine whose cores are busy (the campaign's
other rig in fast mode, the orchestrator scoring its results) an ordinary thread that wakes for
that step waits for a core and is preempted in the middle of it: `bench mesh`'s realtime part,
beside a rig running a fast campaign, read a p99 of 2.3-5.1 ms with the rig at nice -5 and
1.3-1.6 ms with it under ``SCHED_FIFO`` (docs/mesh-cost.md). So, where the process may
(root, ``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO``), the threads on a realtime step's path (the
loop's worker and the sensors' tick timer) run under ``SCHED_FIFO`` at ``priority`` while every
episode in flight on the loop is a realtime one, and back under ``SCHED_OTHER`` (their nice
value kept) as soon as a fast episode starts or the last realtime one ends: a fast episode's
lockstep never sleeps, and under ``SCHED_FIFO`` it would take its core from everything else.
Linux's realtime throttling (``kernel.sched_rt_runtime_us``, 95 % by default) bounds what a
runaway realtime handler could take anyway.

Where the process may not, it logs that once and goes on at its ordinary priority.
``priority`` 0 turns it off (``--realtime-priority 0``, ``RA2VIPAS_REALTIME_PRIORITY=0``).
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Callable, Hashable

log = logging.getLogger("ra2vipas")

ENV = "RA2VIPAS_REALTIME_PRIORITY"
DEFAULT_PRIORITY = 10  # SCHED_FIFO 1-99: above ordinary threads, below the kernel's own realtime threads (50)
MAX_PRIORITY = 49


def parse_priority(text: str, what: str = "--realtime-priority") -> int:
    """A priority as given (0-49; 0: off); a ValueError says what is wrong, naming ``what``."""
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{what} must be an integer 0-{MAX_PRIORITY}, got {text!r}") from None
    return check_priority(value, what)


def priority_from_env(default: int = DEFAULT_PRIORITY) -> int:
    """``RA2VIPAS_REALTIME_PRIORITY`` (0-49; 0: off), else ``default``; a ValueError says what is wrong."""
    text = os.environ.get(ENV, "").strip()
    return parse_priority(text, ENV) if text else default


def check_priority(value: int, what: str = "--realtime-priority") -> int:
    if not 0 <= value <= MAX_PRIORITY:
        raise ValueError(f"{what} must be 0-{MAX_PRIORITY} (0: off), got {value}")
    return value


def set_thread_policy(tid: int, realtime: bool, priority: int) -> None:
    """Thread ``tid`` (a native thread id) under ``SCHED_FIFO`` at ``priority``, or back under
    ``SCHED_OTHER`` (its nice value stays: Linux keeps a thread's static priority). Raises
    OSError (EPERM) where the process may not."""
    if realtime:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    else:
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))


class RealtimeClass:
    """Which scheduling class a loop's threads run under, from the modes of the episodes in flight.

    Nodes say when an episode starts (``began(key, realtime)``) and ends (``ended(key)``), keys
    being anything hashable and unique per node and episode; threads join with
    ``add_thread(native_id)``. The threads run under ``SCHED_FIFO`` while at least one realtime
    episode and no fast one is in flight. ``set_policy`` is the system call (replaced in tests).
    Called from the loop's worker (``began``, ``ended``) and at set-up (``add_thread``)."""

    def __init__(self, priority: int, set_policy: Callable[[int, bool, int], None] = set_thread_policy) -> None:
        self.priority = check_priority(priority, "realtime priority")
        self._set_policy = set_policy
        self._modes: dict[Hashable, bool] = {}
        self._realtime = 0  # realtime episodes in flight; the rest of ``_modes`` are fast
        self._threads: list[int] = []
        self._lock = threading.Lock()
        self.active = False  # the threads run under SCHED_FIFO now
        self.refused: str | None = None  # why the system refused (then it is off for good)

    def add_thread(self, tid: int | None) -> None:
        if tid is None:
            return
        with self._lock:
            self._threads.append(tid)
            if self.active:
                self._apply([tid], True)

    def began(self, key: Hashable, realtime: bool) -> None:
        with self._lock:
            if key in self._modes:
                return
            self._modes[key] = realtime
            self._realtime += realtime
            self._update()

    def ended(self, key: Hashable) -> None:
        with self._lock:
            realtime = self._modes.pop(key, None)
            if realtime is None:
                return
            self._realtime -= realtime
            self._update()

    def _update(self) -> None:
        want = self.priority > 0 and self.refused is None and self._realtime > 0 and self._realtime == len(self._modes)
        if want != self.active:
            self.active = want
            self._apply(self._threads, want)

    def _apply(self, threads: list[int], realtime: bool) -> None:
        for tid in threads:
            try:
                self._set_policy(tid, realtime, self.priority)
            except OSError as err:
                if not realtime:  # a thread that is gone; the others still go back
                    continue
                self.refused = err.strerror or str(err)
                self.active = False
                log.info("realtime episodes run at the ordinary priority: SCHED_FIFO %d refused (%s; it needs root, "
                         "CAP_SYS_NICE or an RLIMIT_RTPRIO; %s=0 stops asking)", self.priority, self.refused, ENV)
                for done in self._threads:  # undo those already switched
                    try:
                        self._set_policy(done, False, 0)
                    except OSError:
                        pass
                return
