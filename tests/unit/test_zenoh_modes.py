"""Which Zenoh mode a service runs in when nobody chose one, and when a peer warns that no other
host can reach it (issue 18, section 2: peers on different hosts said "up" and exchanged nothing)."""

from __future__ import annotations

import pytest

from ra2vipas.services.transport.zenoh_config import ZenohSettings, is_loopback, peer_reach_warning

ROUTER = "tcp/10.0.0.1:7447"


@pytest.mark.parametrize(("flags", "env", "mode"), [
    ({}, {}, "peer"),  # alone: nothing to join
    ({"connect": [ROUTER]}, {}, "client"),  # --connect alone: join that router
    ({}, {"RA2VIPAS_ZENOH_CONNECT": ROUTER}, "client"),
    ({"connect": [ROUTER], "listen": ["tcp/0.0.0.0:7448"]}, {}, "peer"),  # accepts connections itself: a peer
    ({"listen": ["tcp/0.0.0.0:7448"]}, {}, "peer"),
    ({"connect": [ROUTER]}, {"RA2VIPAS_ZENOH_MODE": "peer"}, "peer"),  # chosen: the flag or the environment decides
    ({"mode": "peer", "connect": [ROUTER]}, {}, "peer"),
    ({"mode": "client"}, {"RA2VIPAS_ZENOH_MODE": "peer"}, "client"),
    ({"mode": "router", "connect": [ROUTER]}, {}, "router"),
])
def test_the_default_mode_is_client_when_told_only_where_to_connect(flags, env, mode):
    assert ZenohSettings.from_sources(env=env, **flags).mode == mode


def test_a_client_by_default_listens_nowhere_and_gives_up_on_an_absent_router_after_its_timeout():
    import json

    conf = json.loads(ZenohSettings.from_sources(connect=[ROUTER], env={}).to_zenoh().get_json("connect"))
    assert conf["timeout_ms"] == 30000 and conf["endpoints"] == [ROUTER]


@pytest.mark.parametrize(("endpoint", "loopback"), [
    ("tcp/127.0.0.1:7447", True), ("tcp/127.1.2.3:0", True), ("tcp/localhost:7447", True), ("tcp/[::1]:7447", True),
    ("unixsock-stream//tmp/z.sock", True), ("tcp/0.0.0.0:0", False), ("tcp/[::]:0", False), ("tcp/router:7447", False),
    ("tls/10.0.0.1:7447", False), ("tcp/127.0.0.1:7447#iface=lo", True),
])
def test_loopback_endpoints(endpoint, loopback):
    assert is_loopback(endpoint) is loopback


def test_a_peer_joining_another_host_while_listening_on_loopback_says_it_cannot_be_reached():
    settings = ZenohSettings.from_sources(mode="peer", connect=["tcp/router:7447"], env={})
    warning = settings.reach_warning()
    assert warning is not None
    assert warning.startswith("Zenoh peer mode: this node listens on tcp/127.0.0.1:0 only, so no node on another host can "
                              "reach it, and a Zenoh router (at tcp/router:7447) relays nothing between peers")
    assert "--zenoh-mode client" in warning and "--listen" in warning


@pytest.mark.parametrize("settings", [
    ZenohSettings.from_sources(connect=["tcp/router:7447"], env={}),  # the default: a client of the router
    ZenohSettings.from_sources(mode="client", connect=["tcp/router:7447"], env={}),
    ZenohSettings.from_sources(mode="peer", connect=["tcp/127.0.0.1:7447"], env={}),  # everything on this machine
    ZenohSettings.from_sources(mode="peer", connect=["tcp/router:7447"], listen=["tcp/0.0.0.0:0"], env={}),
    ZenohSettings.from_sources(mode="peer", env={}),  # alone
    ZenohSettings.from_sources(mode="router", connect=["tcp/10.0.0.2:7447"], env={}),
])
def test_no_warning_where_the_node_can_be_reached_or_needs_not_be(settings):
    assert settings.reach_warning() is None


def test_the_warning_reads_the_endpoints_in_effect():
    assert peer_reach_warning("peer", [ROUTER], ["tcp/127.0.0.1:7448", "tcp/[::1]:7448"]) is not None
    assert peer_reach_warning("peer", [ROUTER], ["tcp/127.0.0.1:7448", "tcp/10.0.0.5:7448"]) is None
    assert peer_reach_warning("client", [ROUTER], []) is None


@pytest.mark.parametrize(("text", "mode"), [
    ('{mode: "client", connect: {endpoints: ["tcp/10.0.0.1:7447"]}}', "client"),
    ('{mode: "peer", connect: {endpoints: ["tcp/10.0.0.1:7447"]}}', "peer"),  # the file chose
    ('{connect: {endpoints: ["tcp/10.0.0.1:7447"]}}', "client"),  # the file's endpoints, nobody's mode
    ('{connect: {endpoints: ["tcp/10.0.0.1:7447"]}, listen: {endpoints: ["tcp/0.0.0.0:7448"]}}', "peer"),
    ("{}", "peer"),
])
def test_a_config_files_mode_and_endpoints_count_when_no_flag_or_variable_chooses(tmp_path, text, mode):
    path = tmp_path / "zenoh.json5"
    path.write_text(text)
    assert ZenohSettings.from_sources(config_file=str(path), env={}).mode == mode
    assert ZenohSettings.from_sources(mode="router", config_file=str(path), env={}).mode == "router"
    assert ZenohSettings.from_sources(config_file=str(path), env={"RA2VIPAS_ZENOH_MODE": "peer"}).mode == "peer"
