"""Policy files an operator got wrong: refused at start naming the file and the entry, never read in
a form that loosens what safety enforces."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from services import datafile
from services.robotmodel import ArmModel
from services.safety.policyfile import DEFAULT_POLICY, Limits, PolicyError, load_policy
from services.worldmodel import load_world

WORLD = load_world()
DEFAULT_TOML = DEFAULT_POLICY.read_text()
# The default policy with a zone of its own, in YAML, as an operator who prefers YAML writes it.
POLICY_YAML = """\
base: {max_linear_speed: 0.6, max_angular_speed: 1.2, max_linear_acceleration: 1.5, max_angular_acceleration: 3.0}
arm: {max_joint_speed: 1.5}
workspace: {min: {x: -0.45, y: -0.95, z: 0.3}, max: {x: 1.2, y: 0.95, z: 1.9}}
payload: {max_mass: 3.0}
gripper: {max_force: 70.0}
humans: {slow_distance: 1.5, stop_distance: 0.2, reduced_speed_scale: 0.4}
rate: {max_goals_per_second: 10, max_cmd_vel_per_second: 1200}
keep_out:
  - {id: nursery, name: nursery, polygon: [[1.0, 6.0], [3.0, 6.0], [3.0, 8.0], [1.0, 8.0]]}
"""

NURSERY_TOML = """
[[keep_out]]
id = "nursery"
name = "nursery"
polygon = [[1.0, 6.0], [3.0, 6.0], [3.0, 8.0], [1.0, 8.0]]
"""


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel(WORLD.robot.arm_urdf)


def load(path: Path, arm: ArmModel) -> Limits:
    return load_policy(path, WORLD.robot, arm, WORLD.keep_out)


def refused(path: Path, arm: ArmModel, error: str) -> None:
    with pytest.raises(PolicyError, match=rf"^policy file {re.escape(str(path))}: {error}"):
        load(path, arm)


def test_the_hand_written_yaml_policy_loads_with_its_zone(tmp_path: Path, arm: ArmModel) -> None:
    path = tmp_path / "policy.yaml"
    path.write_text(POLICY_YAML)
    assert [zone.id for zone in load(path, arm).keep_out] == ["stairs", "nursery"]


def test_a_second_keep_out_key_in_yaml_is_refused_not_read_as_dropping_the_first(tmp_path: Path, arm: ArmModel) -> None:
    # YAML loaders keep the last of two equal keys: the nursery would have gone unguarded.
    path = tmp_path / "policy.yaml"
    path.write_text(POLICY_YAML + "keep_out: []\n")
    refused(path, arm, r"key 'keep_out' appears twice in one mapping \(line 10\)")


def test_a_limit_given_twice_in_yaml_is_refused(tmp_path: Path, arm: ArmModel) -> None:
    path = tmp_path / "policy.yml"
    text = POLICY_YAML.replace("max_mass: 3.0}", "max_mass: 1.0, max_mass: 3.0}")
    path.write_text(text)
    refused(path, arm, r"key 'max_mass' appears twice in one mapping \(line 4\)")


@pytest.mark.parametrize("z", [-0.5, -10.0])
def test_a_workspace_reaching_below_the_floor_is_refused(tmp_path: Path, arm: ArmModel, z: float) -> None:
    path = tmp_path / "policy.toml"
    path.write_text(
        DEFAULT_TOML.replace("min = { x = -0.45, y = -0.95, z = 0.3 }", f"min = {{ x = -0.45, y = -0.95, z = {z} }}")
    )
    refused(path, arm, rf"workspace\.min\.z: {z:g} m is below the floor")


def test_a_workspace_down_to_the_floor_loads(tmp_path: Path, arm: ArmModel) -> None:
    path = tmp_path / "policy.toml"
    path.write_text(DEFAULT_TOML.replace("z = 0.3 }", "z = 0.0 }") + NURSERY_TOML)
    limits = load(path, arm)
    assert limits.policy.workspace.min.z == 0.0
    assert [zone.id for zone in limits.keep_out] == ["stairs", "nursery"]


def test_a_huge_policy_file_is_refused_unread(tmp_path: Path, arm: ArmModel) -> None:
    path = tmp_path / "policy.toml"
    with path.open("wb") as file:
        file.truncate(datafile.MAX_FILE_BYTES + 1)  # sparse: no disk for the test
    refused(path, arm, rf"more than {datafile.MAX_FILE_BYTES} bytes; not read")


@pytest.mark.parametrize(
    ("content", "said"),
    [
        (b'[limits]\nx = "\xff"\n', "not UTF-8 text"),
        (b"x = " + b"[" * 100_000 + b"]" * 100_000 + b"\n", "nested too deeply"),
        (b"x = 1" + b"0" * 5000 + b"\n", "digits"),
    ],
)
def test_a_toml_policy_its_reader_chokes_on_is_refused_naming_it(
    tmp_path: Path, arm: ArmModel, content: bytes, said: str
) -> None:
    """A recording's policy file is anyone's: tether recheck ended in a traceback on each of these."""
    path = tmp_path / "policy.toml"
    path.write_bytes(content)
    with pytest.raises(PolicyError, match=rf"^policy file {re.escape(str(path))} is not valid TOML: .*{said}"):
        load(path, arm)
