"""`tether deploy init`: a secured deployment directory (router, one identity per service, TLS) for a fleet."""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import secrets
import stat
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from schemas import keys
from services.runtime import DEFAULT_BASE_PORT

# Not 7447 (rmw_zenoh's router on a ROS 2 robot) and clear of the services' own loopback ports.
DEFAULT_ROUTER_PORT = DEFAULT_BASE_PORT + 10
DEFAULT_ROUTER_HOST = "localhost"
# The services of a robot, each its own identity, then the two that are not services: a person and an LLM agent.
SERVICE_IDENTITIES = ("sim", "safety", "parser", "resolver", "executor", "recorder", "planner", "ros2")
IDENTITIES = (*SERVICE_IDENTITIES, "operator", "agent")
# An identity's name (`username`: ROBOT-IDENTITY) is its certificate's common name, which holds at
# most 64 characters (RFC 5280's ub-common-name): this leaves the rest for the robot's name.
MAX_ROBOT_NAME = 64 - len("-") - max(len(i) for i in IDENTITIES)
ROBOT_BACKEND_IDENTITIES = ("sim", "ros2")
# A robot's backend (`deploy init --backend`): only its identity reports the robot's state and serves
# its actions; the other backend gets no login. ANY_BACKEND, for a robot that runs either (the sim now,
# the real one later), has both.
ANY_BACKEND = "any"
BACKENDS_OF_A_ROBOT = (*ROBOT_BACKEND_IDENTITIES, ANY_BACKEND)
MANIFEST = "deployment.json"
ROUTER_CONFIG = "router.json5"
USERS_FILE = "router-users.txt"
CA_DIR = "ca"
# Beside DIR/<robot>/: the CA, the systemd units, the open compose variant's configs.
OWN_DIRS = (CA_DIR, "systemd", "compose")
# Certificates outlive a robot's usual service interval; `tether deploy init` never renews one, so an
# installer renews by deleting the expired files (and the CA, to rotate everything) and rerunning it.
CA_LIFETIME = dt.timedelta(days=3650)
CERT_LIFETIME = dt.timedelta(days=1825)
# A service started before the router is reachable waits for it (-1: no deadline), trying again after
# 0.2 s and then every second; a person's or agent's command gives up at once and says so.
SERVICE_CONNECT = {
    "timeout_ms": -1,
    "exit_on_failure": False,
    "retry": {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2},
}
PERSON_RETRY = {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2}
SECRET_MODE = 0o600
# Every directory it writes holds secrets or sits among them (a world-writable one lets anyone swap a
# key, a certificate or a unit), so it is its owner's alone, whatever the umask.
PRIVATE_DIR_MODE = 0o700
# The planner's LLM API key: written empty (no key), for the installer to fill; never overwritten.
LLM_KEY_FILE = "llm-api-key"


class DeploymentError(Exception):
    """A deployment directory that cannot be written or extended as asked; the message says why."""


@dataclass(frozen=True)
class RouterAddress:
    """Where clients reach the router: a host name or IP address and a port."""

    host: str = DEFAULT_ROUTER_HOST
    port: int = DEFAULT_ROUTER_PORT

    @classmethod
    def parse(cls, text: str) -> RouterAddress:
        """`HOST`, `HOST:PORT`, `[IPv6]` or `[IPv6]:PORT`."""
        text = text.strip()
        host, port_text = text, ""
        if text.startswith("["):
            host, _, rest = text[1:].partition("]")
            if rest and not rest.startswith(":"):
                raise DeploymentError(f"router address {text!r}: expected [IPv6]:PORT")
            port_text = rest[1:]
        elif text.count(":") == 1:
            host, port_text = text.split(":")
        elif text.count(":") > 1:
            host = text  # a bare IPv6 address
        if not host:
            raise DeploymentError(f"router address {text!r} has no host")
        if not _is_ip(host) and not all(part.replace("-", "").isalnum() for part in host.split(".")):
            raise DeploymentError(f"router address {text!r}: {host!r} is neither a host name nor an IP address")
        if not host.isascii():
            # A certificate names a host in ASCII (DNS's A-labels), and so does a resolver.
            raise DeploymentError(
                f"router address {text!r}: a host name is ASCII; give {host!r} in its IDNA form (xn--...)"
            )
        if not port_text:
            return cls(host)
        try:
            port = int(port_text)
        except ValueError:
            raise DeploymentError(f"router address {text!r}: port {port_text!r} is not a number") from None
        if not 1 <= port <= 65535:
            raise DeploymentError(f"router address {text!r}: port {port} is not between 1 and 65535")
        return cls(host, port)

    @property
    def loopback(self) -> bool:
        """Whether only this host reaches the router at this address (then nothing crosses a network)."""
        if self.host == "localhost":
            return True
        return _is_ip(self.host) and ipaddress.ip_address(self.host).is_loopback

    @property
    def container_alias(self) -> str | None:
        """The host name, when it is one a container network can give the router (not an IP, not localhost)."""
        return None if self.host == "localhost" or _is_ip(self.host) else self.host

    def endpoint(self, tls: bool) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'tls' if tls else 'tcp'}/{host}:{self.port}"

    def __str__(self) -> str:
        return f"{f'[{self.host}]' if ':' in self.host else self.host}:{self.port}"


@dataclass(frozen=True)
class Written:
    """One file of the deployment: `created` when written now (new, or its content changed), else kept as it was."""

    path: Path
    created: bool
    secret: bool


def username(robot: str, identity: str) -> str:
    """The Zenoh user name, and with TLS the certificate's common name, of one identity of one robot."""
    return f"{robot}-{identity}"


def check_robot_name(robot: str) -> str:
    # NodeSettings' alphabet, and no name that the rules' key expressions would widen. ASCII only:
    # the name is in systemd unit names and compose service names, which take no other letters.
    if not robot or not robot.isascii() or not robot.replace("_", "").replace("-", "").isalnum():
        raise DeploymentError(f"robot name {robot!r} must be ASCII letters, digits, '-' or '_'")
    if robot in OWN_DIRS:
        # DIR/<robot>/ would be one of them: the robot's files, copied to its hosts, beside the CA's key or the units.
        raise DeploymentError(f"robot name {robot!r} is taken by the deployment's own {robot}/ directory")
    return robot


def robot_identities(backend: str) -> tuple[str, ...]:
    """The identities of a robot with this backend: all but the other backend's."""
    if backend == ANY_BACKEND:
        return IDENTITIES
    return tuple(i for i in IDENTITIES if i not in ROBOT_BACKEND_IDENTITIES or i == backend)


def check_backend(backend: str) -> str:
    if backend not in BACKENDS_OF_A_ROBOT:
        raise DeploymentError(f"backend {backend!r} is none of {', '.join(BACKENDS_OF_A_ROBOT)}")
    return backend


def init(
    directory: Path,
    robots: Sequence[str],
    *,
    tls: bool = False,
    router: RouterAddress | None = None,
    backend: str | None = None,
) -> list[Written]:
    """Write (or extend) the deployment in `directory` for `robots`; return every file, written or kept.

    `backend` is that of `robots`: a new one without it gets ANY_BACKEND, one already there keeps its
    own. A robot whose backend narrows loses the other backend's identity (login, files and unit).

    A secret, key or certificate already there is never changed, but for a certificate the CA in
    `ca/` did not sign (a CA replaced: delete `ca/` and rerun), one out of date, or one not for the
    key beside it: issued anew, with a new key. The router's config, its password
    list (each user's password kept as it was), the manifest and the generated units and compose
    files are rewritten to cover every robot, and reported as written only when their content changed.
    """
    for robot in robots:
        check_robot_name(robot)
        if len(robot) > MAX_ROBOT_NAME:
            # Refused whatever --tls: a longer one also names unit files longer than a file name may be.
            raise DeploymentError(
                f"robot name {robot!r} has {len(robot)} characters: at most {MAX_ROBOT_NAME} characters, for "
                f"its identities' names ({username('ROBOT', 'operator')}) to fit a certificate's 64"
            )
    if backend is not None:
        check_backend(backend)
    if not robots:
        raise DeploymentError("name at least one robot (--robot NAME)")
    directory = directory.resolve()
    if not _is_utf8(str(directory)):
        # Its configs name their files by absolute path, in TOML, which is UTF-8 text.
        raise DeploymentError(f"{str(directory)!r} is not a UTF-8 path, which tether.toml cannot hold: use another one")
    if directory.exists() and not directory.is_dir():
        raise DeploymentError(f"{directory} exists and is not a directory")
    manifest = _read_manifest(directory)
    if manifest is not None:
        if manifest["tls"] != tls:
            was = "with" if manifest["tls"] else "without"
            raise DeploymentError(f"{directory} was made {was} --tls; rerun it {was} --tls to add robots")
        known = RouterAddress.parse(manifest["router"])
        if router is not None and router != known:
            raise DeploymentError(
                f"{directory} was made for the router at {known}, not {router}; "
                "its clients and certificates name that address (start a new directory to change it)"
            )
        router = known
    router = router or RouterAddress()
    if tls and ":" in router.host:
        # zenoh's TLS link takes the bracketed IPv6 address for a DNS name and never connects.
        raise DeploymentError(
            f"--tls with the router at an IPv6 address ({router}) cannot connect (Zenoh's TLS client refuses "
            "IPv6 address literals): give --router a host name that resolves to it"
        )
    all_robots = list(dict.fromkeys([*(manifest["robots"] if manifest else []), *robots]))
    backends = {r: (manifest["backends"].get(r, ANY_BACKEND) if manifest else ANY_BACKEND) for r in all_robots}
    if backend is not None:
        backends |= dict.fromkeys(robots, backend)
    private_dir(directory, ours=False)
    written: list[Written] = []

    ca: tuple[ec.EllipticCurvePrivateKey, x509.Certificate] | None = None
    if tls:
        ca = _certificate_authority(directory, written)
        _router_certificate(directory, router, ca, written)

    passwords = _passwords(directory, backends, written)
    for robot in all_robots:
        _robot_files(directory, robot, router, tls, ca, passwords, robot_identities(backends[robot]), written)
    written.append(
        _write_text(directory / ROUTER_CONFIG, router_config(all_robots, router, tls, backends), replace=True)
    )
    made = {"robots": all_robots, "tls": tls, "router": str(router), "backends": backends}
    manifest_text = json.dumps(made, indent=2) + "\n"
    written.append(_write_text(directory / MANIFEST, manifest_text, replace=True))
    # The systemd units and compose files of the same deployment, by their own module.
    from tether import deployunits

    written += deployunits.write_all(directory, all_robots, tls=tls, router=router)
    return written


@dataclass(frozen=True)
class Deployment:
    """A deployment directory made by `init`: its robots, whether it uses TLS, where its router is,
    each robot's backend."""

    directory: Path
    robots: tuple[str, ...]
    tls: bool
    router: RouterAddress
    backends: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def load(cls, directory: Path) -> Deployment:
        manifest = _read_manifest(directory)
        if manifest is None:
            raise DeploymentError(
                f"{directory} is not a deployment (no {MANIFEST}); make one with `tether deploy init {directory} "
                "--robot NAME`"
            )
        return cls(
            directory.resolve(),
            tuple(manifest["robots"]),
            manifest["tls"],
            RouterAddress.parse(manifest["router"]),
            manifest["backends"],
        )

    def backend(self, robot: str) -> str:
        return self.backends.get(robot, ANY_BACKEND)

    def client_config(self, robot: str, identity: str) -> Path:
        """The Zenoh config of `identity` on `robot`; a clear error when the deployment has none."""
        if robot not in self.robots:
            raise DeploymentError(f"robot {robot!r} is not in {self.directory} (robots: {', '.join(self.robots)})")
        if identity not in IDENTITIES:
            raise DeploymentError(f"{identity!r} is not an identity of a deployment ({', '.join(IDENTITIES)})")
        if identity not in robot_identities(backend := self.backend(robot)):
            raise DeploymentError(
                f"robot {robot!r} of {self.directory} has the {backend} backend, so no {identity} identity: "
                f"start its backend with --backend {backend}"
            )
        path = self.directory / robot / f"{identity}.json5"
        if not path.is_file():
            raise DeploymentError(f"{path} is missing: is {identity} installed on this host?")
        return path

    def robot_config(self, robot: str) -> Path:
        return self.directory / robot / "tether.toml"


def cleartext_warning(made: Deployment) -> str | None:
    """What to tell the installer when logins and traffic would cross a network unencrypted."""
    if made.tls or made.router.loopback:
        return None
    return (
        f"the router is reached at {made.router} without --tls: every password (and all traffic) crosses "
        "the network in the clear, and anyone on the path can log in as that identity. Make a new "
        "directory with --tls, or keep the router's port on a network only you can reach."
    )


def _read_manifest(directory: Path) -> dict[str, Any] | None:
    path = directory / MANIFEST
    if not path.exists():
        if (directory / ROUTER_CONFIG).exists():
            raise DeploymentError(f"{directory} holds a {ROUTER_CONFIG} but no {MANIFEST}: not made by tether deploy")
        return None
    try:
        data = json.loads(path.read_text())
        robots = [check_robot_name(str(r)) for r in data["robots"]]
        # Made before robots had a backend: each has both (ANY_BACKEND), as it was made.
        backends = {str(r): check_backend(str(b)) for r, b in data.get("backends", {}).items()}
        if not backends.keys() <= set(robots):
            raise ValueError(f"backends of robots it does not list: {', '.join(backends.keys() - set(robots))}")
        return {"robots": robots, "tls": bool(data["tls"]), "router": str(data["router"]), "backends": backends}
    except (OSError, ValueError, KeyError, TypeError, AttributeError, DeploymentError) as exc:
        raise DeploymentError(f"{path} is unreadable or damaged: {exc}") from None


# Files


def private_dir(path: Path, *, ours: bool = True) -> None:
    """Make `path` mode 700 (its missing parents 755, whatever the umask). One already there must be
    the user's (or root's): one of deploy init's own subdirectories (`ours`) is then set to 700 if others
    may use it; the directory the installer named, perhaps a shared one (/tmp), is never changed, but
    refused when others may write in it."""
    for parent in reversed(path.parents):
        if not parent.exists():
            parent.mkdir(mode=0o755, exist_ok=True)  # the umask only takes bits away: never writable by others
    try:
        path.mkdir(mode=PRIVATE_DIR_MODE)
        return
    except FileExistsError:
        pass
    found = path.stat()
    if not stat.S_ISDIR(found.st_mode):
        raise DeploymentError(f"{path} exists and is not a directory")
    if found.st_uid not in (os.geteuid(), 0):
        raise DeploymentError(
            f"{path} belongs to uid {found.st_uid}, not to you: its owner could swap the keys and "
            "certificates in it; use a directory of your own"
        )
    mode = stat.S_IMODE(found.st_mode)
    if ours and mode & 0o077:
        os.chmod(path, PRIVATE_DIR_MODE)
    elif not ours and mode & 0o022:
        raise DeploymentError(
            f"others may write in {path} (mode {mode:o}): anyone could swap a key, certificate or unit "
            "there; use a directory only you can write in (`chmod go-w` it, or another one)"
        )


def _kept(path: Path, secret: bool) -> Written:
    """A file kept as it was; a secret others could read or change is made 600 (a copy may have loosened
    it). A link is left as it is: what it points to is not deploy init's."""
    found = path.lstat()
    if secret and stat.S_ISREG(found.st_mode) and stat.S_IMODE(found.st_mode) & 0o077:
        os.chmod(path, SECRET_MODE)
    return Written(path, created=False, secret=secret)


def _write_bytes(path: Path, data: bytes, *, secret: bool = False, replace: bool = False) -> Written:
    """Create `path` (mode 600 when `secret`), or keep it as it is when it exists and not `replace`
    (or `replace` but it already holds `data`). Replaced, it is written beside and renamed over: a
    symlink planted there is replaced, never written through nor kept."""
    if path.exists() and (not replace or (not path.is_symlink() and path.is_file() and path.read_bytes() == data)):
        return _kept(path, secret)
    if not path.parent.is_dir():
        private_dir(path.parent)
    mode = SECRET_MODE if secret else 0o644
    target = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp") if replace else path
    # O_EXCL: never write through a file or link someone else put there; the mode is set at creation.
    fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if replace:
            os.replace(target, path)
    except BaseException:
        target.unlink(missing_ok=True)
        raise
    return Written(path, created=True, secret=secret)


def _write_text(path: Path, text: str, *, secret: bool = False, replace: bool = False) -> Written:
    return _write_bytes(path, text.encode(), secret=secret, replace=replace)


def write_generated(path: Path, text: str) -> Written:
    """A file deploy init generates and rewrites when its text changes (nothing secret in it)."""
    return _write_text(path, text, replace=True)


def _passwords(directory: Path, backends: Mapping[str, str], written: list[Written]) -> dict[str, str]:
    """Every identity's password: those in router-users.txt kept, else the one its client config
    holds (the list lost, its robots' copies still installed), new ones for new identities. An
    identity a robot's backend leaves out has none: it cannot log in."""
    path = directory / USERS_FILE
    known: dict[str, str] = {}
    if path.exists():
        try:
            text = path.read_text()
        except UnicodeDecodeError as exc:
            raise DeploymentError(f"{path} is not text ({exc}): not made by tether deploy") from None
        for number, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            user, sep, password = line.partition(":")
            if not sep or not password:
                raise DeploymentError(f"{path}:{number} is not a `user:password` line")
            known[user] = password
    dropped = {username(r, i) for r, b in backends.items() for i in IDENTITIES if i not in robot_identities(b)}
    passwords = {user: password for user, password in known.items() if user not in dropped}
    for robot, backend in backends.items():
        for identity in robot_identities(backend):
            if (user := username(robot, identity)) not in passwords:
                installed = _client_password(directory / robot / f"{identity}.json5", user)
                passwords[user] = installed or secrets.token_urlsafe(24)
    if passwords != known or not path.exists():
        text = "".join(f"{user}:{password}\n" for user, password in passwords.items())
        written.append(_write_text(path, text, secret=True, replace=True))
    else:
        written.append(_kept(path, secret=True))
    return passwords


def _client_password(path: Path, user: str) -> str | None:
    """The password of `user` in the client config `client_config` wrote at `path`, if it is there."""
    try:
        lines = path.read_text().splitlines()
        auth = json.loads("\n".join(line for line in lines if not line.startswith("//")))["transport"]["auth"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    found = auth.get("usrpwd", {}) if isinstance(auth, dict) else {}
    password = found.get("password") if isinstance(found, dict) and found.get("user") == user else None
    return password if isinstance(password, str) and password and "\n" not in password else None


def _robot_files(
    directory: Path,
    robot: str,
    router: RouterAddress,
    tls: bool,
    ca: tuple[ec.EllipticCurvePrivateKey, x509.Certificate] | None,
    passwords: dict[str, str],
    identities: Sequence[str],
    written: list[Written],
) -> None:
    home = directory / robot
    private_dir(home)
    for dropped in (i for i in IDENTITIES if i not in identities):
        # Its login is gone from the router; its files would only mislead an installer copying them.
        for suffix in (".json5", ".key", ".pem"):
            (home / f"{dropped}{suffix}").unlink(missing_ok=True)
    if ca is not None:
        ca_pem = ca[1].public_bytes(serialization.Encoding.PEM)
        written.append(_write_bytes(home / "ca.pem", ca_pem, replace=True))  # the CA's, should it be replaced
    for identity in identities:
        user = username(robot, identity)
        if ca is not None:
            key_path, cert_path = home / f"{identity}.key", home / f"{identity}.pem"
            if not _usable(key_path, cert_path, ca[1]):
                key_path.unlink(missing_ok=True)  # a certificate is only ever made with a new key of its own
                cert_path.unlink(missing_ok=True)
                key, cert = _issue(ca, user, sans=(), server=False)
                written.append(_write_bytes(key_path, _key_pem(key), secret=True))
                written.append(_write_bytes(cert_path, cert.public_bytes(serialization.Encoding.PEM)))
            else:
                written += [_kept(key_path, secret=True), _kept(cert_path, secret=False)]
        text = client_config(robot, identity, router, passwords[user], tls)
        written.append(_write_text(home / f"{identity}.json5", text, secret=True))
    written.append(_write_text(home / "operator.token", secrets.token_hex(24) + "\n", secret=True))
    written.append(_write_text(home / "robot.key", secrets.token_hex(32) + "\n", secret=True))
    written.append(_write_text(home / LLM_KEY_FILE, "", secret=True))
    written.append(_write_text(home / "tether.toml", robot_config(home)))
    private_dir(home / "state")


def robot_config(home: Path) -> str:
    """The services' shared config for one robot: where safety keeps its secrets and latch, where recordings go."""
    key = json.dumps(str(home / "robot.key"))
    return (
        f"# tether config for robot {home.name}, written by `tether deploy init`. The paths are absolute;\n"
        "# edit them when the files are installed elsewhere (docs: deploy/README.md).\n\n"
        "[safety]\n"
        f"operator_token_file = {json.dumps(str(home / 'operator.token'))}\n"
        f"estop_state_file = {json.dumps(str(home / 'state' / 'estop.json'))}\n"
        f"mode_state_file = {json.dumps(str(home / 'state' / 'mode.json'))}\n"
        f"robot_key_file = {key}\n\n"
        "# Only safety and the robot backend read the robot key.\n"
        f"[sim]\nrobot_key_file = {key}\n\n"
        f"[ros2]\nrobot_key_file = {key}\n\n"
        "[recorder]\n"
        f"output_dir = {json.dumps(str(home / 'recordings'))}\n"
    )


# Zenoh configs


def client_config(robot: str, identity: str, router: RouterAddress, password: str, tls: bool) -> str:
    """One identity's Zenoh client config; its file paths are relative to the config's own directory."""
    connect: dict[str, Any] = {"endpoints": [router.endpoint(tls)]}
    connect |= SERVICE_CONNECT if identity in SERVICE_IDENTITIES else {"retry": PERSON_RETRY}
    transport: dict[str, Any] = {"auth": {"usrpwd": {"user": username(robot, identity), "password": password}}}
    if tls:
        transport["link"] = {
            "tls": {
                "root_ca_certificate": "ca.pem",
                "connect_private_key": f"{identity}.key",
                "connect_certificate": f"{identity}.pem",
                "enable_mtls": True,
                "verify_name_on_connect": True,
            }
        }
    conf = {"mode": "client", "connect": connect, "scouting": {"multicast": {"enabled": False}}, "transport": transport}
    header = (
        f"// {username(robot, identity)}: the Zenoh client config of {identity} on robot {robot}, written by\n"
        "// `tether deploy init`. It holds a password: keep it readable by that identity only (mode 600).\n"
        "// Relative file paths are relative to this file's directory.\n"
    )
    return header + json.dumps(conf, indent=2) + "\n"


def router_config(
    robots: Sequence[str], router: RouterAddress, tls: bool, backends: Mapping[str, str] | None = None
) -> str:
    """The router: every client authenticated, every message denied unless a rule of its robot allows it.
    `backends`: each robot's (ANY_BACKEND for one it does not name)."""
    # Every interface of the family of the address its clients use: 0.0.0.0 takes no IPv6 client.
    wildcard = "[::]" if ":" in router.host else "0.0.0.0"
    listen = f"{'tls' if tls else 'tcp'}/{wildcard}:{router.port}"
    transport: dict[str, Any] = {"auth": {"usrpwd": {"dictionary_file": USERS_FILE}}}
    if tls:
        transport["link"] = {
            "tls": {
                "root_ca_certificate": f"{CA_DIR}/ca.pem",
                "listen_private_key": "router.key",
                "listen_certificate": "router.pem",
                "enable_mtls": True,
            }
        }
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for robot in robots:
        r, s, p = access_rules(robot, tls, (backends or {}).get(robot, ANY_BACKEND))
        rules += r
        subjects += s
        policies += p
    conf = {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "adminspace": {"permissions": {"read": False, "write": False}},
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        },
    }
    header = (
        "// The tether router, written by `tether deploy init` (rewritten when a robot is added: edit the\n"
        "// generator, not this file). Every client logs in as one identity of one robot"
        + (" and shows a certificate\n// with the same common name" if tls else "")
        + "; each may only send what its robot's rules allow, under\n"
        "// tether/<robot>/, and receives only that robot's traffic. Relative paths: from this file's directory.\n"
    )
    return header + json.dumps(conf, indent=2) + "\n"


@dataclass(frozen=True)
class Owners:
    """Who may use one key of schemas/keys.py, beyond receiving it (everyone of its robot may).

    A topic's `by` publish it. A service's `by` serve it and its `asked_by` query it. An action's `by`
    serve its goals (send, cancel, result, status) and alone publish its feedback and status; its
    `asked_by` are its clients: they send, cancel and follow goals.
    """

    by: tuple[str, ...]
    asked_by: tuple[str, ...] = ()


BACKENDS = ROBOT_BACKEND_IDENTITIES
# Every key any identity may put, serve or query, by the key's path in schemas/keys.py (who calls what:
# each service's node.py, the command line's tether/*.py as the operator, tether/agentapi.py as the
# agent). A key not here is denied to all but its receivers: a new key works in a deployment once it
# is granted here (tests/unit/test_deploy_owners.py names each one that is not).
OWNERS: dict[str, Owners] = {
    # The planner side: only the executor asks the parser and the resolver; plans come from the planner,
    # a person and an agent; only the planner reports its attempts.
    keys.PLAN_PARSE.path: Owners(("parser",), asked_by=("executor",)),
    keys.PLAN_RESOLVE.path: Owners(("resolver",), asked_by=("executor",)),
    keys.EXECUTE_PLAN.path: Owners(("executor",), asked_by=("planner", "operator", "agent")),
    keys.PLAN_ASK.path: Owners(("planner",), asked_by=("operator", "agent")),
    keys.PLAN_ASK_CANCEL.path: Owners(("planner",), asked_by=("operator", "agent")),
    keys.PLANNER_ATTEMPTS.path: Owners(("planner",)),
    keys.PLANNER_RECOVERIES.path: Owners(("planner",)),
    keys.SCENE.path: Owners(("resolver",), asked_by=("executor", "planner", "operator", "agent")),
    # The doors to safety: motion from the executor, and from the operator (`tether replay
    # --live-commands`); a person's stream only from the operator.
    keys.PLAN_CHECK.path: Owners(("safety",), asked_by=("executor",)),
    keys.CMD_NAVIGATE.path: Owners(("safety",), asked_by=("executor", "operator")),
    keys.CMD_TRAJECTORY.path: Owners(("safety",), asked_by=("executor", "operator")),
    keys.CMD_GRIPPER.path: Owners(("safety",), asked_by=("executor", "operator")),
    keys.CMD_VEL.path: Owners(("executor", "operator")),
    keys.TELEOP_CMD_VEL.path: Owners(("operator",)),
    # Safety: anyone stops the robot; only the operator resets, sets the mode, decides and forgets
    # (DESIGN invariant 3; safety checks the token too); only the executor asks to move a plan.
    keys.HEARTBEAT.path: Owners(("safety",)),
    keys.ESTOP.path: Owners(IDENTITIES),
    keys.SAFETY_EVENTS.path: Owners(("safety",)),
    keys.RESET.path: Owners(("safety",), asked_by=("operator",)),
    keys.SET_MODE.path: Owners(("safety",), asked_by=("operator",)),
    keys.APPROVAL_REQUEST.path: Owners(("safety",), asked_by=("executor",)),
    keys.APPROVAL_DECIDE.path: Owners(("safety",), asked_by=("operator",)),
    keys.PENDING_PLANS.path: Owners(("safety",), asked_by=("operator",)),
    keys.INCIDENTS.path: Owners(("safety",), asked_by=("planner", "operator", "agent")),
    keys.FORGET_INCIDENT.path: Owners(("safety",), asked_by=("operator",)),
    keys.INCIDENT_REPORT.path: Owners(("executor", *BACKENDS)),
    keys.NEW_INCIDENT.path: Owners(("safety",)),
    # The robot: only safety commands it; only the backend reports its state and the people near it
    # (safety slows down for them).
    keys.ROBOT_NAVIGATE.path: Owners(BACKENDS, asked_by=("safety",)),
    keys.ROBOT_TRAJECTORY.path: Owners(BACKENDS, asked_by=("safety",)),
    keys.ROBOT_GRIPPER.path: Owners(BACKENDS, asked_by=("safety",)),
    keys.ROBOT_CMD_VEL.path: Owners(("safety",)),
    keys.JOINT_STATES.path: Owners(BACKENDS),
    keys.ODOM.path: Owners(BACKENDS),
    keys.OBJECTS.path: Owners(BACKENDS),
    keys.HUMANS.path: Owners(BACKENDS),
    keys.CAMERA_IMAGE.path: Owners(BACKENDS, asked_by=("operator", "agent")),
    keys.ROBOT_DIAGNOSTICS.path: Owners(BACKENDS, asked_by=("operator", "agent")),
    # The simulated world and the recording: changed and read by a person; the recording's name by safety.
    keys.GROUND_TRUTH.path: Owners(("sim",), asked_by=("operator",)),
    keys.SIM_MOVE.path: Owners(("sim",), asked_by=("operator",)),
    keys.SIM_FAULT.path: Owners(("sim",), asked_by=("operator",)),
    keys.RECORDER_STATUS.path: Owners(("recorder",), asked_by=("safety", "operator")),
}

PUT = ["put", "delete"]
SERVE = ["declare_queryable", "reply"]
ASK = ["query"]
ALL_MESSAGES = [
    "put",
    "delete",
    "query",
    "reply",
    "declare_subscriber",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


def declared_keys() -> dict[str, keys.Topic[Any] | keys.Service[Any, Any] | keys.ActionKeys[Any, Any, Any]]:
    """Every topic, service and action schemas/keys.py defines, by its path (not only those in its tuples)."""
    kinds = (keys.Topic, keys.Service, keys.ActionKeys)
    return {v.path: v for v in vars(keys).values() if isinstance(v, kinds)}


def rights(identity: str) -> dict[str, list[str]]:
    """The key paths (under tether/<robot>/) `identity` may publish, serve and ask, from OWNERS."""
    declared = declared_keys()
    found: dict[str, list[str]] = {"publish": [], "serve": [], "ask": []}
    for path, owners in OWNERS.items():
        match declared.get(path):
            case keys.ActionKeys() as action:
                goals = [s.path for s in (action.send_goal, action.cancel_goal, action.get_result, action.get_status)]
                if identity in owners.by:
                    found["serve"] += goals
                    found["publish"] += [action.feedback.path, action.status.path]
                if identity in owners.asked_by:
                    found["ask"] += goals
            case keys.Service():
                if identity in owners.by:
                    found["serve"].append(path)
                if identity in owners.asked_by:
                    found["ask"].append(path)
            case keys.Topic() if not owners.asked_by:
                if identity in owners.by:
                    found["publish"].append(path)
            case _:
                raise DeploymentError(f"OWNERS grants {path!r}: no topic (asked by none), service or action of keys.py")
    return found


def access_rules(
    robot: str, tls: bool, backend: str = ANY_BACKEND
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
    """Rules, subjects and policies of one robot, all scoped to tether/<robot>/, for the identities
    its `backend` has (the other backend's is no subject: denied everything).

    Deny by default. Every one of the robot's identities may subscribe to and receive its robot's keys;
    beyond that each gets exactly what OWNERS grants it: it publishes only the topics (and the feedback
    and status of the actions) it owns, serves only its own services and actions, and asks only what it
    is a client of. So no service can answer in another's place or forge another's publication (a
    plan's or a command's status, the planner's attempts), and only the executor and the operator send
    goals through safety's command doors. Each identity holds a liveliness token and publishes query
    traces only under its own name; each service answers `_process/<itself>` only, and the services and
    the operator ask `_process/*`.
    """
    root = keys.prefix(robot)
    identities = robot_identities(backend)
    services = [s for s in SERVICE_IDENTITIES if s in identities]

    def rule(name: str, messages: list[str], key_exprs: Iterable[str], flow: str = "ingress") -> dict[str, Any]:
        return {
            "id": f"{robot}-{name}",
            "permission": "allow",
            "flows": [flow],
            "messages": messages,
            "key_exprs": [f"{root}/{k}" for k in key_exprs],
        }

    def own(key: str) -> str:
        return key.removeprefix(root + "/")

    rules = [
        rule("receive", ALL_MESSAGES, ["**"], flow="egress"),
        rule("subscribe", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"], ["**"]),
        # Each service's own figures (`tether status`): asked by the operator and the services, not the agent.
        rule("ask-processes", ["query"], [own(keys.process_key(robot))]),
    ]
    policies_of: dict[str, list[str]] = {}
    for identity in identities:
        granted = rights(identity)
        names = []
        for what, messages in (("publish", PUT), ("serve", SERVE), ("ask", ASK)):
            if granted[what]:
                rules.append(rule(f"{what}-{identity}", messages, granted[what]))
                names.append(f"{what}-{identity}")
        policies_of[identity] = names
    for identity in identities:
        rules.append(rule(f"alive-{identity}", ["liveliness_token"], [own(keys.alive_key(robot, identity))]))
        rules.append(rule(f"trace-{identity}", ["put"], [own(keys.trace_key(robot, identity, "**"))]))
    # Each service answers for its own process only (services/runtime.py `declare_process_status`).
    for service in services:
        rules.append(rule(f"process-{service}", SERVE, [own(keys.process_key(robot, service))]))

    subjects = []
    for identity in identities:
        name = username(robot, identity)
        # Within one subject the properties must all match: with TLS the password and the certificate
        # must both be this identity's.
        subject: dict[str, Any] = {"id": name, "usernames": [name]}
        if tls:
            subject["cert_common_names"] = [name]
        subjects.append(subject)

    def policy(name: str, rule_names: Sequence[str], members: Sequence[str]) -> dict[str, Any]:
        return {
            "id": f"{robot}-{name}",
            "rules": [f"{robot}-{r}" for r in rule_names],
            "subjects": [username(robot, i) for i in members],
        }

    people_and_services = [i for i in identities if i != "agent"]
    policies = [
        policy("everyone", ["receive", "subscribe"], identities),
        policy("ask-processes", ["ask-processes"], people_and_services),
    ]
    policies += [policy(f"rights-{i}", policies_of[i], [i]) for i in identities if policies_of[i]]
    policies += [policy(f"own-{i}", [f"alive-{i}", f"trace-{i}"], [i]) for i in identities]
    policies += [policy(f"own-process-{s}", [f"process-{s}"], [s]) for s in services]
    return rules, subjects, policies


# Certificates


def _is_utf8(text: str) -> bool:
    try:
        text.encode()
    except UnicodeEncodeError:  # bytes of another encoding, carried as surrogates
        return False
    return True


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    pkcs8 = serialization.PrivateFormat.PKCS8
    return key.private_bytes(serialization.Encoding.PEM, pkcs8, serialization.NoEncryption())


def _key_usage(*, ca: bool) -> x509.KeyUsage:
    """A CA signs certificates (and revocation lists); an identity's key only signs its TLS handshakes."""
    return x509.KeyUsage(
        digital_signature=not ca,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def _load_ca(key_path: Path, cert_path: Path) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """The CA in ca/, when it can still sign: its key, and its certificate for that key, valid now."""
    replace = f"delete {key_path.parent} and rerun to make a new CA (then reinstall every certificate and key)"
    try:
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    except (ValueError, TypeError) as exc:
        raise DeploymentError(f"the CA in {key_path.parent} is unreadable or damaged ({exc}): {replace}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise DeploymentError(f"{key_path} is not an elliptic-curve key made by tether deploy init: {replace}")
    if key.public_key() != cert.public_key():
        # Certificates signed with this key would name a CA that did not sign them: every one refused.
        raise DeploymentError(f"{key_path} is not the key of {cert_path}: {replace}")
    if dt.datetime.now(dt.UTC) >= cert.not_valid_after_utc:
        raise DeploymentError(f"the CA in {key_path.parent} expired on {cert.not_valid_after_utc:%Y-%m-%d}: {replace}")
    return key, cert


def _certificate_authority(
    directory: Path, written: list[Written]
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key_path, cert_path = directory / CA_DIR / "ca.key", directory / CA_DIR / "ca.pem"
    private_dir(directory / CA_DIR)
    if key_path.exists() and cert_path.exists():
        ca = _load_ca(key_path, cert_path)
        written += [_kept(key_path, secret=True), _kept(cert_path, secret=False)]
        return ca
    if key_path.exists() or cert_path.exists():
        raise DeploymentError(f"{directory / CA_DIR} holds only half a CA (ca.key and ca.pem go together)")
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"tether deployment CA {directory.name}")])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + CA_LIFETIME)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    written.append(_write_bytes(key_path, _key_pem(key), secret=True))
    written.append(_write_bytes(cert_path, cert.public_bytes(serialization.Encoding.PEM)))
    return key, cert


def _router_certificate(
    directory: Path,
    router: RouterAddress,
    ca: tuple[ec.EllipticCurvePrivateKey, x509.Certificate],
    written: list[Written],
) -> None:
    key_path, cert_path = directory / "router.key", directory / "router.pem"
    if _usable(key_path, cert_path, ca[1]):
        written += [_kept(key_path, secret=True), _kept(cert_path, secret=False)]
        return
    key_path.unlink(missing_ok=True)
    cert_path.unlink(missing_ok=True)
    sans = list(dict.fromkeys([router.host, "localhost", "127.0.0.1"]))
    key, cert = _issue(ca, "tether-router", sans=sans, server=True)
    written.append(_write_bytes(key_path, _key_pem(key), secret=True))
    written.append(_write_bytes(cert_path, cert.public_bytes(serialization.Encoding.PEM)))


def _usable(key_path: Path, cert_path: Path, ca_cert: x509.Certificate) -> bool:
    """Whether the certificate and key there can be kept: both there, the certificate signed by the
    deployment's CA (not one replaced since: its clients would all be refused), valid now, and for
    that key. Anything else is issued anew, with a new key."""
    if not key_path.exists() or not cert_path.exists():
        return False
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        cert.verify_directly_issued_by(ca_cert)
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError, InvalidSignature):
        return False
    now = dt.datetime.now(dt.UTC)
    in_time = cert.not_valid_before_utc <= now < cert.not_valid_after_utc
    return in_time and key.public_key() == cert.public_key()


def _issue(
    ca: tuple[ec.EllipticCurvePrivateKey, x509.Certificate], common_name: str, *, sans: Sequence[str], server: bool
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A new key and its certificate signed by the CA: a server's (with its names) or a client's."""
    ca_key, ca_cert = ca
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(min(now + CERT_LIFETIME, ca_cert.not_valid_after_utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
    )
    if sans:
        names: list[x509.GeneralName] = [
            x509.IPAddress(ipaddress.ip_address(n)) if _is_ip(n) else x509.DNSName(n) for n in sans
        ]
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return key, builder.sign(ca_key, hashes.SHA256())
