"""systemd units and compose files for a deployment directory written by `tether deploy init`."""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from services.planner.config import KEY_FILE_ENV
from tether import deployment
from tether.deployment import SERVICE_IDENTITIES, RouterAddress, Written, write_generated

# Where the installer puts things on a host (deploy/README.md): the venv with the `tether` command, and
# the deployment directory's files, DIR/router* in /etc/tether and DIR/<robot>/ in /etc/tether/<robot>/.
TETHER_EXECUTABLE = Path("/opt/tether/venv/bin/tether")
INSTALL_DIR = Path("/etc/tether")
# The image deploy/Containerfile builds, once, for every container; its user `tether` has this uid, which
# must own the secret files on a compose host (compose mounts file secrets as they are on the host).
IMAGE = "localhost/tether:latest"
IMAGE_UID = 10001

# The robot backend for a real robot (one of SERVICE_IDENTITIES): instead of sim, never together with it.
ROS2 = "ros2"
# A robot's config under systemd (tether.toml with this layout's paths), handed to each unit as a credential.
CONFIG_CREDENTIAL = "systemd.toml"
# Seconds without WATCHDOG=1 before systemd restarts a service. Safety feeds it from its heartbeat loop
# (50 Hz): a hung safety is replaced within 2 s, while the robot, without heartbeats, has already stopped.
WATCHDOG_SEC = {"safety": 2, "sim": 5, ROS2: 5}
DEFAULT_WATCHDOG_SEC = 10
CONTAINER_HOME = Path("/var/lib/tether")
# One file per robot, given to each service that needs it.
SHARED_FILES = ("ca.pem", "operator.token", "robot.key", deployment.LLM_KEY_FILE)
OPEN_ROUTER_NOTE = (
    "# Its router lets anyone in, so its port is published on this host's loopback only (127.0.0.1):\n"
    "# other hosts use compose.secured.yaml.\n"
)


@dataclass(frozen=True)
class Identity:
    """One service of one robot: its unit, its files, what it keeps."""

    robot: str
    service: str

    @property
    def unit(self) -> str:
        return f"tether-{self.robot}-{self.service}"

    def zenoh_files(self, tls: bool) -> list[str]:
        """Its Zenoh identity in DIR/<robot>/: its client config (with its password), with TLS its
        certificate and key and the CA's certificate."""
        return [f"{self.service}.json5"] + ([f"{self.service}.pem", f"{self.service}.key", "ca.pem"] if tls else [])

    @property
    def shared_secrets(self) -> list[str]:
        """The robot's secrets it is one of the few to hold."""
        return {
            "safety": ["operator.token", "robot.key"],
            "sim": ["robot.key"],
            ROS2: ["robot.key"],
            # The LLM endpoint's API key, as a file: not in an environment `docker inspect` shows.
            "planner": [deployment.LLM_KEY_FILE],
        }.get(self.service, [])

    def credentials(self, tls: bool) -> list[str]:
        return self.zenoh_files(tls) + self.shared_secrets

    def secret_name(self, file: str) -> str:
        """The compose secret of one of its files: the robot's own for the files several services share."""
        shared = file in SHARED_FILES
        return f"{self.robot}-{file if shared else self.service + '-' + file.split('.', 1)[1]}".replace(".", "-")


def write_all(
    directory: Path,
    robots: Sequence[str],
    *,
    tls: bool,
    router: RouterAddress | None = None,
    executable: Path = TETHER_EXECUTABLE,
) -> list[Written]:
    """Write DIR/systemd/*.service, DIR/<robot>/{systemd,compose}.toml, DIR/compose.yaml and
    DIR/compose.secured.yaml for `robots` (all of the deployment's); return each file, `created`
    when its content is new or changed.

    `router` and each robot's backend default to those of the deployment's manifest. `executable` is
    the absolute `tether` in ExecStart (tests point it at one that exists, for `systemd-analyze
    verify`). Nothing here is secret, and every file is generated: a rerun overwrites an edit made to one of them."""
    try:
        made: deployment.Deployment | None = deployment.Deployment.load(directory)
    except deployment.DeploymentError:
        made = None
    router = router or (made.router if made else RouterAddress())
    backends = {robot: made.backend(robot) if made else deployment.ANY_BACKEND for robot in robots}
    written: list[Written] = []
    units = directory / "systemd"
    for own in (units, directory / "compose", *(directory / robot for robot in robots)):
        deployment.private_dir(own)
    written.append(write_generated(units / "tether-router.service", router_unit(tls, executable)))
    for robot in robots:
        identities = deployment.robot_identities(backends[robot])
        for service in SERVICE_IDENTITIES:
            path = units / f"tether-{robot}-{service}.service"
            if service not in identities:
                path.unlink(missing_ok=True)  # the other backend's, of a robot that had both: it has no login now
                continue
            alone = service in deployment.ROBOT_BACKEND_IDENTITIES and backends[robot] != deployment.ANY_BACKEND
            written.append(write_generated(path, service_unit(Identity(robot, service), tls, executable, alone=alone)))
        source = directory / robot / "tether.toml"
        base = _installer_config(source)
        written.append(
            write_generated(directory / robot / CONFIG_CREDENTIAL, managed_config(base, systemd_paths(robot), source))
        )
        written.append(
            write_generated(directory / robot / "compose.toml", managed_config(base, container_paths(), source))
        )
    port, name = router.port, router.container_alias
    written.append(write_generated(directory / "compose" / "router.json5", open_router_config(port)))
    written.append(write_generated(directory / "compose" / "client.json5", open_client_config(port)))
    written.append(
        write_generated(
            directory / "compose.yaml", compose_yaml(robots, tls=tls, secured=False, port=port, backends=backends)
        )
    )
    written.append(
        write_generated(
            directory / "compose.secured.yaml",
            compose_yaml(robots, tls=tls, secured=True, port=port, router_host=name, backends=backends),
        )
    )
    return written


# systemd

HARDENING = """\
# Hardening: `systemd-analyze security {unit}.service` rates this 3.0 or better (tests/unit/test_deployunits.py).
# DynamicUser: a user of its own for each start, no home, reads only what LoadCredential gives it.
DynamicUser=yes
UMask=0077
ProtectSystem=strict
ProtectHome=yes
PrivateTmp=yes
PrivateDevices=yes
PrivateIPC=yes
PrivateUsers=yes
ProtectKernelTunables=yes
ProtectKernelModules=yes
ProtectKernelLogs=yes
ProtectControlGroups=yes
ProtectClock=yes
ProtectHostname=yes
ProtectProc=invisible
# Zenoh over TCP/TLS, sd_notify over AF_UNIX; AF_NETLINK to list the host's interfaces.
RestrictAddressFamilies=AF_INET AF_INET6 AF_UNIX AF_NETLINK
RestrictNamespaces=yes
RestrictRealtime=yes
RestrictSUIDSGID=yes
LockPersonality=yes
# Checked with the kernel's PR_SET_MDWE: pybullet, numpy and OMPL map no writable code.
MemoryDenyWriteExecute=yes
NoNewPrivileges=yes
RemoveIPC=yes
KeyringMode=private
DevicePolicy=closed
CapabilityBoundingSet=
AmbientCapabilities=
SystemCallArchitectures=native
SystemCallFilter=@system-service
SystemCallFilter=~@privileged @resources
SystemCallErrorNumber=EPERM
"""


def service_unit(identity: Identity, tls: bool, executable: Path, *, alone: bool = False) -> str:
    """The unit of one service; `alone`: a robot backend whose robot has no other one to conflict with."""
    robot, service, unit = identity.robot, identity.service, identity.unit
    home = INSTALL_DIR / robot
    # The config too: a DynamicUser reads nothing of root's 600 files in /etc/tether but what
    # LoadCredential hands it (with --config at its install path every start failed, EACCES).
    credentials = "\n".join(
        f"LoadCredential={name}:{home / name}" for name in (*identity.credentials(tls), CONFIG_CREDENTIAL)
    )
    # Its robot's other backend, by name: never one of another robot's units (robot `sim`, `lab-ros2`).
    other = {"sim": ROS2, ROS2: "sim"}.get(service)
    backend = "" if alone or other is None else f"Conflicts={Identity(robot, other).unit}.service\n"
    start = (
        "# It is ready once the robot reports, which may take a while after boot; until then it holds the robot.\n"
        "TimeoutStartSec=infinity\n"
        if service == ROS2
        # The executor builds its planners before it is ready.
        else "TimeoutStartSec=120\n"
    )
    command = (
        f"{executable} --zenoh-config ${{CREDENTIALS_DIRECTORY}}/{service}.json5 --robot {robot} "
        f"run {service} --config ${{CREDENTIALS_DIRECTORY}}/{CONFIG_CREDENTIAL}"
    )
    feeders = {"safety": " from the heartbeat loop", "sim": " from the physics loop", ROS2: " from the heartbeat watch"}
    fed_from = feeders.get(service, "")
    environment = ""
    if service == "planner":
        environment = (
            "# The LLM endpoint: TETHER_LLM_URL, TETHER_LLM_MODEL (services/planner/README.md); its API key\n"
            f"# from the credential {deployment.LLM_KEY_FILE} (empty: none).\n"
            f"EnvironmentFile=-{home / 'planner.env'}\n"
            f"Environment={KEY_FILE_ENV}=%d/{deployment.LLM_KEY_FILE}\n"
        )
    return f"""\
# tether {service} of robot {robot}, written by `tether deploy init` (deploy/README.md, "systemd").
# Its files come from {home}/ (a copy of the deployment directory's {robot}/, kept root-only):
# LoadCredential hands them to this service alone, in $CREDENTIALS_DIRECTORY; the Zenoh config's
# relative paths resolve there. {home / "systemd.toml"} is tether.toml with the paths of this layout.
[Unit]
Description=tether {service} of robot {robot}
Documentation=file:///opt/tether/deploy/README.md
After=network-online.target
Wants=network-online.target
{backend}# Restart however often it fails: a robot stays stopped without safety and its backend.
StartLimitIntervalSec=0

[Service]
Type=notify
NotifyAccess=main
# systemd restarts it (SIGABRT, then start again) when WATCHDOG=1 stops coming{fed_from}.
WatchdogSec={WATCHDOG_SEC.get(service, DEFAULT_WATCHDOG_SEC)}s
Restart=always
RestartSec=1s
{start}# SIGTERM is a clean stop: the recorder finishes its MCAP file, safety and the robot backend stop the robot.
TimeoutStopSec=15
{credentials}
StateDirectory={unit}
StateDirectoryMode=0700
WorkingDirectory=%S/{unit}
Environment=TETHER_LOG_LEVEL=INFO
{environment}ExecStart={command}
{HARDENING.format(unit=unit)}
[Install]
WantedBy=multi-user.target
"""


def router_unit(tls: bool, executable: Path) -> str:
    files = ["router.json5", "router-users.txt"] + (["router.pem", "router.key", "ca.pem"] if tls else [])
    credentials = "\n".join(
        f"LoadCredential={name}:{INSTALL_DIR / ('ca/ca.pem' if name == 'ca.pem' else name)}" for name in files
    )
    # A credential is a file name, and router.json5 names the CA ca/ca.pem (from its own directory): the
    # router runs from a copy in its private runtime directory (memory, this unit's user only).
    ca = '&& mkdir "$RUNTIME_DIRECTORY/ca" && mv "$RUNTIME_DIRECTORY/ca.pem" "$RUNTIME_DIRECTORY/ca/" ' if tls else ""
    copy = f"""/bin/sh -c 'cp "$CREDENTIALS_DIRECTORY"/* "$RUNTIME_DIRECTORY"/ {ca}'"""
    return f"""\
# The tether Zenoh router, written by `tether deploy init` (deploy/README.md, "systemd").
# Its files come from {INSTALL_DIR}/ (the deployment directory's {", ".join(files)});
# never the CA's key, which stays on the machine that ran `tether deploy init`.
[Unit]
Description=tether Zenoh router
Documentation=file:///opt/tether/deploy/README.md
After=network-online.target
Wants=network-online.target
StartLimitIntervalSec=0

[Service]
Type=simple
Restart=always
RestartSec=1s
{credentials}
RuntimeDirectory=tether-router
RuntimeDirectoryMode=0700
ExecStartPre={copy}
ExecStart={executable} router ${{RUNTIME_DIRECTORY}}
{HARDENING.format(unit="tether-router")}
[Install]
WantedBy=multi-user.target
"""


# The services' config under a service manager: tether.toml with the paths where that manager puts
# the secrets and the state.


def systemd_paths(robot: str) -> dict[tuple[str, str], str]:
    def credential(service: str, name: str) -> str:
        # $CREDENTIALS_DIRECTORY of that unit: systemd mounts it at /run/credentials/<unit name>.
        return f"/run/credentials/tether-{robot}-{service}.service/{name}"

    return {
        ("safety", "operator_token_file"): credential("safety", "operator.token"),
        ("safety", "estop_state_file"): f"/var/lib/tether-{robot}-safety/estop.json",
        # Beside the e-stop's state, not the token's default place: the credentials are read-only.
        ("safety", "mode_state_file"): f"/var/lib/tether-{robot}-safety/mode.json",
        ("safety", "robot_key_file"): credential("safety", "robot.key"),
        ("sim", "robot_key_file"): credential("sim", "robot.key"),
        (ROS2, "robot_key_file"): credential(ROS2, "robot.key"),
        ("recorder", "output_dir"): f"/var/lib/tether-{robot}-recorder/recordings",
    }


def container_paths() -> dict[tuple[str, str], str]:
    return {
        ("safety", "operator_token_file"): "/run/secrets/operator.token",
        ("safety", "estop_state_file"): str(CONTAINER_HOME / "state" / "estop.json"),
        ("safety", "mode_state_file"): str(CONTAINER_HOME / "state" / "mode.json"),
        ("safety", "robot_key_file"): "/run/secrets/robot.key",
        ("sim", "robot_key_file"): "/run/secrets/robot.key",
        (ROS2, "robot_key_file"): "/run/secrets/robot.key",
        ("recorder", "output_dir"): str(CONTAINER_HOME / "recordings"),
    }


def _installer_config(source: Path) -> str:
    """A robot's tether.toml as the installer left it ("" when there is none); a clear error when it is not TOML."""
    if not source.exists():
        return ""
    try:
        text = source.read_text()
        tomllib.loads(text)
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise deployment.DeploymentError(f"{source} is not valid TOML ({exc}): fix it and rerun") from None
    return text


_TABLE = re.compile(r"^\s*\[([A-Za-z0-9_.-]+)\]\s*(#.*)?$")
_KEY = re.compile(r"^\s*([A-Za-z0-9_-]+)\s*=")


def managed_config(base: str, paths: dict[tuple[str, str], str], source: Path) -> str:
    """`base` (a robot's tether.toml) with `paths` set: each line of a key replaced, or the key added
    to its table, or the table added; everything else (world, policy, ...) as the installer wrote it."""
    pending = dict(paths)
    lines = base.splitlines()
    out: list[str] = []
    table = ""

    def flush(name: str) -> None:
        for (t, key), value in list(pending.items()):
            if t == name:
                out.append(f"{key} = {json.dumps(value)}")
                del pending[(t, key)]

    for line in lines:
        if match := _TABLE.match(line):
            flush(table)
            table = match.group(1)
        elif (match := _KEY.match(line)) and (table, match.group(1)) in pending:
            line = f"{match.group(1)} = {json.dumps(pending.pop((table, match.group(1))))}"
        out.append(line)
    flush(table)
    for name in dict.fromkeys(t for t, _ in pending):
        out += ["", f"[{name}]"]
        flush(name)
    header = (
        f"# Written by `tether deploy init` from {source.name}, with the paths of this service manager's\n"
        "# secrets and state. Edit tether.toml and rerun `tether deploy init` (or edit both).\n"
    )
    text = header + "\n".join(out) + "\n"
    try:
        tomllib.loads(text)  # neither a bug here nor a layout it does not follow may reach a robot
    except tomllib.TOMLDecodeError as exc:
        raise deployment.DeploymentError(
            f"cannot set this host's paths in {source} ({exc}): write each of its tables as a [table] "
            "header with one `key = value` per line (no dotted, quoted or inline keys), and rerun"
        ) from None
    return text


# compose


def open_router_config(port: int) -> str:
    conf = {
        "mode": "router",
        "listen": {"endpoints": [f"tcp/0.0.0.0:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
    }
    return (
        "// The router of compose.yaml (the open variant, for trying tether on one host): no logins, no\n"
        "// access control. compose.secured.yaml uses ../router.json5. Written by `tether deploy init`.\n"
        + json.dumps(conf, indent=2)
        + "\n"
    )


def open_client_config(port: int) -> str:
    conf = {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/router:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
    }
    return (
        "// Every service of compose.yaml (the open variant): the router by its compose service name.\n"
        + json.dumps(conf, indent=2)
        + "\n"
    )


def compose_yaml(
    robots: Sequence[str],
    *,
    tls: bool,
    secured: bool,
    port: int,
    router_host: str | None = None,
    backends: Mapping[str, str] | None = None,
) -> str:
    secrets: dict[str, Any] = {}
    configs: dict[str, Any] = {}
    volumes: dict[str, Any] = {}
    services: dict[str, Any] = {"router": _router_service(secured, tls, port, secrets, configs, router_host)}
    if not secured:
        configs["client"] = {"file": "./compose/client.json5"}
    for robot in robots:
        configs[f"{robot}-config"] = {"file": f"./{robot}/compose.toml"}
        volumes[f"{robot}-safety-state"] = {}
        volumes[f"{robot}-recordings"] = {}
        backend = (backends or {}).get(robot, deployment.ANY_BACKEND)
        for service in deployment.robot_identities(backend):
            if service in SERVICE_IDENTITIES:
                entry = _service(Identity(robot, service), secured, tls, secrets)
                if service == ROS2 and backend == deployment.ANY_BACKEND:
                    entry["profiles"] = [ROS2]  # a robot that may run either: the sim unless asked
                services[f"{robot}-{service}"] = entry
    document = {
        "services": services,
        "networks": {"tether": {"driver": "bridge"}},
        "volumes": volumes,
        "secrets": secrets,
        "configs": configs,
    }
    variant = (
        "the secured variant: the router of router.json5 (logins, access control per robot"
        + (", mutual TLS" if tls else "")
        + "), each service with its own identity"
        if secured
        else "the open variant, to try tether on one host: a router without logins or access control"
    )
    header = f"""\
# tether in containers, {variant}.
# Written by `tether deploy init` (rewritten on every run); deploy/README.md, "compose", walks through it.
#   podman build -f deploy/Containerfile -t {IMAGE} .     (from the repository root, once)
#   docker compose -f {"compose.secured.yaml" if secured else "compose.yaml"} up -d      (or podman compose)
# One container per service, each on the `tether` network (none shares another's network namespace),
# reaching the router by its service name; each gets only its own files as secrets. Compose mounts
# them as they are on the host: they must be readable by uid {IMAGE_UID}, the image's user
# (sudo chown -R {IMAGE_UID} <robot>/). Safety's latch and the recordings live on named volumes.
# A robot of either backend (`deploy init` without --backend) has sim and ros2 (a real robot's backend),
# which starts only with `--profile ros2`; a robot of one backend has only that one. The planner's LLM
# endpoint: $TETHER_LLM_URL and $TETHER_LLM_MODEL of the shell that runs compose; its API key, if it
# wants one, in <robot>/{deployment.LLM_KEY_FILE} (a secret file, not a variable `docker inspect` shows).
{"" if secured else OPEN_ROUTER_NOTE}"""
    return header + yaml.safe_dump(document, sort_keys=False, width=120)


def _router_service(
    secured: bool,
    tls: bool,
    port: int,
    secrets: dict[str, Any],
    configs: dict[str, Any],
    router_host: str | None,
) -> dict[str, Any]:
    service: dict[str, Any] = {"image": IMAGE}
    if secured:
        files = ["router.json5", "router-users.txt"] + (["router.pem", "router.key", "ca/ca.pem"] if tls else [])
        for name in files:
            secrets[f"router-{name.replace('/', '-')}"] = {"file": f"./{name}"}
        service["secrets"] = [{"source": f"router-{name.replace('/', '-')}", "target": name} for name in files]
        service["command"] = ["router", "/run/secrets"]
    else:
        configs["router"] = {"file": "./compose/router.json5"}
        service["configs"] = [{"source": "router", "target": "/etc/tether/router/router.json5"}]
        service["command"] = ["router", "/etc/tether/router"]
    aliases = ["router"] + ([router_host] if router_host and router_host != "router" else [])
    service["networks"] = {"tether": {"aliases": aliases}}
    # Secured: published on every interface, for the services and people on other hosts (drop it
    # when everything runs here). Open: it lets anyone in, so only this host's loopback reaches it.
    service["ports"] = [f"{port}:{port}" if secured else f"127.0.0.1:{port}:{port}"]
    service["restart"] = "unless-stopped"
    return service


def _service(identity: Identity, secured: bool, tls: bool, secrets: dict[str, Any]) -> dict[str, Any]:
    robot, service = identity.robot, identity.service
    names = identity.credentials(tls) if secured else identity.shared_secrets
    for name in names:
        secrets[identity.secret_name(name)] = {"file": f"./{robot}/{name}"}
    zenoh = "/run/secrets/" + f"{service}.json5" if secured else "/etc/tether/client.json5"
    entry: dict[str, Any] = {
        "image": IMAGE,
        "command": ["--zenoh-config", zenoh, "--robot", robot, "run", service, "--config", "/etc/tether/tether.toml"],
        # The same identity for the health probe (`tether status --check`), which reads these.
        "environment": {"TETHER_ROBOT": robot, "TETHER_ZENOH_CONFIG": zenoh, "TETHER_LOG_LEVEL": "INFO"},
        "configs": [{"source": f"{robot}-config", "target": "/etc/tether/tether.toml"}]
        + ([] if secured else [{"source": "client", "target": "/etc/tether/client.json5"}]),
        "networks": ["tether"],
        "depends_on": {"router": {"condition": "service_started"}},
        "restart": "unless-stopped",
        "stop_grace_period": "15s",
        "healthcheck": {
            "test": ["CMD", "tether", "status", "--check", "--service", service],
            "interval": "10s",
            "timeout": "5s",
            "retries": 3,
            "start_period": "120s" if service in ("executor", ROS2) else "60s",
        },
    }
    if names:
        entry["secrets"] = [{"source": identity.secret_name(name), "target": name} for name in names]
    if service == "safety":
        entry["volumes"] = [f"{robot}-safety-state:{CONTAINER_HOME / 'state'}"]
    elif service == "recorder":
        entry["volumes"] = [f"{robot}-recordings:{CONTAINER_HOME / 'recordings'}"]
    elif service == "planner":
        entry["environment"] |= {
            "TETHER_LLM_URL": "${TETHER_LLM_URL:-}",
            "TETHER_LLM_MODEL": "${TETHER_LLM_MODEL:-}",
            KEY_FILE_ENV: f"/run/secrets/{deployment.LLM_KEY_FILE}",
        }
    return entry
