"""Data files as an operator or an attacker could leave them: each refused with one error naming the
file and what is wrong, never a traceback, a hang, or a world or policy that guards less than it says."""

from __future__ import annotations

import contextlib
import json
import os
import re
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from services.parser.text import load_grammar
from services.parser.vocabulary import VocabularyError, default_vocabulary_path, load_vocabulary
from services.robotmodel import ArmModel
from services.safety.policy import load_safety_policy
from services.safety.policyfile import DEFAULT_POLICY, PolicyError, load_policy
from services.worldmodel import DEFAULT_WORLD, WorldFileError, load_world, world_path

HOUSEHOLD = world_path(DEFAULT_WORLD).read_text()
WORLD = load_world()
STAIRS = "polygon: [[10.5, 7], [12, 7], [12, 9], [10.5, 9]]"
# Long enough to wait for a load that is going to finish; a hung one never does.
LOAD_DEADLINE = 10.0


def world_file(tmp_path: Path, old: str, new: str) -> Path:
    """The household world with one piece of text replaced, written to a file."""
    assert HOUSEHOLD.count(old) == 1, old
    path = tmp_path / "world.yaml"
    path.write_text(HOUSEHOLD.replace(old, new))
    return path


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel(WORLD.robot.arm_urdf)


def release(fifo: Path) -> None:
    """Let go a reader still blocked opening `fifo`: a writer that opens and closes gives it its end of file."""
    with contextlib.suppress(OSError):  # no reader blocked on it
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))


def finished(load: Callable[[], object]) -> BaseException | None:
    """What `load` raised (None if nothing), failing the test if it has not returned by the deadline."""
    outcome: list[BaseException | None] = []

    def run() -> None:
        try:
            load()
        except BaseException as exc:  # handed to the test to judge
            outcome.append(exc)
        else:
            outcome.append(None)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(LOAD_DEADLINE)
    assert outcome, f"still loading after {LOAD_DEADLINE} s: it waits on the file for ever"
    return outcome[0]


@pytest.mark.parametrize(
    ("what", "suffix"), [("world", ".yaml"), ("policy", ".toml"), ("vocabulary", ".yaml"), ("grammar", ".yaml")]
)
def test_a_fifo_named_as_a_data_file_is_refused_not_waited_on(
    tmp_path: Path, arm: ArmModel, what: str, suffix: str
) -> None:
    readers: dict[str, Callable[[Path], object]] = {
        "world": load_world,
        "policy": lambda path: load_policy(path, WORLD.robot, arm, WORLD.keep_out),
        "vocabulary": load_vocabulary,
        "grammar": load_grammar,
    }
    fifo = tmp_path / f"{what}{suffix}"
    os.mkfifo(fifo)
    try:
        raised = finished(lambda: readers[what](fifo))
    finally:
        release(fifo)
    assert isinstance(raised, (WorldFileError, PolicyError, VocabularyError)), raised
    assert str(raised) == f"{what} file {fifo} is not a regular file"


def test_a_device_named_as_a_world_is_refused_unread() -> None:
    # /dev/zero was read to the size limit (16 MB into memory) before it was refused.
    with pytest.raises(WorldFileError, match=r"^world file /dev/zero is not a regular file$"):
        load_world(Path("/dev/zero"))


def test_a_directory_named_as_a_world_is_refused_and_its_descriptor_closed(tmp_path: Path) -> None:
    """Each refusal of a directory left the descriptor opened on it open: a service asked again and
    again (a reloaded world, a config) ran out of descriptors."""
    path = tmp_path / "world.yaml"
    path.mkdir()
    descriptors = len(os.listdir("/proc/self/fd"))
    for _ in range(20):
        with pytest.raises(WorldFileError, match=rf"^world file {re.escape(str(path))} is not a regular file$"):
            load_world(path)
    assert len(os.listdir("/proc/self/fd")) == descriptors


def test_a_symlink_loop_named_as_a_world_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "world.yaml"
    path.symlink_to(path)
    with pytest.raises(WorldFileError, match=rf"^cannot read world file {re.escape(str(path))}: Too many levels"):
        load_world(path)


def test_a_json_world_that_is_not_utf8_is_refused_naming_it(tmp_path: Path) -> None:
    # msgspec's JSON decoder raised UnicodeDecodeError: a traceback, the file not named.
    path = tmp_path / "world.json"
    path.write_bytes(b'{"name": "house\xffhold"}')
    with pytest.raises(WorldFileError, match=rf"^world file {re.escape(str(path))} is not valid JSON: not UTF-8"):
        load_world(path)


def test_a_json_vocabulary_that_is_not_utf8_is_refused_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "vocabulary.json"
    path.write_bytes(b'{"actions": {"go\xff": {}}}')
    with pytest.raises(VocabularyError, match=rf"^vocabulary file {re.escape(str(path))} is not valid JSON"):
        load_vocabulary(path)


@pytest.mark.parametrize(
    ("old", "new", "error"),
    [
        ("payload: 3.0", "payload: " + "1" * 5000, "Exceeds the limit (4300 digits)"),
        ("name: household", "name: 2026-13-01", "month must be in 1..12"),
        ("name: household", "name: !!bool household", "'household'"),
        ("name: household", "name: !!timestamp household", "has no attribute"),
    ],
)
def test_a_yaml_value_its_loader_cannot_build_is_refused_naming_the_file(
    tmp_path: Path, old: str, new: str, error: str
) -> None:
    # PyYAML let Python's own errors out of its loader (int() past its limit on digits, a 13th month,
    # a look-up of a word that is no boolean): a traceback, the file not named. (msgspec 0.23 wraps
    # them in its DecodeError itself; 0.22 let them out, and datafile's wrapper says so.)
    path = world_file(tmp_path, old, new)
    with pytest.raises(WorldFileError) as refused:
        load_world(path)
    said = str(refused.value)
    assert said.startswith(f"world file {path} is not valid YAML: ") and error in said, said


def test_a_keep_out_zone_outside_every_room_is_refused(tmp_path: Path) -> None:
    # The stairs' corners typed 100 m east: the zone guarded nothing and the stairs were open.
    path = world_file(tmp_path, STAIRS, "polygon: [[110.5, 7], [112, 7], [112, 9], [110.5, 9]]")
    with pytest.raises(
        WorldFileError,
        match=rf"^world file {re.escape(str(path))}: keep_out\[0\] \(stairs\)\.polygon: is outside every room",
    ):
        load_world(path)


def test_a_keep_out_zone_reaching_into_a_room_loads(tmp_path: Path) -> None:
    path = world_file(tmp_path, STAIRS, "polygon: [[11.5, 7], [13, 7], [13, 9], [11.5, 9]]")
    assert [zone.id for zone in load_world(path).keep_out] == ["stairs"]


def test_a_policy_keep_out_zone_outside_every_room_is_refused_by_safety(tmp_path: Path) -> None:
    path = tmp_path / "policy.toml"
    far = 'id = "nursery"\nname = "nursery"\npolygon = [[-9.0, 6.0], [-7.0, 6.0], [-7.0, 8.0], [-9.0, 8.0]]\n'
    path.write_text(DEFAULT_POLICY.read_text() + "\n[[keep_out]]\n" + far)
    with pytest.raises(
        PolicyError, match=rf"^policy file {re.escape(str(path))}: keep_out\[0\] \(nursery\): is outside every room"
    ):
        load_safety_policy(WORLD, path, "world household")


def test_tether_policy_refuses_a_keep_out_zone_outside_every_room_as_safety_does(tmp_path: Path) -> None:
    """`tether policy FILE` checks a policy as safety does at start: it passed this one, safety refused it."""
    from typer.testing import CliRunner

    from tether.cli import app

    path = tmp_path / "policy.toml"
    far = 'id = "nursery"\nname = "nursery"\npolygon = [[-9.0, 6.0], [-7.0, 6.0], [-7.0, 8.0], [-9.0, 8.0]]\n'
    path.write_text(DEFAULT_POLICY.read_text() + "\n[[keep_out]]\n" + far)
    checked = CliRunner().invoke(app, ["policy", str(path), "--json"])
    assert checked.exit_code == 2, checked.output
    assert "is outside every room" in json.loads(checked.stdout)["error"]


def test_a_policy_keep_out_zone_in_a_room_is_enforced(tmp_path: Path) -> None:
    path = tmp_path / "policy.toml"
    near = 'id = "nursery"\nname = "nursery"\npolygon = [[1.0, 6.0], [3.0, 6.0], [3.0, 8.0], [1.0, 8.0]]\n'
    path.write_text(DEFAULT_POLICY.read_text() + "\n[[keep_out]]\n" + near)
    policy = load_safety_policy(WORLD, path, "world household")
    assert [zone.id for zone in policy.limits.keep_out] == ["stairs", "nursery"]


@pytest.mark.parametrize("bound", [".nan", ".inf", "-.inf"])
def test_a_vocabulary_bound_that_is_no_number_is_refused(tmp_path: Path, bound: str) -> None:
    # A NaN bound compares false with every number: the parser let any grip force through as within it.
    vocabulary = default_vocabulary_path().read_text()
    old = "force: {type: float, unit: N, min: 0.0, max: 70.0, aliases: [grip_force, effort]}"
    assert vocabulary.count(old) == 1
    path = tmp_path / "vocabulary.yaml"
    path.write_text(vocabulary.replace(old, old.replace("max: 70.0", f"max: {bound}")))
    shown = {".nan": "nan", ".inf": "inf", "-.inf": "-inf"}[bound]
    error = rf"^vocabulary file {re.escape(str(path))}: close_gripper\.force: max {shown} is not a finite number$"
    with pytest.raises(VocabularyError, match=error):
        load_vocabulary(path)
