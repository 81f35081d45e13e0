"""The orchestrator's settings: CLI flag > environment > default, built once in ``main()``."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

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
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)

    @classmethod
    def from_sources(cls, *, host: str | None = None, port: int | None = None, db_path: str | None = None,
                     window: int | None = None, expect_rigs: int | None = None, token: str | None = None,
                     zenoh: ZenohSettings | None = None, env: dict | None = None) -> "OrchestratorSettings":
        env = os.environ if env is None else env
        return cls(
            host=host or env.get("RA2VIPAS_HOST") or "127.0.0.1",
            port=int(port or env.get("RA2VIPAS_PORT") or 8080),
            db_path=db_path or env.get("RA2VIPAS_DB") or "ra2vipas.db",
            window=int(window or env.get("RA2VIPAS_WINDOW") or 8),
            expect_rigs=int(expect_rigs if expect_rigs is not None else env.get("RA2VIPAS_EXPECT_RIGS") or 1),
            token=token or env.get("RA2VIPAS_TOKEN") or None,
            zenoh=zenoh or ZenohSettings.from_sources(env=env),
        )
