"""`tether deploy init --backend`, and a rerun that finds its password list lost."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from typer.testing import CliRunner

from tether import deployment, deployunits
from tether.cli import app

STATE = "tether/r1/robot/odom"


def users(directory: Path) -> dict[str, str]:
    lines = (directory / deployment.USERS_FILE).read_text().splitlines()
    return dict(line.split(":", 1) for line in lines)


def publishers(directory: Path, key: str) -> set[str]:
    """The users whose policies let them put `key` (read from router.json5, as the router reads it)."""
    text = (directory / deployment.ROUTER_CONFIG).read_text()
    control: dict[str, Any] = json.loads("\n".join(line for line in text.splitlines() if not line.startswith("//")))[
        "access_control"
    ]
    rules = {r["id"]: r for r in control["rules"]}
    found = set()
    for policy in control["policies"]:
        for name in policy["rules"]:
            rule = rules[name]
            if rule["flows"] == ["ingress"] and "put" in rule["messages"] and key in rule["key_exprs"]:
                found |= set(policy["subjects"])
    return found


def client_password(directory: Path, robot: str, identity: str) -> str:
    text = (directory / robot / f"{identity}.json5").read_text()
    conf = json.loads("\n".join(line for line in text.splitlines() if not line.startswith("//")))
    password: str = conf["transport"]["auth"]["usrpwd"]["password"]
    return password


def test_a_real_robot_has_no_sim_identity_login_unit_or_container(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], tls=True, backend="ros2")
    assert publishers(tmp_path, STATE) == {"r1-ros2"}
    assert "r1-sim" not in users(tmp_path) and "r1-ros2" in users(tmp_path)
    subjects = (tmp_path / deployment.ROUTER_CONFIG).read_text()
    assert '"r1-sim"' not in subjects
    assert not any((tmp_path / "r1" / f"sim{suffix}").exists() for suffix in (".json5", ".key", ".pem"))
    units = {p.name for p in (tmp_path / "systemd").glob("*.service")}
    assert "tether-r1-ros2.service" in units and "tether-r1-sim.service" not in units
    assert "Conflicts=" not in (tmp_path / "systemd" / "tether-r1-ros2.service").read_text()
    services = yaml.safe_load((tmp_path / "compose.secured.yaml").read_text())["services"]
    assert "r1-sim" not in services and "profiles" not in services["r1-ros2"], "its only backend starts with it"
    with pytest.raises(deployment.DeploymentError, match="ros2 backend, so no sim identity"):
        deployment.Deployment.load(tmp_path).client_config("r1", "sim")


def test_a_sim_robot_gives_the_ros2_identity_nothing(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], backend="sim")
    assert publishers(tmp_path, STATE) == {"r1-sim"}
    assert "r1-ros2" not in users(tmp_path)


def test_narrowing_a_robot_drops_the_other_backend_and_keeps_every_other_secret(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], tls=True)  # either backend, as before --backend
    assert publishers(tmp_path, STATE) == {"r1-sim", "r1-ros2"}
    before = users(tmp_path)
    kept = {p.name: p.read_bytes() for p in (tmp_path / "r1").iterdir() if p.is_file() and not p.name.startswith("sim")}
    deployment.init(tmp_path, ["r1"], tls=True, backend="ros2")
    assert publishers(tmp_path, STATE) == {"r1-ros2"}
    assert users(tmp_path) == {u: p for u, p in before.items() if u != "r1-sim"}
    assert not (tmp_path / "systemd" / "tether-r1-sim.service").exists()
    assert not (tmp_path / "r1" / "sim.json5").exists()
    for name, data in kept.items():
        assert (tmp_path / "r1" / name).read_bytes() == data, name
    # Adding a robot keeps r1's backend; the new one, named without --backend, has both.
    deployment.init(tmp_path, ["r2"], tls=True)
    assert publishers(tmp_path, STATE) == {"r1-ros2"}
    assert publishers(tmp_path, "tether/r2/robot/odom") == {"r2-sim", "r2-ros2"}
    made = deployment.Deployment.load(tmp_path)
    assert (made.backend("r1"), made.backend("r2")) == ("ros2", deployment.ANY_BACKEND)


def test_the_backend_is_checked_and_reported(tmp_path: Path) -> None:
    with pytest.raises(deployment.DeploymentError, match="backend 'gazebo'"):
        deployment.init(tmp_path / "a", ["r1"], backend="gazebo")
    result = CliRunner().invoke(
        app, ["deploy", "init", str(tmp_path / "b"), "--robot", "r1", "--backend", "ros2", "--json"]
    )
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["backends"] == {"r1": "ros2"}


def test_a_manifest_with_a_bad_backend_is_a_clear_error(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    manifest = json.loads((tmp_path / deployment.MANIFEST).read_text())
    (tmp_path / deployment.MANIFEST).write_text(json.dumps(manifest | {"backends": {"r1": "gazebo"}}))
    with pytest.raises(deployment.DeploymentError, match="unreadable or damaged"):
        deployment.Deployment.load(tmp_path)


def test_a_rerun_after_the_password_list_was_lost_keeps_the_installed_passwords(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    before = users(tmp_path)
    (tmp_path / deployment.USERS_FILE).unlink()
    deployment.init(tmp_path, ["r1"])
    # Every client config still logs in: the router's list holds the password each one sends.
    assert users(tmp_path) == before
    for identity in deployment.IDENTITIES:
        assert client_password(tmp_path, "r1", identity) == before[f"r1-{identity}"], identity


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_the_units_of_a_robot_of_one_backend_verify(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], backend="ros2")
    deployunits.write_all(tmp_path, ["r1"], tls=False, executable=Path(sys.executable).parent / "tether")
    for unit in sorted((tmp_path / "systemd").glob("tether-r1-*.service")):
        result = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0 and not result.stderr.strip(), f"{unit.name}:\n{result.stderr}"


def test_an_error_naming_a_long_path_is_one_line(tmp_path: Path) -> None:
    directory = tmp_path / ("deployment-" * 8)
    deployment.init(directory, ["r1"])
    (directory / "r1" / "tether.toml").write_text("[safety\n")
    result = CliRunner().invoke(app, ["deploy", "init", str(directory), "--robot", "r1"])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: ") and result.stderr.count("\n") == 1, result.stderr
    assert f"{directory / 'r1' / 'tether.toml'} is not valid TOML" in result.stderr


def test_tls_to_a_router_at_an_ipv6_address_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    with pytest.raises(deployment.DeploymentError, match="host name"):
        deployment.init(tmp_path / "d", ["r1"], tls=True, router=deployment.RouterAddress.parse("[fd00::1]:7470"))
    assert not (tmp_path / "d").exists()


def test_a_router_at_an_ipv6_address_listens_on_ipv6(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], router=deployment.RouterAddress.parse("[fd00::1]:7470"))
    assert '"tcp/[::]:7470"' in (tmp_path / deployment.ROUTER_CONFIG).read_text()
