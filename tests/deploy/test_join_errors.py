"""A node that cannot join the Zenoh network says why in one line, in bounded time (issue 13):
a client whose --connect reaches nothing, a client with the wrong password for a router that
requires one, and a peer whose --connect reaches nothing (it keeps trying, but says so). A node
given --connect and no mode is a client (issue 18)."""

from __future__ import annotations

import time

from tests.deploy.conftest import clean_env, free_port, wait_port

CONNECT_TIMEOUT_S = "3"


def _error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("error: ")]


def test_a_client_whose_connect_reaches_nothing_says_so(procs):
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    started = time.monotonic()
    node = procs.start_cli("learner", "learner", "--zenoh-mode", "client", "--connect", endpoint,
                           env=clean_env({"RA2VIPAS_ZENOH_CONNECT_TIMEOUT": CONNECT_TIMEOUT_S}))
    assert node.proc.wait(60) == 1
    assert time.monotonic() - started < 30
    (line,) = _error_lines(node.output())
    assert line == (f"error: cannot join the Zenoh network: nothing answers at {endpoint}: check --connect "
                    "(RA2VIPAS_ZENOH_CONNECT) and that the router there is running")
    assert "Traceback" not in node.output() and ".rs:" not in node.output()


def test_a_wrong_password_is_named_as_the_likely_cause(procs, tmp_path):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    (tmp_path / "credentials").write_text("ra2vipas:the-right-password\n")
    router = procs.start_cli("router", "router", "--listen", endpoint,
                             env=clean_env({"RA2VIPAS_ZENOH_CREDENTIALS": str(tmp_path / "credentials")}))
    wait_port("127.0.0.1", port, router)
    started = time.monotonic()
    node = procs.start_cli("learner", "learner", "--zenoh-mode", "client", "--connect", endpoint,
                           env=clean_env({"RA2VIPAS_ZENOH_CONNECT_TIMEOUT": CONNECT_TIMEOUT_S, "RA2VIPAS_ZENOH_USER": "ra2vipas",
                                          "RA2VIPAS_ZENOH_PASSWORD": "a-guess"}))
    assert node.proc.wait(60) == 1
    assert time.monotonic() - started < 30
    (line,) = _error_lines(node.output())
    assert line.startswith(f"error: cannot join the Zenoh network: {endpoint} accepts connections but did not let this "
                           "node's Zenoh session in: check its user/password (RA2VIPAS_ZENOH_USER")
    assert ".rs:" not in node.output()


def test_connect_without_a_mode_is_a_client_and_says_when_nothing_answers(procs):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = procs.start_cli("learner", "learner", "--connect", endpoint, env=clean_env({"RA2VIPAS_ZENOH_CONNECT_TIMEOUT": "0.5"}))
    assert node.proc.wait(60) == 1
    (line,) = _error_lines(node.output())
    assert line.startswith(f"error: cannot join the Zenoh network: nothing answers at {endpoint}")


def test_a_peer_whose_connect_reaches_nothing_logs_it(procs):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = procs.start_cli("learner", "learner", "--zenoh-mode", "peer", "--connect", endpoint, env=clean_env())  # opens anyway
    node.wait_for_output("not connected to any Zenoh node after 10 s (still trying): nothing answers at", timeout=40)
    assert node.proc.poll() is None  # still up, still trying


def test_the_old_spelling_of_zenoh_mode_still_works_with_a_warning(procs):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = procs.start_cli("learner", "learner", "--mode", "client", "--connect", endpoint,
                           env=clean_env({"RA2VIPAS_ZENOH_CONNECT_TIMEOUT": "0.5"}))
    assert node.proc.wait(60) == 1
    out = node.output()
    assert "warning: --mode is deprecated; use --zenoh-mode" in out
    assert "error: cannot join the Zenoh network: nothing answers at" in out  # it did run as a client
