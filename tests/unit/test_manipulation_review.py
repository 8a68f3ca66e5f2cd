"""Review of the executor's picks: the object is grasped where it is, or the pick fails saying why
before the robot moves for nothing. Against the real pybullet sim, in process."""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from schemas.actions import ResultResponse
from schemas.common import Vec3
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, FailureKind, PlanStatus
from schemas.plan import Action, GroundedPlan, PickStep, PlaceStep, Plan, Step
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal
from services.executor.armplanning import ArmPlanner, ArmScene
from services.executor.config import ExecutorConfig
from services.executor.errors import Canceled, ExecutionError, PlanningFailed, PostconditionFailed, PreconditionFailed
from services.executor.manipulation import Manipulator
from services.executor.navigation import BasePlanner
from services.executor.runner import PlanRunner
from services.sim.simulation import Simulation
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_PHYSICS_HZ
from tests.unit.test_manipulation import SimRobot
from tests.unit.test_runner import ScriptedPlanServices

WORLD = WorldModel(load_world())


@pytest.fixture(scope="module")
def planners() -> tuple[ArmPlanner, BasePlanner]:
    return ArmPlanner(WORLD), BasePlanner(WORLD)


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(load_world(), physics_hz=FAST_PHYSICS_HZ)
    yield simulation
    simulation.close()


class Recording(SimRobot):
    """The real sim, every goal recorded; after the arm's first trajectory (the hand now above the
    object it picks) `object_id` is put down `shift` metres along y from where it stood, as a person
    moving it would."""

    def __init__(self, sim: Simulation, object_id: str = "", shift: float = 0.0) -> None:
        super().__init__(sim)
        self.object_id = object_id
        self.shift = shift
        self.goals: list[Any] = []

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        return super().navigate(goal, cancel)

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        first = not any(isinstance(g, FollowJointTrajectoryGoal) for g in self.goals)
        self.goals.append(goal)
        result = super().trajectory(goal, cancel)
        if first and self.object_id:
            where = self.sim.scene.object_position(self.object_id)
            self.sim.scene.set_down(self.object_id, where.x, where.y + self.shift)
            self.sim.settle(1.0)
        return result

    def gripper(self, goal: GripperCommandGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        return super().gripper(goal, cancel)

    def closed_on(self, object_id: str) -> int:
        return sum(1 for g in self.goals if isinstance(g, GripperCommandGoal) and g.object_id == object_id)


def pick_step(world: WorldModel, sim: Simulation, object_id: str) -> PickStep:
    obj = world.objects[object_id]
    support = world.furniture[obj.support]
    return PickStep(
        object_id=obj.id,
        object_name=obj.name,
        position=sim.scene.object_position(obj.id),
        mass=obj.mass,
        support_id=support.id,
        approach=support.approach,
    )


def test_a_cup_moved_while_the_hand_came_above_it_is_not_reached_for_where_it_was(
    sim: Simulation, planners: tuple[ArmPlanner, BasePlanner]
) -> None:
    """The hand went down where the cup had stood and the fingers closed on nothing beside it (a
    grasp_failed incident), or came down on its rim."""
    robot = Recording(sim, "red_cup", 0.05)
    world = WorldModel(sim.world)
    manipulator = Manipulator(robot, *planners, world, ExecutorConfig())
    with pytest.raises(
        ExecutionError, match="red cup moved while the arm moved above it: seen 5 cm short of where"
    ) as err:
        manipulator.pick(pick_step(world, sim, "red_cup"), threading.Event())
    assert err.value.kind is FailureKind.EXECUTION  # retried: the retry sees it where it is now
    assert robot.closed_on("red_cup") == 0


def test_a_pick_of_a_cup_moved_meanwhile_is_retried_from_where_it_is_seen_and_grasps_it(
    sim: Simulation, planners: tuple[ArmPlanner, BasePlanner]
) -> None:
    robot = Recording(sim, "red_cup", 0.05)
    world = WorldModel(sim.world)
    config = ExecutorConfig()
    source = Plan(steps=[Step(action=Action.PICK, target="red cup")])
    plan = GroundedPlan(source=source, steps=[pick_step(world, sim, "red_cup")])
    runner = PlanRunner(
        ScriptedPlanServices(parse=source, resolve=plan), robot, Manipulator(robot, *planners, world, config), config
    )
    feedback: list[ExecutePlanFeedback] = []
    result = runner.run(ExecutePlanGoal(text="pick the red cup"), threading.Event(), feedback.append)
    assert result.status is PlanStatus.SUCCEEDED, result
    assert result.steps[0].attempts == 2
    assert sim.scene.ground_truth().holding == "red_cup"
    assert robot.closed_on("red_cup") == 1  # only where it was seen after it moved


def test_an_object_too_big_for_the_gripper_fails_the_pick_before_anything_moves(
    sim: Simulation, planners: tuple[ArmPlanner, BasePlanner]
) -> None:
    """The base drove to the counter, then no grasp was found (a planning failure, tried twice more)."""
    robot = Recording(sim)
    world = WorldModel(sim.world)
    manipulator = Manipulator(robot, *planners, world, ExecutorConfig())
    with pytest.raises(PreconditionFailed, match="cast-iron pan is too big for the gripper: 26 cm across"):
        manipulator.pick(pick_step(world, sim, "cast_iron_pan"), threading.Event())
    assert robot.goals == []


class Tipping(Recording):
    """After the first arm motion once the hand has let go of `object_id` (the place's retreat), the
    object falls over where it stands: on its side, lengthwise along x."""

    def __init__(self, sim: Simulation) -> None:
        super().__init__(sim)
        self.tip: str | None = None

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        result = super().trajectory(goal, cancel)
        scene = self.sim.scene
        if self.tip is not None and scene.ground_truth().holding is None:
            obj = next(o for o in self.sim.world.objects if o.id == self.tip)
            where = scene.object_position(self.tip)
            bottom = where.z - obj.size.z / 2
            lying = scene.bullet.getQuaternionFromEuler([0.0, math.pi / 2, 0.0])
            body = scene.object_bodies[self.tip]
            scene.bullet.resetBasePositionAndOrientation(body, [where.x, where.y, bottom + obj.size.x / 2], lying)
            self.sim.settle(1.0)
            self.tip = None
        return result


def red_cup_picked(
    robot: Recording, sim: Simulation, planners: tuple[ArmPlanner, BasePlanner]
) -> tuple[Manipulator, PlaceStep]:
    """The red cup picked by `robot`, and the step that places it near the coffee table's edge."""
    world = WorldModel(sim.world)
    manipulator = Manipulator(robot, *planners, world, ExecutorConfig())
    manipulator.pick(pick_step(world, sim, "red_cup"), threading.Event())
    table = world.furniture["coffee_table"]
    spot = Vec3(x=table.center[0], y=table.center[1] - table.size.y / 2 + 0.15, z=table.size.z)
    return manipulator, PlaceStep(surface_id=table.id, surface_name=table.name, position=spot, approach=table.approach)


def test_a_placed_cup_that_fell_over_fails_the_place(sim: Simulation, planners: tuple[ArmPlanner, BasePlanner]) -> None:
    """On its side on the table, it was reported placed."""
    robot = Tipping(sim)
    manipulator, place = red_cup_picked(robot, sim, planners)
    robot.tip = "red_cup"
    with pytest.raises(
        PostconditionFailed, match=r"red cup on the coffee table but not upright: its centre [34] cm lower"
    ):
        manipulator.place(place, threading.Event())


def test_a_placed_cup_standing_upright_is_placed(sim: Simulation, planners: tuple[ArmPlanner, BasePlanner]) -> None:
    manipulator, place = red_cup_picked(Recording(sim), sim, planners)
    assert manipulator.place(place, threading.Event()) == "placed red cup on the coffee table"


class TimedOut(ArmScene):
    """The real scene, except that each free-space search of the arm fails as one blocked all the
    way does (after its full second, here at once), and meanwhile the step's time runs out."""

    cancel = threading.Event()
    searches = 0

    def plan(self, *args: Any, **kwargs: Any) -> list[Any]:
        TimedOut.searches += 1
        TimedOut.cancel.set()
        raise PlanningFailed("moving above red cup: no collision-free path found in 1 s")


class TimedOutPlanner(ArmPlanner):
    def scene(self, base: Any, objects: Any = (), held: Any = None) -> ArmScene:
        return TimedOut(self, base, tuple(objects), held)


def test_a_pick_whose_time_ran_out_while_planning_stops_planning(sim: Simulation) -> None:
    """Each of the cup's 38 grasps had its search run, a second or two each, before the step ended."""
    TimedOut.cancel, TimedOut.searches = threading.Event(), 0
    world = WorldModel(sim.world)
    robot = Recording(sim)
    manipulator = Manipulator(robot, TimedOutPlanner(world), BasePlanner(world), world, ExecutorConfig())
    step = pick_step(world, sim, "red_cup")
    manipulator.ensure_at(step.approach, threading.Event())
    with pytest.raises(Canceled, match="planning the pick of red cup canceled"):
        manipulator.pick(step, TimedOut.cancel)
    assert TimedOut.searches == 1
    assert not any(isinstance(g, FollowJointTrajectoryGoal | GripperCommandGoal) for g in robot.goals)
