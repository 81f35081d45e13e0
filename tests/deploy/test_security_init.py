"""`ra2vipas security init`: the files of a secured deployment, private, consistent with each
other and with what Zenoh and the services accept."""

from __future__ import annotations

import json
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from ra2vipas.cli.security import compose_services
from ra2vipas.services.transport.acl import access_control, standard_identities
from ra2vipas.services.transport.zenoh_config import ZenohSettings
from tests.deploy.conftest import ROOT, clean_env

USERS = ["orchestrator", "learner", "rig-1", "rig-2", "robot-1.sensors", "robot-1.controller", "lab"]


def init(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "security", "init", *args], capture_output=True, text=True, timeout=120,
                          cwd=cwd, env=clean_env({"PYTHONPATH": str(ROOT)}))


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("init") / "secrets"
    r = init("--rigs", "rig-1,rig-2", "--split-rigs", "robot-1", "--operator", "lab", "--out", str(out),
             "--router-host", "server.lab.example", "--router-host", "10.0.0.1", "--json")
    assert r.returncode == 0, r.stderr
    return out, r


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line and not line.startswith("#"))


def test_every_file_is_private(written):
    out, r = written
    report = json.loads(r.stdout.strip().splitlines()[-1])
    assert [i["user"] for i in report["identities"]] == USERS
    expected = {"ca.pem", "ca.key", "router.pem", "router.key", "credentials", "router.json5", "router.env", "docker-compose.rigs.yml"}
    expected |= {f"{u}.{ext}" for u in USERS for ext in ("pem", "key", "password", "env")}
    assert {p.name for p in out.iterdir()} == expected == set(report["files"])
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in out.iterdir())


def test_one_strong_password_per_identity_known_to_the_router_and_never_printed(written):
    out, r = written
    passwords = {u: (out / f"{u}.password").read_text().strip() for u in USERS}
    assert len(set(passwords.values())) == len(USERS) and all(len(p) >= 32 for p in passwords.values())
    assert (out / "credentials").read_text().splitlines() == [f"{u}:{passwords[u]}" for u in USERS]
    for p in passwords.values():
        assert p not in r.stdout and p not in r.stderr
        assert not any(p in (out / f"{u}.env").read_text() for u in USERS)


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_certificates_name_their_identity_and_the_router_its_hosts(written):
    out, _ = written
    ca = _cert(out / "ca.pem")
    for name in [*USERS, "router"]:
        cert = _cert(out / f"{name}.pem")
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
    sans = _cert(out / "router.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sans.get_values_for_type(x509.DNSName) == ["router", "server.lab.example"]
    assert [str(a) for a in sans.get_values_for_type(x509.IPAddress)] == ["10.0.0.1"]


def test_the_router_config_is_zenohs_and_holds_the_policy(written):
    out, _ = written
    conf = zenoh.Config.from_file(str(out / "router.json5"))
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    text = (out / "router.json5").read_text()
    config = json.loads("\n".join(line for line in text.splitlines() if not line.startswith("//")))
    identities = standard_identities(["rig-1", "rig-2"], ["robot-1"], ["lab"])
    assert config["access_control"] == access_control(identities, match="both")
    assert str(out) not in text, "no file paths: zenohd and ra2vipas router add their own"


def test_each_env_file_configures_a_client_with_its_own_identity(written):
    out, _ = written
    for user in USERS:
        env = read_env(out / f"{user}.env")
        assert env["RA2VIPAS_ZENOH_CONNECT"] == "tls/server.lab.example:7447"
        settings = ZenohSettings.from_sources(env=env)  # every file it names exists
        assert (settings.mode, settings.user, settings.tls_mtls) == ("client", user, True)
        assert settings.password == (out / f"{user}.password").read_text().strip()
        assert Path(settings.tls_cert).name == f"{user}.pem" and Path(settings.tls_ca).name == "ca.pem"
        settings.to_zenoh()
    assert read_env(out / "rig-1.env")["RA2VIPAS_RIG"] == "rig-1"
    assert read_env(out / "robot-1.controller.env")["RA2VIPAS_RIG"] == "robot-1"
    router = ZenohSettings.from_sources(mode="router", env=read_env(out / "router.env"))
    assert router.listen == ("tls/0.0.0.0:7447",) and router.credentials_file == str((out / "credentials").resolve())
    router.to_zenoh()
    assert "ca.key" not in "".join(p.read_text() for p in out.glob("*.env"))


def test_the_compose_rigs_file_names_each_rig_with_only_its_own_secrets(written):
    out, _ = written
    compose = yaml.safe_load((out / "docker-compose.rigs.yml").read_text())
    identities = standard_identities(["rig-1", "rig-2"], ["robot-1"], ["lab"])
    assert compose == yaml.safe_load(compose_services(identities, str(out.resolve())))
    services = compose["services"]
    assert services["orchestrator"]["environment"] == {"RA2VIPAS_EXPECT_RIGS": "3"}
    expected = {"rig-1": ("rig", "rig-1"), "rig-2": ("rig", "rig-2"), "robot-1-sensors": ("sensors", "robot-1.sensors"),
                "robot-1-controller": ("controller", "robot-1.controller")}
    assert set(services) - {"orchestrator"} == set(expected)
    for name, (command, user) in expected.items():
        svc = services[name]
        assert svc["command"] == ["ra2vipas", command]
        assert svc["environment"]["RA2VIPAS_ZENOH_USER"] == user
        assert svc["secrets"] == ["ca.pem", f"{user}.pem", f"{user}.key", f"{user}.password"]


def test_existing_files_are_kept_unless_forced(tmp_path):
    out = tmp_path / "s"
    assert init("--rigs", "rig-1", "--out", str(out)).returncode == 0
    before = (out / "rig-1.password").read_text()
    again = init("--rigs", "rig-1", "--out", str(out))
    assert again.returncode == 1 and again.stderr.strip().splitlines()[-1].startswith("error: ") and "--force" in again.stderr
    assert (out / "rig-1.password").read_text() == before
    assert init("--rigs", "rig-1", "--out", str(out), "--force").returncode == 0
    assert (out / "rig-1.password").read_text() != before


def test_owner_gives_the_files_to_the_containers_user(tmp_path):
    out = tmp_path / "s"
    r = init("--rigs", "rig-1", "--out", str(out), "--owner", "10001")
    assert r.returncode == 0, r.stderr
    assert out.stat().st_uid == 10001 and all(p.stat().st_uid == 10001 and p.stat().st_gid == 10001 for p in out.iterdir())


@pytest.mark.parametrize("args, message", [
    ([], "name at least one rig"),
    (["--rigs", "rig/1"], "rig 'rig/1' must be"),
    (["--rigs", "rig-1,rig-1"], "unique"),
    (["--rigs", "router"], "clashes with a compose service"),
    (["--rigs", "rig-1", "--owner", "me"], "--owner"),
])
def test_bad_usage_is_one_line_and_exit_2(tmp_path, args, message):
    r = init(*args, "--out", str(tmp_path / "s"))
    assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())
