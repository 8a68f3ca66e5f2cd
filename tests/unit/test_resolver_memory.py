"""The resolver's object memory: refined sightings, moves, staleness, the gripper, and when its version changes."""

from __future__ import annotations

import msgspec
import pytest

from schemas.common import Vec3
from schemas.world import PerceivedObject, PerceivedObjects
from services.resolver.memory import MAX_OBJECTS, ObjectMemory

STALE_AFTER = 10.0
TOLERANCE = 0.05


def obj(object_id: str, x: float, y: float, z: float = 0.95, on: str | None = "kitchen_counter") -> PerceivedObject:
    return PerceivedObject(
        id=object_id, name=object_id.replace("_", " "), cls="cup", color="red", position=Vec3(x=x, y=y, z=z), on=on
    )


def frame(stamp: float, *objects: PerceivedObject) -> PerceivedObjects:
    return PerceivedObjects(stamp=stamp, objects=list(objects))


def by_id(snapshot: PerceivedObjects | None) -> dict[str, PerceivedObject]:
    assert snapshot is not None
    return {o.id: o for o in snapshot.objects}


@pytest.fixture
def memory() -> ObjectMemory:
    return ObjectMemory(stale_after=STALE_AFTER, move_tolerance=TOLERANCE)


def test_nothing_before_the_first_frame(memory: ObjectMemory) -> None:
    assert memory.snapshot(0.0) is None
    memory.update(frame(100.0), now=1.0)
    # An empty frame still says something: nothing is in the gripper.
    assert memory.snapshot(1.0) == PerceivedObjects(stamp=100.0, objects=[])
    assert memory.version == 1


def test_sightings_within_tolerance_are_averaged(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.20, 0.55)), now=1.0)
    version = memory.version
    memory.update(frame(100.2, obj("red_cup", 2.204, 0.546)), now=1.2)
    memory.update(frame(100.4, obj("red_cup", 2.196, 0.554)), now=1.4)
    cup = by_id(memory.snapshot(1.4))["red_cup"]
    assert (cup.position.x, cup.position.y) == pytest.approx((2.20, 0.55), abs=1e-9)
    assert cup.stamp == 100.4  # the frame it was last seen in
    assert not cup.stale
    assert memory.version == version  # noise is not news


def test_noise_cannot_drift_a_still_object_away(memory: ObjectMemory) -> None:
    memory.update(frame(0.0, obj("red_cup", 2.2, 0.55)), now=0.0)
    version = memory.version
    for i in range(200):
        jitter = 0.004 if i % 2 else -0.004
        memory.update(frame(i * 0.2, obj("red_cup", 2.2 + jitter, 0.55 - jitter)), now=i * 0.2)
    cup = by_id(memory.snapshot(40.0))["red_cup"]
    assert cup.position.x == pytest.approx(2.2, abs=0.001)
    assert memory.version == version


def test_a_sighting_beyond_tolerance_is_a_move(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.2, 0.55)), now=1.0)
    version = memory.version
    memory.update(frame(101.0, obj("red_cup", 2.2, 0.55 + TOLERANCE * 1.5)), now=2.0)
    cup = by_id(memory.snapshot(2.0))["red_cup"]
    assert cup.position.y == pytest.approx(0.55 + TOLERANCE * 1.5)  # replaced, not averaged
    assert memory.version > version


def test_a_vertical_move_beyond_tolerance_is_a_move(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.2, 0.55, z=0.95)), now=1.0)
    version = memory.version
    memory.update(frame(101.0, obj("red_cup", 2.2, 0.55, z=0.95 + TOLERANCE * 2)), now=2.0)
    assert by_id(memory.snapshot(2.0))["red_cup"].position.z == pytest.approx(0.95 + TOLERANCE * 2)
    assert memory.version > version


def test_a_different_support_is_a_move_even_in_place(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.2, 0.55)), now=1.0)
    version = memory.version
    memory.update(frame(101.0, obj("red_cup", 2.2, 0.55, on=None)), now=2.0)
    assert by_id(memory.snapshot(2.0))["red_cup"].on is None
    assert memory.version > version


def test_objects_out_of_view_keep_their_last_sighting(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.2, 0.55), obj("apple", 2.8, 3.65)), now=1.0)
    version = memory.version
    memory.update(frame(101.0, obj("apple", 2.8, 3.65)), now=2.0)
    remembered = by_id(memory.snapshot(2.0))
    assert remembered["red_cup"].position == Vec3(x=2.2, y=0.55, z=0.95)
    assert remembered["red_cup"].stamp == 100.0
    assert remembered["apple"].stamp == 101.0
    assert memory.version == version


def test_an_object_not_seen_for_long_turns_stale_and_fresh_again(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.2, 0.55), obj("apple", 2.8, 3.65)), now=1.0)
    version = memory.version
    # Ages run on the monotonic receive time: the frame stamps (another machine's clock) do not count.
    memory.update(frame(5000.0, obj("apple", 2.8, 3.65)), now=1.0 + STALE_AFTER)
    assert not by_id(memory.snapshot(1.0 + STALE_AFTER))["red_cup"].stale
    assert memory.version == version
    remembered = by_id(memory.snapshot(1.0 + STALE_AFTER + 0.1))
    assert remembered["red_cup"].stale and not remembered["apple"].stale
    stale_version = memory.version
    assert stale_version != version  # the flip is a change of belief...
    memory.snapshot(1.0 + STALE_AFTER + 5.0)
    assert memory.version == stale_version  # ...once
    memory.update(frame(5001.0, obj("red_cup", 2.201, 0.55)), now=20.0)
    assert not by_id(memory.snapshot(20.0))["red_cup"].stale
    assert memory.version != stale_version


def test_refresh_flips_staleness_without_a_snapshot(memory: ObjectMemory) -> None:
    memory.update(frame(1.0, obj("red_cup", 2.2, 0.55)), now=0.0)
    version = memory.version
    memory.refresh(STALE_AFTER / 2)
    assert memory.version == version
    memory.refresh(STALE_AFTER * 2)
    assert memory.version != version


def test_an_object_released_out_of_view_is_where_it_was_and_stale(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 6.3, 1.2, z=0.7, on="gripper")), now=1.0)
    version = memory.version
    memory.update(frame(100.2), now=1.2)  # the gripper is empty and the cup is not in view
    cup = by_id(memory.snapshot(1.2))["red_cup"]
    assert cup.on is None
    assert cup.position == Vec3(x=6.3, y=1.2, z=0.7)
    assert cup.stale  # right away: where it went is not known
    assert memory.version != version
    released = memory.version
    memory.update(frame(100.4), now=1.4)
    assert memory.version == released
    # Seen again: fresh, where it is now.
    memory.update(frame(100.6, obj("red_cup", 6.5, 1.2, z=0.05, on=None)), now=1.6)
    cup = by_id(memory.snapshot(1.6))["red_cup"]
    assert not cup.stale and cup.position.z == pytest.approx(0.05)
    assert memory.version != released


def test_a_released_object_in_view_is_simply_seen(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 8.0, 1.9, z=0.6, on="gripper")), now=1.0)
    memory.update(frame(100.2, obj("red_cup", 8.0, 2.4, z=0.5, on="coffee_table")), now=1.2)
    cup = by_id(memory.snapshot(1.2))["red_cup"]
    assert cup.on == "coffee_table" and not cup.stale


def test_a_different_object_in_the_gripper_updates_both(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 6.3, 1.2, z=0.7, on="gripper")), now=1.0)
    version = memory.version
    memory.update(frame(100.2, obj("blue_cup", 6.3, 1.2, z=0.7, on="gripper")), now=1.2)
    remembered = by_id(memory.snapshot(1.2))
    assert remembered["blue_cup"].on == "gripper" and not remembered["blue_cup"].stale
    assert remembered["red_cup"].on is None and remembered["red_cup"].stale
    assert memory.version != version


def test_a_held_object_moving_with_the_robot_is_followed(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 6.3, 1.2, z=0.7, on="gripper")), now=1.0)
    memory.update(frame(100.2, obj("red_cup", 6.6, 1.2, z=0.7, on="gripper")), now=1.2)
    cup = by_id(memory.snapshot(1.2))["red_cup"]
    assert cup.on == "gripper" and cup.position.x == pytest.approx(6.6) and not cup.stale


def test_version_changes_only_on_real_changes(memory: ObjectMemory) -> None:
    versions = [memory.version]

    def step(now: float, *objects: PerceivedObject) -> bool:
        memory.update(frame(now, *objects), now=now)
        memory.snapshot(now)
        versions.append(memory.version)
        return versions[-1] != versions[-2]

    assert step(0.0, obj("red_cup", 2.2, 0.55))  # the first frame, first seen
    assert not step(0.2, obj("red_cup", 2.21, 0.55))  # refined
    assert step(0.4, obj("red_cup", 2.21, 0.55), obj("apple", 2.8, 3.65))  # a new object
    assert not step(0.6, obj("apple", 2.8, 3.65))  # the cup out of view, not yet stale
    assert step(0.8, obj("apple", 3.8, 3.65))  # moved
    assert not step(1.0, obj("apple", 3.8, 3.65))


def test_a_frame_listing_an_id_twice_counts_it_once(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.2, 0.55), obj("red_cup", 9.0, 9.0, on=None)), now=1.0)
    remembered = memory.snapshot(1.0)
    assert remembered is not None and len(remembered.objects) == 1
    assert remembered.objects[0].position.x == pytest.approx(2.2)
    version = memory.version
    # The same contradictory frame again changes nothing.
    memory.update(frame(100.2, obj("red_cup", 2.2, 0.55), obj("red_cup", 9.0, 9.0, on=None)), now=1.2)
    assert memory.version == version


def test_a_flood_of_invented_ids_is_bounded(memory: ObjectMemory) -> None:
    memory.update(frame(100.0, obj("red_cup", 2.2, 0.55)), now=1.0)
    flood = [obj(f"fake_{i}", 1.0, 1.0) for i in range(MAX_OBJECTS + 50)]
    memory.update(frame(100.2, *flood), now=2.0)
    assert len(memory) == MAX_OBJECTS
    # The one seen longest ago went first.
    assert "red_cup" not in by_id(memory.snapshot(2.0))


def test_frames_come_validated_off_the_wire() -> None:
    # What a frame may hold is the schema's business: NaN is not JSON and positions are bounded.
    decode = msgspec.json.Decoder(PerceivedObjects).decode
    bad = (
        b'{"stamp": 1, "objects": [{"id": "a", "name": "a", "cls": "c", "color": "r",'
        b' "position": {"x": %s, "y": 0, "z": 0}}]}'
    )
    for value in (b"NaN", b"1e400", b"2000"):
        with pytest.raises(msgspec.DecodeError):
            decode(bad % value)


def test_configuration_is_checked() -> None:
    with pytest.raises(ValueError, match="must be positive"):
        ObjectMemory(stale_after=0.0, move_tolerance=0.05)


def test_where_a_held_object_was_before_the_gripper_took_it(memory: ObjectMemory) -> None:
    memory.update(frame(1.0, obj("red_cup", 2.2, 0.55), obj("apple", 2.8, 3.65, 0.79, "kitchen_table")), now=1.0)
    assert memory.origins() == {}  # nothing held
    memory.update(frame(1.2, obj("red_cup", 2.21, 0.56), obj("apple", 2.8, 3.65, 0.79, "kitchen_table")), now=1.2)
    memory.update(frame(1.4, obj("red_cup", 2.3, 0.8, 1.2, "gripper")), now=1.4)
    # Where it was last seen on the counter (the refined position), while it is held.
    (origin,) = memory.origins().values()
    assert origin.on == "kitchen_counter"
    assert (origin.position.x, origin.position.y) == pytest.approx((2.205, 0.555))
    memory.update(frame(1.6, obj("red_cup", 2.5, 0.9, 1.1, "gripper")), now=1.6)
    assert memory.origins()["red_cup"] is origin  # carried about: still where it came from
    memory.update(frame(1.8, obj("red_cup", 8.0, 2.35, 0.5, "coffee_table")), now=1.8)
    assert memory.origins() == {}  # put down: not held any more


def test_no_origin_for_what_was_first_seen_held_or_lost_from_view(memory: ObjectMemory) -> None:
    memory.update(frame(1.0, obj("red_cup", 6.3, 1.2, 1.0, "gripper")), now=1.0)
    assert memory.origins() == {}  # never seen anywhere else
    memory.update(frame(1.2), now=1.2)  # let go out of view: where it went is not known
    memory.update(frame(1.4, obj("red_cup", 6.3, 1.2, 1.0, "gripper")), now=1.4)
    assert memory.origins() == {}
    memory.update(frame(1.6, obj("apple", 6.0, 1.0, 0.04, None)), now=1.6)
    memory.update(frame(1.8, obj("apple", 6.0, 1.0, 0.3, "gripper")), now=1.8)
    assert memory.origins()["apple"].on is None  # from the floor


def test_an_object_creeping_within_tolerance_at_every_sighting_is_believed_where_it_went() -> None:
    """1 mm a frame: every sighting refined the average, the version never changed, and a pick cached
    at the start still reached for where the object stood 38 cm before."""
    memory = ObjectMemory(stale_after=STALE_AFTER, move_tolerance=TOLERANCE)
    versions = []
    for i in range(400):
        memory.update(frame(i * 0.1, obj("red_cup", 8.0 + i * 0.001, 0.55)), now=i * 0.1)
        versions.append(memory.version)
    snapshot = memory.snapshot(40.0)
    assert snapshot is not None
    [seen] = snapshot.objects
    assert seen.position.x > 8.3, "the average followed it"
    assert len(set(versions)) > 5, "and the belief changed with it"
    # Noise around one place changes nothing.
    still = ObjectMemory(stale_after=STALE_AFTER, move_tolerance=TOLERANCE)
    still.update(frame(0.0, obj("red_cup", 8.0, 0.55)), now=0.0)
    before = still.version
    for i in range(100):
        still.update(frame(i * 0.1, obj("red_cup", 8.0 + (0.01 if i % 2 else -0.01), 0.55)), now=i * 0.1)
    assert still.version == before
