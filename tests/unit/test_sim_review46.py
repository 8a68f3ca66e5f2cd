"""sim/fault's block and clear never put a box or an object inside another object: Bullet throws out
what is put inside something solid (a cup under a room's box sank through the floor, to z = -0.06 m,
where ground truth then had it). Refused, they change nothing. And a navigation the robot plans from
where the base comes to rest is checked against the keep-out zones from there."""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest

from schemas.actions import GoalState
from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.robot import NavigateToPoseGoal, Twist
from schemas.world import FaultInjected, FaultKind, InjectFault, MoveEntity
from services.footprint import footprint
from services.robotrules import KeepOut
from services.sim.faults import block_for
from services.sim.simulation import Simulation
from services.sim.world import Drop
from services.worldmodel import load_world
from tests.fastsim import FAST_PHYSICS_HZ

WORLD = load_world("household")


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(WORLD, physics_hz=FAST_PHYSICS_HZ, visuals=False)
    yield simulation
    simulation.close()


def fault(sim: Simulation, kind: FaultKind, target: str = "") -> FaultInjected | ServiceError:
    return sim.faults.inject(InjectFault(kind=kind, target=target))


def set_down(sim: Simulation, object_id: str, x: float, y: float) -> None:
    """sim/move as the service does it (SimLoop.move): a hidden object moved is hidden no more."""
    drop = sim.scene.move(MoveEntity(id=object_id, x=x, y=y))
    assert isinstance(drop, Drop), drop
    sim.faults.moved(object_id)
    sim.run(drop, timeout=5.0)


def test_block_refuses_a_box_where_an_object_lies(sim: Simulation) -> None:
    box = block_for(sim.faults.model, sim.faults.doors, "office")
    assert not isinstance(box, ServiceError)
    set_down(sim, "red_cup", box.centre[0] + 0.2, box.centre[1])  # on the floor, under where the box goes
    cup = sim.scene.object_position("red_cup")
    reply = fault(sim, FaultKind.BLOCK, "office")
    assert isinstance(reply, ServiceError), "the box put up over the cup"
    assert reply.kind is ErrorKind.PRECONDITION and "red cup" in reply.message, reply
    sim.settle(0.5)
    assert sim.scene.blocks == {}
    after = sim.scene.object_position("red_cup")
    assert math.dist((after.x, after.y, after.z), (cup.x, cup.y, cup.z)) < 1e-3, "the cup was pushed out"
    # Moved out of the way, the box goes up.
    set_down(sim, "red_cup", box.centre[0] + 1.0, box.centre[1])
    assert isinstance(fault(sim, FaultKind.BLOCK, "office"), FaultInjected)


def test_clear_refuses_to_put_an_object_back_into_another(sim: Simulation) -> None:
    cup = sim.scene.object_position("red_cup")  # on the kitchen counter
    assert isinstance(fault(sim, FaultKind.HIDE, "red_cup"), FaultInjected)
    sim.settle(0.5)
    set_down(sim, "coffee_mug", cup.x, cup.y)  # where the cup stood
    hidden_at, mug = sim.scene.object_position("red_cup"), sim.scene.object_position("coffee_mug")
    reply = fault(sim, FaultKind.CLEAR)
    assert isinstance(reply, ServiceError), "the cup put back inside the mug"
    assert reply.kind is ErrorKind.PRECONDITION, reply
    assert "coffee mug" in reply.message and "red cup" in reply.message, reply
    assert "red_cup" in sim.faults.hidden
    assert sim.scene.object_position("red_cup") == hidden_at and sim.scene.object_position("coffee_mug") == mug
    # The mug moved elsewhere, clear puts the cup back.
    set_down(sim, "coffee_mug", cup.x, cup.y - 0.25)
    assert isinstance(fault(sim, FaultKind.CLEAR), FaultInjected)
    assert sim.faults.hidden == {}


def test_clear_refuses_to_put_two_objects_hidden_from_one_spot_back_into_each_other(sim: Simulation) -> None:
    cup = sim.scene.object_position("red_cup")
    assert isinstance(fault(sim, FaultKind.HIDE, "red_cup"), FaultInjected)
    sim.settle(0.5)
    set_down(sim, "coffee_mug", cup.x, cup.y)
    assert isinstance(fault(sim, FaultKind.HIDE, "coffee_mug"), FaultInjected)
    sim.settle(0.5)
    reply = fault(sim, FaultKind.CLEAR)
    assert isinstance(reply, ServiceError), "the cup and the mug put back into each other"
    assert reply.kind is ErrorKind.PRECONDITION, reply
    assert "coffee mug" in reply.message and "red cup" in reply.message, reply
    assert set(sim.faults.hidden) == {"red_cup", "coffee_mug"}
    # One brought back elsewhere (hidden no more), clear puts the other back.
    set_down(sim, "coffee_mug", cup.x, cup.y - 0.25)
    assert isinstance(fault(sim, FaultKind.CLEAR), FaultInjected)
    assert sim.faults.hidden == {}


def test_a_navigation_planned_from_where_the_base_comes_to_rest_is_checked_against_keep_out_zones(
    sim: Simulation,
) -> None:
    """A goal without `start` that finds the base rolling brakes, then drives from where it came to
    rest: the robot's keep-out check of the route from where it stood when the goal came is not a
    check of that route. Before: the base turned in place 12 cm on, with its corner in the stairs."""
    keep_out = KeepOut.of(WORLD)
    sim.controllers.route_check = keep_out.goal  # as the sim node wires it (with a diagnostics note)
    robot = sim.robot
    for joint, value in zip(robot.base_joints, (9.0, 8.0, 0.0), strict=True):  # the hallway, facing the stairs
        sim.scene.bullet.resetJointState(robot.id, joint, value)
    # A cmd_vel stream east, each command one the robot's keep-out check lets through.
    last = -math.inf
    while robot.base_pose().x < 10.03:
        if sim.sim_time - last >= 0.1 and keep_out.drive(robot.base_pose(), 0.6, 0.0, 0.5) is None:
            assert sim.controllers.set_cmd_vel(Twist(linear_x=0.6), 0.5)
            last = sim.sim_time
        sim.step()
        assert sim.sim_time < 10.0, "the base did not get near the stairs"
    here = robot.base_pose()
    goal = NavigateToPoseGoal(pose=Pose2D(x=here.x, y=6.5, yaw=-math.pi / 2))
    assert keep_out.goal(goal, here) is None  # what the node checked as the goal came
    motion = sim.controllers.navigate(goal)
    stairs = keep_out.zones["stairs"]
    entered = 0.0
    ended_at = math.inf
    while sim.sim_time < min(60.0, ended_at + 1.0):  # until a second after the goal ended
        sim.step()
        pose = robot.base_pose()
        entered = max(entered, footprint(pose.x, pose.y, pose.yaw, 0.6, 0.5).intersection(stairs).area)
        if not motion.running:
            ended_at = min(ended_at, sim.sim_time)
    assert entered == 0.0, f"the base entered the stairs ({entered * 1e4:.0f} cm2)"
    assert motion.state is GoalState.ABORTED and "keep-out zone 'stairs'" in motion.message, motion.message
