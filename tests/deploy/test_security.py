"""Zenoh over TLS with user/password authentication: a `ra2vipas router` configured only by
environment (certificate and key files, a credentials file) lets authenticated clients talk
and keeps out every peer that is not: wrong or missing credentials, plain TCP, a TLS client
that does not trust the router's CA, and (with mutual TLS) one without a certificate."""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from ra2vipas.services.protocol import keys
from ra2vipas.services.transport.zenoh_config import (
    AUTH_DICTIONARY,
    AUTH_PASSWORD,
    AUTH_USER,
    TLS_CONNECT_CERT,
    TLS_CONNECT_KEY,
    TLS_LISTEN_CERT,
    TLS_LISTEN_KEY,
    TLS_MTLS,
    TLS_ROOT_CA,
    TLS_VERIFY_NAME,
    ZenohSettings,
    ZenohSettingsError,
)
from tests.deploy.conftest import clean_env, free_port, wait_port
from tests.deploy.pki import CertificateAuthority, Identity

USER, PASSWORD = "ra2vipas", "correct horse battery staple"
TOPIC = "ra2vipas/v1/test/security"


@dataclass(frozen=True)
class PKI:
    ca: str
    router: Identity
    client: Identity
    rogue_ca: str  # a CA that signed nothing the router presents
    credentials: str  # user:password lines the router accepts
    password_file: str


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> PKI:
    d: Path = tmp_path_factory.mktemp("pki")
    ca = CertificateAuthority(d)
    rogue = CertificateAuthority(d / "rogue", name="rogue CA")
    (d / "credentials.txt").write_text(f"{USER}:{PASSWORD}\nother:other-password\n")
    (d / "password").write_text(PASSWORD + "\n")
    return PKI(ca=ca.cert, router=ca.issue("router", dns=("localhost", "router"), ips=("127.0.0.1",)),
               client=ca.issue("client", dns=("client",)), rogue_ca=rogue.cert,
               credentials=str(d / "credentials.txt"), password_file=str(d / "password"))


def start_router(procs, pki: PKI, mtls: bool = False) -> str:
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    env = {"RA2VIPAS_ZENOH_TLS_CERT": pki.router.cert, "RA2VIPAS_ZENOH_TLS_KEY": pki.router.key,
           "RA2VIPAS_ZENOH_CREDENTIALS": pki.credentials}
    if mtls:
        env.update({"RA2VIPAS_ZENOH_TLS_MTLS": "true", "RA2VIPAS_ZENOH_TLS_CA": pki.ca})
    router = procs.start_cli("router", "router", "--listen", endpoint, env=clean_env(env))
    wait_port("127.0.0.1", port, router)
    return endpoint


def session(endpoint: str, mode: str = "client", **security) -> zenoh.Session:
    return zenoh.open(ZenohSettings(mode=mode, connect=(endpoint,), connect_timeout_s=0, **security).to_zenoh())


class Inbox:
    def __init__(self) -> None:
        self.items: list[bytes] = []
        self.event = threading.Event()

    def __call__(self, sample: zenoh.Sample) -> None:
        self.items.append(sample.payload.to_bytes())
        self.event.set()


def exchange(sender: zenoh.Session, receiver: zenoh.Session, payload: bytes, wait: float) -> bool:
    """Whether ``payload`` put by ``sender`` reaches a subscriber of ``receiver``."""
    inbox = Inbox()
    sub = receiver.declare_subscriber(TOPIC, inbox)
    try:
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            sender.put(TOPIC, payload)
            if inbox.event.wait(0.2) and payload in inbox.items:
                return True
        return False
    finally:
        sub.undeclare()


@pytest.fixture()
def secure_router(procs, pki):
    return start_router(procs, pki)


def test_authenticated_clients_exchange_messages_over_tls(secure_router, pki):
    with session(secure_router, tls_ca=pki.ca, user=USER, password=PASSWORD) as a, \
            session(secure_router, tls_ca=pki.ca, user="other", password="other-password") as b:
        assert a.info.routers_zid() and b.info.routers_zid()
        assert exchange(a, b, b"hello over TLS", wait=10.0)
        assert exchange(b, a, b"and back", wait=10.0)


INTRUDERS = {
    "wrong password": dict(tls_ca="CA", user=USER, password="wrong"),
    "unknown user": dict(tls_ca="CA", user="mallory", password=PASSWORD),
    "no credentials": dict(tls_ca="CA"),
    "does not trust the router's CA": dict(tls_ca="ROGUE", user=USER, password=PASSWORD),
    "plain tcp": dict(user=USER, password=PASSWORD),
}


@pytest.mark.parametrize("intruder", sorted(INTRUDERS))
def test_an_unauthenticated_peer_cannot_join(secure_router, pki, intruder):
    security = {k: (pki.ca if v == "CA" else pki.rogue_ca if v == "ROGUE" else v) for k, v in INTRUDERS[intruder].items()}
    endpoint = secure_router.replace("tls/", "tcp/") if intruder == "plain tcp" else secure_router
    # a client cannot open a session at all ...
    with pytest.raises(zenoh.ZError):
        session(endpoint, "client", **security).close()
    # ... and a peer, which opens without a router, is left alone: nothing it puts arrives,
    # nothing it subscribes to is delivered, its liveliness token is not seen
    with session(secure_router, tls_ca=pki.ca, user=USER, password=PASSWORD) as member, \
            session(endpoint, "peer", **security) as intruder_session:
        token = intruder_session.liveliness().declare_token(keys.alive("sensors", "intruder"))
        assert not intruder_session.info.routers_zid()
        assert not exchange(intruder_session, member, b"from the intruder", wait=1.5)
        assert not exchange(member, intruder_session, b"for members only", wait=1.5)
        seen = [str(r.ok.key_expr) for r in member.liveliness().get(keys.alive_all(), timeout=1.0) if r.ok]
        assert keys.alive("sensors", "intruder") not in seen
        token.undeclare()
        # the member itself is connected: the check above could have failed
        assert member.info.routers_zid()


def test_a_service_joins_with_credentials_from_its_environment_and_not_without(secure_router, pki, procs):
    base = {"RA2VIPAS_ZENOH_MODE": "client", "RA2VIPAS_ZENOH_CONNECT": secure_router, "RA2VIPAS_ZENOH_TLS_CA": pki.ca,
            "RA2VIPAS_ZENOH_USER": USER, "RA2VIPAS_ZENOH_CONNECT_TIMEOUT": "3"}  # a rejected client retries 3 s, not 30
    good = procs.start_cli("learner-ok", "learner", "--name", "learner-ok",
                           env=clean_env({**base, "RA2VIPAS_ZENOH_PASSWORD_FILE": pki.password_file}))
    bad = procs.start_cli("learner-bad", "learner", "--name", "learner-bad",
                          env=clean_env({**base, "RA2VIPAS_ZENOH_PASSWORD": "guess"}))
    assert bad.proc.wait(60) == 1, bad.tail()
    assert bad.output().strip().splitlines()[-1].startswith("error: cannot join the Zenoh network: "), bad.tail()
    good.wait_for_output(" up (zenoh", 60)
    with session(secure_router, tls_ca=pki.ca, user=USER, password=PASSWORD) as observer:
        seen: list[str] = []
        for _ in range(50):
            seen = [str(r.ok.key_expr) for r in observer.liveliness().get(keys.alive_all(), timeout=1.0) if r.ok]
            if keys.alive("learner", "learner-ok") in seen:
                break
            time.sleep(0.1)
        assert keys.alive("learner", "learner-ok") in seen
        assert keys.alive("learner", "learner-bad") not in seen


def test_mutual_tls_requires_a_client_certificate(procs, pki):
    endpoint = start_router(procs, pki, mtls=True)
    creds = dict(user=USER, password=PASSWORD)
    with session(endpoint, tls_ca=pki.ca, tls_cert=pki.client.cert, tls_key=pki.client.key, tls_mtls=True, **creds) as ok:
        assert ok.info.routers_zid()
    with pytest.raises(zenoh.ZError):
        session(endpoint, tls_ca=pki.ca, **creds).close()


# -- the settings: environment -> Zenoh configuration keys ---------------------------------------

def test_security_settings_map_onto_zenohs_configuration_keys(pki):
    env = {"RA2VIPAS_ZENOH_TLS_CA": pki.ca, "RA2VIPAS_ZENOH_TLS_CERT": pki.client.cert, "RA2VIPAS_ZENOH_TLS_KEY": pki.client.key,
           "RA2VIPAS_ZENOH_TLS_MTLS": "true", "RA2VIPAS_ZENOH_TLS_VERIFY_NAME": "false", "RA2VIPAS_ZENOH_USER": USER,
           "RA2VIPAS_ZENOH_PASSWORD_FILE": pki.password_file, "RA2VIPAS_ZENOH_CREDENTIALS": pki.credentials}
    settings = ZenohSettings.from_sources(env=env)
    assert settings.security_entries() == {
        TLS_ROOT_CA: pki.ca, TLS_LISTEN_CERT: pki.client.cert, TLS_CONNECT_CERT: pki.client.cert,
        TLS_LISTEN_KEY: pki.client.key, TLS_CONNECT_KEY: pki.client.key, TLS_MTLS: True, TLS_VERIFY_NAME: False,
        AUTH_USER: USER, AUTH_PASSWORD: PASSWORD, AUTH_DICTIONARY: pki.credentials,
    }
    conf = settings.to_zenoh()  # every key is one the installed Zenoh knows (it rejects unknown keys)
    assert PASSWORD not in repr(settings)
    assert '"enable_mtls":true' in str(conf).replace(" ", "")
    assert ZenohSettings.from_sources(env={}).security_entries() == {}
    # flag > environment > default
    flagged = ZenohSettings.from_sources(env={**env, "RA2VIPAS_ZENOH_PASSWORD": "from-env"}, password="from-flag", tls_mtls=False)
    assert flagged.password == "from-flag" and not flagged.tls_mtls
    assert ZenohSettings.from_sources(env={**env, "RA2VIPAS_ZENOH_PASSWORD": "from-env"}).password == "from-env"


def config_json(settings: ZenohSettings) -> dict:
    return json.loads(str(settings.to_zenoh()))  # a zenoh.Config prints as JSON


def test_clients_wait_for_their_router_at_start_up_for_a_while():
    assert config_json(ZenohSettings.from_sources(env={"RA2VIPAS_ZENOH_MODE": "client"}))["connect"]["timeout_ms"] == 30000
    forever = {"RA2VIPAS_ZENOH_MODE": "client", "RA2VIPAS_ZENOH_CONNECT_TIMEOUT": "-1"}
    assert config_json(ZenohSettings.from_sources(env=forever))["connect"]["timeout_ms"] == -1
    assert config_json(ZenohSettings.from_sources(mode="client", connect_timeout_s=2.5, env=forever))["connect"]["timeout_ms"] == 2500
    peer = config_json(ZenohSettings.from_sources(env={}))["connect"]["timeout_ms"]
    assert peer != 30000  # peers keep Zenoh's default: they start without their endpoints and keep trying
    for bad in ("soon", "-2", "inf"):
        with pytest.raises(ZenohSettingsError, match="(?i)timeout"):
            ZenohSettings.from_sources(env={"RA2VIPAS_ZENOH_CONNECT_TIMEOUT": bad})


@pytest.mark.parametrize("env, message", [
    ({"RA2VIPAS_ZENOH_USER": USER}, "needs both a user"),
    ({"RA2VIPAS_ZENOH_PASSWORD": PASSWORD}, "needs both a user"),
    ({"RA2VIPAS_ZENOH_TLS_CERT": "CERT"}, "needs its private key"),
    ({"RA2VIPAS_ZENOH_TLS_CA": "/nonexistent/ca.pem"}, "does not exist"),
    ({"RA2VIPAS_ZENOH_USER": USER, "RA2VIPAS_ZENOH_PASSWORD_FILE": "/nonexistent/pw"}, "cannot read"),
    ({"RA2VIPAS_ZENOH_TLS_MTLS": "maybe"}, "must be true or false"),
    ({"RA2VIPAS_ZENOH_TLS_MTLS": "1"}, "mutual TLS needs"),
    ({"RA2VIPAS_ZENOH_LISTEN": "tls/0.0.0.0:7447"}, "needs a certificate and key"),
])
def test_inconsistent_security_settings_are_one_line_errors(pki, env, message):
    env = {k: (pki.client.cert if v == "CERT" else v) for k, v in env.items()}
    with pytest.raises(ZenohSettingsError, match=message):
        ZenohSettings.from_sources(env=env)
