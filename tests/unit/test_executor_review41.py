"""Review 41 of the executor's carrying out of plans: a step's outcome is what it did, and what the
robot reports is checked before it is used."""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from schemas.actions import GoalState, ResultResponse
from schemas.common import Vec3
from schemas.executor import (
    ExecutePlanFeedback,
    ExecutePlanGoal,
    ExecutePlanResult,
    FailureKind,
    PlanStatus,
    StepStatus,
)
from schemas.plan import GroundedPlan, PickStep, PlaceStep, Plan, Step
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal
from services.executor.armplanning import ArmPlanner
from services.executor.config import ExecutorConfig
from services.executor.manipulation import Manipulator
from services.executor.navigation import BasePlanner
from services.executor.runner import PlanRunner
from services.runtime import decoder, encode
from services.sim.simulation import Simulation
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_PHYSICS_HZ
from tests.unit.test_manipulation import SimRobot
from tests.unit.test_runner import WORLD, ScriptedPlanServices, ScriptedRobot, planners, run


class NanJoints(ScriptedRobot):
    """Joint states whose positions are not numbers (a broken encoder, a hostile robot side)."""

    def arm_positions(self) -> list[float] | None:
        return [math.nan] * 7


def test_joint_states_that_are_not_numbers_fail_the_step_and_move_nothing() -> None:
    robot = NanJoints()
    result, _ = run(ScriptedPlanServices(), robot)
    assert result.status is PlanStatus.FAILED
    first = result.steps[0]
    assert (first.status, first.failure) == (StepStatus.FAILED, FailureKind.PRECONDITION)
    assert "joint states" in first.message and "nan" in first.message
    assert robot.goals == []  # the base never drove


class LiftBlocked(SimRobot):
    """The real sim, except that the arm's third trajectory of the plan (the pick's lift: above the
    cup, in, then up) is aborted where it starts, as the sim aborts one a joint falls behind on
    (blocked, pushed): the cup is in the closed hand, the hand still down at the cup."""

    def __init__(self, sim: Simulation) -> None:
        super().__init__(sim)
        self.trajectories = 0

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.trajectories += 1
        if self.trajectories == 3:
            return ResultResponse(goal_id="x", state=GoalState.ABORTED, message="a joint fell behind: blocked")
        return super().trajectory(goal, cancel)


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(load_world(), physics_hz=FAST_PHYSICS_HZ)
    yield simulation
    simulation.close()


def pick_red_cup(world: WorldModel, sim: Simulation) -> PickStep:
    cup, counter = world.objects["red_cup"], world.furniture["kitchen_counter"]
    return PickStep(
        object_id=cup.id,
        object_name=cup.name,
        position=sim.scene.object_position(cup.id),
        mass=cup.mass,
        support_id=counter.id,
        approach=counter.approach,
    )


def run_on(sim: Simulation, robot: SimRobot, plan: GroundedPlan) -> Any:
    world = WorldModel(sim.world)
    config = ExecutorConfig()
    runner = PlanRunner(
        ScriptedPlanServices(parse=plan.source, resolve=plan),
        robot,
        Manipulator(robot, ArmPlanner(world), BasePlanner(world), world, config),
        config,
    )
    feedback: list[ExecutePlanFeedback] = []
    return runner.run(ExecutePlanGoal(text="..."), threading.Event(), feedback.append)


def stowed(sim: Simulation) -> bool:
    home = sim.world.robot.home_joints
    return max(abs(a - h) for a, h in zip(sim.robot.arm_positions(), home, strict=True)) < 0.05


def test_a_pick_retried_after_its_lift_failed_with_the_object_in_hand_succeeds(sim: Simulation) -> None:
    """The retry found the cup in the hand and failed ("the gripper already holds red_cup"): the pick
    was reported failed with what it was to do done, and the plan failed."""
    world = WorldModel(sim.world)
    source = Plan(steps=[Step(action="pick", target="red cup")])  # type: ignore[arg-type]
    robot = LiftBlocked(sim)
    result = run_on(sim, robot, GroundedPlan(steps=[pick_red_cup(world, sim)], source=source))
    assert robot.trajectories >= 3, "the lift was never tried"
    step = result.steps[0]
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert (step.status, step.attempts) == (StepStatus.SUCCEEDED, 2), step
    assert "red cup" in step.message
    assert sim.scene.ground_truth().holding == "red_cup"
    assert stowed(sim)


class RetreatBlocked(SimRobot):
    """The real sim, except that the first arm motion after the hand let go of what it held (a
    place's retreat) is aborted where it starts: the cup stands on the table, the open hand round it."""

    def __init__(self, sim: Simulation) -> None:
        super().__init__(sim)
        self.armed = False
        self.aborted = 0

    def gripper(self, goal: GripperCommandGoal, cancel: threading.Event) -> ResultResponse[Any]:
        held = self.held_object()
        result = super().gripper(goal, cancel)
        if held is not None and goal.position > 0.0 and self.aborted == 0:
            self.armed = True
        return result

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        if self.armed:
            self.armed = False
            self.aborted += 1
            return ResultResponse(goal_id="x", state=GoalState.ABORTED, message="a joint fell behind: blocked")
        return super().trajectory(goal, cancel)


def test_a_place_retried_after_its_retreat_failed_with_the_object_on_the_surface_succeeds(sim: Simulation) -> None:
    """The retry found the hand empty and failed ("the gripper holds nothing to place"), the cup on
    the table where the step put it."""
    world = WorldModel(sim.world)
    table = world.furniture["kitchen_table"]
    spot = Vec3(x=table.center[0] - 0.1, y=table.center[1] - table.size.y / 2 + 0.15, z=table.size.z)
    place = PlaceStep(surface_id=table.id, surface_name=table.name, position=spot, approach=table.approach)
    source = Plan(
        steps=[Step(action="pick", target="red cup"), Step(action="place", location="kitchen table")]  # type: ignore[arg-type]
    )
    robot = RetreatBlocked(sim)
    result = run_on(sim, robot, GroundedPlan(steps=[pick_red_cup(world, sim), place], source=source))
    assert robot.aborted == 1, "the retreat was never tried"
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    step = result.steps[1]
    assert (step.status, step.attempts) == (StepStatus.SUCCEEDED, 2), step
    assert step.message == "placed red cup on the kitchen table"
    truth = sim.scene.ground_truth()
    cup = next(o for o in truth.objects if o.id == "red_cup")
    assert (truth.holding, cup.on) == (None, "kitchen_table")
    assert stowed(sim)


class LongWinded(ScriptedRobot):
    """Navigation aborts each time with a message as long as the robot may send (schemas.common.Text),
    each a little different, as a planner's or controller's words about what blocked it are."""

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        words = f"attempt {len(self.goals)} blocked: " + "the way is blocked by a chair " * 200
        return ResultResponse(goal_id="g", state=GoalState.ABORTED, message=words[:3900])


def test_a_result_gathering_long_reasons_still_decodes_as_the_client_reads_it() -> None:
    """Three attempts' reasons, each near the robot's limit, made a result reason of over 11000
    characters: the client's decoder (schemas.common.Text, 4000 at most) refused the result, so the
    goal's outcome never reached whoever sent it; the feedback of each retry was refused likewise."""
    robot = LongWinded()
    result, feedback = run(ScriptedPlanServices(), robot, config=ExecutorConfig())
    assert len(robot.goals) == 3
    decoded = decoder(ExecutePlanResult).decode(encode(result))
    assert decoded.status is PlanStatus.FAILED
    assert decoded.reason.startswith("step 1 (navigate_to) failed after 3 attempts (execution): ")
    assert decoded.steps[0].failure is FailureKind.EXECUTION
    for sent in feedback:
        decoder(ExecutePlanFeedback).decode(encode(sent))


class FailingBasePlanner(BasePlanner):
    """The base planner as it ends when one of its checks raised inside OMPL (omplsetup.Guard)."""

    def plan(self, *args: Any, **kwargs: Any) -> Any:
        raise RuntimeError("a check of the base planner failed inside OMPL:\nTraceback ...\nKeyError: 'x'")


def test_a_planner_that_fails_inside_fails_the_step_with_results_and_nothing_more_is_tried() -> None:
    """The RuntimeError left the runner: the plan goal ended aborted with no result at all (no step
    results, no failure kind), the remaining steps never reported."""
    robot = ScriptedRobot()
    arm, _ = planners()
    config = ExecutorConfig()  # navigate_to retries twice: an internal fault is not retried
    runner = PlanRunner(
        ScriptedPlanServices(), robot, Manipulator(robot, arm, FailingBasePlanner(WORLD), WORLD, config), config
    )
    feedback: list[ExecutePlanFeedback] = []
    result = runner.run(ExecutePlanGoal(text="..."), threading.Event(), feedback.append)
    assert result.status is PlanStatus.FAILED and result.failure is FailureKind.EXECUTION
    assert [(s.status, s.attempts) for s in result.steps] == [(StepStatus.FAILED, 1), (StepStatus.SKIPPED, 1)]
    assert "a check of the base planner failed inside OMPL" in result.steps[0].message
    assert "Traceback" not in result.reason
    assert robot.goals == []
