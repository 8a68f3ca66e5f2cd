"""A navigation is done when odometry has the base at its goal, not when the robot says it succeeded."""

from __future__ import annotations

import math
import threading

import pytest

from schemas.actions import GoalState
from schemas.common import Pose2D, fmt_pose
from schemas.executor import FailureKind, PlanStatus, StepStatus
from schemas.plan import SayStep
from services.executor.config import ExecutorConfig, StepRetries
from services.executor.errors import PostconditionFailed
from services.executor.manipulation import Manipulator
from tests.unit.test_runner import (
    KITCHEN,
    WORLD,
    ScriptedPlanServices,
    ScriptedRobot,
    Stop,
    at_goal,
    go,
    grounded,
    planners,
    run,
    short_of,
)

PLAN = grounded([go(KITCHEN, "kitchen"), SayStep(text="there")])


def retrying(navigate_to: int) -> ExecutorConfig:
    return ExecutorConfig(retries=StepRetries(navigate_to=navigate_to))


def lies_first(times: int, stop: Stop) -> Stop:
    """A robot that stops as `stop` says the first `times` navigations, then arrives."""
    ended = 0

    def stops(start: Pose2D, goal: Pose2D) -> Pose2D:
        nonlocal ended
        ended += 1
        return stop(start, goal) if ended <= times else goal

    return stops


def facing(yaw: float) -> Stop:
    return lambda start, goal: Pose2D(x=goal.x, y=goal.y, yaw=goal.yaw + yaw)


def test_a_robot_that_says_it_arrived_short_of_the_goal_fails_the_step_naming_where_the_base_is() -> None:
    robot = ScriptedRobot(stops=short_of(0.6))
    result, _ = run(ScriptedPlanServices(resolve=PLAN), robot)
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.POSTCONDITION), result.reason
    assert [s.status for s in result.steps] == [StepStatus.FAILED, StepStatus.SKIPPED]
    message = result.steps[0].message
    assert fmt_pose(robot.pose) in message and fmt_pose(KITCHEN) in message
    assert "0.60 m" in message, message
    assert "reached" not in message


def test_a_base_facing_the_wrong_way_has_not_arrived() -> None:
    robot = ScriptedRobot(stops=facing(math.radians(40)))
    result, _ = run(ScriptedPlanServices(resolve=PLAN), robot)
    assert result.failure is FailureKind.POSTCONDITION, result.reason
    assert "40°" in result.steps[0].message and fmt_pose(KITCHEN) in result.steps[0].message


def test_a_missed_arrival_is_retried_and_a_retry_that_arrives_succeeds() -> None:
    robot = ScriptedRobot(stops=lies_first(1, short_of(0.6)))
    result, feedback = run(ScriptedPlanServices(resolve=PLAN), robot, config=retrying(2))
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert (result.steps[0].attempts, result.steps[0].message) == (2, "reached kitchen")
    assert robot.pose == KITCHEN
    retry = next(f for f in feedback if f.attempt == 2 and f.failure is not None)
    assert retry.failure is FailureKind.POSTCONDITION and "attempt 1 failed (postcondition)" in retry.message
    assert [g.pose for g in robot.goals] == [KITCHEN, KITCHEN], "the retry drove there again"


def test_a_robot_that_always_stops_short_fails_after_every_retry() -> None:
    robot = ScriptedRobot(stops=short_of(0.6))
    result, _ = run(ScriptedPlanServices(resolve=PLAN), robot, config=retrying(2))
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.POSTCONDITION)
    assert (result.steps[0].attempts, len(robot.goals)) == (3, 3)
    assert result.reason.startswith("step 1 (navigate_to) failed after 3 attempts (postcondition): ")


def test_no_odometry_after_the_navigation_is_a_failure_not_an_arrival() -> None:
    robot = ScriptedRobot(odometry_after=False)
    result, _ = run(ScriptedPlanServices(resolve=PLAN), robot)
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.POSTCONDITION), result.reason
    assert "no odometry" in result.steps[0].message and fmt_pose(KITCHEN) in result.steps[0].message


@pytest.mark.parametrize("stops", [at_goal, short_of(0.05), facing(0.05)], ids=["exact", "5 cm short", "0.05 rad"])
def test_an_honest_robot_arrives_within_the_robot_contracts_tolerance(stops: Stop) -> None:
    """docs/robot.md: a navigation succeeds within 5 cm and 0.05 rad of its goal pose."""
    robot = ScriptedRobot(stops=stops)
    result, _ = run(ScriptedPlanServices(resolve=PLAN), robot)
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert result.steps[0].message == "reached kitchen"


def test_the_base_moves_of_other_steps_check_arrival_too() -> None:
    """A pick or place drives to its approach pose through the same drive: a robot stopped short
    there fails it before the arm plans from the wrong place."""
    robot = ScriptedRobot(stops=short_of(0.5))
    arm, base = planners()
    manipulator = Manipulator(robot, arm, base, WORLD, ExecutorConfig())
    approach = WORLD.furniture["kitchen_table"].approach
    with pytest.raises(PostconditionFailed, match=r"0\.50 m"):
        manipulator.ensure_at(approach, threading.Event())
    assert [g.pose for g in robot.goals] == [approach]


def test_a_navigation_that_does_not_succeed_is_not_checked_against_odometry() -> None:
    robot = ScriptedRobot(state=GoalState.ABORTED, odometry_after=False)
    result, _ = run(ScriptedPlanServices(resolve=PLAN), robot)
    assert result.failure is FailureKind.EXECUTION and "stalled" in result.reason
