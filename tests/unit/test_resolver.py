"""The resolver: names become ids and poses from the world model and perception, or a clear refusal."""

from __future__ import annotations

import json
import math
import time
from typing import Any

import msgspec
import pytest

from schemas.common import ErrorKind, Pose2D, ServiceError, Stage, Vec3
from schemas.plan import (
    DetectStep,
    GripperStep,
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
from schemas.world import KeepOut, PerceivedHuman, PerceivedHumans, PerceivedObject, PerceivedObjects
from services.footprint import TRACKING_TOLERANCE, footprint
from services.resolver.config import ResolverConfig
from services.resolver.errors import ResolveError
from services.resolver.memory import Origin
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
    # Imported here so a parser mid-change fails this test only, not the whole module.
    from services.parser.parser import parse

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
        # By synonym. The living room's centre is at the coffee table: the free spot nearest it.
        ("sitting room", Pose2D(x=9.001, y=2.5, yaw=1.5708)),
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


def test_picking_what_is_already_held_is_done_already_with_a_warning(resolver: Resolver, model: WorldModel) -> None:
    held = seen(model, red_cup=(Vec3(x=6.0, y=1.2, z=1.0), "gripper"))
    grounded = resolver.resolve(plan_of({"action": "pick", "target": "red cup"}), held, START)
    assert grounded.steps == []
    assert any("step 1: red cup is already in the gripper" in w for w in grounded.warnings), grounded.warnings
    # "Pick up the red cup" and then "bring it to me" (a pick and a place): one pick, one place.
    plan = plan_of(
        {"action": "pick", "target": "red cup"},
        {
            "substeps": [
                {"action": "pick", "target": "it"},
                {"action": "place", "target": "it", "location": "me"},
            ]
        },
    )
    grounded = resolver.resolve(plan, None, START)
    assert [type(s).__name__ for s in grounded.steps] == ["PickStep", "PlaceStep"]


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
    assert sorted(error.candidates) == ["blue cup on the kitchen table", "red cup on the kitchen counter"]
    assert "red cup" in error.message and "blue cup" in error.message


def test_ambiguous_object_is_settled_by_the_location_it_is_on(resolver: Resolver) -> None:
    step = resolver.resolve(plan_of({"action": "pick", "target": "cup", "location": "kitchen table"})).steps[0]
    assert isinstance(step, PickStep) and step.object_id == "blue_cup"


def test_a_near_miss_resolves_with_a_warning(resolver: Resolver) -> None:
    grounded = resolver.resolve(plan_of({"action": "navigate_to", "target": "coffe tabel"}))
    assert grounded.resolutions[0].id == "coffee_table" and grounded.resolutions[0].via == "fuzzy"
    assert 0.8 <= grounded.resolutions[0].confidence < 1.0
    assert grounded.warnings == ["step 1: 'coffe tabel' read as coffee table (match 0.87)"]


def test_unknown_name_suggests_the_nearest(resolver: Resolver) -> None:
    error = refusal(resolver, plan_of({"action": "navigate_to", "target": "kofi tabel"}))
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


OPERATOR = (9.5, 1.5)  # where the world file puts the operator


def operator_at(x: float, y: float) -> PerceivedHumans:
    return PerceivedHumans(stamp=1.0, humans=[PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=x, y=y))])


@pytest.mark.parametrize(
    "place",
    [
        {"action": "place", "target": "red cup", "target_location": "me"},
        {"action": "place", "target": "me"},
        {"action": "place", "target_location": "the user"},
        {"action": "place", "object": "red cup", "destination": "operator"},
    ],
)
def test_placing_at_me_puts_it_on_the_free_surface_nearest_the_operator(
    resolver: Resolver, model: WorldModel, place: dict[str, str]
) -> None:
    from services.parser.parser import parse

    plan = parse(json.dumps({"plan": [{"action": "pick", "target": "red cup"}, place]}))
    grounded = resolver.resolve(plan, seen(model), Pose2D(x=6.0, y=1.2))
    step = grounded.steps[1]
    # The coffee table's free spot nearest the operator is 1.4 m from them; the chair's is 2.0 m.
    assert isinstance(step, PlaceStep) and step.surface_id == "coffee_table"
    assert step.approach == model.furniture["coffee_table"].approach
    spot = (step.position.x, step.position.y)
    assert spot == pytest.approx((8.35, 2.35)) and step.position.z == pytest.approx(0.45)
    book = model.initial_position(model.objects["blue_book"])
    assert math.dist(spot, (book.x, book.y)) >= resolver.config.place_clearance - 1e-9
    assert math.dist(spot, OPERATOR) == pytest.approx(1.43, abs=0.01)
    assert any("the free surface nearest them (1.4 m)" in w and "coffee table" in w for w in grounded.warnings)
    kinds = [(r.kind, r.id) for r in grounded.resolutions if r.label == "2" and r.kind != "object"]
    assert kinds == [("human", "operator"), ("furniture", "coffee_table")]


def test_a_delivery_skips_a_full_top_and_never_goes_where_the_person_is(resolver: Resolver, model: WorldModel) -> None:
    pick_place = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": "me"})
    # North of the chair: its top is nearest.
    step = resolver.resolve(pick_place, seen(model), humans=operator_at(9.5, 4.6)).steps[1]
    assert isinstance(step, PlaceStep) and step.surface_id == "chair"
    assert step.position.y <= 3.85 and math.dist((step.position.x, step.position.y), (9.5, 4.6)) >= 0.4
    # The apple on the chair leaves no spot clear of it: the next nearest top.
    apple_on_chair = seen(model, apple=(Vec3(x=9.5, y=3.6, z=0.49), "chair"))
    step = resolver.resolve(pick_place, apple_on_chair, humans=operator_at(9.5, 4.6)).steps[1]
    assert isinstance(step, PlaceStep) and step.surface_id == "coffee_table"
    # Someone sitting on the chair: not on their lap.
    step = resolver.resolve(pick_place, seen(model), humans=operator_at(9.5, 3.6)).steps[1]
    assert isinstance(step, PlaceStep) and step.surface_id == "coffee_table"


def test_a_delivery_avoids_keep_out_zones(model: WorldModel) -> None:
    pick_place = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": "me"})
    near_chair = operator_at(9.5, 4.6)
    rug = KeepOut(id="rug", name="rug", polygon=[(9.0, 2.5), (10.0, 2.5), (10.0, 3.1), (9.0, 3.1)])
    fenced = Resolver(WorldModel(msgspec.structs.replace(model.world, keep_out=[*model.world.keep_out, rug])))
    # The chair's approach pose is in the zone: the base could not stand there to reach its top.
    step = fenced.resolve(pick_place, seen(model), humans=near_chair).steps[1]
    assert isinstance(step, PlaceStep) and step.surface_id == "coffee_table"
    error = refusal(Resolver(fenced.model, ResolverConfig(deliver_max_distance=1.0)), pick_place, humans=near_chair)
    assert "the chair (0.7 m, its approach pose is in a keep-out zone)" in error.message  # 0.75 m to its top


def test_a_delivery_with_no_top_near_the_person_is_refused_naming_the_nearest(
    resolver: Resolver, model: WorldModel
) -> None:
    plan = plan_of({"action": "pick", "target": "apple"}, {"action": "place", "location": "here"})
    error = refusal(resolver, plan, objects=seen(model), humans=operator_at(11.5, 6.0))
    assert error.kind is ErrorKind.PRECONDITION and error.step == 1
    assert "within 3 m of them" in error.message and "the chair (3.1 m)" in error.message
    assert error.candidates[0] == "chair"
    wider = Resolver(model, ResolverConfig(deliver_max_distance=5.0))
    step = wider.resolve(plan, seen(model), humans=operator_at(11.5, 6.0)).steps[1]
    assert isinstance(step, PlaceStep) and step.surface_id == "chair"


def test_delivering_by_hand_drives_to_the_person_and_keeps_holding(model: WorldModel) -> None:
    by_hand = Resolver(model, ResolverConfig(deliver="hand"))
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "target": "red cup", "location": "me"})
    grounded = by_hand.resolve(plan, seen(model), Pose2D(x=6.0, y=1.2))
    _, step = grounded.steps
    assert isinstance(step, NavigateStep) and step.target == "operator (handing over red cup)"
    # 0.8 m short of the operator on the line from the kitchen counter's approach, facing them.
    assert math.dist((step.goal.x, step.goal.y), OPERATOR) == pytest.approx(0.8, abs=1e-3)
    assert math.atan2(OPERATOR[1] - step.goal.y, OPERATOR[0] - step.goal.x) == pytest.approx(step.goal.yaw, abs=1e-3)
    assert any('keeps holding it (deliver = "hand")' in w for w in grounded.warnings)
    # Still held: nothing else can be picked.
    error = refusal(by_hand, plan_of(*plan_steps(plan), {"action": "pick", "target": "apple"}), objects=seen(model))
    assert error.step == 2 and "already holds red cup" in error.message
    empty = refusal(by_hand, plan_of({"action": "place", "location": "me"}), objects=seen(model))
    assert empty.kind is ErrorKind.PRECONDITION and "holds nothing" in empty.message


def plan_steps(plan: Plan) -> list[dict[str, Any]]:
    return [msgspec.to_builtins(s) for s in plan.steps]


@pytest.mark.parametrize("phrase", ["where it was found", "back", "its place", "Where it was."])
def test_putting_it_back_returns_it_to_where_this_plan_picked_it_up(
    resolver: Resolver, model: WorldModel, phrase: str
) -> None:
    plan = plan_of(
        {"action": "pick", "target": "apple"},
        {"action": "navigate_to", "target": "bed"},
        {"action": "place", "location": phrase},
    )
    grounded = resolver.resolve(plan, seen(model))
    step = grounded.steps[2]
    apple = model.initial_position(model.objects["apple"])
    assert isinstance(step, PlaceStep) and step.surface_id == "kitchen_table"
    assert (step.position.x, step.position.y) == pytest.approx((apple.x, apple.y))
    assert step.position.z == pytest.approx(0.75)
    assert any("where step 1 picked it up, at the same spot" in w for w in grounded.warnings)


def test_putting_it_back_means_where_the_latest_pick_took_it_from(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "pick", "target": "apple"},
        {"action": "place", "location": "coffee table"},
        {"action": "pick", "target": "apple"},
        {"action": "place", "target": "apple", "location": "back"},
    )
    grounded = resolver.resolve(plan)
    first, again = grounded.steps[1], grounded.steps[3]
    assert isinstance(again, PlaceStep) and again.surface_id == "coffee_table"
    assert isinstance(first, PlaceStep) and again.position == first.position
    assert any("where step 3 picked it up" in w for w in grounded.warnings)


def test_putting_back_what_was_held_from_the_start_uses_memory_and_moves_over_when_taken(
    resolver: Resolver, model: WorldModel
) -> None:
    apple = model.initial_position(model.objects["apple"])
    # A plan earlier picked the apple (the memory saw it on the kitchen table until then); since,
    # the blue cup was put where the apple was.
    held = seen(model, apple=(Vec3(x=2.5, y=2.5, z=1.0), "gripper"), blue_cup=(apple, "kitchen_table"))
    origins = {"apple": Origin("kitchen_table", apple)}
    grounded = resolver.resolve(plan_of({"action": "place", "location": "where it was found"}), held, origins=origins)
    (step,) = grounded.steps
    assert isinstance(step, PlaceStep) and step.surface_id == "kitchen_table"
    spot = (step.position.x, step.position.y)
    assert 0.15 - 1e-9 <= math.dist(spot, (apple.x, apple.y)) <= 0.25
    assert any("the camera last saw it before it was in the gripper" in w for w in grounded.warnings)
    assert any("the free spot nearest its old one" in w for w in grounded.warnings)
    # Memory of where something not in the gripper was is not a reason to move it.
    error = refusal(resolver, plan_of({"action": "place", "location": "back"}), objects=seen(model), origins=origins)
    assert "holds nothing" in error.message


def test_putting_back_with_nowhere_known_or_from_the_floor_is_refused(resolver: Resolver, model: WorldModel) -> None:
    held = seen(model, apple=(Vec3(x=6.3, y=1.2, z=1.0), "gripper"))
    put_back = plan_of({"action": "place", "location": "back"})
    error = refusal(resolver, put_back, objects=held)
    assert error.kind is ErrorKind.PRECONDITION and "this plan did not pick it up" in error.message
    floor = {"apple": Origin(None, Vec3(x=6.0, y=1.0, z=0.04))}
    error = refusal(resolver, put_back, objects=held, origins=floor)
    assert error.kind is ErrorKind.PRECONDITION and "it was on the floor" in error.message
    # Nothing perceived: which object the gripper holds is not known, and the plan does not say.
    error = refusal(resolver, put_back)
    assert "what the gripper holds is not known" in error.message


def test_put_back_phrases_are_configured(model: WorldModel) -> None:
    german = Resolver(model, ResolverConfig(put_back_phrases=("wo es war", "zurück")))
    plan = plan_of({"action": "pick", "target": "apple"}, {"action": "place", "location": "zurück"})
    step = german.resolve(plan).steps[1]
    assert isinstance(step, PlaceStep) and step.surface_id == "kitchen_table"
    plan = plan_of({"action": "pick", "target": "apple"}, {"action": "place", "location": "back"})
    assert refusal(german, plan).kind is ErrorKind.UNKNOWN_NAME
    with pytest.raises(msgspec.ValidationError, match="put_back_phrases"):
        msgspec.convert({"put_back_phrases": [""]}, ResolverConfig)
    with pytest.raises(msgspec.ValidationError, match=r"\$\.deliver"):
        msgspec.convert({"deliver": "mail"}, ResolverConfig)


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
        ({"action": "detect", "target": "bed"}, "bed is furniture, not an object"),
    ],
)
def test_incomplete_steps_are_refused(resolver: Resolver, step: dict[str, Any], expected: str) -> None:
    error = refusal(resolver, plan_of({"action": "stop"}, step))
    assert error.step == 1 and expected in error.message and error.message.startswith("step 2:")


def test_answer_is_always_a_value(resolver: Resolver) -> None:
    assert isinstance(answer(resolver, plan_of({"action": "stop"})), GroundedPlan)
    reply = answer(resolver, plan_of({"action": "pick", "target": "cup"}))
    assert isinstance(reply, ServiceError) and reply.kind is ErrorKind.AMBIGUOUS_NAME


# Groups, sub-steps and on_failure alternatives

START = Pose2D(x=6.0, y=1.2, yaw=0.0)


def test_groups_are_flattened_in_order_with_labels(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "navigate_to", "target": "kitchen counter"},
        {"substeps": [{"action": "pick", "target": "red cup"}, {"substeps": [{"action": "say", "target": "got it"}]}]},
        {"action": "place", "location": "coffee table"},
    )
    grounded = resolver.resolve(plan, None, START)
    assert [type(s).__name__ for s in grounded.steps] == ["NavigateStep", "PickStep", "SayStep", "PlaceStep"]
    assert grounded.labels == ["1", "2.1", "2.2.1", "3"]
    assert grounded.fallbacks == []
    assert msgspec.json.decode(msgspec.json.encode(grounded), type=GroundedPlan) == grounded


def test_a_refused_sub_step_is_named_by_its_label(resolver: Resolver) -> None:
    plan = plan_of({"action": "stop"}, {"substeps": [{"action": "stop"}, {"action": "pick", "target": "cup"}]})
    error = refusal(resolver, plan)
    assert error.kind is ErrorKind.AMBIGUOUS_NAME
    assert error.step == 1 and error.message.startswith("step 2.2: 'cup' is ambiguous")


def test_on_failure_covers_the_grounded_range_of_its_step(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "say", "target": "hello"},
        {
            "substeps": [{"action": "navigate_to", "target": "counter"}, {"action": "pick", "target": "red cup"}],
            "on_failure": [{"action": "navigate_to", "target": "dock"}, {"action": "say", "target": "no cup"}],
        },
        {"action": "navigate_to", "target": "coffee table"},
    )
    grounded = resolver.resolve(plan, None, START)
    assert grounded.labels == ["1", "2.1", "2.2", "3"]
    (fallback,) = grounded.fallbacks
    assert (fallback.first, fallback.last) == (1, 2)
    assert fallback.labels == ["2 on_failure 1", "2 on_failure 2"]
    assert fallback.steps == [NavigateStep(target="charging dock", goal=Pose2D(x=11.2, y=0.8)), SayStep(text="no cup")]


def test_alternatives_are_grounded_from_the_state_at_the_start_of_their_step(resolver: Resolver) -> None:
    # Before step 2 the gripper holds the cup, so the alternative may place it; after step 2 it
    # would hold nothing and the alternative would be refused.
    plan = plan_of(
        {"action": "pick", "target": "red cup"},
        {
            "action": "place",
            "location": "coffee table",
            "on_failure": [{"action": "place", "location": "kitchen table"}],
        },
        {"action": "pick", "target": "apple"},
    )
    grounded = resolver.resolve(plan, None, START)
    (fallback,) = grounded.fallbacks
    assert (fallback.first, fallback.last) == (1, 1)
    (place,) = fallback.steps
    assert isinstance(place, PlaceStep) and place.surface_id == "kitchen_table"


def test_an_alternative_is_refused_by_its_label(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "stop"}, {"action": "say", "target": "hi", "on_failure": [{"action": "pick", "target": "cup"}]}
    )
    error = refusal(resolver, plan)
    assert error.step == 1 and error.message.startswith("step 2 on_failure 1: 'cup' is ambiguous")


def test_an_on_failure_inside_an_alternative_is_refused(resolver: Resolver) -> None:
    plan = plan_of(
        {
            "substeps": [
                {
                    "action": "detect",
                    "target": "apple",
                    "on_failure": [{"action": "say", "target": "hm", "on_failure": [{"action": "stop"}]}],
                }
            ]
        }
    )
    error = refusal(resolver, plan)
    assert error.kind is ErrorKind.INVALID_REQUEST and error.step == 0
    assert error.message.startswith("step 1.1 on_failure 1: an on_failure inside an on_failure alternative")


def test_on_failure_inside_a_group_with_its_own_on_failure_is_fine(resolver: Resolver) -> None:
    plan = plan_of(
        {
            "substeps": [
                {"action": "detect", "target": "apple", "on_failure": [{"action": "say", "target": "no apple"}]},
                {"action": "detect", "target": "blue book"},
            ],
            "on_failure": [{"action": "say", "target": "nothing found"}],
        }
    )
    inner, outer = resolver.resolve(plan).fallbacks
    assert (inner.first, inner.last, inner.labels) == (0, 0, ["1.1 on_failure 1"])
    assert (outer.first, outer.last, outer.labels) == (0, 1, ["1 on_failure 1"])


# Relative moves: drive, turn, look_at


def test_drive_and_turn_are_relative_to_the_predicted_pose(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "drive", "params": {"distance": 1.0}, "units": {"distance": "m"}},
        {"action": "turn", "params": {"angle": math.pi / 2}, "units": {"angle": "rad"}},
        {"action": "drive", "params": {"distance": 0.5, "speed": 0.2}},
        {"action": "navigate_to", "target": "kitchen counter"},
        {"action": "turn", "params": {"angle": -math.pi / 2}},
    )
    steps = resolver.resolve(plan, None, START).steps
    assert steps == [
        NavigateStep(target="1.00 m forward", goal=Pose2D(x=7.0, y=1.2, yaw=0.0)),
        NavigateStep(target="90° left", goal=Pose2D(x=7.0, y=1.2, yaw=1.5708)),
        NavigateStep(target="0.50 m forward", goal=Pose2D(x=7.0, y=1.7, yaw=1.5708), max_speed=0.2),
        NavigateStep(target="kitchen counter", goal=Pose2D(x=2.5, y=1.05, yaw=-1.5708)),
        # From the counter's approach pose (facing south): a right turn faces west.
        NavigateStep(target="90° right", goal=Pose2D(x=2.5, y=1.05, yaw=3.1416)),
    ]


def test_after_pick_and_place_the_robot_stands_at_their_approach(resolver: Resolver, model: WorldModel) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "drive", "params": {"distance": -0.2}})
    back = resolver.resolve(plan, None, START).steps[1]
    approach = model.furniture["kitchen_counter"].approach  # facing south at (2.5, 1.05)
    assert isinstance(back, NavigateStep) and back.target == "0.20 m backward"
    assert (back.goal.x, back.goal.y, back.goal.yaw) == pytest.approx((approach.x, approach.y + 0.2, approach.yaw))


def test_a_long_backward_drive_turns_round_drives_and_turns_back(resolver: Resolver) -> None:
    plan = plan_of({"action": "drive", "params": {"distance": -1.0}}, {"action": "say", "target": "done"})
    grounded = resolver.resolve(plan, None, START)
    away, back, _ = grounded.steps
    # Facing the way it goes, so the straight-in leg to the goal lies between start and goal.
    assert isinstance(away, NavigateStep) and away.goal == Pose2D(x=5.0, y=1.2, yaw=3.1416)
    assert isinstance(back, NavigateStep) and back.goal == Pose2D(x=5.0, y=1.2, yaw=0.0)
    assert grounded.labels == ["1", "1", "2"]


def test_a_turn_past_120_degrees_is_split_so_it_turns_the_way_asked(resolver: Resolver) -> None:
    plan = plan_of({"action": "turn", "params": {"angle": 1.5 * math.pi}})
    steps = resolver.resolve(plan, None, START).steps
    assert [s.target for s in steps if isinstance(s, NavigateStep)] == [
        "270° left (1/3)",
        "270° left (2/3)",
        "270° left (3/3)",
    ]
    yaws = [s.goal.yaw for s in steps if isinstance(s, NavigateStep)]
    assert yaws == pytest.approx([math.pi / 2, math.pi, -math.pi / 2], abs=1e-3)
    # A full turn ends where it started, but does turn.
    full = resolver.resolve(plan_of({"action": "turn", "params": {"angle": -2 * math.pi}}), None, START).steps
    assert len(full) == 3 and [s.goal.yaw for s in full if isinstance(s, NavigateStep)][-1] == pytest.approx(0.0)


def test_look_at_turns_in_place_to_face_the_target(resolver: Resolver) -> None:
    plan = plan_of({"action": "look_at", "target": "me"}, {"action": "look_at", "target": "coffee table"})
    me, table = resolver.resolve(plan, None, START).steps
    assert isinstance(me, NavigateStep) and me.target == "facing operator"
    assert (me.goal.x, me.goal.y) == (6.0, 1.2)
    assert me.goal.yaw == pytest.approx(math.atan2(1.5 - 1.2, 9.5 - 6.0), abs=1e-4)
    assert isinstance(table, NavigateStep) and table.goal.yaw == pytest.approx(
        math.atan2(2.5 - 1.2, 8.0 - 6.0), abs=1e-4
    )
    held = seen_holding(resolver)
    error = refusal(resolver, plan_of({"action": "look_at", "target": "red cup"}), objects=held, robot=START)
    assert error.kind is ErrorKind.PRECONDITION and "in the gripper" in error.message


def seen_holding(resolver: Resolver) -> PerceivedObjects:
    return seen(resolver.model, red_cup=(Vec3(x=6.0, y=1.2, z=1.0), "gripper"))


@pytest.mark.parametrize(
    "step",
    [
        {"action": "drive", "params": {"distance": 1.0}},
        {"action": "turn", "params": {"angle": 1.0}},
        {"action": "look_at", "target": "me"},
    ],
)
def test_relative_moves_without_a_robot_pose_are_refused(resolver: Resolver, step: dict[str, Any]) -> None:
    error = refusal(resolver, plan_of(step))
    assert error.kind is ErrorKind.PRECONDITION and "pose is unknown" in error.message
    # A named place first makes the pose known.
    grounded = resolver.resolve(plan_of({"action": "navigate_to", "target": "kitchen"}, step))
    assert len(grounded.steps) == 2


def test_a_relative_move_after_an_on_failure_that_ends_elsewhere_is_refused(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "navigate_to", "target": "kitchen", "on_failure": [{"action": "navigate_to", "target": "dock"}]},
        {"action": "turn", "params": {"angle": 1.0}},
    )
    error = refusal(resolver, plan, robot=START)
    assert error.step == 1 and "depends on whether its on_failure ran" in error.message
    # If both ways end at the same place, the pose after is known.
    plan = plan_of(
        {"action": "navigate_to", "target": "kitchen", "on_failure": [{"action": "navigate_to", "target": "kitchen"}]},
        {"action": "turn", "params": {"angle": 1.0}},
    )
    assert resolver.resolve(plan, None, START).steps[1] == NavigateStep(
        target="57° left", goal=Pose2D(x=2.5, y=2.5, yaw=1.0)
    )


def test_relative_moves_in_an_alternative_need_a_step_that_kept_the_base_still(resolver: Resolver) -> None:
    turn = {"action": "turn", "params": {"angle": math.pi / 2}}
    # The failing step may stop the base anywhere: where to turn from is unknown.
    error = refusal(
        resolver, plan_of({"action": "navigate_to", "target": "kitchen", "on_failure": [turn]}), robot=START
    )
    assert error.message.startswith("step 1 on_failure 1: turn moves relative to where the robot stands")
    assert "when step 1 fails is not known in advance" in error.message
    # A say does not move the base: the alternative turns from where it stands. (A detect may: it
    # turns round and drives to furniture when the object is not in view.)
    plan = plan_of(
        {"action": "say", "params": {"text": "hello"}, "on_failure": [turn, {"action": "detect", "target": "apple"}]}
    )
    (fallback,) = resolver.resolve(plan, None, START).fallbacks
    assert fallback.steps[0] == NavigateStep(target="90° left", goal=Pose2D(x=6.0, y=1.2, yaw=1.5708))


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        ({"action": "drive"}, "drive needs a 'distance' in metres"),
        ({"action": "drive", "params": {"distance": 8.0}}, "outside -5..5 m"),
        ({"action": "drive", "params": {"distance": 50}, "units": {"distance": "cm"}}, "it must be in m"),
        ({"action": "drive", "params": {"distance": "far"}}, "must be a number in m"),
        ({"action": "drive", "params": {"distance": 1.0, "speed": -1.0}}, "speed -1 m/s is outside"),
        ({"action": "turn"}, "turn needs an 'angle' in radians"),
        ({"action": "turn", "params": {"angle": 90}}, "outside one full turn"),
        ({"action": "turn", "params": {"angle": 1.0, "speed": 0.3}}, "cannot yet turn slower"),
        ({"action": "look_at"}, "look_at needs a target"),
    ],
)
def test_bad_relative_moves_are_refused(resolver: Resolver, step: dict[str, Any], expected: str) -> None:
    error = refusal(resolver, plan_of({"action": "stop"}, step), robot=START)
    assert error.step == 1 and expected in error.message and error.message.startswith("step 2:")


def test_navigate_to_carries_the_plan_speed(resolver: Resolver) -> None:
    step = resolver.resolve(plan_of({"action": "navigate_to", "target": "kitchen", "params": {"speed": 0.3}})).steps[0]
    assert isinstance(step, NavigateStep) and step.max_speed == 0.3


def test_too_many_robot_steps_are_refused(resolver: Resolver) -> None:
    turns = [{"action": "turn", "params": {"angle": 2 * math.pi}} for _ in range(34)]  # 3 goals each
    error = refusal(resolver, plan_of(*turns), robot=START)
    assert "needs more than 100 robot steps in a row (step 34 brings it to 102" in error.message


def test_a_plan_of_groups_naming_thousands_of_steps_is_refused_before_they_are_all_grounded(
    resolver: Resolver,
) -> None:
    """Groups of 100 sub-steps each: 10,000 steps took 9 s of CPU before the count was looked at."""
    group = {"substeps": [{"action": "turn", "params": {"angle": 0.5}} for _ in range(100)]}
    started = time.process_time()
    error = refusal(resolver, plan_of(*[group] * 100), robot=START)
    assert "needs more than 100 robot steps in a row (step 2.1 brings it to 101" in error.message
    assert time.process_time() - started < 1.0


# The gripper, and what this robot cannot do


def test_open_and_close_gripper(resolver: Resolver) -> None:
    plan = plan_of({"action": "close_gripper"}, {"action": "open_gripper", "params": {"width": 0.05}})
    assert resolver.resolve(plan).steps == [GripperStep(open=False), GripperStep(open=True)]


def test_opening_the_gripper_releases_what_it_holds(resolver: Resolver) -> None:
    plan = plan_of(
        {"action": "pick", "target": "red cup"},
        {"action": "open_gripper"},
        {"action": "close_gripper"},  # on nothing: holds nothing
        {"action": "place", "location": "coffee table"},
    )
    error = refusal(resolver, plan, robot=START)
    assert error.step == 3 and error.kind is ErrorKind.PRECONDITION and "holds nothing" in error.message
    # The cup was released: it may be picked again.
    plan = plan_of(
        {"action": "pick", "target": "red cup"}, {"action": "open_gripper"}, {"action": "pick", "target": "red cup"}
    )
    pick = resolver.resolve(plan, None, START).steps[2]
    assert isinstance(pick, PickStep) and pick.support_id == "floor"


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        ({"action": "gesture", "params": {"gesture": "wave"}}, "this robot cannot gesture yet"),
        ({"action": "move_arm", "target": "home"}, "this robot cannot move its arm on its own yet"),
    ],
)
def test_what_this_robot_cannot_do_is_refused_not_skipped(
    resolver: Resolver, step: dict[str, Any], expected: str
) -> None:
    error = refusal(resolver, plan_of({"action": "say", "target": "hi"}, step))
    assert error.kind is ErrorKind.INVALID_REQUEST and error.step == 1
    assert expected in error.message and "remove the step" in error.message


@pytest.mark.parametrize(
    ("at", "robot"),
    [
        ((2.5, 3.4), Pose2D(x=1.0, y=4.7, yaw=0.0)),  # just south of the kitchen table, the robot north-west
        ((3.0, 0.8), START),  # against the counter, the robot in the living room
        ((2.0, 5.3), Pose2D(x=2.0, y=3.0, yaw=1.57)),  # by the bedroom's wall, the robot in the kitchen
    ],
)
def test_an_object_on_the_floor_is_approached_from_a_side_where_the_base_fits(
    resolver: Resolver, model: WorldModel, at: tuple[float, float], robot: Pose2D
) -> None:
    """Straight from the robot, the base was sent into the table, the counter, or the far side of a wall."""
    cup = (Vec3(x=at[0], y=at[1], z=0.05), None)
    plan = resolver.resolve(plan_of({"action": "pick", "target": "red cup"}), seen(model, red_cup=cup), robot)
    pick = plan.steps[0]
    assert isinstance(pick, PickStep)
    a, size = pick.approach, model.world.robot.base_size
    assert model.clear_by(footprint(a.x, a.y, a.yaw, size.x, size.y)) >= TRACKING_TOLERANCE
    assert model.room_of(a.x, a.y) == model.room_of(*at)
    assert math.dist((a.x, a.y), at) == pytest.approx(resolver.config.object_standoff, abs=1e-3)


def test_an_object_on_the_floor_with_nowhere_to_stand_is_refused(resolver: Resolver, model: WorldModel) -> None:
    widest = max(model.world.furniture, key=lambda f: min(f.size.x, f.size.y))
    under = (Vec3(x=widest.center[0], y=widest.center[1], z=0.05), None)  # every side of it is furniture
    error = refusal(resolver, plan_of({"action": "pick", "target": "red cup"}), objects=seen(model, red_cup=under))
    assert "the base fits nowhere" in error.message and error.kind is ErrorKind.PRECONDITION
