"""``ra2vipas security init``: everything a secured deployment needs, written to one private
directory.

The secured deployment (docs/deployment.md, "Security"): every service is a Zenoh *client*
of one router; every link is mutual TLS; every service authenticates with its own identity
(a user name and password, and a certificate whose common name is the same user name); the
router's access control lets each identity do only what its role needs, on its own keys
(``services/transport/acl.py``). ``init`` writes, all files 0600 in a 0700 directory:

``ca.pem``, ``ca.key``
    the certificate authority (keep ``ca.key`` off the machines; it only signs).
``router.pem``, ``router.key``
    the router's certificate, naming ``router`` (the compose service) and every
    ``--router-host``.
``USER.pem``, ``USER.key``, ``USER.password``, ``USER.env``
    per identity: its certificate (common name USER), its password, and the environment of
    a bare process using it (``set -a; . DIR/USER.env; set +a; ra2vipas rig``).
``credentials``
    the router's ``user:password`` lines.
``router.json5``, ``router.env``
    the router's Zenoh configuration (mode, mutual TLS, access control; no file paths, so
    the official ``zenohd`` and ``ra2vipas router`` share it) and a bare router's
    environment (the file paths, the listener).
``docker-compose.rigs.yml``
    the compose services of the rigs, one per rig identity (with ``docker-compose.yml`` and
    ``docker-compose.tls.yml``).

Identities: ``orchestrator``, ``learner``, one per ``--rigs`` name (role ``rig``: sensors
and controller of that rig, as ``ra2vipas rig`` runs them), ``RIG.sensors`` and
``RIG.controller`` per ``--split-rigs`` name, and one per ``--operator``.
Passwords never go to stdout, a log or a command line.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import secrets
from pathlib import Path
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail, print_json, stderr

app = typer.Typer(help="Credentials, certificates and Zenoh access control for a secured deployment.", no_args_is_help=True)

ROUTER_SERVICE = "router"
COMPOSE_SERVICES = ("router", "orchestrator", "learner", "rig", "sensors", "controller")  # docker-compose.yml's own
SECRETS_IN_CONTAINER = "/run/secrets"
COMPOSE_FILE = "docker-compose.rigs.yml"


def _split_names(value: str, what: str) -> list[str]:
    from ra2vipas.services.protocol.keys import check_chunk

    names = [v.strip() for v in value.split(",") if v.strip()]
    for name in names:
        try:
            check_chunk(name, what)
        except ValueError as err:
            fail(str(err), EXIT_USAGE)
    return names


class _Writer:
    """Writes files 0600 into a 0700 directory and remembers them."""

    def __init__(self, directory: Path, owner: tuple[int, int] | None) -> None:
        self.dir = directory
        self.owner = owner
        self.files: list[Path] = []

    def write(self, name: str, data: str | bytes) -> Path:
        path = self.dir / name
        if path.exists():
            path.unlink()
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        if self.owner is not None:
            os.chown(path, *self.owner)
        self.files.append(path)
        return path


class _CertificateAuthority:
    """An EC P-256 certificate authority (``cryptography``) issuing TLS certificates."""

    def __init__(self, days: int) -> None:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import NameOID

        self.days = days
        self.key = ec.generate_private_key(ec.SECP256R1())
        self.name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ra2vipas CA")])
        now = datetime.datetime.now(datetime.timezone.utc)
        self.cert = (x509.CertificateBuilder().subject_name(self.name).issuer_name(self.name).public_key(self.key.public_key())
                     .serial_number(x509.random_serial_number())
                     .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
                     .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                     .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                                                  key_encipherment=False, data_encipherment=False, key_agreement=False,
                                                  encipher_only=False, decipher_only=False), critical=True)
                     .sign(self.key, hashes.SHA256()))

    def issue(self, common_name: str, hosts: list[str] = ()) -> tuple[bytes, bytes]:
        """(certificate PEM, PKCS#8 private key PEM) for ``common_name``, valid for TLS
        servers and clients, naming ``hosts`` (DNS names or IP addresses)."""
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

        key = ec.generate_private_key(ec.SECP256R1())
        now = datetime.datetime.now(datetime.timezone.utc)
        names = []
        for host in hosts:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                names.append(x509.DNSName(host))
        builder = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
                   .issuer_name(self.name).public_key(key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=self.days))
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                   .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False))
        if names:
            builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
        cert = builder.sign(self.key, hashes.SHA256())
        return (cert.public_bytes(serialization.Encoding.PEM),
                key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))

    def pem(self) -> tuple[bytes, bytes]:
        from cryptography.hazmat.primitives import serialization

        return (self.cert.public_bytes(serialization.Encoding.PEM),
                self.key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))


def router_config(access_control: dict) -> str:
    """The router's Zenoh configuration (JSON5): router mode, no multicast scouting, mutual TLS,
    the access control. No file paths and no listener: ``router.env`` (a bare router) or the
    compose command (``zenohd --cfg``) add them."""
    config = {"mode": "router", "scouting": {"multicast": {"enabled": False}},
              "transport": {"link": {"tls": {"enable_mtls": True}}}, "access_control": access_control}
    return ("// Zenoh router configuration written by `ra2vipas security init` (docs/deployment.md).\n"
            "// Access control: services/transport/acl.py. TLS files, the credentials file and the listener\n"
            "// come from router.env (ra2vipas router) or the zenohd command line (docker-compose.tls.yml).\n"
            + json.dumps(config, indent=2) + "\n")


def identity_env(identity, directory: str, connect: str) -> dict[str, str]:
    """The RA2VIPAS_* environment of a service using ``identity``, its files under ``directory``."""
    env = {
        "RA2VIPAS_ZENOH_MODE": "client",
        "RA2VIPAS_ZENOH_CONNECT": connect,
        "RA2VIPAS_ZENOH_TLS_CA": f"{directory}/ca.pem",
        "RA2VIPAS_ZENOH_TLS_CERT": f"{directory}/{identity.user}.pem",
        "RA2VIPAS_ZENOH_TLS_KEY": f"{directory}/{identity.user}.key",
        "RA2VIPAS_ZENOH_TLS_MTLS": "true",
        "RA2VIPAS_ZENOH_USER": identity.user,
        "RA2VIPAS_ZENOH_PASSWORD_FILE": f"{directory}/{identity.user}.password",
    }
    if identity.role in ("sensors", "controller", "rig"):
        env["RA2VIPAS_RIG"] = identity.name
    elif identity.role == "learner":
        env["RA2VIPAS_LEARNER_NAME"] = identity.name
    return env


def _env_file(title: str, env: dict[str, str]) -> str:
    return f"# {title}\n" + "".join(f"{k}={v}\n" for k, v in env.items())


COMMANDS = {"rig": "rig", "sensors": "sensors", "controller": "controller"}


def compose_services(identities, secrets_dir: str) -> str:
    """``docker-compose.rigs.yml``: one compose service per rig identity (``ra2vipas rig``, or
    ``sensors``/``controller`` for a split rig), each with its own secrets only, and the
    number of rigs ``/health`` waits for. ``secrets_dir`` is the directory of the files as
    seen from the compose project directory (e.g. ``./secrets``)."""
    q = json.dumps  # a JSON string is a YAML double-quoted scalar
    rig_identities = [i for i in identities if i.role in COMMANDS]
    rigs = sorted({i.name for i in rig_identities})
    lines = ["# Written by `ra2vipas security init` (docs/deployment.md): the rigs of the secured deployment, one",
             "# service per rig identity. Use with docker-compose.yml and docker-compose.tls.yml:",
             f"#   docker compose -f docker-compose.yml -f docker-compose.tls.yml -f {secrets_dir}/{COMPOSE_FILE} up -d",
             "services:",
             "  orchestrator:",
             "    environment:",
             f"      RA2VIPAS_EXPECT_RIGS: {q(str(len(rigs)))}"]
    secret_names: list[str] = []
    for identity in rig_identities:
        service = identity.user if identity.role == "rig" else f"{identity.name}-{identity.role}"
        env = identity_env(identity, SECRETS_IN_CONTAINER, f"tls/{ROUTER_SERVICE}:7447")
        own = ["ca.pem", f"{identity.user}.pem", f"{identity.user}.key", f"{identity.user}.password"]
        lines += [f"  {service}:", "    build: .", "    image: ra2vipas:local", "    init: true", "    restart: unless-stopped",
                  "    depends_on: [router]", f"    command: [\"ra2vipas\", {q(COMMANDS[identity.role])}]", "    environment:"]
        lines += [f"      {k}: {q(v)}" for k, v in env.items()]
        lines += ["      RA2VIPAS_LOG_LEVEL: \"${RA2VIPAS_LOG_LEVEL:-INFO}\"", "    secrets:"]
        lines += [f"      - {q(name)}" for name in own]
        secret_names += [n for n in own if n not in secret_names and n != "ca.pem"]
    lines.append("secrets:")
    for name in secret_names:
        lines += [f"  {q(name)}:", f"    file: {q(f'{secrets_dir}/{name}')}"]
    return "\n".join(lines) + "\n"


def _owner(value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    uid, _, gid = value.partition(":")
    try:
        return int(uid), int(gid or uid)
    except ValueError:
        fail(f"--owner expects UID or UID:GID (numbers), got {value!r}", EXIT_USAGE)


@app.command("init")
def init(
    rigs: Annotated[str, typer.Option("--rigs", help="Comma-separated rig names; each gets one identity for its sensors and controller (`ra2vipas rig`).")] = "",
    split_rigs: Annotated[str, typer.Option("--split-rigs", help="Comma-separated rigs whose sensors and controller run apart: identities RIG.sensors and RIG.controller.")] = "",
    operators: Annotated[Optional[list[str]], typer.Option("--operator", metavar="NAME", help="An operator identity, who may publish ground truth for real rigs (repeatable).")] = None,
    out: Annotated[str, typer.Option("--out", help="Directory to write (created with mode 0700).")] = "secrets",
    router_hosts: Annotated[Optional[list[str]], typer.Option("--router-host", metavar="NAME", help="A host name or IP address clients reach the router by (repeatable; `router`, its compose name, is always included).")] = None,
    router_port: Annotated[int, typer.Option(min=1, max=65535, help="The router's TLS port.")] = 7447,
    install_dir: Annotated[Optional[str], typer.Option(help="Where the files will be on the machines that use them, for the env files (default: OUT's absolute path).")] = None,
    days: Annotated[int, typer.Option(min=1, max=3650, help="Validity of the certificates, in days.")] = 365,
    owner: Annotated[Optional[str], typer.Option(metavar="UID[:GID]", help="Give the files to this user (e.g. 10001, the containers' user); needs the privilege to chown.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace the files of an earlier init in OUT (new CA, new passwords).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line: the identities and files written (never a password).")] = False,
) -> None:
    """Write a CA and certificates, one password per identity, the router's credentials file
    and Zenoh configuration with the access control, per-service env files and the compose
    services of the rigs, for a deployment whose every link is mutual TLS and whose every
    service may touch only its own keys (docs/deployment.md)."""
    from ra2vipas.services.transport.acl import AclError, access_control, standard_identities

    rig_names = _split_names(rigs, "rig")
    split_names = _split_names(split_rigs, "rig")
    if not rig_names and not split_names:
        fail("name at least one rig: --rigs rig-1,rig-2 (or --split-rigs)", EXIT_USAGE)
    try:
        identities = standard_identities(rig_names, split_names, _split_names(",".join(operators or []), "operator"))
        policy = access_control(identities, match="both")
    except AclError as err:
        fail(str(err), EXIT_USAGE)
    clash = sorted(set(rig_names) & set(COMPOSE_SERVICES)) + sorted(
        f"{r}-{role}" for r in split_names for role in ("sensors", "controller") if f"{r}-{role}" in set(rig_names))
    if clash:
        fail(f"rig name {clash[0]!r} clashes with a compose service name; choose another", EXIT_USAGE)
    hosts = [ROUTER_SERVICE] + [h for h in (router_hosts or []) if h != ROUTER_SERVICE]
    uid_gid = _owner(owner)

    directory = Path(out)
    try:
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        os.chmod(directory, 0o700)
        if not force and any(directory.iterdir()):
            fail(f"{directory} is not empty: give an empty --out directory, or --force to replace an earlier init (new CA, new passwords)")
        if uid_gid is not None:
            os.chown(directory, *uid_gid)
        writer = _Writer(directory, uid_gid)
        where = install_dir or str(directory.resolve())
        connect = f"tls/{hosts[1] if len(hosts) > 1 else ROUTER_SERVICE}:{router_port}"

        ca = _CertificateAuthority(days)
        ca_cert, ca_key = ca.pem()
        writer.write("ca.pem", ca_cert)
        writer.write("ca.key", ca_key)
        cert, key = ca.issue(ROUTER_SERVICE, hosts)
        writer.write("router.pem", cert)
        writer.write("router.key", key)
        lines = []
        for identity in identities:
            password = secrets.token_urlsafe(32)
            lines.append(f"{identity.user}:{password}\n")
            cert, key = ca.issue(identity.user)
            writer.write(f"{identity.user}.pem", cert)
            writer.write(f"{identity.user}.key", key)
            writer.write(f"{identity.user}.password", password + "\n")
            writer.write(f"{identity.user}.env", _env_file(
                f"Zenoh identity {identity.user!r} (role {identity.role}) for a bare process: set -a; . {where}/{identity.user}.env; set +a",
                identity_env(identity, where, connect)))
        writer.write("credentials", "".join(lines))
        writer.write("router.json5", router_config(policy))
        writer.write("router.env", _env_file(f"The Zenoh router: set -a; . {where}/router.env; set +a; ra2vipas router", {
            "RA2VIPAS_ZENOH_CONFIG": f"{where}/router.json5",
            "RA2VIPAS_ZENOH_LISTEN": f"tls/0.0.0.0:{router_port}",
            "RA2VIPAS_ZENOH_TLS_CA": f"{where}/ca.pem",
            "RA2VIPAS_ZENOH_TLS_CERT": f"{where}/router.pem",
            "RA2VIPAS_ZENOH_TLS_KEY": f"{where}/router.key",
            "RA2VIPAS_ZENOH_TLS_MTLS": "true",
            "RA2VIPAS_ZENOH_CREDENTIALS": f"{where}/credentials",
        }))
        relative = os.path.relpath(directory.resolve(), Path.cwd())
        writer.write(COMPOSE_FILE, compose_services(identities, "./" + relative if not relative.startswith("..") else str(directory.resolve())))
    except OSError as err:
        fail(f"cannot write {directory}: {err.strerror or err}")

    report = {"out": str(directory), "router": {"hosts": hosts, "port": router_port},
              "identities": [{"user": i.user, "role": i.role, "name": i.name, "env": f"{directory}/{i.user}.env"} for i in identities],
              "files": sorted(p.name for p in writer.files)}
    if as_json:
        print_json(report)
        return
    stderr.print(f"wrote {len(writer.files)} files to {directory} (mode 0600, directory 0700); identities: "
                 + ", ".join(f"{i.user} ({i.role})" for i in identities))
    stderr.print(f"keep {directory}/ca.key off the machines; give each machine only its own files: ca.pem and USER.pem, "
                 f"USER.key, USER.password, USER.env (the router: router.*, credentials)")
    stderr.print(f"compose: docker compose -f docker-compose.yml -f docker-compose.tls.yml -f {directory}/{COMPOSE_FILE} up -d")
