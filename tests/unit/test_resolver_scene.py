"""Reading names into their parts, the scene graph and its description, spots next to things."""

from __future__ import annotations

import math
from typing import Any

import msgspec
import pytest

from schemas.common import Pose2D, Vec3
from schemas.plan import PlaceStep, Plan, Step
from schemas.world import PerceivedObject, PerceivedObjects
from services.resolver.reference import Relation, parse_reference
from services.resolver.resolver import Resolver
from services.worldmodel import WorldModel, load_world

START = Pose2D(x=6.0, y=1.2, yaw=0.0)
AT_KITCHEN_TABLE = Pose2D(x=2.5, y=3.05, yaw=math.pi / 2)


@pytest.fixture(scope="module")
def resolver() -> Resolver:
    return Resolver(WorldModel(load_world("household")))


def plan_of(*steps: dict[str, Any]) -> Plan:
    return Plan(steps=[msgspec.convert(s, Step) for s in steps])


@pytest.mark.parametrize(
    ("text", "noun", "colour", "size", "superlative"),
    [
        ("the big red cup", "cup", "red", "big", None),
        ("The nearest mug!", "mug", None, None, "nearest"),
        ("the cup on the left", "cup", None, None, "leftmost"),
        ("the left cup", "cup", None, None, "leftmost"),
        ("the red one", "one", "red", None, None),
        ("top of the stairs", "top of stairs", None, None, None),
    ],
)
def test_a_name_is_read_into_its_parts(
    text: str, noun: str, colour: str | None, size: str | None, superlative: str | None
) -> None:
    ref = parse_reference(text)
    assert (ref.noun, ref.colour, ref.size, ref.superlative, ref.pronoun) == (noun, colour, size, superlative, False)


def test_relations_nest_to_the_right() -> None:
    ref = parse_reference("the cup on the table in the kitchen")
    assert ref.noun == "cup"
    (on,) = ref.relations
    assert on.kind == "on" and on.other.noun == "table"
    assert on.other.relations == (Relation("in", parse_reference("kitchen")),)
    assert parse_reference("the cup to the left of the apple").relations[0].kind == "left_of"
    assert parse_reference("the mug closest to me").relations[0].kind == "nearest_to"


def test_a_place_named_by_what_is_there_is_that_thing() -> None:
    assert parse_reference("next to the apple").noun == "apple"
    assert parse_reference("at the counter").noun == "counter"


@pytest.mark.parametrize("text", ["it", "It.", "that", "this one", "the same one"])
def test_pronouns(text: str) -> None:
    assert parse_reference(text).pronoun


def test_a_long_chain_of_relations_is_bounded() -> None:
    ref = parse_reference(" on ".join(["cup"] * 50))
    depth = 0
    while ref.relations:
        ref, depth = ref.relations[0].other, depth + 1
    assert depth <= 4


def test_the_scene_graph_relates_objects_furniture_and_rooms(resolver: Resolver) -> None:
    scene = resolver.describe(None, AT_KITCHEN_TABLE)
    relations = {(r.subject, r.relation, r.object) for r in scene.relations}
    assert {("red_cup", "on", "kitchen_counter"), ("blue_book", "in", "living_room")} <= relations
    assert {("kitchen_table", "in", "kitchen"), ("blue_cup", "near", "apple")} <= relations
    # Facing the kitchen table, the blue cup is on the robot's left of the apple.
    assert {("blue_cup", "left_of", "apple"), ("apple", "right_of", "blue_cup")} <= relations
    assert ("red_cup", "near", "cast_iron_pan") not in relations  # 1.05 m apart
    assert scene.robot_room == "kitchen"


def test_the_description_says_where_things_are_and_what_cannot_be_lifted(resolver: Resolver) -> None:
    text = resolver.describe(None, START).text
    assert text.startswith("The robot is in the living room at (6.0, 1.2), facing east.")
    assert "the cast-iron pan (too heavy to lift) are on the kitchen counter" in text
    assert "The blue book is on the coffee table." in text
    assert "The operator is in the living room, 3.5 m from the robot." in text
    assert resolver.describe(None, None).text.startswith("The robot's position is not known.")


def test_the_description_follows_perception(resolver: Resolver) -> None:
    seen = PerceivedObjects(
        stamp=5.0,
        objects=[
            PerceivedObject(
                id="red_cup", name="red cup", cls="cup", color="red", position=Vec3(x=2.5, y=1.0, z=1.2), on="gripper"
            ),
            PerceivedObject(
                id="blue_cup",
                name="blue cup",
                cls="cup",
                color="blue",
                position=Vec3(x=8.2, y=2.4, z=0.5),
                on="coffee_table",
                stamp=4.0,
                stale=True,
            ),
        ],
    )
    scene = resolver.describe(seen, START)
    assert "It is holding the red cup." in scene.text
    assert "blue cup (not seen lately)" in scene.text
    cup = next(o for o in scene.objects if o.id == "blue_cup")
    assert (cup.on, cup.room, cup.stamp, cup.stale) == ("coffee_table", "living_room", 4.0, True)
    book = next(o for o in scene.objects if o.id == "blue_book")
    assert book.stamp == 0.0  # never seen: where the world file puts it


def test_next_to_a_thing_is_the_free_spot_on_its_surface_nearest_it(resolver: Resolver) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": "next to the apple"})
    place = resolver.resolve(plan, None, START).steps[1]
    assert isinstance(place, PlaceStep) and place.surface_id == "kitchen_table"
    apple = (2.8, 3.65)
    gap = math.dist((place.position.x, place.position.y), apple)
    assert resolver.config.place_clearance - 1e-6 <= gap <= resolver.config.place_clearance + 0.06


def test_it_follows_what_the_plan_handled_last(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "detect", "target": "blue book"},
        {"action": "pick", "target": "apple"},
        {"action": "place", "target": "it", "location": "coffee table"},
        {"action": "pick", "target": "it"},
    )
    grounded = resolver.resolve(plan, None, START)
    pronouns = [(r.label, r.id) for r in grounded.resolutions if r.via == "pronoun"]
    assert pronouns == [("3", "apple"), ("4", "apple")]
