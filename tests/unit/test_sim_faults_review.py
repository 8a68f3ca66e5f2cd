"""sim/fault's block and clear never put a box or an object inside the robot: not where its base
stands, nor where its arm reaches out over the floor or a table. Refused, they change nothing."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import pytest

from schemas.common import ErrorKind, ServiceError
from schemas.world import FaultInjected, FaultKind, InjectFault, MoveEntity
from services.sim.simulation import Simulation
from services.sim.world import Drop
from services.worldmodel import load_world
from tests.fastsim import FAST_PHYSICS_HZ

WORLD = load_world("household")
# The arm reaching forward and down: the hand 0.74 m ahead of the base's centre, 0.56 m up, well
# beyond the base's front edge (0.3 m ahead).
REACHING_LOW = (0.0, 0.7, 0.0, -2.0, 0.0, 2.7, 0.785)
# Reaching forward less low: the hand 0.84 m ahead, 0.74 m up (a table top's height).
REACHING = (0.0, 0.6, 0.0, -1.6, 0.0, 2.2, 0.785)


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(WORLD, physics_hz=FAST_PHYSICS_HZ, visuals=False)
    yield simulation
    simulation.close()


def pose(sim: Simulation, x: float, y: float, arm: Sequence[float] = WORLD.robot.home_joints) -> None:
    """The base set at (x, y) facing east, its arm at `arm`, at rest."""
    bullet, robot = sim.scene.bullet, sim.robot
    for joint, value in zip(robot.base_joints, (x, y, 0.0), strict=True):
        bullet.resetJointState(robot.id, joint, value)
    for joint, value in zip(robot.arm_joints, arm, strict=True):
        bullet.resetJointState(robot.id, joint, value)


def fault(sim: Simulation, kind: FaultKind, target: str = "") -> FaultInjected | ServiceError:
    return sim.faults.inject(InjectFault(kind=kind, target=target))


def hand_ahead(sim: Simulation, arm: Sequence[float]) -> float:
    """How far ahead of the base's centre the hand is with the arm at `arm`."""
    base = sim.robot.base_pose()
    pose(sim, base.x, base.y, arm)
    ahead = sim.scene.hand_position()[0] - base.x
    pose(sim, base.x, base.y)
    return ahead


def test_block_refuses_a_box_where_the_arm_reaches_though_the_base_stands_clear(sim: Simulation) -> None:
    # The office's box: a 0.8 m square around (6.0, 7.0), 0.6 m high. The base's front edge stops
    # 5 cm short of it; the arm reaches over it, low.
    assert hand_ahead(sim, REACHING_LOW) > 0.6
    pose(sim, 5.25, 7.0, REACHING_LOW)
    reply = fault(sim, FaultKind.BLOCK, "office")
    assert isinstance(reply, ServiceError), "a box put up around the arm"
    assert reply.kind is ErrorKind.PRECONDITION and "arm" in reply.message and "office" in reply.message
    assert sim.scene.blocks == {}, "nothing put up"
    # The arm drawn in, the same base: the box goes up.
    pose(sim, 5.25, 7.0)
    assert isinstance(fault(sim, FaultKind.BLOCK, "office"), FaultInjected)


def test_block_still_refuses_a_box_where_the_base_stands(sim: Simulation) -> None:
    pose(sim, 6.0, 7.0)
    reply = fault(sim, FaultKind.BLOCK, "office")
    assert isinstance(reply, ServiceError) and "the robot stands" in reply.message
    assert sim.scene.blocks == {}


def settled(sim: Simulation, drop: Drop) -> None:
    while drop.running:
        sim.step()
        assert sim.sim_time < 10.0, "never settled"


def test_clear_refuses_to_put_an_object_back_where_the_base_now_stands(sim: Simulation) -> None:
    # The blue cup set on the living room's floor, hidden; the base then driven (set) over that spot.
    moved = sim.scene.move(MoveEntity(id="blue_cup", x=7.5, y=1.2))
    assert isinstance(moved, Drop)
    settled(sim, moved)
    assert isinstance(fault(sim, FaultKind.HIDE, "blue_cup"), FaultInjected)
    assert isinstance(fault(sim, FaultKind.SLIP), FaultInjected)
    assert isinstance(fault(sim, FaultKind.BLOCK, "office"), FaultInjected)
    hidden_at = sim.scene.object_position("blue_cup")
    pose(sim, 7.5, 1.2)
    reply = fault(sim, FaultKind.CLEAR)
    assert isinstance(reply, ServiceError), "the cup put back inside the base"
    assert reply.kind is ErrorKind.PRECONDITION
    assert "robot stands" in reply.message and "blue cup" in reply.message
    # Nothing changed: still hidden, the slip armed, the box up.
    assert "blue_cup" in sim.faults.hidden and sim.scene.object_position("blue_cup") == hidden_at
    assert sim.faults.slip is not None and set(sim.scene.blocks) == {"office"}
    # The robot moved away, clear puts everything back.
    pose(sim, 6.0, 1.2)
    cleared = fault(sim, FaultKind.CLEAR)
    assert isinstance(cleared, FaultInjected) and "blue cup" in cleared.message
    assert sim.faults.hidden == {} and sim.faults.slip is None and sim.scene.blocks == {}


def test_clear_refuses_to_put_an_object_back_where_the_arm_now_reaches(sim: Simulation) -> None:
    before = sim.scene.object_position("blue_cup")  # on the kitchen table
    assert isinstance(fault(sim, FaultKind.HIDE, "blue_cup"), FaultInjected)
    # The base beside the table, its hand where the cup stood (its outline far from the cup).
    ahead = hand_ahead(sim, REACHING)
    pose(sim, before.x - ahead, before.y, REACHING)
    hand = sim.scene.hand_position()
    assert abs(hand[2] - before.z) < 0.1
    reply = fault(sim, FaultKind.CLEAR)
    assert isinstance(reply, ServiceError), "the cup put back around the hand"
    assert "arm" in reply.message and "blue cup" in reply.message
    assert "blue_cup" in sim.faults.hidden
    pose(sim, before.x - ahead, before.y)
    assert isinstance(fault(sim, FaultKind.CLEAR), FaultInjected)
    assert sim.faults.hidden == {}
