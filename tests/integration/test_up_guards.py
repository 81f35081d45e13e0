"""``ra2vipas up`` never lies about itself (issue 13): a second stack on a busy port or on a
database another orchestrator holds fails fast with one line and exit 1, before starting
anything; the database's folder is created or refused in one line; a crashing service is
restarted with backoff and, after 5 crashes in a minute, stops the stack with its last words;
and ``up`` only accepts its own orchestrator's /health."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from ra2vipas.cli.stack import CRASH_LIMIT, Child, Stack, StackConfig, StackError, free_port, prepare_database
from ra2vipas.services.orchestrator.dblock import DatabaseInUse, DatabaseLock
from tests.integration.conftest import ROOT, Procs, children_of, start_stack, stop_stack


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    registry = Procs()
    state = start_stack(registry, tmp_path_factory.mktemp("first"), rigs=1)
    yield state
    stop_stack(registry, state["up"])


def _up(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "up", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:  # gone meanwhile
        return ""


def test_a_second_up_on_a_busy_port_fails_fast_naming_who_holds_it(first, tmp_path):
    port = int(first["api"].rsplit(":", 1)[1])
    before = set(children_of(first["up"].pid))
    r = _up("--port", str(port), "--db", str(tmp_path / "second.db"), "--log-dir", str(tmp_path / "logs"))
    assert r.returncode == 1, r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert f"port {port}" in lines[0] and re.search(r"taken by pid \d+", lines[0]) and "orchestrator" in lines[0]
    assert "API on" not in r.stdout
    assert not (tmp_path / "logs").exists(), "nothing was started"
    assert set(children_of(first["up"].pid)) == before


def test_a_second_up_on_the_same_database_fails_fast(first, tmp_path):
    r = _up("--port", str(free_port()), "--db", str(first["db"]), "--log-dir", str(tmp_path / "logs"))
    assert r.returncode == 1, r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and f"the database {first['db']} is in use by another orchestrator (pid" in lines[0], r.stderr
    assert not (tmp_path / "logs").exists()


def test_an_orchestrator_on_a_held_database_refuses_in_one_line(first):
    r = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "orchestrator", "--port", str(free_port()), "--db", str(first["db"])],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and r.stderr.strip().splitlines() == [r.stderr.strip()] and "in use by another orchestrator" in r.stderr


def test_up_does_not_adopt_another_stacks_orchestrator(first, tmp_path):
    """Even if the port check were raced, /health must come from this stack's orchestrator."""
    port = int(first["api"].rsplit(":", 1)[1])
    stack = Stack(StackConfig(port=port, db_path=str(tmp_path / "x.db")))
    with pytest.raises(StackError, match="another server"):
        stack._wait_ready(timeout=1.5)


def test_the_database_folder_is_created_or_refused_in_one_line(tmp_path):
    db = tmp_path / "a" / "b" / "ra2vipas.db"
    prepare_database(str(db))
    assert db.parent.is_dir()
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(StackError, match="cannot create the database folder") as err:
        prepare_database(str(blocker / "sub" / "ra2vipas.db"))
    assert "\n" not in str(err.value)
    r = _up("--port", str(free_port()), "--db", str(blocker / "sub" / "ra2vipas.db"), "--log-dir", str(tmp_path / "logs"))
    assert r.returncode == 1 and r.stderr.startswith("error: cannot create the database folder") and r.stderr.count("\n") == 1


def test_the_database_lock_is_exclusive_and_released(tmp_path):
    db = tmp_path / "x.db"
    with DatabaseLock(db):
        with pytest.raises(DatabaseInUse, match=r"in use by another orchestrator \(pid \d+\)"):
            DatabaseLock(db).acquire()
    with DatabaseLock(db):  # released: it can be taken again
        pass


def test_crash_backoff_doubles_and_gives_up_after_the_limit():
    stack = Stack(StackConfig())
    child = Child("learner", ["true"], {}, Path("/dev/null"))
    delays = [stack.crashed(child, now=float(t)) for t in range(CRASH_LIMIT)]
    assert delays[:-1] == [0.5, 1.0, 2.0, 4.0] and delays[-1] is None
    child.crashes.clear()
    assert [stack.crashed(child, now=t * 100.0) for t in range(CRASH_LIMIT + 2)] == [0.5] * (CRASH_LIMIT + 2)  # far apart: no limit


def test_a_service_that_keeps_crashing_stops_up_with_its_last_words(tmp_path):
    """The learner is killed again each time `up` restarts it: restarts come after growing
    delays, and the fifth crash within a minute stops the whole stack with exit 1 and the
    learner's last log lines."""
    import os
    import signal
    import time

    registry = Procs()
    try:
        state = start_stack(registry, tmp_path, rigs=1)
        up = state["up"]
        kills, last_pid, deadline = 0, None, time.monotonic() + 120
        while up.poll() is None and time.monotonic() < deadline:
            pids = [p for p in children_of(up.pid) if "learner" in _cmdline(p)]
            if pids and pids[0] != last_pid:
                last_pid = pids[0]
                os.kill(last_pid, signal.SIGKILL)
                kills += 1
            time.sleep(0.05)
        assert up.wait(30) == 1
        out = up.stdout.read()
        assert kills == CRASH_LIMIT
        assert "restarting it in 0.5 s" in out and "restarting it in 4 s" in out
        assert f"learner crashed {CRASH_LIMIT} times within 60 s; stopping" in out and "learner.log" in out
        assert not children_of(up.pid)
    finally:
        registry.cleanup()


def _time_wait_on(port: int) -> bool:
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            parts = line.split()
            if parts[3] == "06" and int(parts[1].rsplit(":", 1)[1], 16) == port:  # 06: TIME_WAIT
                return True
    return False


def test_the_port_check_ignores_time_wait_sockets():
    """Issue 18: `up` right after a stop refused its own router port for ~80 s while only
    TIME-WAIT sockets remained (the check bound without SO_REUSEADDR, unlike the services)."""
    import socket

    from ra2vipas.cli.stack import check_port_free

    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    client = socket.create_connection(("127.0.0.1", port))
    accepted, _ = listener.accept()
    accepted.close()  # the server side closes first: its end of the connection waits in TIME-WAIT
    client.recv(1)
    client.close()
    with pytest.raises(StackError, match=f"port {port} on 127.0.0.1 is taken by pid"):
        check_port_free("127.0.0.1", port, "the test's")  # still listening: taken
    listener.close()
    assert _time_wait_on(port)
    check_port_free("127.0.0.1", port, "the test's")  # only TIME-WAIT left: free


def test_up_restarts_at_once_on_its_own_ports(tmp_path):
    """Stop a stack and start it again at once on the same API and router ports."""
    registry = Procs()
    try:
        port, router = free_port(), free_port()
        for run in range(2):
            state = start_stack(registry, tmp_path / f"run{run}", "--port", str(port), "--router-port", str(router), rigs=1)
            assert state["api"].endswith(f":{port}")
            stop_stack(registry, state["up"])
            assert state["up"].returncode == 0
            registry = Procs()
    finally:
        registry.cleanup()
