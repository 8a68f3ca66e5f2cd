"""The resolver against camera reports that contradict themselves or the map: a report is evidence,
not truth. Where it says an object rests is checked against where it says the object is, a place
off the map or under the floor is not believed, and a gripper said to hold two things holds an
unknown one."""

from __future__ import annotations

import pytest

from schemas.common import ErrorKind, Stage, Vec3
from schemas.plan import PickStep, PlaceStep
from schemas.world import PerceivedObjects
from services.resolver.errors import ResolveError
from services.resolver.resolver import Resolver
from services.worldmodel import WorldModel
from tests.unit.test_resolver import model as model  # the module-scoped fixtures, shared
from tests.unit.test_resolver import plan_of, seen
from tests.unit.test_resolver import resolver as resolver

# Where the world file puts the red cup: on the kitchen counter.
RED_CUP_ON_THE_COUNTER = Vec3(x=2.2, y=0.55, z=0.95)
# In the gripper, above the kitchen floor.
IN_THE_GRIPPER = (Vec3(x=2.0, y=1.0, z=0.9), "gripper")


def only_pick(resolver: Resolver, objects: PerceivedObjects, **location: str) -> tuple[PickStep, list[str]]:
    grounded = resolver.resolve(plan_of({"action": "pick", "target": "red cup", **location}), objects)
    (pick,) = grounded.steps
    assert isinstance(pick, PickStep)
    return pick, grounded.warnings


def test_an_object_said_to_be_on_furniture_it_is_nowhere_near_is_on_what_is_under_it(
    resolver: Resolver, model: WorldModel
) -> None:
    # The report says the coffee table (in the living room); its position is the kitchen counter's top.
    objects = seen(model, red_cup=(RED_CUP_ON_THE_COUNTER, "coffee_table"))
    pick, warnings = only_pick(resolver, objects, location="coffee table")
    assert pick.support_id == "kitchen_counter"
    assert pick.position == RED_CUP_ON_THE_COUNTER
    assert any(
        "on coffee table, but at (2.20, 0.55), not over it: taken to be on kitchen counter" in w for w in warnings
    )
    # And the plan's location is now seen not to match where the cup is.
    assert any("not at the coffee table" in w for w in warnings), warnings


def test_an_object_said_to_be_on_furniture_the_world_does_not_have_is_on_what_is_under_it(
    resolver: Resolver, model: WorldModel
) -> None:
    objects = seen(model, red_cup=(RED_CUP_ON_THE_COUNTER, "the_moon"))
    pick, warnings = only_pick(resolver, objects)
    assert pick.support_id == "kitchen_counter"
    assert any("on 'the_moon'" in w for w in warnings), warnings


def test_an_object_at_the_edge_of_its_furniture_stays_on_it_without_a_warning(
    resolver: Resolver, model: WorldModel
) -> None:
    counter = model.furniture["kitchen_counter"]
    # Just past the counter's front edge, as a camera's estimate of an object there may be.
    edge = Vec3(x=2.2, y=counter.center[1] + counter.size.y / 2 + 0.05, z=0.95)
    pick, warnings = only_pick(resolver, seen(model, red_cup=(edge, "kitchen_counter")))
    assert pick.support_id == "kitchen_counter"
    assert warnings == []


@pytest.mark.parametrize(
    ("position", "why"),
    [
        (Vec3(x=500.0, y=-300.0, z=0.8), "off the map"),
        (Vec3(x=2.2, y=0.55, z=-5.0), "under the floor"),
        (Vec3(x=2.2, y=0.55, z=40.0), "in the air"),
    ],
)
def test_a_sighting_that_cannot_be_right_is_not_believed(
    resolver: Resolver, model: WorldModel, position: Vec3, why: str
) -> None:
    pick, warnings = only_pick(resolver, seen(model, red_cup=(position, None)))
    # Where the world file puts it, as for an object the camera has not seen; never where the report says.
    assert pick.position == RED_CUP_ON_THE_COUNTER
    assert pick.support_id == "kitchen_counter"
    assert [w for w in warnings if "red cup is not believed" in w and why in w], warnings


def test_a_sighting_just_outside_the_walls_is_still_believed(resolver: Resolver, model: WorldModel) -> None:
    # 10 cm past the map's south wall, on the floor: an estimate near a wall, not a broken report.
    outside = Vec3(x=2.2, y=-0.1, z=0.05)
    pick, warnings = only_pick(resolver, seen(model, red_cup=(outside, None)))
    assert pick.position == outside
    assert not [w for w in warnings if "not believed" in w]


def test_a_gripper_said_to_hold_two_objects_holds_neither_for_sure(resolver: Resolver, model: WorldModel) -> None:
    objects = seen(model, red_cup=IN_THE_GRIPPER, blue_cup=IN_THE_GRIPPER)
    # "Put it back" needs to know what is held: refused, naming both.
    with pytest.raises(ResolveError) as caught:
        resolver.resolve(plan_of({"action": "place", "location": "where it was"}), objects)
    error = caught.value.error
    assert error.stage is Stage.RESOLVE
    assert error.kind is ErrorKind.PRECONDITION
    assert "both red cup and blue cup in the gripper" in error.message
    # Named, either may be placed (before, the last one listed was the one held and the other refused).
    for name in ("red cup", "blue cup"):
        grounded = resolver.resolve(plan_of({"action": "place", "target": name, "location": "coffee table"}), objects)
        assert isinstance(grounded.steps[0], PlaceStep)
        assert any("which holds one thing" in w for w in grounded.warnings), grounded.warnings


def test_one_object_listed_twice_in_the_gripper_is_held(resolver: Resolver, model: WorldModel) -> None:
    objects = seen(model, red_cup=IN_THE_GRIPPER)
    twice = PerceivedObjects(stamp=objects.stamp, objects=[*objects.objects, *objects.objects])
    # It is the one held: placing another is refused for it, and no warning of two.
    with pytest.raises(ResolveError) as caught:
        resolver.resolve(plan_of({"action": "place", "target": "blue cup", "location": "coffee table"}), twice)
    assert "the gripper holds red cup" in caught.value.error.message
    grounded = resolver.resolve(plan_of({"action": "place", "target": "red cup", "location": "coffee table"}), twice)
    assert isinstance(grounded.steps[0], PlaceStep)
    assert not [w for w in grounded.warnings if "gripper" in w]
