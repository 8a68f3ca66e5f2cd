"""The plan check's on_failure alternatives for a pick (a review): a pick that grasped its object and
then failed (its lift or stow) leaves it in the hand, so an alternative covering the pick starts from
there too, and one that opens the gripper is refused before anything moves."""

from __future__ import annotations

import pytest

from schemas.common import Pose2D, Vec3
from schemas.plan import (
    Fallback,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    SayStep,
    Step,
)
from schemas.safety import Rule
from services.robotmodel import ArmModel
from services.safety.errors import Vetoed
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world

SOURCE = Plan(steps=[Step(action="stop")])  # type: ignore[arg-type]
COUNTER = Pose2D(x=2.5, y=1.05, yaw=-1.57)
COUNTER_SIDE = Pose2D(x=2.5, y=2.0)
CLEAR = Pose2D(x=9.0, y=6.0)
CUP = PickStep(
    object_id="red_cup",
    object_name="red cup",
    position=Vec3(x=2.2, y=0.55, z=0.95),
    mass=0.25,
    support_id="kitchen_counter",
    approach=COUNTER,
)
PUT_BACK = PlaceStep(
    surface_id="kitchen_counter", surface_name="kitchen counter", position=CUP.position, approach=COUNTER
)
OPEN = GripperStep(open=True)


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    world = load_world()
    arm = ArmModel(world.robot.arm_urdf)
    return SafetyPolicy(WorldModel(world), load_policy(None, world.robot, arm, world.keep_out), arm)


def plan_of(steps: list[GroundedStep], labels: list[str], *fallbacks: Fallback) -> GroundedPlan:
    return GroundedPlan(steps=steps, source=SOURCE, labels=labels, fallbacks=list(fallbacks))


def refused(policy: SafetyPolicy, plan: GroundedPlan) -> str:
    with pytest.raises(Vetoed) as info:
        policy.check_plan(plan, COUNTER_SIDE)
    assert info.value.rule is Rule.GRIPPER_DROP
    return str(info.value)


def test_opening_the_gripper_after_a_failed_pick_is_refused_naming_the_step_and_the_object(
    policy: SafetyPolicy,
) -> None:
    # `pick red cup` with `on_failure: open_gripper`: approved before as "the gripper opens with nothing in it".
    plan = plan_of([CUP], ["1"], Fallback(first=0, last=0, steps=[OPEN], labels=["1 on_failure 1"]))
    assert refused(policy, plan) == (
        "step 1 on_failure 1 (gripper): opening the gripper would drop red cup from the stowed arm "
        "(held if the pick at step 1 grasped it and then failed); use place to put it down"
    )


def test_a_range_ending_with_a_pick_is_followed_into_the_hand_holding_it(policy: SafetyPolicy) -> None:
    # A group (go to the counter, pick the cup) whose on_failure drives off and then opens the hand.
    steps: list[GroundedStep] = [NavigateStep(target="counter", goal=COUNTER), CUP]
    away = Fallback(
        first=0,
        last=1,
        steps=[NavigateStep(target="hallway", goal=CLEAR), OPEN],
        labels=["1 on_failure 1", "1 on_failure 2"],
    )
    message = refused(policy, plan_of(steps, ["1.1", "1.2"], away))
    assert message.startswith("step 1 on_failure 2 (gripper): opening the gripper would drop red cup")
    assert "the pick at step 1.2 grasped it" in message


def test_an_enclosing_alternative_starts_where_a_pick_inside_an_inner_one_failed(policy: SafetyPolicy) -> None:
    # If saying it fails, the inner alternative picks the cup; if that pick fails after grasping,
    # the enclosing alternative opens the hand holding it.
    inner = Fallback(first=1, last=1, steps=[CUP], labels=["1.2 on_failure 1"])
    outer = Fallback(first=0, last=1, steps=[OPEN], labels=["1 on_failure 1"])
    steps: list[GroundedStep] = [SayStep(text="hi"), SayStep(text="now the cup")]
    message = refused(policy, plan_of(steps, ["1.1", "1.2"], inner, outer))
    assert message.startswith("step 1 on_failure 1 (gripper): opening the gripper would drop red cup")
    assert "the pick at step 1.2 on_failure 1 grasped it" in message


@pytest.mark.parametrize(
    "alternative",
    [
        [PUT_BACK],
        [NavigateStep(target="hallway", goal=CLEAR)],
        [SayStep(text="I could not pick it up")],
        [CUP],
        [PUT_BACK, OPEN],
    ],
    ids=["place", "navigate", "say", "pick again", "place then open"],
)
def test_an_alternative_fine_in_every_state_a_failed_pick_leaves_is_approved(
    policy: SafetyPolicy, alternative: list[GroundedStep]
) -> None:
    labels = [f"1 on_failure {n + 1}" for n in range(len(alternative))]
    plan = plan_of([CUP, PUT_BACK], ["1", "2"], Fallback(first=0, last=0, steps=alternative, labels=labels))
    assert policy.check_plan(plan, COUNTER_SIDE)


def test_opening_the_gripper_is_approved_where_the_hand_is_empty_in_every_way(policy: SafetyPolicy) -> None:
    # Covering the steps before the pick or after the place, the hand is empty however they fail.
    steps: list[GroundedStep] = [NavigateStep(target="counter", goal=COUNTER_SIDE), CUP, PUT_BACK, SayStep(text="done")]
    for first, last in ((0, 0), (3, 3)):
        plan = plan_of(steps, ["1", "2", "3", "4"], Fallback(first=first, last=last, steps=[OPEN]))
        assert f"step {last + 1} on_failure 1: the gripper opens with nothing in it" in policy.check_plan(
            plan, COUNTER_SIDE
        )
