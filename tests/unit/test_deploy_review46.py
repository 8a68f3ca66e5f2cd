"""Review 46 of `tether deploy init`: backend units that conflict with the wrong unit, router hosts and
robot names that crashed deploy init (or left a directory no rerun could use) instead of a clear error."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import NameOID
from typer.testing import CliRunner

from tether import deployment, deployunits
from tether.cli import app
from tether.deployment import DeploymentError, RouterAddress


def conflicts(directory: Path, unit: str) -> list[str]:
    text = (directory / "systemd" / f"{unit}.service").read_text()
    return [line.removeprefix("Conflicts=") for line in text.splitlines() if line.startswith("Conflicts=")]


@pytest.mark.parametrize("robot", ["sim", "ros2", "my-sim-bot", "lab-ros2"])
def test_a_backend_unit_conflicts_with_its_own_robots_other_backend(tmp_path: Path, robot: str) -> None:
    """The other backend's unit was found by replacing every `-sim` (or `-ros2`) in the unit's name:
    robot `sim`'s sim unit conflicted with robot `ros2`'s backend (starting one robot stopped the other's),
    and none with its own robot's ros2 unit, so both backends could drive the robot."""
    deployment.init(tmp_path, [robot])
    assert conflicts(tmp_path, f"tether-{robot}-sim") == [f"tether-{robot}-ros2.service"]
    assert conflicts(tmp_path, f"tether-{robot}-ros2") == [f"tether-{robot}-sim.service"]


def test_in_a_fleet_of_robots_named_sim_and_ros2_no_unit_conflicts_with_another_robots() -> None:
    for robot, service in (("sim", "sim"), ("ros2", "ros2"), ("sim", "ros2"), ("ros2", "sim")):
        unit = deployunits.service_unit(deployunits.Identity(robot, service), False, Path("/bin/true"))
        named = [line for line in unit.splitlines() if line.startswith("Conflicts=")]
        assert named == [f"Conflicts=tether-{robot}-{'ros2' if service == 'sim' else 'sim'}.service"], named


@pytest.mark.parametrize("host", ["röuter", "ロボット.lan", "١٢٣"])
def test_a_router_host_that_is_not_ascii_is_a_clear_error(host: str) -> None:
    """It passed as a host name (str.isalnum takes any script's letters and digits); with --tls the
    router's certificate then failed with cryptography's traceback, CA and keys half written."""
    with pytest.raises(DeploymentError, match=r"router address .*ASCII"):
        RouterAddress.parse(host)


def test_deploy_init_with_a_non_ascii_router_host_writes_nothing(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        app, ["deploy", "init", str(tmp_path / "d"), "--robot", "r1", "--tls", "--router", "röuter", "--json"]
    )
    assert result.exit_code == 2, result.output
    assert "röuter" in json.loads(result.stdout)["error"]
    assert not (tmp_path / "d").exists()


def test_the_idna_form_of_a_host_name_is_taken(tmp_path: Path) -> None:
    router = RouterAddress.parse("xn--ruter-jua.lan:7480")
    deployment.init(tmp_path, ["r1"], tls=True, router=router)
    cert = x509.load_pem_x509_certificate((tmp_path / "router.pem").read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "xn--ruter-jua.lan" in names.get_values_for_type(x509.DNSName)


@pytest.mark.parametrize("tls", [True, False], ids=["tls", "plain"])
def test_a_robot_name_too_long_for_its_certificates_is_refused_before_anything_is_written(
    tmp_path: Path, tls: bool
) -> None:
    """56 letters with --tls: cryptography's traceback (a common name holds 64 characters), the CA and
    the router's key written. Without --tls a longer name (a unit file name of more than 255 bytes) failed
    after deployment.json listed it, so every later run, for any robot, failed the same way."""
    longest = "r" * deployment.MAX_ROBOT_NAME
    with pytest.raises(DeploymentError, match=f"at most {deployment.MAX_ROBOT_NAME} characters"):
        deployment.init(tmp_path, [longest + "r"], tls=tls)
    assert not any(tmp_path.iterdir())
    deployment.init(tmp_path, [longest], tls=tls)
    if tls:
        cert = x509.load_pem_x509_certificate((tmp_path / longest / "operator.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == f"{longest}-operator"
    assert deployment.Deployment.load(tmp_path).robots == (longest,)


def test_a_very_long_robot_name_leaves_the_directory_usable(tmp_path: Path) -> None:
    with pytest.raises(DeploymentError, match="robot name"):
        deployment.init(tmp_path, ["r" * 240])
    deployment.init(tmp_path, ["r1"])
    assert deployment.Deployment.load(tmp_path).robots == ("r1",)
