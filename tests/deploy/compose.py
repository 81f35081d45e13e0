"""Reading docker-compose.yml the way Docker Compose does, without a Docker engine: YAML with
merge keys, ``${VAR}`` interpolation, override files, and each service's command and
environment turned into the ``ra2vipas`` command line a test can run."""

from __future__ import annotations

import copy
import re
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
COMPOSE_FILE = ROOT / "docker-compose.yml"
TLS_OVERRIDE_FILE = ROOT / "docker-compose.tls.yml"
COMPOSE_SCHEMA = ROOT.parent / "shared" / "schemas" / "compose-spec.json"

# ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?error}, ${VAR?error}, $VAR, and $$ (a literal $)
_VAR = re.compile(r"\$(?:(\$)|\{(?P<braced>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?[-?])(?P<arg>[^}]*))?\}|(?P<bare>[A-Za-z_][A-Za-z0-9_]*))")


class InterpolationError(ValueError):
    pass


def interpolate(value, env: dict):
    """Compose's variable substitution applied to every string in ``value``."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def sub(m: re.Match) -> str:
        if m.group(1):
            return "$"
        name = m.group("braced") or m.group("bare")
        op, arg = m.group("op"), m.group("arg") or ""
        current = env.get(name)
        missing = current is None or (op is not None and op.startswith(":") and current == "")
        if op in (":-", "-"):
            return arg if missing else current
        if op in (":?", "?"):
            if missing:
                raise InterpolationError(f"{name}: {arg}")
            return current
        return current or ""

    return _VAR.sub(sub, value)


def generated_rigs(rigs: tuple[str, ...] = ("rig-1", "rig-2"), split_rigs: tuple[str, ...] = ("robot-1",)) -> dict:
    """The ``docker-compose.rigs.yml`` that ``ra2vipas security init --rigs ... --split-rigs ...``
    writes into ./secrets (the same function writes it)."""
    from ra2vipas.cli.security import compose_services
    from ra2vipas.services.transport.acl import standard_identities

    return yaml.safe_load(compose_services(standard_identities(list(rigs), list(split_rigs)), "./secrets"))


def load(path: Path = COMPOSE_FILE) -> dict:
    """The compose file as YAML gives it (merge keys ``<<`` resolved, variables not)."""
    return yaml.safe_load(path.read_text())


def merge(base: dict, override: dict) -> dict:
    """``docker compose -f base -f override``, for the keys this project uses: mappings
    merge key by key, ``command`` and other sequences are replaced, ``volumes``, ``ports`` and
    ``secrets`` of a service are appended."""
    out = copy.deepcopy(base)

    def go(a: dict, b: dict, path: tuple) -> None:
        for key, value in b.items():
            if isinstance(value, dict) and isinstance(a.get(key), dict):
                go(a[key], value, (*path, key))
            elif isinstance(value, list) and isinstance(a.get(key), list) and key in ("volumes", "ports", "secrets") and len(path) == 2:
                a[key] = a[key] + [v for v in value if v not in a[key]]
            else:
                a[key] = copy.deepcopy(value)

    go(out, override, ())
    return out


def environment(service: dict) -> dict[str, str]:
    """A service's ``environment`` as a dict of strings (list form ``KEY=VALUE`` accepted)."""
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.split("=", 1) if "=" in item else (item, "") for item in env)
    return {k: "" if v is None else str(v) for k, v in env.items()}


def ra2vipas_argv(service: dict) -> list[str]:
    """The service's command as an argv for this interpreter: ``ra2vipas X ...`` ->
    ``python -m ra2vipas.cli.main X ...``."""
    command = service["command"]
    assert isinstance(command, list) and command[0] == "ra2vipas", f"expected ['ra2vipas', ...], got {command!r}"
    return [sys.executable, "-m", "ra2vipas.cli.main", *command[1:]]


def our_services(compose: dict) -> dict[str, dict]:
    """The services built from this repository's Dockerfile."""
    return {name: svc for name, svc in compose["services"].items() if "build" in svc}
