"""Faults in the simulated world without Zenoh: doorways and blocks found from the world file, where a
slipped object lands, and the sim's Faults slipping, hiding, blocking and clearing, and its reports."""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from typing import cast

import pytest
from shapely.geometry import Point

from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.executor import ExecutePlanGoal, FailureKind, PlanStatus
from schemas.incidents import IncidentKind, IncidentReport
from schemas.plan import GroundedPlan, GroundedStep, PickStep, Plan, PlanApproved, Step
from schemas.robot import Twist
from schemas.world import FaultInjected, FaultKind, InjectFault
from services.executor.config import ExecutorConfig, StepRetries
from services.executor.errors import GraspFailed
from services.executor.manipulation import Manipulator
from services.executor.ports import Robot
from services.executor.runner import PlanRunner
from services.sim.faults import CONTACT_GAP, SLIP_DISTANCE, block_for, doorways, find_doorway, landing_spot
from services.sim.simulation import REST_AFTER, Simulation
from services.sim.world import BlockShape
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_PHYSICS_HZ

WORLD = load_world("household")
MODEL = WorldModel(WORLD)
DOORS = doorways(WORLD)
CUP_RADIUS = 0.03


def test_the_doorways_are_the_gaps_between_walls_named_by_their_rooms() -> None:
    assert {d: (door.centre, door.width) for d, door in DOORS.items()} == {
        "kitchen-living_room": ((5.0, 2.1), pytest.approx(1.0)),
        "kitchen-bedroom": ((1.1, 5.0), pytest.approx(1.0)),
        "living_room-hallway": ((9.3, 5.0), pytest.approx(1.0)),
        "bedroom-office": ((4.0, 6.3), pytest.approx(1.0)),
        "office-hallway": ((8.0, 6.9), pytest.approx(1.0)),
    }
    assert find_doorway(DOORS, "living_room-kitchen") is DOORS["kitchen-living_room"]
    assert find_doorway(DOORS, "kitchen-office") is None  # a wall, not a doorway


def test_a_block_fills_its_doorway_or_stands_where_the_room_is_driven_to() -> None:
    door = block_for(MODEL, DOORS, "living_room-kitchen")
    assert isinstance(door, BlockShape)
    assert door.id == "kitchen-living_room" and (door.centre[0], door.centre[1]) == (5.0, 2.1)
    assert door.half[0] * 2 == pytest.approx(1.0), "as wide as the doorway"
    assert "kitchen" in door.name and "living room" in door.name
    room = block_for(MODEL, DOORS, "office")
    assert isinstance(room, BlockShape)
    goal = MODEL.room_pose("office")
    assert (room.centre[0], room.centre[1]) == (goal.x, goal.y)
    unknown = block_for(MODEL, DOORS, "attic")
    assert isinstance(unknown, ServiceError) and unknown.kind is ErrorKind.INVALID_REQUEST
    assert "attic" in unknown.message
    assert {"kitchen", "hallway", "kitchen-living_room", "office-hallway"} <= set(unknown.candidates)


def test_an_object_slipping_beside_a_top_lands_on_it_within_reach() -> None:
    # Just set off from the kitchen counter's approach pose, heading for the kitchen table.
    base = Pose2D(x=2.5, y=1.35, yaw=math.pi / 2)
    spot = landing_spot(MODEL, base, CUP_RADIUS)
    assert spot is not None and spot.on == "kitchen_counter" and spot.bottom == 0.9
    counter = MODEL.footprint(MODEL.furniture["kitchen_counter"])
    assert counter.buffer(-CUP_RADIUS).covers(Point(spot.x, spot.y)), "wholly on the top"
    assert math.dist((spot.x, spot.y), (base.x, base.y)) <= WORLD.robot.reach
    # Another cup where it would land: it lands beside that one.
    taken = landing_spot(MODEL, base, CUP_RADIUS, others=[(spot.x, spot.y, CUP_RADIUS)])
    assert taken is not None and taken.on == "kitchen_counter"
    assert math.dist((taken.x, taken.y), (spot.x, spot.y)) >= 2 * CUP_RADIUS


def test_an_object_slipping_in_the_open_lands_on_free_floor_beside_the_base() -> None:
    base = Pose2D(x=2.5, y=2.2, yaw=math.pi / 2)
    behind = landing_spot(MODEL, base, CUP_RADIUS)
    assert behind is not None and behind.on is None and behind.bottom == 0.0
    assert behind.y < base.y - WORLD.robot.base_size.x / 2 and abs(behind.x - base.x) < 1e-6
    # Something behind the base: it lands on one side instead, never on a person or in a block.
    person = landing_spot(MODEL, base, CUP_RADIUS, people=[(behind.x, behind.y)])
    assert person is not None and person.y == pytest.approx(base.y, abs=1e-6)
    assert MODEL.room_of(person.x, person.y) == "kitchen"
    # With its back to the kitchen's east wall, it does not land in the wall.
    walled = landing_spot(MODEL, Pose2D(x=4.55, y=3.2, yaw=math.pi), CUP_RADIUS)
    assert walled is not None and walled.on is None and walled.x <= 4.55 + 1e-6, "not behind it, in the wall"
    assert not any(Point(walled.x, walled.y).buffer(CUP_RADIUS).intersects(o.shape) for o in MODEL.obstacles)


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(WORLD, physics_hz=FAST_PHYSICS_HZ, visuals=False)
    yield simulation
    simulation.close()


def reports(sim: Simulation) -> list[IncidentReport]:
    got: list[IncidentReport] = []
    sim.faults.report = got.append
    return got


def hold(sim: Simulation, object_id: str) -> None:
    """The object put between the open fingers and grasped, as a pick leaves it."""
    x, y, z = sim.scene.hand_position()
    body = sim.scene.object_bodies[object_id]
    sim.scene.bullet.resetBasePositionAndOrientation(body, [x, y, z - 0.1], [0, 0, 0, 1])
    assert sim.scene.grasp(object_id) is None


def inject(sim: Simulation, kind: FaultKind, target: str = "") -> FaultInjected:
    reply = sim.faults.inject(InjectFault(kind=kind, target=target))
    assert isinstance(reply, FaultInjected), reply
    return reply


def refused(sim: Simulation, kind: FaultKind, target: str = "") -> ServiceError:
    reply = sim.faults.inject(InjectFault(kind=kind, target=target))
    assert isinstance(reply, ServiceError), reply
    return reply


def test_a_slip_drops_the_carried_object_once_after_the_base_drove_on(sim: Simulation) -> None:
    got = reports(sim)
    inject(sim, FaultKind.SLIP)
    assert refused(sim, FaultKind.SLIP).kind is ErrorKind.PRECONDITION, "one slip at a time"
    hold(sim, "red_cup")
    start = sim.robot.base_pose()
    sim.controllers.set_cmd_vel(Twist(linear_x=0.3), hold_for=10.0)
    while sim.scene.holding is not None and sim.sim_time < 10.0:
        sim.step()
    assert sim.scene.holding is None, "it never slipped"
    driven = math.dist((start.x, start.y), (sim.robot.base_pose().x, sim.robot.base_pose().y))
    assert SLIP_DISTANCE <= driven < SLIP_DISTANCE + 0.05
    sim.settle(1.0)
    cup = next(o for o in sim.scene.ground_truth().objects if o.id == "red_cup")
    assert cup.on is None and cup.room == "living_room" and cup.position.z == pytest.approx(0.05, abs=0.01)
    dropped = [r for r in got if r.kind is IncidentKind.DROPPED]
    assert len(dropped) == 1 and dropped[0].objects == ["red cup"]
    assert (dropped[0].x, dropped[0].y) == pytest.approx((cup.position.x, cup.position.y), abs=0.01)
    # Once only: held again and carried on, it stays held.
    hold(sim, "red_cup")
    sim.settle(2.0)
    assert sim.scene.holding == "red_cup"
    assert not [r for r in got if r.kind is IncidentKind.COLLISION]


def test_a_slip_for_one_object_waits_for_that_one(sim: Simulation) -> None:
    assert refused(sim, FaultKind.SLIP, "unicorn").candidates
    inject(sim, FaultKind.SLIP, "apple")
    hold(sim, "red_cup")
    sim.controllers.set_cmd_vel(Twist(linear_x=0.3), hold_for=3.0)
    sim.settle(2.5)
    assert sim.scene.holding == "red_cup" and sim.faults.slip is not None


def test_hide_takes_an_object_out_of_the_house_and_clear_puts_it_back(sim: Simulation) -> None:
    before = sim.scene.object_position("blue_cup")
    hidden = inject(sim, FaultKind.HIDE, "blue_cup")
    assert hidden.position == before
    sim.settle(0.5)
    cup = next(o for o in sim.scene.ground_truth().objects if o.id == "blue_cup")
    assert cup.room is None, "outside every room"
    assert refused(sim, FaultKind.HIDE, "blue_cup").kind is ErrorKind.PRECONDITION
    unknown = refused(sim, FaultKind.HIDE, "unicorn")
    assert unknown.kind is ErrorKind.INVALID_REQUEST and "red_cup" in unknown.candidates
    hold(sim, "apple")
    assert "gripper" in refused(sim, FaultKind.HIDE, "apple").message
    cleared = inject(sim, FaultKind.CLEAR)
    assert "blue cup" in cleared.message
    sim.settle(0.5)
    back = next(o for o in sim.scene.ground_truth().objects if o.id == "blue_cup")
    assert (back.on, back.room) == ("kitchen_table", "kitchen")
    assert math.dist((back.position.x, back.position.y), (before.x, before.y)) < 0.005
    assert inject(sim, FaultKind.CLEAR).message == "no fault was in force"
    assert refused(sim, FaultKind.CLEAR, "blue_cup").kind is ErrorKind.INVALID_REQUEST


def place(sim: Simulation, x: float, y: float) -> None:
    """The base set at (x, y) facing east, at rest."""
    for joint, value in zip(sim.robot.base_joints, (x, y, 0.0), strict=True):
        sim.scene.bullet.resetJointState(sim.robot.id, joint, value)


def test_a_block_stops_the_base_and_the_touch_is_reported_once(sim: Simulation) -> None:
    got = reports(sim)
    # Not where the robot stands; not twice.
    place(sim, 4.8, 2.1)
    assert "robot stands" in refused(sim, FaultKind.BLOCK, "kitchen-living_room").message
    place(sim, 3.9, 2.1)
    blocked = inject(sim, FaultKind.BLOCK, "kitchen-living_room")
    assert blocked.position is not None and (blocked.position.x, blocked.position.y) == (5.0, 2.1)
    assert refused(sim, FaultKind.BLOCK, "kitchen-living_room").kind is ErrorKind.PRECONDITION
    assert refused(sim, FaultKind.BLOCK, "attic").candidates
    # Driving east into the doorway: the box holds the base back.
    sim.controllers.set_cmd_vel(Twist(linear_x=0.4), hold_for=4.0)
    sim.settle(4.0)
    front = sim.robot.base_pose().x + WORLD.robot.base_size.x / 2
    assert front < 4.86, f"the base's front reached x = {front:.2f}, through the box"
    collisions = [r for r in got if r.kind is IncidentKind.COLLISION]
    assert len(collisions) == 1, collisions
    assert collisions[0].objects == [blocked.message.split(" at ")[0]]
    inject(sim, FaultKind.CLEAR)
    sim.controllers.set_cmd_vel(Twist(linear_x=0.4), hold_for=4.0)
    sim.settle(4.0)
    assert sim.robot.base_pose().x > 5.3, "cleared, it drives through"


def test_a_touch_that_lasts_while_the_world_rests_is_reported_once() -> None:
    """At rest physics is not stepped and the contact checks are not run (Simulation.step): a base
    standing against a block through the rest, then pushing on, is still the touch already reported."""
    sim = Simulation(WORLD, physics_hz=FAST_PHYSICS_HZ, visuals=False, rest=True)
    try:
        got = reports(sim)
        place(sim, 3.9, 2.1)
        inject(sim, FaultKind.BLOCK, "kitchen-living_room")
        sim.controllers.set_cmd_vel(Twist(linear_x=0.4), hold_for=3.0)
        sim.settle(3.0)
        assert sim.scene.bullet.getContactPoints(bodyA=sim.robot.id), "the base does not stand against the box"
        sim.settle(REST_AFTER + 3 * CONTACT_GAP)
        assert sim.resting, "the world did not come to rest"
        sim.controllers.set_cmd_vel(Twist(linear_x=0.4), hold_for=1.0)
        sim.settle(1.0)
        assert not sim.resting
        collisions = [r for r in got if r.kind is IncidentKind.COLLISION]
        assert len(collisions) == 1, collisions
    finally:
        sim.close()


# The executor's half: a grasp that closed on nothing is its to report (the sim reports drops).


class GraspMisses:
    """A manipulator whose pick closes on nothing every time (what Manipulator.pick raises then)."""

    search_time = 0.0

    def run(self, step: GroundedStep, *_: object) -> str:
        assert isinstance(step, PickStep)
        raise GraspFailed(f"{step.object_name} was not in the gripper after closing (top grasp)", step.object_name)

    def recover(self, *_: object) -> None:
        pass


class StillRobot:
    """All the runner asks of the robot around a step: nothing holds it still, full speed."""

    def safety_stop(self) -> str | None:
        return None

    def speed_scale(self) -> float:
        return 1.0


def test_the_executor_reports_each_grasp_that_closed_on_nothing() -> None:
    cup = next(o for o in WORLD.objects if o.id == "red_cup")
    counter = MODEL.furniture["kitchen_counter"]
    pick = PickStep(
        object_id=cup.id,
        object_name=cup.name,
        position=MODEL.initial_position(cup),
        mass=cup.mass,
        support_id=counter.id,
        approach=counter.approach,
    )
    plan = Plan(steps=[Step(action="pick", target="red cup")])  # type: ignore[arg-type]
    grounded = GroundedPlan(steps=[pick], source=plan, labels=["grab"])

    class Planner:
        def parse(self, text: str, fmt: str) -> Plan:
            return plan

        def resolve(self, _: Plan) -> GroundedPlan:
            return grounded

        def check(self, _: GroundedPlan) -> PlanApproved:
            return PlanApproved()

    reported: list[tuple[IncidentKind, str, list[str], int, str]] = []
    config = ExecutorConfig(retries=StepRetries(pick=1))
    runner = PlanRunner(
        Planner(),
        cast(Robot, StillRobot()),
        cast(Manipulator, GraspMisses()),
        config,
        lambda *report: reported.append(report),
    )
    result = runner.run(ExecutePlanGoal(text="..."), threading.Event(), lambda _: None)
    assert result.status is PlanStatus.FAILED and result.failure is FailureKind.POSTCONDITION
    assert [(k, objects, step, label) for k, _, objects, step, label in reported] == [
        (IncidentKind.GRASP_FAILED, ["red cup"], 0, "grab")
    ] * 2, "once per attempt"
    assert "not in the gripper" in reported[0][1]
