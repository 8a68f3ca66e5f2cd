"""The resolver: names become ids and poses from the world model and perception, or a clear refusal."""

from __future__ import annotations

import json
import math
from typing import Any

import msgspec
import pytest

from schemas.common import ErrorKind, Pose2D, ServiceError, Stage, Vec3
from schemas.plan import (
    DetectStep,
    GroundedPlan,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    SayStep,
    Step,
    StopStep,
    WaitStep,
)
from schemas.world import PerceivedHuman, PerceivedHumans, PerceivedObject, PerceivedObjects
from services.parser.parser import parse
from services.resolver.errors import ResolveError
from services.resolver.names import normalise_name
from services.resolver.resolver import Resolver, answer
from services.worldmodel import WorldModel, load_world

DEMO = {
    "plan": [
        {"action": "navigate_to", "target": "kitchen counter"},
        {"action": "pick", "target": "red cup"},
        {"action": "navigate_to", "target": "coffee table"},
        {"action": "place", "target": "coffee table"},
    ]
}


@pytest.fixture(scope="module")
def model() -> WorldModel:
    return WorldModel(load_world("household"))


@pytest.fixture(scope="module")
def resolver(model: WorldModel) -> Resolver:
    return Resolver(model)


def plan_of(*steps: dict[str, Any]) -> Plan:
    return Plan(steps=[msgspec.convert(s, Step) for s in steps])


def seen(model: WorldModel, **changes: tuple[Vec3, str | None]) -> PerceivedObjects:
    """Perception of every world object where the file puts it, except those in `changes`."""
    objects = []
    for obj in model.world.objects:
        position, on = changes.get(obj.id, (model.initial_position(obj), obj.support))
        objects.append(
            PerceivedObject(id=obj.id, name=obj.name, cls=obj.cls, color=obj.color, position=position, on=on)
        )
    return PerceivedObjects(stamp=1.0, objects=objects)


def refusal(resolver: Resolver, plan: Plan, **kwargs: Any) -> ServiceError:
    with pytest.raises(ResolveError) as caught:
        resolver.resolve(plan, **kwargs)
    assert caught.value.error.stage is Stage.RESOLVE
    return caught.value.error


def test_demo_plan_parses_and_resolves(resolver: Resolver, model: WorldModel) -> None:
    plan = parse(json.dumps(DEMO))
    grounded = resolver.resolve(plan, seen(model), Pose2D(x=6.0, y=1.2))
    go_counter, pick, go_table, place = grounded.steps
    assert isinstance(go_counter, NavigateStep) and go_counter.goal == model.furniture["kitchen_counter"].approach
    assert isinstance(pick, PickStep) and pick.object_id == "red_cup"
    assert isinstance(go_table, NavigateStep) and go_table.goal == model.furniture["coffee_table"].approach
    assert isinstance(place, PlaceStep) and place.surface_id == "coffee_table"
    assert grounded.source == plan
    assert msgspec.json.decode(msgspec.json.encode(grounded), type=GroundedPlan) == grounded


def test_names_are_normalised(resolver: Resolver) -> None:
    assert normalise_name("the Red Cup.") == "red cup"
    assert normalise_name("Cast-Iron  pan!") == "cast iron pan"
    step = resolver.resolve(plan_of({"action": "pick", "target": "the Red Cup."})).steps[0]
    assert isinstance(step, PickStep) and step.object_id == "red_cup"


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("kitchen", Pose2D(x=2.5, y=2.5, yaw=0.0)),  # a room: its centroid
        ("sitting room", Pose2D(x=8.5, y=2.5, yaw=0.0)),  # by synonym
        ("counter", Pose2D(x=2.5, y=1.05, yaw=-1.5708)),  # furniture: its approach pose
        ("bookshelf", Pose2D(x=6.0, y=7.9, yaw=1.5708)),
        ("charging dock", Pose2D(x=11.2, y=0.8, yaw=0.0)),  # a place: its pose
        ("blue book", Pose2D(x=8.0, y=1.75, yaw=1.5708)),  # an object: the approach of its support
        ("stairs", Pose2D(x=11.2, y=8.0, yaw=1.5708)),  # resolves; refusing it is safety's job
    ],
)
def test_navigate_to_every_kind_of_place(resolver: Resolver, name: str, expected: Pose2D) -> None:
    step = resolver.resolve(plan_of({"action": "navigate_to", "target": name})).steps[0]
    assert isinstance(step, NavigateStep)
    assert step.goal == expected


def test_navigate_to_an_object_uses_where_it_was_seen(resolver: Resolver, model: WorldModel) -> None:
    moved = seen(model, blue_book=(Vec3(x=2.4, y=3.9, z=0.765), "kitchen_table"))
    step = resolver.resolve(plan_of({"action": "navigate_to", "target": "book"}), moved).steps[0]
    assert isinstance(step, NavigateStep) and step.goal == model.furniture["kitchen_table"].approach


def test_navigate_to_the_operator_from_the_robot(resolver: Resolver) -> None:
    robot = Pose2D(x=6.5, y=1.5, yaw=0.0)
    step = resolver.resolve(plan_of({"action": "navigate_to", "target": "me"}), None, robot).steps[0]
    assert isinstance(step, NavigateStep) and step.target == "operator"
    # 0.8 m short of the operator (9.5, 1.5) on the line from the robot, facing them.
    assert (step.goal.x, step.goal.y, step.goal.yaw) == pytest.approx((8.7, 1.5, 0.0))


def test_navigate_to_the_operator_without_a_robot_pose_stands_in_front(resolver: Resolver) -> None:
    step = resolver.resolve(plan_of({"action": "navigate_to", "target": "operator"})).steps[0]
    assert isinstance(step, NavigateStep)
    # The operator faces west (yaw pi): stand 0.8 m west of them, facing east.
    assert (step.goal.x, step.goal.y) == pytest.approx((8.7, 1.5), abs=1e-3)
    assert math.cos(step.goal.yaw) == pytest.approx(1.0, abs=1e-3)


def test_navigate_to_a_person_where_they_were_last_seen(resolver: Resolver) -> None:
    humans = PerceivedHumans(
        stamp=1.0, humans=[PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=2.0, y=7.0))]
    )
    robot = Pose2D(x=2.0, y=5.0)
    step = resolver.resolve(plan_of({"action": "navigate_to", "target": "user"}), None, robot, humans=humans).steps[0]
    assert isinstance(step, NavigateStep)
    assert (step.goal.x, step.goal.y, step.goal.yaw) == pytest.approx((2.0, 6.2, math.pi / 2), abs=1e-3)


def test_pick_red_cup_from_the_world_file(resolver: Resolver, model: WorldModel) -> None:
    step = resolver.resolve(plan_of({"action": "pick", "target": "red cup"})).steps[0]
    assert step == PickStep(
        object_id="red_cup",
        object_name="red cup",
        position=Vec3(x=2.2, y=0.55, z=0.95),
        mass=0.25,
        support_id="kitchen_counter",
        approach=model.furniture["kitchen_counter"].approach,
    )


def test_pick_uses_the_perceived_position_over_the_file(resolver: Resolver, model: WorldModel) -> None:
    where = Vec3(x=2.05, y=0.5, z=0.95)
    objects = seen(model, red_cup=(where, "kitchen_counter"))
    step = resolver.resolve(plan_of({"action": "pick", "target": "red cup"}), objects).steps[0]
    assert isinstance(step, PickStep)
    assert step.position == where
    assert step.support_id == "kitchen_counter"
    assert step.approach == model.furniture["kitchen_counter"].approach


def test_pick_from_the_floor_stands_short_of_the_object(resolver: Resolver, model: WorldModel) -> None:
    where = Vec3(x=4.0, y=2.0, z=0.05)
    robot = Pose2D(x=6.0, y=2.0)
    objects = seen(model, apple=(where, None))
    step = resolver.resolve(plan_of({"action": "pick", "target": "apple"}), objects, robot).steps[0]
    assert isinstance(step, PickStep)
    assert (step.position, step.support_id) == (where, "floor")
    assert (step.approach.x, step.approach.y, step.approach.yaw) == pytest.approx((4.6, 2.0, math.pi), abs=1e-3)


def test_pick_mass_comes_from_the_world_file(resolver: Resolver) -> None:
    # Over the arm's payload: safety refuses it later, not the resolver.
    step = resolver.resolve(plan_of({"action": "pick", "target": "cast-iron pan", "params": {"mass": 0.1}})).steps[0]
    assert isinstance(step, PickStep)
    assert (step.object_id, step.mass) == ("cast_iron_pan", 4.5)


def test_picking_what_is_already_held_is_refused(resolver: Resolver, model: WorldModel) -> None:
    held = seen(model, red_cup=(Vec3(x=6.0, y=1.2, z=1.0), "gripper"))
    error = refusal(resolver, plan_of({"action": "pick", "target": "red cup"}), objects=held)
    assert error.kind is ErrorKind.PRECONDITION
    assert error.step == 0 and "step 1" in error.message and "already in the gripper" in error.message


def test_picking_a_second_object_while_holding_one_is_refused(resolver: Resolver) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "pick", "target": "apple"})
    error = refusal(resolver, plan)
    assert error.kind is ErrorKind.PRECONDITION and error.step == 1
    assert "holds red cup" in error.message


@pytest.mark.parametrize(
    ("name", "noun"), [("kitchen counter", "furniture"), ("kitchen", "a room"), ("me", "a person")]
)
def test_picking_what_is_not_an_object_is_refused(resolver: Resolver, name: str, noun: str) -> None:
    error = refusal(resolver, plan_of({"action": "pick", "target": name}))
    assert error.kind is ErrorKind.INVALID_REQUEST
    assert f"is {noun}, not an object" in error.message


def test_ambiguous_name_lists_the_candidates(resolver: Resolver) -> None:
    plan = plan_of({"action": "navigate_to", "target": "kitchen"}, {"action": "pick", "target": "cup"})
    error = refusal(resolver, plan)
    assert error.kind is ErrorKind.AMBIGUOUS_NAME
    assert error.step == 1 and error.message.startswith("step 2: 'cup' is ambiguous")
    assert sorted(error.candidates) == ["blue cup", "red cup"]
    assert "red cup" in error.message and "blue cup" in error.message


def test_ambiguous_object_is_settled_by_the_location_it_is_on(resolver: Resolver) -> None:
    step = resolver.resolve(plan_of({"action": "pick", "target": "cup", "location": "kitchen table"})).steps[0]
    assert isinstance(step, PickStep) and step.object_id == "blue_cup"


def test_unknown_name_suggests_the_nearest(resolver: Resolver) -> None:
    error = refusal(resolver, plan_of({"action": "navigate_to", "target": "coffe tabel"}))
    assert error.kind is ErrorKind.UNKNOWN_NAME
    assert error.candidates[0] == "coffee table"
    assert "did you mean 'coffee table'" in error.message
    error = refusal(resolver, plan_of({"action": "navigate_to", "target": "spaceship"}))
    assert error.kind is ErrorKind.UNKNOWN_NAME and "household" in error.message


def test_place_on_the_coffee_table_away_from_the_blue_book(resolver: Resolver, model: WorldModel) -> None:
    # The book lies right where the cup would go by default: the near edge, in line with the approach.
    book = Vec3(x=8.0, y=2.35, z=0.465)
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": "coffee table"})
    place = resolver.resolve(plan, seen(model, blue_book=(book, "coffee_table"))).steps[1]
    assert isinstance(place, PlaceStep)
    assert (place.surface_id, place.surface_name) == ("coffee_table", "coffee table")
    assert place.approach == model.furniture["coffee_table"].approach
    assert place.position.z == pytest.approx(0.45)
    # On the near (south) edge, 0.15 m in, shifted sideways clear of the book.
    assert place.position.y == pytest.approx(2.2 + 0.15)
    assert math.dist((place.position.x, place.position.y), (book.x, book.y)) >= 0.15 - 1e-9
    assert 7.5 < place.position.x < 8.5


def test_default_spot_is_in_line_with_the_approach(resolver: Resolver) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": "coffee table"})
    place = resolver.resolve(plan).steps[1]
    assert isinstance(place, PlaceStep) and place.position == Vec3(x=8.0, y=2.35, z=0.45)


def test_two_things_placed_on_one_table_do_not_overlap(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "pick", "target": "red cup"},
        {"action": "place", "location": "bed"},
        {"action": "pick", "target": "mug"},
        {"action": "place", "location": "bed"},
    )
    first, second = (s for s in resolver.resolve(plan).steps if isinstance(s, PlaceStep))
    # The bed's approach is east of it: the spots are 0.15 m in from its east edge (x = 2.3).
    assert first.position.x == pytest.approx(2.15) == second.position.x
    assert math.dist((first.position.x, first.position.y), (second.position.x, second.position.y)) >= 0.15 - 1e-9


def test_place_without_a_location_is_refused_naming_the_step(resolver: Resolver) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "target": "red cup"})
    error = refusal(resolver, plan)
    assert error.step == 1 and "step 2: place needs a location" in error.message


def test_place_on_a_room_is_refused(resolver: Resolver) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": "kitchen"})
    error = refusal(resolver, plan)
    assert "kitchen is a room, not furniture" in error.message


def test_place_with_an_empty_gripper_is_refused(resolver: Resolver, model: WorldModel) -> None:
    error = refusal(resolver, plan_of({"action": "place", "location": "shelf"}), objects=seen(model))
    assert error.kind is ErrorKind.PRECONDITION and "holds nothing" in error.message


def test_the_other_actions(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "detect", "target": "apple"},
        {"action": "say", "params": {"text": "Here you are"}},
        {"action": "wait", "params": {"duration": 2.5}},
        {"action": "stop"},
    )
    assert resolver.resolve(plan).steps == [
        DetectStep(object_id="apple", object_name="apple"),
        SayStep(text="Here you are"),
        WaitStep(duration=2.5),
        StopStep(),
    ]


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        ({"action": "wait"}, "wait needs a 'duration'"),
        ({"action": "wait", "params": {"duration": 90}}, "outside 0..60 s"),
        ({"action": "say"}, "say needs the words"),
        ({"action": "navigate_to"}, "navigate_to needs a target"),
        ({"action": "detect", "target": "bed"}, "bed is furniture, not an object or a person"),
    ],
)
def test_incomplete_steps_are_refused(resolver: Resolver, step: dict[str, Any], expected: str) -> None:
    error = refusal(resolver, plan_of({"action": "stop"}, step))
    assert error.step == 1 and expected in error.message and error.message.startswith("step 2:")


def test_answer_is_always_a_value(resolver: Resolver) -> None:
    assert isinstance(answer(resolver, plan_of({"action": "stop"})), GroundedPlan)
    reply = answer(resolver, plan_of({"action": "pick", "target": "cup"}))
    assert isinstance(reply, ServiceError) and reply.kind is ErrorKind.AMBIGUOUS_NAME
