"""The world file's robot.arm_urdf is read as the other data files are: a regular file, bounded, a
relative path inside pybullet_data's folder; anything else is one error naming the field, from the
world's loading and from ArmModel alike, never a hang or a read without end."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.bundled import world_path
from services.datafile import MAX_FILE_BYTES
from services.robotmodel import ArmModel, arm_urdf_path
from services.worldmodel import WorldFileError, load_world

PANDA = "franka_panda/panda.urdf"
ROOT = Path(__file__).resolve().parents[2]
# Long enough for a child process to import pinocchio and load on a loaded machine; a load that
# takes longer hangs, and fails the test.
DEADLINE = 60.0
# The load in a child process, printing what it raised.
CHILD = """
import sys
from services.robotmodel import ArmModel
from services.worldmodel import load_world
try:
    ArmModel(sys.argv[2]) if sys.argv[1] == "arm" else load_world(sys.argv[2])
except Exception as exc:
    print(f"{type(exc).__name__}: {exc}")
"""


def world_naming(tmp_path: Path, arm_urdf: str) -> Path:
    """The household world, its robot.arm_urdf `arm_urdf`, as a file in tmp_path."""
    text = world_path("household").read_text()
    assert "arm_urdf" not in text, "the bundled world names no arm_urdf: the default"
    robot = text.index("\nrobot:\n") + len("\nrobot:\n")
    # Indented as the next line of the robot's mapping is.
    indent = text[robot:].index(text[robot:].lstrip(" ")[0])
    path = tmp_path / "world.yaml"
    path.write_text(f"{text[:robot]}{' ' * indent}arm_urdf: {arm_urdf!r}\n{text[robot:]}")
    return path


def raised_in_a_child(load: str, path: Path) -> str:
    """What `ArmModel(path)` (load "arm") or `load_world(path)` ("world") raised, as "Type: message"
    ("" when nothing), run in a child process that is killed past DEADLINE: pinocchio holds the GIL
    while it waits to open a FIFO, so no thread of this process could give up on it."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", CHILD, load, str(path)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=DEADLINE,
            check=True,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"{load} {path}: still loading after {DEADLINE:g} s; it hangs")
    return done.stdout.strip()


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "arm.urdf"
    os.mkfifo(path)
    return path


@pytest.fixture
def huge(tmp_path: Path) -> Path:
    path = tmp_path / "huge.urdf"
    with path.open("wb") as file:
        file.truncate(MAX_FILE_BYTES + 1)  # sparse: no disk taken
    return path


def test_a_fifo_named_as_the_arm_urdf_is_refused_not_waited_on(tmp_path: Path, fifo: Path) -> None:
    refused = raised_in_a_child("world", world_naming(tmp_path, str(fifo)))
    assert refused.startswith("WorldFileError: ") and f"robot.arm_urdf {str(fifo)!r}" in refused, refused
    assert "is not a regular file" in refused
    refused = raised_in_a_child("arm", fifo)
    assert refused.startswith("ValueError: ") and f"robot.arm_urdf {str(fifo)!r}" in refused, refused
    assert "is not a regular file" in refused


def test_the_world_refuses_a_device_or_a_huge_file_as_its_arm_urdf(tmp_path: Path, huge: Path) -> None:
    for arm_urdf, why in [
        ("/dev/zero", "is not a regular file"),
        (str(huge), f"{huge}: more than {MAX_FILE_BYTES} bytes; not read"),
    ]:
        with pytest.raises(WorldFileError) as refused:
            load_world(world_naming(tmp_path, arm_urdf))
        assert f"robot.arm_urdf {arm_urdf!r}" in str(refused.value) and why in str(refused.value)


def test_arm_model_reads_its_urdf_bounded_not_whatever_the_path_is(huge: Path) -> None:
    # Not /dev/zero here: the code before read it until memory ran out.
    for arm_urdf, why in [
        (Path("/dev/null"), "is not a regular file"),
        (huge, f"{huge}: more than {MAX_FILE_BYTES} bytes; not read"),
    ]:
        with pytest.raises(ValueError) as refused:
            ArmModel(arm_urdf)
        assert f"robot.arm_urdf {str(arm_urdf)!r}" in str(refused.value) and why in str(refused.value)


def test_a_missing_or_unreadable_arm_urdf_is_one_error_naming_the_field_and_where_it_looked(tmp_path: Path) -> None:
    with pytest.raises(WorldFileError) as missing:
        load_world(world_naming(tmp_path, "franka_panda/no_such_arm.urdf"))
    message = str(missing.value)
    assert "robot.arm_urdf 'franka_panda/no_such_arm.urdf'" in message and "world.yaml" in message
    assert str(arm_urdf_path("franka_panda/no_such_arm.urdf")) in message, "where a relative path was looked for"
    with pytest.raises(WorldFileError, match=r"robot\.arm_urdf 'franka_panda': "):
        load_world(world_naming(tmp_path, "franka_panda"))  # a folder
    latin = tmp_path / "latin.urdf"
    latin.write_bytes(b"<robot name='\xe9'/>")
    with pytest.raises(ValueError, match=r"robot\.arm_urdf .*not UTF-8"):
        ArmModel(latin)


def test_the_urdfs_that_ship_with_pybullet_and_a_copy_elsewhere_still_load(tmp_path: Path) -> None:
    assert load_world(world_naming(tmp_path, PANDA)).robot.arm_urdf == PANDA
    shipped = ArmModel(PANDA)
    copy = tmp_path / "panda_copy.urdf"
    copy.write_bytes(arm_urdf_path(PANDA).read_bytes())
    assert load_world(world_naming(tmp_path, str(copy))).robot.arm_urdf == str(copy)
    elsewhere = ArmModel(copy)
    q = [0.0, -1.3, 0.0, -2.35, 0.0, 1.05, 0.785]
    assert elsewhere.joint_names == shipped.joint_names
    assert elsewhere.grasp_point(q).tolist() == pytest.approx(shipped.grasp_point(q).tolist())
    assert (elsewhere.lower == shipped.lower).all() and (elsewhere.upper == shipped.upper).all()
