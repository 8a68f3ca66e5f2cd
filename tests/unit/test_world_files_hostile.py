"""World files an operator got wrong: each refused at load, naming the file and the entry, never
accepted in a form that makes safety's checks wrong or the sim misbehave."""

from __future__ import annotations

import json
import re
from pathlib import Path

import msgspec
import pytest

from services import datafile
from services.worldmodel import DEFAULT_WORLD, WorldFileError, load_world, world_path

HOUSEHOLD = world_path(DEFAULT_WORLD).read_text()
STAIRS = "polygon: [[10.5, 7], [12, 7], [12, 9], [10.5, 9]]"
KITCHEN = "polygon: [[0, 0], [5, 0], [5, 5], [0, 5]]"
START = "start: {x: 6.0, y: 1.2, yaw: 0.0}"


def edited(old: str, new: str) -> str:
    """The household world with one piece of text replaced, as an operator would edit it."""
    assert HOUSEHOLD.count(old) == 1, old
    return HOUSEHOLD.replace(old, new)


CASES = {
    # A second zone named like the stairs took the stairs' place in safety: the stairs went unguarded.
    "a keep-out id given twice": (
        edited("places:", "  - {id: stairs, name: nursery, polygon: [[0, 6], [3, 6], [3, 8.5], [0, 8.5]]}\nplaces:"),
        r"duplicate ids \['stairs'\]",
    ),
    "a keep-out id that names a room": (
        edited("  - id: stairs\n", "  - id: hallway\n"),
        r"duplicate ids \['hallway'\]",
    ),
    # Corners out of order: a bow-tie, which covers two triangles of the stairs and not the rest.
    "a crossed keep-out polygon": (
        edited(STAIRS, "polygon: [[10.5, 7], [12, 9], [12, 7], [10.5, 9]]"),
        r"keep_out\[0\] \(stairs\)\.polygon: is not a simple polygon \(Self-intersection",
    ),
    "a keep-out polygon with no area": (
        edited(STAIRS, "polygon: [[10.5, 7], [12, 7], [11, 7]]"),
        r"keep_out\[0\] \(stairs\)\.polygon: is not a simple polygon",
    ),
    "a crossed room polygon": (
        edited(KITCHEN, "polygon: [[0, 0], [5, 5], [5, 0], [0, 5]]"),
        r"rooms\[0\] \(kitchen\)\.polygon: is not a simple polygon",
    ),
    "rooms that overlap": (
        edited(KITCHEN, "polygon: [[0, 0], [6, 0], [6, 5], [0, 5]]"),
        r"rooms\[1\] \(living_room\): overlaps rooms\[0\] \(kitchen\)",
    ),
    "a robot starting in a keep-out zone": (
        edited(START, "start: {x: 11.2, y: 8.0, yaw: 0.0}"),
        r"robot\.start: the base would start in keep-out zone 'stairs'",
    ),
    "a robot starting in a wall": (
        edited(START, "start: {x: 5.0, y: 0.5, yaw: 0.0}"),
        r"robot\.start: the base would start in 'wall_kitchen_living_1'",
    ),
    "a robot starting in furniture": (
        edited(START, "start: {x: 2.5, y: 3.9, yaw: 0.0}"),
        r"robot\.start: the base would start in 'kitchen_table'",
    ),
    "a robot starting outside every room": (
        edited(START, "start: {x: 50.0, y: 50.0, yaw: 0.0}"),
        r"robot\.start: \(50, 50\) is outside every room",
    ),
    "a home joint that is not a number": (
        edited("home_joints: [0.0,", "home_joints: [.nan,"),
        r"robot\.home_joints: every joint position must be a finite number",
    ),
    "furniture outside every room": (
        edited("center: [9.5, 3.6]", "center: [30, 30]"),
        r"furniture\[5\] \(chair\): is not inside the rooms",
    ),
    "an approach pose outside every room": (
        edited("approach: {x: 9.5, y: 2.8,", "approach: {x: 20, y: 2.8,"),
        r"furniture\[5\] \(chair\)\.approach: \(20, 2\.8\) is outside every room",
    ),
    "a place outside every room": (
        edited("pose: {x: 11.2, y: 0.8,", "pose: {x: 13.2, y: 0.8,"),
        r"places\[0\] \(charging_dock\)\.pose: \(13\.2, 0\.8\) is outside every room",
    ),
    "a person outside every room": (
        edited("pose: {x: 9.5, y: 1.5,", "pose: {x: 9.5, y: -1.5,"),
        r"humans\[0\] \(operator\)\.pose: \(9\.5, -1\.5\) is outside every room",
    ),
    "an object off the top it rests on": (
        edited("offset: [0.3, 0.0]", "offset: [3.0, 0.0]"),
        r"objects\[5\] \(blue_book\)\.offset: \[3\.0, 0\.0\] is off the top of 'coffee_table'",
    ),
    "a wall of no length": (
        edited("start: [8, 7.4], end: [8, 9]", "start: [8, 7.4], end: [8, 7.4]"),
        r"walls\[15\] \(wall_office_hallway_2\): starts where it ends",
    ),
    # YAML keeps the last of two equal keys: the second list of zones silently replaced the stairs.
    "a key given twice": (HOUSEHOLD + "\nkeep_out: []\n", r"key 'keep_out' appears twice in one mapping \(line 108\)"),
    "a key given twice in an entry": (
        edited("  - id: stairs\n", "  - id: stairs\n    polygon: [[0, 0], [0.1, 0], [0.1, 0.1]]\n"),
        r"key 'polygon' appears twice in one mapping \(line 18\)",
    ),
}


@pytest.mark.parametrize(("text", "error"), CASES.values(), ids=CASES.keys())
def test_a_wrong_world_is_refused_naming_the_file_and_the_entry(tmp_path: Path, text: str, error: str) -> None:
    path = tmp_path / "world.yaml"
    path.write_text(text)
    with pytest.raises(WorldFileError, match=rf"^world file {re.escape(str(path))}: {error}"):
        load_world(path)


def test_the_household_world_still_loads() -> None:
    world = load_world(DEFAULT_WORLD)
    assert [zone.id for zone in world.keep_out] == ["stairs"]


def test_a_key_given_twice_in_a_json_world_is_refused(tmp_path: Path) -> None:
    data = json.dumps(msgspec.yaml.decode(HOUSEHOLD))
    path = tmp_path / "world.json"
    path.write_text(data[:-1] + ', "keep_out": []}')
    with pytest.raises(
        WorldFileError, match=rf"^world file {re.escape(str(path))}: key 'keep_out' appears twice in one object"
    ):
        load_world(path)
    path.write_text(data)
    assert [zone.id for zone in load_world(path).keep_out] == ["stairs"]


def test_a_huge_world_file_is_refused_unread(tmp_path: Path) -> None:
    path = tmp_path / "world.yaml"
    with path.open("wb") as file:
        file.truncate(datafile.MAX_FILE_BYTES + 1)  # sparse: no disk for the test
    with pytest.raises(
        WorldFileError,
        match=rf"^world file {re.escape(str(path))}: more than {datafile.MAX_FILE_BYTES} bytes; not read",
    ):
        load_world(path)
