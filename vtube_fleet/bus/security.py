"""Bus security: client credentials, TLS, and ``vtube-fleet bus-setup`` (everything a mosquitto
deployment of one mission needs).

Clients (:class:`~vtube_fleet.bus.mqtt.MqttBus`) read a **credentials file** (TOML, mode 0600)::

    username = "vehicle-3"
    password = "…"
    ca = "../ca.crt"      # optional: the CA that signed the broker's certificate (relative to
                          # this file); without it the system's CAs are trusted

and connect with TLS (``mqtts://HOST:8883``), verifying the broker's certificate and host name.

:func:`bus_setup` writes, for a mission of N vehicles, into a new directory:

* ``ca.crt`` / ``ca.key`` — a private certificate authority (EC P-256; keep ``ca.key`` offline);
* ``server.crt`` / ``server.key`` — the broker's certificate, for the host names and addresses
  the clients use (``localhost`` and ``127.0.0.1`` always);
* ``passwd`` — mosquitto's password file (PBKDF2-SHA512 ``$7$`` hashes, written by
  ``mosquitto_passwd`` when installed, else by :func:`mosquitto_hash`, the same format);
* ``acl`` — vehicle i may publish only its own state, last-seen state and status; only the
  coordinator may publish the mission config and commands; everyone reads what it needs;
* ``mosquitto.conf`` — anonymous access off, the password file and the ACL, a TLS listener
  (a plain listener only on loopback and only when asked);
* ``credentials/vehicle-I.toml`` and ``credentials/coordinator.toml`` — one per client.

See ``docs/security.md`` for the threat model and key rotation.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import ipaddress
import os
import secrets
import shutil
import ssl
import stat
import subprocess
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vtube_fleet.bus.topics import MissionTopics
from vtube_fleet.errors import UserError

__all__ = [
    "COORDINATOR_USER",
    "DEFAULT_TLS_PORT",
    "BusCredentials",
    "BusSetup",
    "CredentialsError",
    "SetupError",
    "bus_setup",
    "is_loopback",
    "mosquitto_acl",
    "mosquitto_hash",
    "tls_context",
    "vehicle_user",
]

#: The TLS port of MQTT (IANA "secure-mqtt").
DEFAULT_TLS_PORT = 8883
#: User name of the mission coordinator (``vtube-fleet mission``).
COORDINATOR_USER = "coordinator"
#: mosquitto 2's password hash: PBKDF2-SHA512, 101 iterations, 12-byte salt, 64-byte key.
_PW_ITERATIONS = 101
_PW_SALT_BYTES = 12


class CredentialsError(UserError):
    """A credentials file that cannot be used (missing, unreadable, readable by others)."""


class SetupError(UserError):
    """``bus-setup`` cannot write its files (existing setup, bad host name, bad count)."""


def vehicle_user(vehicle_id: int) -> str:
    """The broker user name of vehicle ``vehicle_id``'s agent."""
    return f"vehicle-{int(vehicle_id)}"


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (127.0.0.0/8, ::1)."""
    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


# -- client side ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class BusCredentials:
    """A client's user name, password and the CA file it trusts (None: the system's)."""

    username: str
    password: str
    ca_file: Path | None = None
    source: str = ""

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> BusCredentials:
        """Read a credentials file (module docstring); refuses one readable by others."""
        p = Path(path)
        try:
            st = p.stat()
            text = p.read_text()
        except OSError as exc:
            raise CredentialsError(
                f"cannot read the credentials file {p}: {exc.strerror or exc}") from None
        if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise CredentialsError(
                f"credentials file {p} is readable by other users (mode "
                f"{stat.S_IMODE(st.st_mode):04o}); chmod 600 {p}")
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise CredentialsError(f"credentials file {p} is not TOML: {exc}") from None
        user, pw = data.get("username"), data.get("password")
        if not isinstance(user, str) or not user or not isinstance(pw, str) or not pw:
            raise CredentialsError(
                f"credentials file {p} needs username = \"…\" and password = \"…\"")
        ca = data.get("ca")
        ca_file = None
        if ca is not None:
            if not isinstance(ca, str) or not ca:
                raise CredentialsError(f"credentials file {p}: ca must be a file name")
            ca_file = (p.parent / ca).resolve()
            if not ca_file.is_file():
                raise CredentialsError(f"credentials file {p}: CA file {ca_file} not found")
        return cls(user, pw, ca_file, str(p))


def tls_context(ca_file: str | os.PathLike[str] | None = None) -> ssl.SSLContext:
    """A client TLS context that verifies the broker's certificate and host name (TLS ≥ 1.2)
    against ``ca_file`` (None: the system's CAs)."""
    try:
        ctx = ssl.create_default_context(cafile=None if ca_file is None else str(ca_file))
    except (OSError, ssl.SSLError) as exc:
        raise CredentialsError(f"cannot load the CA file {ca_file}: {exc}") from None
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    return ctx


# -- password file -------------------------------------------------------------------------------
def mosquitto_hash(password: str, *, salt: bytes | None = None,
                   iterations: int = _PW_ITERATIONS) -> str:
    """The password-file hash mosquitto 2 writes and checks: ``$7$ITER$SALT$HASH`` with
    base64 salt (12 random bytes) and base64 PBKDF2-HMAC-SHA512 (64 bytes)."""
    salt = secrets.token_bytes(_PW_SALT_BYTES) if salt is None else salt
    dk = hashlib.pbkdf2_hmac("sha512", password.encode(), salt, iterations, 64)
    return (f"$7${iterations}${base64.b64encode(salt).decode()}$"
            f"{base64.b64encode(dk).decode()}")


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to a new file readable only by us (0600)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def _write_passwd(path: Path, users: dict[str, str], tool: str | None) -> str:
    """Write mosquitto's password file; returns what hashed it."""
    if tool is not None:
        _write_private(path, "".join(f"{u}:{p}\n" for u, p in users.items()))
        try:
            subprocess.run([tool, "-U", str(path)], check=True, capture_output=True,  # noqa: S603
                           timeout=60)
            return f"{tool} -U"
        except (OSError, subprocess.SubprocessError) as exc:
            path.unlink(missing_ok=True)  # never leave the plain passwords behind
            raise SetupError(f"{tool} -U {path} failed: {exc}") from None
    _write_private(path, "".join(f"{u}:{mosquitto_hash(p)}\n" for u, p in users.items()))
    return "vtube_fleet.bus.security.mosquitto_hash"


# -- ACL -----------------------------------------------------------------------------------------
def mosquitto_acl(mission_id: str, vehicles: int) -> str:
    """The mosquitto ACL of a mission (``docs/security.md``): per-vehicle write rights on its own
    topics only (its clock asks too, and it alone reads the coordinator's echoes), the
    coordinator alone on config, cmd and the clock echoes."""
    t = MissionTopics(mission_id)
    b = t.base
    reads = [f"{b}/state/#", f"{b}/status/+", f"{b}/last/+", t.config, t.cmd]
    lines = [
        f"# mosquitto ACL of mission {mission_id!r}, {vehicles} vehicles (vtube-fleet bus-setup)",
        "# Every client's own delivery marker (MqttBus.sync): its client id.",
        f"pattern readwrite {b}/sync/%c",
        "",
        f"user {COORDINATOR_USER}",
        f"topic readwrite {t.config}",
        f"topic readwrite {t.cmd}",
        f"topic write {b}/clock/echo/+",
        *(f"topic read {r}" for r in reads if r not in (t.config, t.cmd)),
        f"topic read {t.all_clock_asks}",
    ]
    for i in range(vehicles):
        lines += [
            "",
            f"user {vehicle_user(i)}",
            *(f"topic read {r}" for r in reads),
            f"topic read {t.clock_echo(i)}",
            f"topic write {b}/state/+/+/{i}",
            f"topic write {t.status(i)}",
            f"topic write {t.last(i)}",
            f"topic write {t.clock_ask(i)}",
        ]
    return "\n".join(lines) + "\n"


# -- certificates --------------------------------------------------------------------------------
def _certificates(hosts: list[str], days: int) -> tuple[bytes, bytes, bytes, bytes]:
    """(ca_cert, ca_key, server_cert, server_key) as PEM."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC)
    until = now + datetime.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "vtube-fleet bus CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                     content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False,
                                     encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()),
                       critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    server = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hosts[0])]))
        .issuer_name(ca_name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(until)
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                       critical=False)
        .sign(ca_key, hashes.SHA256())
    )

    def pem_key(k: Any) -> bytes:
        return bytes(k.private_bytes(serialization.Encoding.PEM,
                                     serialization.PrivateFormat.PKCS8,
                                     serialization.NoEncryption()))

    return (ca.public_bytes(serialization.Encoding.PEM), pem_key(ca_key),
            server.public_bytes(serialization.Encoding.PEM), pem_key(key))


# -- bus-setup -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class BusSetup:
    """What :func:`bus_setup` wrote (absolute paths)."""

    out: Path
    mission_id: str
    vehicles: int
    port: int
    conf: Path
    ca_file: Path
    passwd: Path
    acl: Path
    credentials: dict[str, Path]
    hosts: tuple[str, ...]
    plain_loopback_port: int | None
    hashed_by: str

    def vehicle_credentials(self, vehicle_id: int) -> Path:
        return self.credentials[vehicle_user(vehicle_id)]

    @property
    def coordinator_credentials(self) -> Path:
        return self.credentials[COORDINATOR_USER]


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def bus_setup(
    out: str | os.PathLike[str],
    mission_id: str,
    vehicles: int,
    *,
    hosts: tuple[str, ...] | list[str] = (),
    port: int = DEFAULT_TLS_PORT,
    bind: str | None = None,
    plain_loopback_port: int | None = None,
    days: int = 365,
    passwd_tool: str | None = "auto",
) -> BusSetup:
    """Write the broker configuration and client credentials of one mission into ``out`` (a new
    or empty directory; module docstring). ``hosts``: extra names / addresses of the broker in
    its certificate; ``bind``: the TLS listener's address (None: every interface);
    ``plain_loopback_port``: also a plain listener on 127.0.0.1 (never on another address);
    ``passwd_tool``: ``"auto"`` (``mosquitto_passwd`` if installed), a path, or None (the
    built-in :func:`mosquitto_hash`)."""
    topics = MissionTopics(mission_id)  # refuses a bad mission id
    if not (isinstance(vehicles, int) and 1 <= vehicles <= 65535):
        raise SetupError(f"vehicles must be an integer in 1..65535, got {vehicles!r}")
    for name, p in (("port", port), ("plain loopback port", plain_loopback_port)):
        if p is not None and not (isinstance(p, int) and 1 <= p <= 65535):
            raise SetupError(f"{name} must be in 1..65535, got {p!r}")
    if not (isinstance(days, int) and 1 <= days <= 3650):
        raise SetupError(f"certificate validity must be 1..3650 days, got {days!r}")
    all_hosts: list[str] = []
    for h in ("localhost", "127.0.0.1", *hosts):
        if not h or any(c.isspace() or c in "/,@" for c in h):
            raise SetupError(f"host name {h!r} cannot go into a certificate")
        if h not in all_hosts:
            all_hosts.append(h)
    root = Path(out).resolve()
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise SetupError(f"{root} exists and is not an empty directory; bus-setup never "
                         "overwrites keys (rotate into a new directory: docs/security.md)")
    tool = shutil.which("mosquitto_passwd") if passwd_tool == "auto" else passwd_tool
    try:
        (root / "credentials").mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(root, 0o700)
        ca_pem, ca_key, srv_pem, srv_key = _certificates(all_hosts, days)
        (root / "ca.crt").write_bytes(ca_pem)
        _write_private(root / "ca.key", ca_key.decode())
        (root / "server.crt").write_bytes(srv_pem)
        _write_private(root / "server.key", srv_key.decode())
        users = {COORDINATOR_USER: secrets.token_urlsafe(24)}
        users.update({vehicle_user(i): secrets.token_urlsafe(24) for i in range(vehicles)})
        hashed_by = _write_passwd(root / "passwd", users, tool)
        (root / "acl").write_text(mosquitto_acl(mission_id, vehicles))
        creds: dict[str, Path] = {}
        for user, pw in users.items():
            p = root / "credentials" / f"{user}.toml"
            _write_private(p, f"# MQTT credentials of {user}, mission {mission_id} "
                              f"(vtube-fleet bus-setup). Keep secret.\n"
                              f"username = {_toml_str(user)}\npassword = {_toml_str(pw)}\n"
                              f'ca = "../ca.crt"\n')
            creds[user] = p
        conf = root / "mosquitto.conf"
        listen = f"listener {port}" + (f" {bind}" if bind else "")
        text = [
            f"# mosquitto 2 configuration of mission {mission_id!r} ({vehicles} vehicles),",
            "# written by vtube-fleet bus-setup. Start: mosquitto -c " + str(conf),
            "# The broker must be able to read the files below: started as root it drops to the",
            f"# mosquitto user, so chown -R mosquitto: {root} first.",
            "per_listener_settings false",
            "allow_anonymous false",
            f"password_file {root / 'passwd'}",
            f"acl_file {root / 'acl'}",
            "persistence false",
            "set_tcp_nodelay true",
            "",
            "# TLS: clients verify this certificate with ca.crt",
            listen,
            f"certfile {root / 'server.crt'}",
            f"keyfile {root / 'server.key'}",
        ]
        if plain_loopback_port is not None:
            text += ["", "# plain MQTT, loopback only (asked for with --plain-loopback)",
                     f"listener {plain_loopback_port} 127.0.0.1"]
        conf.write_text("\n".join(text) + "\n")
    except OSError as exc:
        raise SetupError(f"cannot write the bus setup into {root}: {exc}") from None
    return BusSetup(root, topics.mission_id, vehicles, port, conf, root / "ca.crt",
                    root / "passwd", root / "acl", creds, tuple(all_hosts),
                    plain_loopback_port, hashed_by)
