"""Zenoh settings shared by every service: one place turns flags and environment into a
``zenoh.Config`` (the zenoh-python ``examples/common/common.py`` idea).

Precedence: CLI flag > environment variable > default. Environment variables:

``RA2VIPAS_ZENOH_MODE``
    peer|client|router. Default: the config file's mode if it sets one, else ``client`` when
    ``connect`` endpoints are given (here or in the config file) and no ``listen`` endpoints
    (``--connect tcp/ROUTER:7447`` alone means "join that router"), else ``peer``. A router
    relays nothing between peers, so peers on different hosts talk only if each reaches the
    others' ``listen`` endpoints directly (``peer_reach_warning``).
``RA2VIPAS_ZENOH_CONNECT``, ``RA2VIPAS_ZENOH_LISTEN``
    comma-separated endpoints such as ``tcp/10.0.0.1:7447`` or ``tls/router:7447``.
    Without listen endpoints (here or in the config file) a peer listens on
    ``tcp/127.0.0.1:0`` and a router on ``tcp/127.0.0.1:7447``, loopback only (Zenoh's own
    default is every interface); a client never listens. Listening beyond the machine is
    always explicit, e.g. ``--listen tcp/0.0.0.0:7447``.
``RA2VIPAS_ZENOH_CONFIG``
    a Zenoh JSON5 configuration file, applied first; every other setting overrides it.
``RA2VIPAS_ZENOH_CONNECT_TIMEOUT``
    in client mode, how long (seconds) a service retries its ``connect`` endpoints at start-up
    before it gives up with an error (default 30: services may start before their router,
    as containers do; ``-1``: for ever).

Security (see docs/deployment.md; each maps onto the Zenoh configuration key named in
``to_zenoh``, as documented in Zenoh's ``DEFAULT_CONFIG.json5``):

``RA2VIPAS_ZENOH_TLS_CA``
    PEM file of the certificate authority that signed the peers' certificates
    (``transport/link/tls/root_ca_certificate``). Needed to connect to a ``tls/`` endpoint
    whose certificate is not signed by a public CA.
``RA2VIPAS_ZENOH_TLS_CERT``, ``RA2VIPAS_ZENOH_TLS_KEY``
    this node's certificate and private key (PEM): presented when it listens on a ``tls/``
    endpoint and, with mutual TLS, when it connects.
``RA2VIPAS_ZENOH_TLS_MTLS``
    ``true``: mutual TLS, both sides of every TLS link present a certificate signed by the CA.
``RA2VIPAS_ZENOH_TLS_VERIFY_NAME``
    ``false`` accepts a server certificate whose names do not match the host connected to
    (default ``true``: the certificate must name the host, e.g. ``router`` or its IP address).
``RA2VIPAS_ZENOH_USER``, ``RA2VIPAS_ZENOH_PASSWORD`` (or ``RA2VIPAS_ZENOH_PASSWORD_FILE``)
    the credentials this node presents (``transport/auth/usrpwd/user|password``).
``RA2VIPAS_ZENOH_CREDENTIALS``
    on a router (or any node others connect to): a file of ``user:password`` lines, the
    credentials it accepts (``transport/auth/usrpwd/dictionary_file``). A node with this
    file refuses every session that does not authenticate with one of them.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field

MODES = ("peer", "client", "router")
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/[^\s]+$")
DEFAULT_CLIENT_CONNECT_TIMEOUT_S = 30.0
_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")

# Zenoh configuration keys (eclipse-zenoh 1.x, DEFAULT_CONFIG.json5: transport/link/tls and
# transport/auth/usrpwd). A key Zenoh does not know makes ``insert_json5`` raise, so a test
# that builds a config with every setting checks these names against the installed Zenoh.
TLS_ROOT_CA = "transport/link/tls/root_ca_certificate"
TLS_LISTEN_CERT = "transport/link/tls/listen_certificate"
TLS_LISTEN_KEY = "transport/link/tls/listen_private_key"
TLS_CONNECT_CERT = "transport/link/tls/connect_certificate"
TLS_CONNECT_KEY = "transport/link/tls/connect_private_key"
TLS_MTLS = "transport/link/tls/enable_mtls"
TLS_VERIFY_NAME = "transport/link/tls/verify_name_on_connect"
AUTH_USER = "transport/auth/usrpwd/user"
AUTH_PASSWORD = "transport/auth/usrpwd/password"
AUTH_DICTIONARY = "transport/auth/usrpwd/dictionary_file"


# Zenoh's default listeners (every interface) and ours (loopback): anything that listens binds
# 127.0.0.1 unless told otherwise.
ZENOH_DEFAULT_LISTEN = {"router": ["tcp/[::]:7447"], "peer": ["tcp/[::]:0"]}
LOOPBACK_LISTEN = {"router": ["tcp/127.0.0.1:7447"], "peer": ["tcp/127.0.0.1:0"]}


class ZenohSettingsError(ValueError):
    """A Zenoh setting is invalid; the message names it."""


def default_mode(connect: tuple[str, ...] | list[str], listen: tuple[str, ...] | list[str]) -> str:
    """The mode of a node whose mode nobody chose: ``client`` if it is told where to connect and
    not where to listen (it joins that router: a router relays between clients, never between
    peers), else ``peer`` (alone, or accepting connections itself)."""
    return "client" if connect and not listen else "peer"


def _file_choices(path: str | None) -> tuple[str | None, tuple[str, ...], tuple[str, ...]]:
    """The mode, connect and listen endpoints a Zenoh configuration file sets (None and empty
    where it sets none, or cannot be read: the settings' own check reports that)."""
    if not path or not os.path.isfile(path):
        return None, (), ()
    try:
        import zenoh

        conf = zenoh.Config.from_file(path)
        mode = json.loads(conf.get_json("mode"))
        connect, listen = (json.loads(conf.get_json(f"{key}/endpoints")) for key in ("connect", "listen"))
    except Exception:
        return None, (), ()
    if listen == ZENOH_DEFAULT_LISTEN:  # Zenoh's default, not the file's choice
        listen = []
    flat = lambda v: tuple(ep for eps in v.values() for ep in eps) if isinstance(v, dict) else tuple(v or ())  # noqa: E731
    return (mode if mode in MODES else None), flat(connect), flat(listen)


def endpoint_host(endpoint: str) -> str:
    """The host of a ``proto/host:port`` endpoint (brackets of an IPv6 address removed)."""
    address = endpoint.partition("/")[2].split("#", 1)[0].split("?", 1)[0]
    return address.rpartition(":")[0].strip("[]") if ":" in address else address


def is_loopback(endpoint: str) -> bool:
    """Whether an endpoint names this machine only (127.0.0.0/8, ::1, localhost, a unix socket)."""
    if endpoint.startswith("unixsock-stream/"):
        return True
    host = endpoint_host(endpoint).lower()
    return host == "localhost" or host == "::1" or host.startswith("127.")


def peer_reach_warning(mode: str, connect: list[str], listen: list[str]) -> str | None:
    """Why a peer will exchange nothing with the nodes on other hosts, or None.

    A peer that connects to a router on another host learns from it where the other peers
    listen and connects to them directly; the router relays nothing between peers (Zenoh 1.x).
    So a peer whose ``listen`` endpoints are all loopback (our default) cannot be reached from
    another host, and it cannot reach the loopback endpoints of the peers there: it says "up" and
    then hears nothing. ``connect`` and ``listen`` are the endpoints in effect (defaults and a
    config file's included)."""
    if mode != "peer" or not connect or all(is_loopback(ep) for ep in connect):
        return None
    if listen and not all(is_loopback(ep) for ep in listen):
        return None
    return (f"Zenoh peer mode: this node listens on {', '.join(listen) or 'nothing'} only, so no node on another host can "
            f"reach it, and a Zenoh router (at {', '.join(connect)}) relays nothing between peers: it will exchange "
            "messages with no peer on another host. To join that router use --zenoh-mode client (RA2VIPAS_ZENOH_MODE=client, the default "
            "with --connect and no --listen); to stay a peer, --listen on an address the other hosts can reach")


def _split(value: str | None) -> list[str]:
    return [v.strip() for v in (value or "").split(",") if v.strip()]


def _flag(value: bool | str | None, name: str, default: bool) -> bool:
    if value is None or value == "":
        return default
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise ZenohSettingsError(f"{name} must be true or false, got {value!r}")


def _read_secret(path: str, name: str) -> str:
    try:
        with open(path, encoding="utf-8") as f:
            return f.read().rstrip("\r\n")
    except OSError as err:
        raise ZenohSettingsError(f"{name}: cannot read {path!r} ({err.strerror})") from None


@dataclass(frozen=True)
class ZenohSettings:
    """How a process joins the Zenoh network, and the TLS and user/password credentials it uses."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    connect_timeout_s: float | None = None  # client mode: None = DEFAULT_CLIENT_CONNECT_TIMEOUT_S (or the config file's)
    multicast_scouting: bool = False
    extra: dict = field(default_factory=dict)  # further JSON5 insertions: {"zenoh/config/key": value}
    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    tls_mtls: bool = False
    tls_verify_name: bool = True
    user: str | None = None
    password: str | None = field(default=None, repr=False)
    credentials_file: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ZenohSettingsError(f"zenoh mode must be one of {'|'.join(MODES)}, got {self.mode!r}")
        for ep in (*self.connect, *self.listen):
            if not _ENDPOINT.match(ep):
                raise ZenohSettingsError(f"invalid Zenoh endpoint {ep!r} (expected e.g. tcp/127.0.0.1:7447)")
        t = self.connect_timeout_s
        if t is not None and not (t == -1 or (math.isfinite(t) and t >= 0)):
            raise ZenohSettingsError(f"Zenoh connect timeout must be >= 0 seconds or -1 (for ever), got {t!r}")
        for path, what in ((self.config_file, "Zenoh config file"), (self.tls_ca, "TLS CA certificate (RA2VIPAS_ZENOH_TLS_CA)"),
                           (self.tls_cert, "TLS certificate (RA2VIPAS_ZENOH_TLS_CERT)"), (self.tls_key, "TLS private key (RA2VIPAS_ZENOH_TLS_KEY)"),
                           (self.credentials_file, "credentials file (RA2VIPAS_ZENOH_CREDENTIALS)")):
            if path is not None and not os.path.isfile(path):
                raise ZenohSettingsError(f"{what} {path!r} does not exist")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ZenohSettingsError("a TLS certificate needs its private key: set both RA2VIPAS_ZENOH_TLS_CERT and RA2VIPAS_ZENOH_TLS_KEY")
        if self.tls_mtls and (self.tls_cert is None or self.tls_ca is None):
            raise ZenohSettingsError("mutual TLS needs this node's certificate and key and the CA (RA2VIPAS_ZENOH_TLS_CERT, _KEY, _CA)")
        if (self.user is None) != (self.password is None):
            raise ZenohSettingsError("Zenoh user/password authentication needs both a user (RA2VIPAS_ZENOH_USER) "
                                     "and a password (RA2VIPAS_ZENOH_PASSWORD or RA2VIPAS_ZENOH_PASSWORD_FILE)")
        if self.config_file is None and self.tls_cert is None:
            tls_listen = [ep for ep in self.listen if ep.startswith(("tls/", "quic/"))]
            if tls_listen:
                raise ZenohSettingsError(f"listening on {tls_listen[0]!r} needs a certificate and key "
                                         "(RA2VIPAS_ZENOH_TLS_CERT, RA2VIPAS_ZENOH_TLS_KEY)")

    @classmethod
    def from_sources(cls, mode: str | None = None, connect: list[str] | None = None, listen: list[str] | None = None,
                     config_file: str | None = None, env: dict | None = None, *, connect_timeout_s: float | None = None,
                     tls_ca: str | None = None, tls_cert: str | None = None, tls_key: str | None = None,
                     tls_mtls: bool | None = None, tls_verify_name: bool | None = None, user: str | None = None,
                     password: str | None = None, password_file: str | None = None,
                     credentials_file: str | None = None) -> "ZenohSettings":
        """CLI values (None = not given) over environment over defaults."""
        env = os.environ if env is None else env

        def pick(value, var):
            return value if value is not None else (env.get(var) or None)

        timeout = pick(connect_timeout_s, "RA2VIPAS_ZENOH_CONNECT_TIMEOUT")
        try:
            timeout = float(timeout) if timeout is not None else None
        except ValueError:
            raise ZenohSettingsError(f"RA2VIPAS_ZENOH_CONNECT_TIMEOUT must be a number of seconds, got {timeout!r}") from None
        password = pick(password, "RA2VIPAS_ZENOH_PASSWORD")
        if password is None:
            secret = pick(password_file, "RA2VIPAS_ZENOH_PASSWORD_FILE")
            if secret is not None:
                password = _read_secret(secret, "RA2VIPAS_ZENOH_PASSWORD_FILE")
        connect = tuple(connect) if connect else tuple(_split(env.get("RA2VIPAS_ZENOH_CONNECT")))
        listen = tuple(listen) if listen else tuple(_split(env.get("RA2VIPAS_ZENOH_LISTEN")))
        config_file = config_file or env.get("RA2VIPAS_ZENOH_CONFIG") or None
        mode = mode or env.get("RA2VIPAS_ZENOH_MODE") or None
        if mode is None:
            file_mode, file_connect, file_listen = _file_choices(config_file)
            mode = file_mode or default_mode(connect or file_connect, listen or file_listen)
        return cls(
            mode=mode,
            connect=connect,
            listen=listen,
            config_file=config_file,
            connect_timeout_s=timeout,
            tls_ca=pick(tls_ca, "RA2VIPAS_ZENOH_TLS_CA"),
            tls_cert=pick(tls_cert, "RA2VIPAS_ZENOH_TLS_CERT"),
            tls_key=pick(tls_key, "RA2VIPAS_ZENOH_TLS_KEY"),
            tls_mtls=_flag(pick(tls_mtls, "RA2VIPAS_ZENOH_TLS_MTLS"), "RA2VIPAS_ZENOH_TLS_MTLS", False),
            tls_verify_name=_flag(pick(tls_verify_name, "RA2VIPAS_ZENOH_TLS_VERIFY_NAME"), "RA2VIPAS_ZENOH_TLS_VERIFY_NAME", True),
            user=pick(user, "RA2VIPAS_ZENOH_USER"),
            password=password,
            credentials_file=pick(credentials_file, "RA2VIPAS_ZENOH_CREDENTIALS"),
        )

    def security_entries(self) -> dict:
        """The TLS and authentication part of the configuration: {Zenoh config key: value}.
        Only what is set is written, so a config file's own choices stand otherwise."""
        out: dict = {}
        if self.tls_ca:
            out[TLS_ROOT_CA] = self.tls_ca
        if self.tls_cert:  # one identity for both directions of a link
            out[TLS_LISTEN_CERT] = out[TLS_CONNECT_CERT] = self.tls_cert
            out[TLS_LISTEN_KEY] = out[TLS_CONNECT_KEY] = self.tls_key
        if self.tls_mtls:
            out[TLS_MTLS] = True
        if not self.tls_verify_name:
            out[TLS_VERIFY_NAME] = False
        if self.user is not None:
            out[AUTH_USER] = self.user
            out[AUTH_PASSWORD] = self.password
        if self.credentials_file:
            out[AUTH_DICTIONARY] = self.credentials_file
        return out

    def reach_warning(self) -> str | None:
        """``peer_reach_warning`` for the configuration this node opens with."""
        conf = self.to_zenoh()

        def endpoints(key: str) -> list[str]:  # a list, or one list per mode
            value = json.loads(conf.get_json(key))
            return list((value.get(self.mode) if isinstance(value, dict) else value) or [])

        return peer_reach_warning(self.mode, endpoints("connect/endpoints"), endpoints("listen/endpoints"))

    def to_zenoh(self):
        """The ``zenoh.Config``."""
        import zenoh

        conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        elif json.loads(conf.get_json("listen/endpoints")) == ZENOH_DEFAULT_LISTEN:  # nobody chose: loopback
            conf.insert_json5("listen/endpoints", json.dumps(LOOPBACK_LISTEN))
        if not self.config_file:  # a config file decides scouting itself
            conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        timeout = self.connect_timeout_s
        if timeout is None and not self.config_file:
            timeout = DEFAULT_CLIENT_CONNECT_TIMEOUT_S
        if self.mode == "client" and timeout is not None:  # peers and routers start without their endpoints anyway
            conf.insert_json5("connect/timeout_ms", json.dumps(int(timeout * 1000) if timeout >= 0 else -1))
        for key, value in {**self.security_entries(), **self.extra}.items():
            conf.insert_json5(key, json.dumps(value))
        return conf
