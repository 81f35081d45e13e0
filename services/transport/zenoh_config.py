"""Zenoh settings shared by every service: one place turns flags and environment into a
``zenoh.Config`` (the zenoh-python ``examples/common/common.py`` idea).

Precedence: CLI flag > environment variable > default. Environment variables:
``RA2VIPAS_ZENOH_MODE`` (peer|client|router), ``RA2VIPAS_ZENOH_CONNECT`` and
``RA2VIPAS_ZENOH_LISTEN`` (comma-separated endpoints such as ``tcp/10.0.0.1:7447``),
``RA2VIPAS_ZENOH_CONFIG`` (a Zenoh JSON5 configuration file, applied first; the other
settings override it).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field

MODES = ("peer", "client", "router")
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/[^\s]+$")


class ZenohSettingsError(ValueError):
    """A Zenoh setting is invalid; the message names it."""


def _split(value: str | None) -> list[str]:
    return [v.strip() for v in (value or "").split(",") if v.strip()]


@dataclass(frozen=True)
class ZenohSettings:
    """How a process joins the Zenoh network."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    multicast_scouting: bool = False
    extra: dict = field(default_factory=dict)  # further JSON5 insertions, e.g. TLS or auth

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ZenohSettingsError(f"zenoh mode must be one of {'|'.join(MODES)}, got {self.mode!r}")
        for ep in (*self.connect, *self.listen):
            if not _ENDPOINT.match(ep):
                raise ZenohSettingsError(f"invalid Zenoh endpoint {ep!r} (expected e.g. tcp/127.0.0.1:7447)")
        if self.config_file is not None and not os.path.isfile(self.config_file):
            raise ZenohSettingsError(f"Zenoh config file {self.config_file!r} does not exist")

    @classmethod
    def from_sources(cls, mode: str | None = None, connect: list[str] | None = None, listen: list[str] | None = None,
                     config_file: str | None = None, env: dict | None = None) -> "ZenohSettings":
        """CLI values (None = not given) over environment over defaults."""
        env = os.environ if env is None else env
        return cls(
            mode=mode or env.get("RA2VIPAS_ZENOH_MODE") or "peer",
            connect=tuple(connect) if connect else tuple(_split(env.get("RA2VIPAS_ZENOH_CONNECT"))),
            listen=tuple(listen) if listen else tuple(_split(env.get("RA2VIPAS_ZENOH_LISTEN"))),
            config_file=config_file or env.get("RA2VIPAS_ZENOH_CONFIG") or None,
        )

    def to_zenoh(self):
        """The ``zenoh.Config``."""
        import zenoh

        conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        if not self.config_file:  # a config file decides scouting itself
            conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        for key, value in self.extra.items():
            conf.insert_json5(key, json.dumps(value))
        return conf
