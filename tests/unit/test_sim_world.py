"""The simulated world without Zenoh: how it starts, ground truth, and sim/move changing it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from schemas.common import ErrorKind, ServiceError, Vec3
from schemas.world import Moved, MoveEntity
from services.sim.simulation import Simulation
from services.worldmodel import load_world
from tests.simthread import moved

WORLD = load_world("household")


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(WORLD)
    yield simulation
    simulation.close()


def test_the_world_starts_as_the_file_says(sim: Simulation) -> None:
    truth = sim.scene.ground_truth()
    assert truth.holding is None
    start = WORLD.robot.start
    assert (truth.robot.x, truth.robot.y) == pytest.approx((start.x, start.y), abs=1e-6)
    cup = next(o for o in truth.objects if o.id == "red_cup")
    assert (cup.on, cup.room) == ("kitchen_counter", "kitchen")
    assert sim.robot.arm_positions() == pytest.approx(WORLD.robot.home_joints, abs=1e-6)


def test_an_object_moved_to_the_floor_or_given_a_height_settles_there(sim: Simulation) -> None:
    on_floor = moved(sim, MoveEntity(id="blue_cup", x=7.0, y=1.5))
    assert on_floor.position.z == pytest.approx(0.05, abs=0.003)
    dropped = moved(sim, MoveEntity(id="coffee_mug", x=7.2, y=1.0, z=0.3))
    assert dropped.position.z < 0.055, "let go in the air, it falls to the floor (and may tip over)"
    truth = {o.id: o for o in sim.scene.ground_truth().objects}
    assert (truth["blue_cup"].on, truth["blue_cup"].room) == (None, "living_room")


def test_a_person_moves_at_once_and_keeps_their_heading(sim: Simulation) -> None:
    before = sim.sensors.perceived_humans(0.0).humans[0].pose
    moved = sim.scene.move(MoveEntity(id="operator", x=2.5, y=2.0))
    assert moved == Moved(id="operator", position=Vec3(x=2.5, y=2.0, z=0.0))
    person = sim.sensors.perceived_humans(1.0).humans[0]
    assert (person.pose.x, person.pose.y, person.pose.yaw, person.room) == (2.5, 2.0, before.yaw, "kitchen")
    sim.scene.move(MoveEntity(id="operator", x=2.5, y=2.0, yaw=1.0))
    assert sim.sensors.perceived_humans(2.0).humans[0].pose.yaw == 1.0


@pytest.mark.parametrize(
    ("request_", "kind", "words"),
    [
        (MoveEntity(id="unicorn", x=2.0, y=2.0), ErrorKind.INVALID_REQUEST, "no object or person 'unicorn'"),
        (MoveEntity(id="red_cup", x=-3.0, y=2.0), ErrorKind.INVALID_REQUEST, "outside every room"),
        (MoveEntity(id="red_cup", x=2.5, y=3.9, z=0.2), ErrorKind.INVALID_REQUEST, "inside the kitchen table"),
        (MoveEntity(id="operator", x=6.2, y=1.1), ErrorKind.INVALID_REQUEST, "where the robot stands"),
        (MoveEntity(id="apple", x=2.0, y=2.0), ErrorKind.PRECONDITION, "in the robot's gripper"),
    ],
)
def test_moves_that_make_no_sense_are_refused_and_change_nothing(
    sim: Simulation, request_: MoveEntity, kind: ErrorKind, words: str
) -> None:
    sim.scene.grasp("apple")
    before = sim.scene.ground_truth()
    refused = sim.scene.move(request_)
    assert isinstance(refused, ServiceError)
    assert refused.kind is kind and words in refused.message, refused
    assert sim.scene.ground_truth() == before
    if request_.id == "unicorn":
        assert {"red_cup", "operator"} <= set(refused.candidates)
