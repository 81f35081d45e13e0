"""The orchestrator's settings: CLI flag > environment > default, built once in ``main()``."""

from __future__ import annotations

import os
import secrets
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
    plot_workers: int = 1  # RA2VIPAS_PLOT_WORKERS: figure renderer processes (from_sources: default_plot_workers())
    # RA2VIPAS_INSTANCE_ID: shown by /health, so `ra2vipas up` knows it reached its own orchestrator
    instance_id: str = field(default_factory=lambda: secrets.token_hex(8))
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)

    @classmethod
    def from_sources(cls, *, host: str | None = None, port: int | None = None, db_path: str | None = None,
                     window: int | None = None, expect_rigs: int | None = None, token: str | None = None,
                     plot_workers: int | None = None, zenoh: ZenohSettings | None = None,
                     env: dict | None = None) -> "OrchestratorSettings":
        env = os.environ if env is None else env
        workers = int(plot_workers or env.get("RA2VIPAS_PLOT_WORKERS") or default_plot_workers())
        if workers < 1:
            raise ValueError(f"RA2VIPAS_PLOT_WORKERS: expected an integer >= 1, got {workers}")
        return cls(
            host=host or env.get("RA2VIPAS_HOST") or "127.0.0.1",
            port=int(port or env.get("RA2VIPAS_PORT") or 8080),
            db_path=db_path or env.get("RA2VIPAS_DB") or "ra2vipas.db",
            window=int(window or env.get("RA2VIPAS_WINDOW") or 8),
            expect_rigs=int(expect_rigs if expect_rigs is not None else env.get("RA2VIPAS_EXPECT_RIGS") or 1),
            token=token or env.get("RA2VIPAS_TOKEN") or None,
            plot_workers=workers,
            instance_id=env.get("RA2VIPAS_INSTANCE_ID") or secrets.token_hex(8),
            zenoh=zenoh or ZenohSettings.from_sources(env=env),
        )


def default_plot_workers() -> int:
    """Figure renderer processes: one per two cores (1 on a 2-core machine), at most 4."""
    return max(1, min(4, (os.cpu_count() or 2) // 2))
