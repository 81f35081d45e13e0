"""docker-compose.yml (and docker-compose.tls.yml over it) checked without a Docker engine:
valid against the Compose specification's JSON Schema, every command one the ``ra2vipas``
CLI parses, every RA2VIPAS_* variable one the service it is given to reads, every file it
names mounted into the container, and the router pinned to the Zenoh version of the binding."""

from __future__ import annotations

import ast
import copy
import importlib.metadata
import json
import os
import re
import tomllib
from pathlib import Path

import jsonschema
import pytest
import typer
import zenoh

from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from ra2vipas.services.protocol.keys import check_chunk
from ra2vipas.services.transport.zenoh_config import ZenohSettings
from tests.deploy.compose import (
    COMPOSE_SCHEMA,
    ROOT,
    TLS_OVERRIDE_FILE,
    InterpolationError,
    environment,
    generated_rigs,
    interpolate,
    load,
    merge,
    our_services,
)

VARS = {"RA2VIPAS_TOKEN": "compose-test-token"}  # what an operator's .env must provide
# zenohd's command-line options (eclipse-zenoh/zenoh, zenohd/src/main.rs, 1.x)
ZENOHD_OPTIONS = {"-c", "--config", "-l", "--listen", "-e", "--connect", "-i", "--id", "-P", "--plugin", "--plugin-search-dir",
                  "--no-timestamp", "--no-multicast-scouting", "--rest-http-port", "--cfg", "--adminspace-permissions"}
# environment variables whose value is a file or directory inside the container
PATH_VARS = {"RA2VIPAS_DB", "RA2VIPAS_MODEL_CACHE", "RA2VIPAS_ZENOH_CONFIG", "RA2VIPAS_ZENOH_TLS_CA", "RA2VIPAS_ZENOH_TLS_CERT",
             "RA2VIPAS_ZENOH_TLS_KEY", "RA2VIPAS_ZENOH_CREDENTIALS", "RA2VIPAS_ZENOH_PASSWORD_FILE"}


SECURED = "docker-compose.yml + docker-compose.tls.yml + secrets/docker-compose.rigs.yml"


def variants() -> dict[str, dict]:
    base = load()
    return {"docker-compose.yml": base, SECURED: merge(merge(base, load(TLS_OVERRIDE_FILE)), generated_rigs())}


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft7Validator:
    if not COMPOSE_SCHEMA.is_file():
        pytest.fail(f"the Compose specification schema is missing: expected {COMPOSE_SCHEMA} (../shared/schemas beside the repository)")
    schema = json.loads(COMPOSE_SCHEMA.read_text())
    jsonschema.Draft7Validator.check_schema(schema)
    return jsonschema.Draft7Validator(schema)


def string_constants(path: Path) -> set[str]:
    """Every RA2VIPAS_* name the module uses as a string literal (what it reads)."""
    tree = ast.parse(path.read_text())
    return {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
            and re.fullmatch(r"RA2VIPAS_[A-Z0-9_]+", n.value)}


ZENOH_VARS = string_constants(ROOT / "services/transport/zenoh_config.py")
ORCHESTRATOR_VARS = string_constants(ROOT / "services/orchestrator/settings.py")


def click_command(args: list[str]):
    """The Click command ``ra2vipas ARGS`` runs (Typer's own copy of Click), its name and its
    own arguments."""
    from ra2vipas.cli.main import app

    cmd = typer.main.get_command(app)
    name = "ra2vipas"
    while hasattr(cmd, "commands"):  # a group
        assert args and args[0] in cmd.commands, f"`{name}` has no command {args[:1]}; it has {sorted(cmd.commands)}"
        name, cmd, args = args[0], cmd.commands[args[0]], args[1:]
    return name, cmd, args


def variables_read_by(name: str, cmd) -> set[str]:
    names = set(ZENOH_VARS)  # every service builds its Zenoh settings from the environment
    for p in cmd.params:
        envvar = getattr(p, "envvar", None)
        names.update([envvar] if isinstance(envvar, str) else (envvar or []))
    if name == "orchestrator":
        names |= ORCHESTRATOR_VARS
    return names


def mount_targets(compose: dict, service: dict) -> list[str]:
    targets = []
    for volume in service.get("volumes", []):
        source, target = volume.split(":")[:2]
        if not source.startswith((".", "/")):
            assert source in (compose.get("volumes") or {}), f"named volume {source!r} is not declared under volumes:"
        targets.append(target)
    targets += [f"/run/secrets/{s if isinstance(s, str) else s['source']}" for s in service.get("secrets", [])]
    return targets


def materialize(env: dict[str, str], tmp: Path) -> dict[str, str]:
    """The environment with every container file path replaced by a file here, so settings
    that check their files exist can be built."""
    out = dict(env)
    for var in PATH_VARS & env.keys():
        if var in ("RA2VIPAS_DB", "RA2VIPAS_MODEL_CACHE"):
            out[var] = str(tmp / var.lower())
            continue
        path = tmp / var.lower()
        path.write_text("placeholder-secret\n")
        out[var] = str(path)
    return out


def test_compose_files_follow_the_compose_specification(validator):
    for name, compose in variants().items():
        for form, doc in (("as written", compose), ("interpolated", interpolate(compose, VARS))):
            errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(doc)]
            assert not errors, f"{name} ({form}) is not a valid Compose file:\n" + "\n".join(errors)
    for override in (load(TLS_OVERRIDE_FILE), generated_rigs()):
        errors = list(validator.iter_errors(override))
        assert not errors, errors[0].message


def test_the_schema_check_can_fail(validator):
    broken = copy.deepcopy(load())
    broken["services"]["rig"]["replica"] = 2  # a typo of `deploy: replicas`
    assert list(validator.iter_errors(broken))
    broken = copy.deepcopy(load())
    broken["services"]["orchestrator"]["environment"]["RA2VIPAS_PORT"] = [8080]
    assert list(validator.iter_errors(broken))


@pytest.mark.parametrize("variant", sorted(variants()))
def test_every_command_and_variable_is_one_the_cli_accepts(variant, monkeypatch, tmp_path):
    compose = interpolate(variants()[variant], VARS)
    services = our_services(compose)
    assert {"orchestrator", "learner", "rig", "sensors", "controller"} <= services.keys()
    for svc_name, svc in services.items():
        command = svc["command"]
        assert isinstance(command, list) and command[0] == "ra2vipas", f"{svc_name}: command must be ['ra2vipas', ...]"
        name, cmd, args = click_command(command[1:])
        env = environment(svc)
        unread = set(env) - variables_read_by(name, cmd)
        assert not unread, f"{svc_name}: `ra2vipas {name}` does not read {sorted(unread)}"
        for var in PATH_VARS & env.keys():
            assert any(env[var] == t or env[var].startswith(t.rstrip("/") + "/") for t in mount_targets(compose, svc)), \
                f"{svc_name}: {var}={env[var]} is not on a volume, bind mount or secret of the service"
        env = materialize(env, tmp_path)
        with monkeypatch.context() as m:
            for var in [v for v in os.environ if v.startswith("RA2VIPAS_")]:
                m.delenv(var)
            for var, value in env.items():
                m.setenv(var, value)
            try:
                ctx = cmd.make_context(f"ra2vipas {name}", list(args))  # raises on unknown options or bad values
            except Exception as err:  # Click's UsageError / BadParameter
                message = err.format_message() if hasattr(err, "format_message") else repr(err)
                pytest.fail(f"{svc_name}: `{' '.join(command)}` is rejected by the CLI: {message}")
            if "RA2VIPAS_RIG" in env:
                assert ctx.params["rig"] == env["RA2VIPAS_RIG"]
            if "RA2VIPAS_MODEL_CACHE" in env:
                assert ctx.params["cache_dir"] == env["RA2VIPAS_MODEL_CACHE"]
        zenoh_settings = ZenohSettings.from_sources(env=env)  # raises on a bad mode, endpoint or credentials
        zenoh_settings.to_zenoh()  # every security key is one Zenoh knows
        assert zenoh_settings.mode == "client" and zenoh_settings.connect, f"{svc_name}: must join the router as a client"
        if name == "orchestrator":
            settings = OrchestratorSettings.from_sources(env=env)
            assert settings.host == "0.0.0.0" and settings.token == VARS["RA2VIPAS_TOKEN"]
            assert any(p.endswith(f":{settings.port}") for p in svc["ports"]), "the API port must be published"
        if name in ("sensors", "controller"):
            check_chunk(env["RA2VIPAS_RIG"])


def test_the_router_is_the_official_image_at_the_bindings_version():
    binding = importlib.metadata.version("eclipse-zenoh")
    for variant, compose in variants().items():
        router = compose["services"]["router"]
        assert router["image"] == f"eclipse/zenoh:{binding}", f"{variant}: pin eclipse/zenoh to the binding's version {binding}"
        command = router["command"]
        options = {arg.split("=", 1)[0] for arg in command if arg.startswith("-")}
        assert options <= ZENOHD_OPTIONS, f"{variant}: zenohd has no option {sorted(options - ZENOHD_OPTIONS)}"
        listens = {command[i + 1] for i, arg in enumerate(command) if arg in ("--listen", "-l")}
        conf = zenoh.Config()
        for arg in command:
            if arg.startswith("--cfg="):
                key, value = arg[len("--cfg="):].split(":", 1)
                conf.insert_json5(key, value)  # raises on a key or value this Zenoh does not know
        # every service that runs reaches the router by its compose name, on a protocol and port it listens on
        for svc_name, svc in our_services(interpolate(compose, VARS)).items():
            if str(svc.get("deploy", {}).get("replicas", 1)) == "0":
                continue
            for ep in environment(svc)["RA2VIPAS_ZENOH_CONNECT"].split(","):
                proto, address = ep.split("/", 1)
                host, port = address.rsplit(":", 1)
                assert host in compose["services"], f"{variant}: {svc_name} connects to unknown host {host!r}"
                assert any(x.startswith(f"{proto}/") and x.endswith(f":{port}") for x in listens), \
                    f"{variant}: {svc_name} connects to {ep} but the router listens on {sorted(listens)}"


def test_the_api_token_is_required_and_rigs_scale_by_replicas():
    compose = load()
    with pytest.raises(InterpolationError, match="RA2VIPAS_TOKEN"):
        interpolate(compose, {})
    rig = compose["services"]["rig"]
    assert rig["command"] == ["ra2vipas", "rig"]
    assert "RA2VIPAS_RIG" not in environment(rig), "replicas must name themselves (after their host name)"
    expect = environment(compose["services"]["orchestrator"])["RA2VIPAS_EXPECT_RIGS"]
    assert rig["deploy"]["replicas"] == expect, "/health must expect as many rigs as there are replicas"
    assert int(interpolate(expect, VARS)) >= 1
    db = environment(compose["services"]["orchestrator"])["RA2VIPAS_DB"]
    assert any(db.startswith(t + "/") for t in mount_targets(compose, compose["services"]["orchestrator"])), "the SQLite file must be on a volume"


def test_the_image_installs_the_project():
    lines = [ln.strip() for ln in (ROOT / "Dockerfile").read_text().splitlines() if ln.strip() and not ln.strip().startswith("#")]
    assert lines[0] == "FROM python:3.11-slim"
    copied = {part.rstrip("/") for ln in lines if ln.startswith("COPY") for part in ln.split()[1:-1]}
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = set(project["tool"]["setuptools"]["package-dir"].values())  # the folders the packages come from
    assert packages | {"pyproject.toml", project["project"]["readme"]} <= copied, f"the image must get {sorted(packages)} and the project files"
    assert any("pip install -c constraints.txt ." in ln for ln in lines), "the image installs the pinned versions the tests ran"
    assert "constraints.txt" in copied
    ignored = {ln.strip() for ln in (ROOT / ".dockerignore").read_text().splitlines()}
    assert {".git", ".venv"} <= ignored
    assert not ({"ra2vipas", "services", "cli", "pyproject.toml", "README.md", "constraints.txt"} & ignored)


def test_the_secured_deployment_names_every_rig_and_gives_each_service_only_its_own_secrets():
    compose = interpolate(variants()[SECURED], VARS)
    services = compose["services"]
    router = services["router"]
    command = router["command"]
    assert command[command.index("-c") + 1] == "/run/secrets/router.json5" and "router.json5" in router["secrets"]
    assert [c for c in command if c.startswith("--listen") or c.startswith("tls/")] == ["--listen", "tls/0.0.0.0:7447"]
    for replicated in ("rig", "sensors", "controller"):  # replicas cannot hold one identity each
        assert services[replicated]["deploy"]["replicas"] == 0
    running = {name: svc for name, svc in our_services(compose).items() if svc.get("deploy", {}).get("replicas", 1) != 0}
    assert set(running) == {"orchestrator", "learner", "rig-1", "rig-2", "robot-1-sensors", "robot-1-controller"}
    for name, svc in running.items():
        env = environment(svc)
        user = env["RA2VIPAS_ZENOH_USER"]
        assert env["RA2VIPAS_ZENOH_TLS_MTLS"] == "true" and env["RA2VIPAS_ZENOH_CONNECT"] == "tls/router:7447"
        assert sorted(svc["secrets"]) == sorted(["ca.pem", f"{user}.pem", f"{user}.key", f"{user}.password"]), name
        if "RA2VIPAS_RIG" in env:
            assert user in (env["RA2VIPAS_RIG"], f"{env['RA2VIPAS_RIG']}.{svc['command'][1]}")
    assert environment(services["orchestrator"])["RA2VIPAS_EXPECT_RIGS"] == "3"
    assert all(s["file"].startswith("./secrets/") for s in compose["secrets"].values())
