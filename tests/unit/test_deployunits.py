"""The systemd units and compose files of `tether deploy init`: verified by systemd-analyze and the compose schema."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from services.recorder.config import RecorderConfig
from services.ros2.config import Ros2Config
from services.runtime import load_config
from services.safety.config import SafetyConfig
from services.sim.config import SimConfig
from tether import deployment, deployunits

ROBOTS = ("robot1", "robot2")
# tests/data/compose-spec/README.md says where this schema comes from.
COMPOSE_SCHEMA = Path(__file__).parents[1] / "data" / "compose-spec" / "compose-spec.json"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd_analyze = pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze is not installed here")
# `systemd-analyze verify` checks that ExecStart's program exists: the units under test name this
# environment's `tether` (write_all's `executable`) instead of the install path /opt/tether/venv/bin/tether.
EXECUTABLE = Path(sys.executable).parent / "tether"


@pytest.fixture(scope="module", params=[True, False], ids=["tls", "plain"])
def deploy_dir(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("deploy")
    deployment.init(directory, ROBOTS, tls=request.param, router=deployment.RouterAddress.parse("robothost"))
    deployunits.write_all(directory, ROBOTS, tls=request.param, executable=EXECUTABLE)
    return directory


def units(directory: Path) -> list[Path]:
    found = sorted((directory / "systemd").glob("*.service"))
    assert len(found) == 1 + len(ROBOTS) * len(deployment.SERVICE_IDENTITIES)
    return found


def unit_settings(path: Path) -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            settings.setdefault(key, []).append(value)
    return settings


def analyze(*args: str) -> subprocess.CompletedProcess[str]:
    assert SYSTEMD_ANALYZE is not None
    return subprocess.run([SYSTEMD_ANALYZE, *args], capture_output=True, text=True, timeout=60)


# systemd


@needs_systemd_analyze
def test_every_unit_verifies(deploy_dir: Path) -> None:
    for unit in units(deploy_dir):
        result = analyze("verify", str(unit))
        assert result.returncode == 0 and not result.stderr.strip(), f"{unit.name}:\n{result.stderr}"


@needs_systemd_analyze
def test_verify_catches_a_missing_program(tmp_path: Path) -> None:
    """The check above can fail: a unit whose ExecStart does not exist does not verify."""
    deployunits.write_all(tmp_path, ["robot1"], tls=False, executable=tmp_path / "no-such-tether")
    result = analyze("verify", str(tmp_path / "systemd" / "tether-robot1-safety.service"))
    assert result.returncode != 0 and "is not executable" in result.stderr


@needs_systemd_analyze
def test_every_unit_rated_3_or_better(deploy_dir: Path) -> None:
    for unit in units(deploy_dir):
        result = analyze("security", "--offline=yes", str(unit))
        match = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", result.stdout)
        assert match, f"{unit.name}: no rating in\n{result.stdout[-2000:]}\n{result.stderr}"
        assert float(match.group(1)) <= 3.0, f"{unit.name} rated {match.group(1)}:\n{result.stdout}"


def test_each_service_gets_only_its_own_files(deploy_dir: Path) -> None:
    tls = json.loads((deploy_dir / "deployment.json").read_text())["tls"]
    for robot in ROBOTS:
        for service in deployment.SERVICE_IDENTITIES:
            settings = unit_settings(deploy_dir / "systemd" / f"tether-{robot}-{service}.service")
            loaded = {value.split(":", 1)[0]: value.split(":", 1)[1] for value in settings["LoadCredential"]}
            expected = {f"{service}.json5", "systemd.toml"}
            expected |= {f"{service}.pem", f"{service}.key", "ca.pem"} if tls else set()
            expected |= {
                "safety": {"operator.token", "robot.key"},
                "sim": {"robot.key"},
                "ros2": {"robot.key"},
                "planner": {"llm-api-key"},
            }.get(service, set())
            assert set(loaded) == expected, service
            # Every credential is a file deploy init wrote for this robot, at its install path.
            for name, source in loaded.items():
                assert source == f"/etc/tether/{robot}/{name}"
                assert (deploy_dir / robot / name).is_file()
            assert settings["DynamicUser"] == ["yes"] and settings["Type"] == ["notify"]
            assert settings["NotifyAccess"] == ["main"] and settings["Restart"] == ["always"]
            assert settings["StateDirectory"] == [f"tether-{robot}-{service}"]
            (command,) = settings["ExecStart"]
            assert command.startswith(f"{EXECUTABLE} --zenoh-config ${{CREDENTIALS_DIRECTORY}}/{service}.json5 ")
            # The config as a credential too: the DynamicUser cannot read root's 600 file at its install path.
            assert command.endswith(f"--robot {robot} run {service} --config ${{CREDENTIALS_DIRECTORY}}/systemd.toml")


def test_safety_watchdog_is_the_shortest(deploy_dir: Path) -> None:
    watchdogs = {
        unit.name: int(unit_settings(unit)["WatchdogSec"][0].rstrip("s"))
        for unit in units(deploy_dir)
        if unit.name != "tether-router.service"
    }
    assert watchdogs["tether-robot1-safety.service"] == 2
    assert min(watchdogs.values()) == 2 and max(watchdogs.values()) > 2


def test_the_default_install_path_is_absolute(tmp_path: Path) -> None:
    deployunits.write_all(tmp_path, ["robot1"], tls=False)
    (command,) = unit_settings(tmp_path / "systemd" / "tether-robot1-parser.service")["ExecStart"]
    assert command.split()[0] == "/opt/tether/venv/bin/tether"


def test_router_unit_copies_the_ca_where_its_config_names_it(deploy_dir: Path) -> None:
    settings = unit_settings(deploy_dir / "systemd" / "tether-router.service")
    router = (deploy_dir / "router.json5").read_text()
    if '"ca/ca.pem"' in router:
        assert "LoadCredential=ca.pem:/etc/tether/ca/ca.pem" in [
            f"LoadCredential={v}" for v in settings["LoadCredential"]
        ]
        assert '"$RUNTIME_DIRECTORY/ca/"' in settings["ExecStartPre"][0]
    assert settings["ExecStart"] == [f"{EXECUTABLE} router ${{RUNTIME_DIRECTORY}}"]


# The services' config under systemd and in containers


@pytest.mark.parametrize("name", ["systemd.toml", "compose.toml"])
def test_managed_configs_load_into_the_services(deploy_dir: Path, name: str) -> None:
    path = deploy_dir / "robot1" / name
    safety = load_config(SafetyConfig, path, "safety")
    recorder = load_config(RecorderConfig, path, "recorder")
    sim = load_config(SimConfig, path, "sim")
    ros2 = load_config(Ros2Config, path, "ros2")
    if name == "systemd.toml":
        assert safety.operator_token_file == "/run/credentials/tether-robot1-safety.service/operator.token"
        assert safety.estop_state_file == "/var/lib/tether-robot1-safety/estop.json"
        assert sim.robot_key_file == "/run/credentials/tether-robot1-sim.service/robot.key"
        assert ros2.robot_key_file == "/run/credentials/tether-robot1-ros2.service/robot.key"
        assert recorder.output_dir == "/var/lib/tether-robot1-recorder/recordings"
    else:
        assert safety.operator_token_file == "/run/secrets/operator.token"
        assert safety.estop_state_file == "/var/lib/tether/state/estop.json"
        assert sim.robot_key_file == ros2.robot_key_file == "/run/secrets/robot.key"
        assert recorder.output_dir == "/var/lib/tether/recordings"


def test_managed_config_keeps_what_the_installer_wrote(tmp_path: Path) -> None:
    base = '[safety]\nworld = "warehouse"\nestop_state_file = "/old/estop.json"\n\n[sim]\nrealtime_factor = 2.0\n'
    text = deployunits.managed_config(base, deployunits.container_paths(), tmp_path / "tether.toml")
    data = tomllib.loads(text)
    assert data["safety"]["world"] == "warehouse" and data["sim"]["realtime_factor"] == 2.0
    assert data["safety"]["estop_state_file"] == "/var/lib/tether/state/estop.json"
    assert data["safety"]["operator_token_file"] == "/run/secrets/operator.token"  # added to its table
    assert data["recorder"]["output_dir"] == "/var/lib/tether/recordings"  # a table added


# compose


def compose_validator() -> jsonschema.protocols.Validator:
    schema = json.loads(COMPOSE_SCHEMA.read_text())
    return jsonschema.Draft201909Validator(schema, format_checker=jsonschema.Draft201909Validator.FORMAT_CHECKER)


def schema_errors(document: Any) -> list[str]:
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in compose_validator().iter_errors(document)]


@pytest.mark.parametrize("name", ["compose.yaml", "compose.secured.yaml"])
def test_compose_files_match_the_compose_specification(deploy_dir: Path, name: str) -> None:
    document = yaml.safe_load((deploy_dir / name).read_text())
    assert schema_errors(document) == []


def test_the_schema_check_can_fail() -> None:
    document = {"services": {"a": {"image": "x", "restart": "unless-stopped", "healthcheck": {"intervall": "1s"}}}}
    assert schema_errors(document) != []


@pytest.mark.parametrize("name", ["compose.yaml", "compose.secured.yaml"])
def test_compose_services(deploy_dir: Path, name: str) -> None:
    document = yaml.safe_load((deploy_dir / name).read_text())
    secured = name == "compose.secured.yaml"
    services = document["services"]
    assert set(services) == {"router"} | {
        f"{robot}-{service}" for robot in ROBOTS for service in deployment.SERVICE_IDENTITIES
    }
    for key, service in services.items():
        assert service["restart"] == "unless-stopped", key
        assert "network_mode" not in service, key
        assert service["image"] == deployunits.IMAGE
        for secret in service.get("secrets", []):
            # Every secret is a file the deployment directory holds.
            assert (deploy_dir / document["secrets"][secret["source"]]["file"]).is_file(), secret
        for config in service.get("configs", []):
            assert (deploy_dir / document["configs"][config["source"]]["file"]).is_file(), config
        if key == "router":
            continue
        robot, svc = key.split("-", 1)
        assert service["healthcheck"]["test"] == ["CMD", "tether", "status", "--check", "--service", svc]
        assert service["networks"] == ["tether"]
        targets = {s["target"] for s in service.get("secrets", [])}
        if secured:
            assert (
                f"{svc}.json5" in targets
                and service["environment"]["TETHER_ZENOH_CONFIG"] == f"/run/secrets/{svc}.json5"
            )
            assert not any(t.endswith(".json5") and t != f"{svc}.json5" for t in targets), "another's identity"
        assert ("operator.token" in targets) == (svc == "safety")
        assert ("robot.key" in targets) == (svc in ("safety", "sim", "ros2"))
        command = service["command"]
        assert command[command.index("--robot") + 1] == robot and command[command.index("run") + 1] == svc
    assert services["robot1-safety"]["volumes"] == ["robot1-safety-state:/var/lib/tether/state"]
    assert services["robot2-recorder"]["volumes"] == ["robot2-recordings:/var/lib/tether/recordings"]
    assert {"robot1-safety-state", "robot1-recordings", "robot2-safety-state"} <= set(document["volumes"])
    assert services["robot1-ros2"]["profiles"] == ["ros2"], "the real robot's backend only on request"
    if secured:
        assert "robothost" in services["router"]["networks"]["tether"]["aliases"], "the name the clients connect to"
    # The open router has no logins: only this host's loopback reaches it. The secured one, every host.
    assert services["router"]["ports"] == (["7470:7470"] if secured else ["127.0.0.1:7470:7470"])
    # The planner's LLM key is a secret file, never a variable `docker inspect` would show.
    planner = services["robot1-planner"]
    assert not any("API_KEY" in k and not k.endswith("_FILE") for k in planner["environment"]), planner
    assert planner["environment"]["TETHER_LLM_API_KEY_FILE"] == "/run/secrets/llm-api-key"
    assert {"source": "robot1-llm-api-key", "target": "llm-api-key"} in planner["secrets"]
    holders = {k for k, v in services.items() for s in v.get("secrets", []) if s["target"] == "llm-api-key"}
    assert holders == {"robot1-planner", "robot2-planner"}


def test_rerun_with_another_robot_keeps_units_of_the_first(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["robot1"], tls=False)
    deployment.init(tmp_path, ["robot2"], tls=False)
    names = {p.name for p in (tmp_path / "systemd").glob("*.service")}
    assert {"tether-robot1-safety.service", "tether-robot2-safety.service"} <= names
    services = yaml.safe_load((tmp_path / "compose.secured.yaml").read_text())["services"]
    assert {"robot1-safety", "robot2-safety"} <= set(services)


def test_a_symlink_planted_where_a_file_goes_is_replaced_not_written_through(tmp_path: Path) -> None:
    """write_text followed a link at compose.yaml to overwrite the file it named (a review's finding)."""
    directory = tmp_path / "deploy"
    deployment.init(directory, ROBOTS, tls=False, router=deployment.RouterAddress.parse("robothost"))
    victim, missing = tmp_path / "victim.txt", tmp_path / "created.txt"
    victim.write_text("kept")
    for planted, target in ((directory / "compose.yaml", victim), (directory / "robot1" / "systemd.toml", missing)):
        planted.unlink(missing_ok=True)
        planted.symlink_to(target)
    deployunits.write_all(directory, ROBOTS, tls=False, executable=EXECUTABLE)
    assert victim.read_text() == "kept" and not missing.exists()
    for written in (directory / "compose.yaml", directory / "robot1" / "systemd.toml"):
        assert not written.is_symlink() and written.stat().st_mode & 0o777 == 0o644
    assert not list(directory.glob(".compose.yaml.*")), "no temporary file left behind"
