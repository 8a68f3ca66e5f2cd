"""The resolver against names written to mislead it: near-misses that are other words, "it" inside a
relation, names that start with a relation, and messages that must say what was meant."""

from __future__ import annotations

from typing import Any

import pytest

from schemas.common import ErrorKind, Pose2D, ServiceError, Stage, Vec3
from schemas.plan import DetectStep, NavigateStep, PickStep, PlaceStep, Plan
from services.resolver.errors import ResolveError
from services.resolver.names import normalise_name
from services.resolver.resolver import Resolver
from services.worldmodel import WorldModel
from tests.unit.test_resolver import model as model  # the module-scoped fixtures, shared
from tests.unit.test_resolver import plan_of, seen
from tests.unit.test_resolver import resolver as resolver

# In the kitchen between the counter and the table, facing the table (north): the blue cup is left of
# the apple, nothing is right of it.
FACING_THE_TABLE = Pose2D(x=2.5, y=3.05, yaw=1.5708)
# In the doorway between the kitchen and the living room: the robot's room settles nothing.
IN_THE_DOORWAY = Pose2D(x=5.0, y=2.1, yaw=0.0)
# The blue cup moved off the kitchen table (next to the apple) onto the coffee table.
BLUE_CUP_ON_THE_COFFEE_TABLE = (Vec3(x=7.8, y=2.5, z=0.5), "coffee_table")
# From an ASCII character to its fullwidth form ("a" -> U+FF41).
FULLWIDTH_OFFSET = 0xFEE0


def refusal(resolver: Resolver, plan: Plan, *args: Any) -> ServiceError:
    with pytest.raises(ResolveError) as caught:
        resolver.resolve(plan, *args)
    assert caught.value.error.stage is Stage.RESOLVE
    return caught.value.error


# 1. A near-miss is a typo of a name, never another word that happens to be spelt alike


@pytest.mark.parametrize(
    ("step", "meant"),
    [
        ({"action": "navigate_to", "target": "there"}, "operator"),  # 'here' is the operator's synonym
        ({"action": "place", "target": "red cup", "location": "her"}, "operator"),
        ({"action": "place", "target": "red cup", "location": "there"}, "operator"),
        ({"action": "navigate_to", "target": "upstairs"}, "top of the stairs"),
    ],
)
def test_a_word_that_points_is_refused_not_read_as_a_name(
    resolver: Resolver, model: WorldModel, step: dict[str, Any], meant: str
) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, step) if step["action"] == "place" else plan_of(step)
    error = refusal(resolver, plan, seen(model))
    assert error.kind is ErrorKind.UNKNOWN_NAME
    assert f"unknown name {step.get('location') or step['target']!r}" in error.message
    assert "points without naming" in error.message and f"did you mean '{meant}'" in error.message
    assert error.candidates == [meant]


@pytest.mark.parametrize(
    ("step", "candidate"),
    [
        ({"action": "pick", "target": "coffee pot"}, "coffee mug"),  # a pot is not a cup: another head noun
        ({"action": "navigate_to", "target": "living room sofa"}, "living room"),  # an extra word
    ],
)
def test_another_head_noun_or_an_extra_word_is_not_a_typo(
    resolver: Resolver, step: dict[str, Any], candidate: str
) -> None:
    error = refusal(resolver, plan_of(step))
    assert error.kind is ErrorKind.UNKNOWN_NAME
    assert error.message.startswith(f"step 1: unknown name {step['target']!r} (did you mean")
    assert candidate in error.candidates


@pytest.mark.parametrize(
    ("step", "meant", "warning"),
    [
        ({"action": "navigate_to", "target": "kitchn"}, "kitchen", "'kitchn' read as kitchen (match 0.92)"),
        ({"action": "pick", "target": "red cupp"}, "red_cup", "'red cupp' read as red cup (match 0.93)"),
        ({"action": "navigate_to", "target": "coffe tabel"}, "coffee_table", "read as coffee table (match 0.87)"),
        ({"action": "pick", "target": "bleu cup"}, "blue_cup", "'bleu cup' read as blue cup"),
    ],
)
def test_a_real_typo_still_resolves_with_a_warning(
    resolver: Resolver, step: dict[str, Any], meant: str, warning: str
) -> None:
    grounded = resolver.resolve(plan_of(step))
    assert grounded.resolutions[0].id == meant and grounded.resolutions[0].via == "fuzzy"
    assert len(grounded.warnings) == 1 and warning in grounded.warnings[0]


# 2. "it" inside a relation or a location is the object the plan last handled


def test_it_in_a_relation_is_the_object_last_handled(resolver: Resolver, model: WorldModel) -> None:
    plan = plan_of({"action": "detect", "target": "apple"}, {"action": "pick", "target": "the cup next to it"})
    pick = resolver.resolve(plan, seen(model)).steps[1]
    assert isinstance(pick, PickStep) and pick.object_id == "blue_cup"
    # The blue cup moved 5 m away; "next to it" is next to the apple, not next to any object.
    error = refusal(resolver, plan, seen(model, blue_cup=BLUE_CUP_ON_THE_COFFEE_TABLE))
    assert error.kind is ErrorKind.UNKNOWN_NAME
    assert "nothing called 'cup' is near the apple" in error.message


@pytest.mark.parametrize(
    "step",
    [
        {"action": "pick", "target": "the cup next to it"},
        {"action": "pick", "target": "the cup", "location": "it"},
        {"action": "pick", "target": "the book near that"},  # "that" is a pronoun here, not a filler
    ],
)
def test_it_in_a_relation_before_anything_was_handled_is_refused(
    resolver: Resolver, model: WorldModel, step: dict[str, Any]
) -> None:
    error = refusal(resolver, plan_of(step), seen(model), IN_THE_DOORWAY)
    assert error.kind is ErrorKind.UNKNOWN_NAME
    assert "does not refer to anything yet" in error.message


# 3. A name that starts with a relation names a where: honoured, or refused, never dropped


@pytest.mark.parametrize("target", ["closest to the apple", "next to the apple", "left of the apple"])
def test_a_thing_named_only_by_a_relation_is_refused(resolver: Resolver, model: WorldModel, target: str) -> None:
    error = refusal(resolver, plan_of({"action": "pick", "target": target}), seen(model), FACING_THE_TABLE)
    assert error.kind is ErrorKind.UNKNOWN_NAME
    assert f"{target!r} says where, not what: name the thing first" in error.message


@pytest.mark.parametrize(
    ("location", "why"),
    [
        ("to the right of the apple", "never right of it"),
        ("left of the apple", "never left of it"),
        ("on the apple", "nothing can be on the apple"),
    ],
)
def test_a_place_it_cannot_honour_is_refused(resolver: Resolver, model: WorldModel, location: str, why: str) -> None:
    plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": location})
    error = refusal(resolver, plan, seen(model), FACING_THE_TABLE)
    assert error.kind is ErrorKind.INVALID_REQUEST
    assert why in error.message


def test_a_place_next_to_a_thing_or_on_a_surface_still_goes_there(resolver: Resolver, model: WorldModel) -> None:
    for location in ("next to the apple", "on the kitchen table"):
        plan = plan_of({"action": "pick", "target": "red cup"}, {"action": "place", "location": location})
        place = resolver.resolve(plan, seen(model), FACING_THE_TABLE).steps[1]
        assert isinstance(place, PlaceStep) and place.surface_id == "kitchen_table"


def test_a_side_in_a_step_location_is_kept(resolver: Resolver, model: WorldModel) -> None:
    left = plan_of({"action": "pick", "target": "the cup", "location": "left of the apple"})
    pick = resolver.resolve(left, seen(model), FACING_THE_TABLE).steps[0]
    assert isinstance(pick, PickStep) and pick.object_id == "blue_cup"
    right = plan_of({"action": "pick", "target": "the cup", "location": "to the right of the apple"})
    error = refusal(resolver, right, seen(model), FACING_THE_TABLE)
    assert error.kind is ErrorKind.UNKNOWN_NAME and "is right of the apple" in error.message


# 4. A near-miss anywhere in what decides the target is said back


def test_a_near_miss_location_is_warned(resolver: Resolver, model: WorldModel) -> None:
    plan = plan_of({"action": "pick", "target": "the cup", "location": "kitchn"})
    grounded = resolver.resolve(plan, seen(model, blue_cup=BLUE_CUP_ON_THE_COFFEE_TABLE), IN_THE_DOORWAY)
    pick = grounded.steps[0]
    assert isinstance(pick, PickStep) and pick.object_id == "red_cup"
    assert grounded.warnings == ["step 1: 'kitchn' read as kitchen (match 0.92)"]


def test_a_near_miss_inside_a_relation_is_warned(resolver: Resolver, model: WorldModel) -> None:
    grounded = resolver.resolve(plan_of({"action": "detect", "target": "the cup on the kichen table"}), seen(model))
    detect = grounded.steps[0]
    assert isinstance(detect, DetectStep) and detect.object_id == "blue_cup"
    assert grounded.warnings == ["step 1: 'kichen table' read as kitchen table (match 0.96)"]


def test_a_location_that_is_no_typo_is_refused(resolver: Resolver, model: WorldModel) -> None:
    plan = plan_of({"action": "pick", "target": "the cup", "location": "living room sofa"})
    error = refusal(resolver, plan, seen(model, blue_cup=BLUE_CUP_ON_THE_COFFEE_TABLE), IN_THE_DOORWAY)
    assert error.kind is ErrorKind.UNKNOWN_NAME and "unknown name 'living room sofa'" in error.message


# 5. Messages name what the words meant; names are compared as the letters they show


def test_a_relation_message_names_the_other_thing(resolver: Resolver, model: WorldModel) -> None:
    error = refusal(resolver, plan_of({"action": "pick", "target": "the cup on the counter near me"}), seen(model))
    assert "is near the operator" in error.message and "the me" not in error.message
    error = refusal(resolver, plan_of({"action": "pick", "target": "the cup", "location": "me"}), seen(model))
    assert "is at the operator" in error.message and "the me" not in error.message


def fullwidth(text: str) -> str:
    """`text` as a CJK keyboard types it: each ASCII character its fullwidth form."""
    return "".join("\u3000" if c == " " else chr(ord(c) + FULLWIDTH_OFFSET) for c in text)


def test_fullwidth_letters_are_the_letters_they_show(resolver: Resolver) -> None:
    assert normalise_name(fullwidth("THE red cup")) == "red cup"
    grounded = resolver.resolve(plan_of({"action": "navigate_to", "target": fullwidth("kitchen")}))
    step = grounded.steps[0]
    assert isinstance(step, NavigateStep) and grounded.resolutions[0].via == "name"
    assert grounded.resolutions[0].id == "kitchen" and grounded.warnings == []
