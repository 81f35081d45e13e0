"""CLI tests drive the real ``ra2vipas`` command (a subprocess) against a live API server
(the same fixtures as the API tests)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.api.conftest import TOKEN, done_campaign, guarded, live  # noqa: F401  (fixtures)

ROOT = Path(__file__).resolve().parents[2]


def ra2vipas(*args: str, env: dict | None = None, timeout: float = 120, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m ra2vipas.cli.main ARGS`` with RA2VIPAS_API/RA2VIPAS_TOKEN unset unless given."""
    full_env = {k: v for k, v in os.environ.items() if k not in ("RA2VIPAS_API", "RA2VIPAS_TOKEN")}
    full_env.update(env or {})
    full_env["PYTHONPATH"] = str(ROOT)
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", *args], capture_output=True, text=True, timeout=timeout,
                          env=full_env, cwd=cwd or ROOT)


def one_error_line(proc: subprocess.CompletedProcess) -> str:
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ") and "Traceback" not in proc.stderr
    return lines[0]
