"""The orchestrator's settings: CLI flag > environment > default, built once in ``main()``."""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ra2vipas.services.transport.zenoh_config import ZenohSettings


@dataclass(frozen=True)
class OrchestratorSettings:
    host: str = "127.0.0.1"
    port: int = 8080
    db_path: str = "ra2vipas.db"
    window: int = 8  # episodes in flight per rig
    expect_rigs: int = 1  # /health is 200 once this many rigs (and a learner) are live
    token: str | None = None  # RA2VIPAS_TOKEN: bearer token required by state-changing requests
    name: str = "orchestrator"
    plot_workers: int = 1  # RA2VIPAS_PLOT_WORKERS: figure renderer processes (from_sources: default_plot_workers())
    plot_rate: float = 40.0  # RA2VIPAS_PLOT_RATE: figure requests served per second (beyond: 503 + Retry-After)
    # RA2VIPAS_INSTANCE_ID: shown by /health, so `ra2vipas up` knows it reached its own orchestrator
    instance_id: str = field(default_factory=lambda: secrets.token_hex(8))
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    # RA2VIPAS_SUPERVISOR_STATUS: the JSON file where `ra2vipas up` says which of its services it is
    # restarting or backing off (shown by GET /rigs and the rigs page); None outside `up`
    supervisor_status: str | None = None
    # what one HTTP client can hold (api/guard.py): RA2VIPAS_MAX_CONNECTIONS (all clients; never more
    # than the file descriptor limit allows), RA2VIPAS_MAX_CONNECTIONS_PER_CLIENT (per address) and
    # RA2VIPAS_HEADER_TIMEOUT (seconds for a request's line and headers to arrive)
    max_connections: int = 1000
    max_connections_per_client: int = 256
    header_timeout_s: float = 10.0

    @classmethod
    def from_sources(cls, *, host: str | None = None, port: int | None = None, db_path: str | None = None,
                     window: int | None = None, expect_rigs: int | None = None, token: str | None = None,
                     plot_workers: int | None = None, zenoh: ZenohSettings | None = None,
                     env: dict | None = None) -> "OrchestratorSettings":
        """CLI flag > environment (``RA2VIPAS_*``) > default, validated by pydantic.

        Raises
        ------
        SettingsError
            A value out of range or not a number: one line naming the flag or variable.
        """
        env = os.environ if env is None else env
        given = {"host": host, "port": port, "db_path": db_path, "window": window, "expect_rigs": expect_rigs,
                 "plot_workers": plot_workers, "plot_rate": None, "max_connections": None, "max_connections_per_client": None,
                 "header_timeout_s": None}
        raw: dict[str, object] = {}
        where: dict[str, str] = {}
        for name, value in given.items():
            if value is not None:
                raw[name], where[name] = value, f"--{name.replace('_path', '').replace('_', '-')}"
            elif env.get(ENV[name]):
                raw[name], where[name] = env[ENV[name]], ENV[name]
        try:
            checked = _Checked.model_validate(raw)
        except ValidationError as err:
            first = err.errors()[0]
            name = str(first["loc"][0])
            raise SettingsError(f"{where.get(name, name)}: {first['msg'].lower()}, got {first.get('input')!r}") from None
        return cls(
            host=checked.host, port=checked.port, db_path=checked.db_path, window=checked.window, expect_rigs=checked.expect_rigs,
            token=token or env.get("RA2VIPAS_TOKEN") or None,
            plot_workers=checked.plot_workers or default_plot_workers(), plot_rate=checked.plot_rate,
            instance_id=env.get("RA2VIPAS_INSTANCE_ID") or secrets.token_hex(8),
            zenoh=zenoh or ZenohSettings.from_sources(env=env),
            supervisor_status=env.get("RA2VIPAS_SUPERVISOR_STATUS") or None,
            max_connections=checked.max_connections, max_connections_per_client=checked.max_connections_per_client,
            header_timeout_s=checked.header_timeout_s,
        )


class SettingsError(ValueError):
    """A setting is invalid; the message is one line naming it."""


ENV = {"host": "RA2VIPAS_HOST", "port": "RA2VIPAS_PORT", "db_path": "RA2VIPAS_DB", "window": "RA2VIPAS_WINDOW",
       "expect_rigs": "RA2VIPAS_EXPECT_RIGS", "plot_workers": "RA2VIPAS_PLOT_WORKERS", "plot_rate": "RA2VIPAS_PLOT_RATE",
       "max_connections": "RA2VIPAS_MAX_CONNECTIONS", "max_connections_per_client": "RA2VIPAS_MAX_CONNECTIONS_PER_CLIENT",
       "header_timeout_s": "RA2VIPAS_HEADER_TIMEOUT"}


class _Checked(BaseModel):
    """The orchestrator's settings as they arrive (strings from the environment are parsed)."""

    model_config = ConfigDict(extra="forbid")
    host: str = Field("127.0.0.1", min_length=1)
    port: int = Field(8080, ge=1, le=65535)
    db_path: str = Field("ra2vipas.db", min_length=1)
    window: int = Field(8, ge=1, le=1024)
    expect_rigs: int = Field(1, ge=0, le=1000)
    plot_workers: int | None = Field(None, ge=1, le=64)
    plot_rate: float = Field(40.0, gt=0, le=100000)
    max_connections: int = Field(1000, ge=16, le=100000)
    max_connections_per_client: int = Field(256, ge=1, le=100000)
    header_timeout_s: float = Field(10.0, gt=0, le=3600)


def default_plot_workers() -> int:
    """Figure renderer processes: one per two cores (1 on a 2-core machine), at most 4."""
    return max(1, min(4, (os.cpu_count() or 2) // 2))
