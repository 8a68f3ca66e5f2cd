"""sim/move against hostile or ill-timed requests: nothing is put inside the robot (its base, its arm
reaching out, what it holds), a wall, furniture, a fault's box or another object; an object moved
again while it falls, or a move given up on, leaves no caller told something untrue. Refused, the
world is as it was."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import pytest

from schemas.common import ErrorKind, ServiceError, Vec3
from schemas.world import FaultInjected, FaultKind, InjectFault, Moved, MoveEntity
from services.errors import CallError
from services.sim import loop as loop_module
from services.sim.loop import SimLoop
from services.sim.simulation import Simulation
from services.sim.world import Drop
from services.worldmodel import load_world
from tests.fastsim import FAST_PHYSICS_HZ
from tests.procs import wait_until
from tests.simthread import moved, sim_thread

WORLD = load_world("household")
# The arm reaching forward and down: the hand 0.74 m ahead of the base's centre, 0.56 m up, well
# beyond the base's front edge (0.3 m ahead).
REACHING_LOW = (0.0, 0.7, 0.0, -2.0, 0.0, 2.7, 0.785)
START = (WORLD.robot.start.x, WORLD.robot.start.y)  # facing east


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(WORLD, physics_hz=FAST_PHYSICS_HZ, visuals=False)
    yield simulation
    simulation.close()


@pytest.fixture
def loop(sim: Simulation) -> Iterator[SimLoop]:
    """The sim thread as the services run it (real time), without Zenoh."""
    with sim_thread(sim, 1.0) as looping:
        yield looping


def pose_arm(sim: Simulation, arm: Sequence[float]) -> None:
    """The arm set at `arm` and held there by its motors."""
    robot = sim.robot
    for joint, value in zip(robot.arm_joints, arm, strict=True):
        sim.scene.bullet.resetJointState(robot.id, joint, value)
    robot.drive_arm(np.array(arm), np.zeros(len(arm)))


def refused(sim: Simulation, request: MoveEntity, kind: ErrorKind, *words: str) -> None:
    """`request` refused with `kind`, its message saying `words`, and nothing changed."""
    before = (sim.scene.ground_truth(), dict(sim.scene.human_poses))
    reply = sim.scene.move(request)
    assert isinstance(reply, ServiceError), f"{request} was done: {reply}"
    assert reply.kind is kind and all(w in reply.message for w in words), reply
    assert (sim.scene.ground_truth(), dict(sim.scene.human_poses)) == before
    assert not sim.scene.settling


def test_an_object_is_not_put_among_the_fingers_of_the_arm_reaching_out(sim: Simulation) -> None:
    # Before: accepted, the cup was thrown out of the fingers and landed 9 cm off, on its side.
    pose_arm(sim, REACHING_LOW)
    sim.step()
    x, y, z = sim.scene.hand_position()
    assert x - START[0] > 0.6, "the hand is not beyond the base's front edge"
    refused(sim, MoveEntity(id="red_cup", x=x, y=y, z=z - 0.12), ErrorKind.INVALID_REQUEST, "arm", "red cup")


def test_an_object_is_not_put_into_the_object_the_gripper_holds(sim: Simulation) -> None:
    # Before: accepted, and the cup was shot 23 cm away from the apple.
    assert sim.scene.grasp("apple") is None
    apple = sim.scene.object_position("apple")
    refused(
        sim,
        MoveEntity(id="red_cup", x=apple.x + 0.03, y=apple.y),
        ErrorKind.INVALID_REQUEST,
        "apple in the robot's gripper",
    )


def test_an_object_is_not_put_across_the_base_edge(sim: Simulation) -> None:
    # Its centre 2 cm beyond the base's front edge, its side 1 cm inside it: only the centre was asked.
    refused(sim, MoveEntity(id="red_cup", x=START[0] + 0.32, y=START[1]), ErrorKind.INVALID_REQUEST, "robot stands")


@pytest.mark.parametrize(
    ("request_", "words"),
    [
        # Centre in the kitchen, its side in the outer wall (10 cm thick on x = 0): pushed out.
        (MoveEntity(id="red_cup", x=0.02, y=2.0), "outer wall"),
        # The book half in that wall came to rest below the floor.
        (MoveEntity(id="blue_book", x=0.04, y=2.0, yaw=0.0), "outer wall"),
        # Onto the blue cup's spot on the kitchen table: both shoved apart.
        (MoveEntity(id="red_cup", x=2.2, y=3.65), "blue cup"),
        # On the floor, its centre 1 cm off the kitchen table's west edge (x = 1.8): under its top.
        (MoveEntity(id="red_cup", x=1.79, y=3.9), "kitchen table"),
    ],
)
def test_an_object_is_not_put_into_a_wall_furniture_or_another_object(
    sim: Simulation, request_: MoveEntity, words: str
) -> None:
    refused(sim, request_, ErrorKind.INVALID_REQUEST, words)


def test_an_object_is_not_put_inside_a_faults_box(sim: Simulation) -> None:
    blocked = sim.faults.inject(InjectFault(kind=FaultKind.BLOCK, target="office"))
    assert isinstance(blocked, FaultInjected) and blocked.position is not None
    box = blocked.position
    refused(sim, MoveEntity(id="apple", x=box.x, y=box.y), ErrorKind.INVALID_REQUEST, "a box")


def test_objects_set_down_close_to_things_but_clear_of_them_still_move(sim: Simulation) -> None:
    # 2 cm from the outer wall's face; 1 cm beside the apple on the kitchen table; on the book's top.
    near_wall = moved(sim, MoveEntity(id="red_cup", x=0.05 + 0.03 + 0.02, y=2.0))
    assert (near_wall.position.x, near_wall.position.y) == pytest.approx((0.1, 2.0), abs=0.005)
    apple = sim.scene.object_position("apple")
    beside = apple.x + 0.0375 + 0.03 + 0.01
    assert moved(sim, MoveEntity(id="coffee_mug", x=beside, y=apple.y)).position.x == pytest.approx(beside, abs=0.005)
    book = sim.scene.object_position("blue_book")
    on_book = moved(sim, MoveEntity(id="blue_cup", x=book.x, y=book.y, z=book.z + 0.015))
    assert on_book.position.z == pytest.approx(book.z + 0.015 + 0.05, abs=0.005)


def test_a_person_is_not_put_over_the_base_nor_into_the_arm(sim: Simulation) -> None:
    # Their centre 0.15 m ahead of the base's front edge: their body (0.2 m around it) over the base,
    # reported as the robot running into them. Only the centre was asked.
    refused(sim, MoveEntity(id="operator", x=START[0] + 0.45, y=START[1]), ErrorKind.INVALID_REQUEST, "robot stands")
    # Where the arm reaches out, 0.44 m beyond the base's edge.
    pose_arm(sim, REACHING_LOW)
    sim.step()
    x, y, _ = sim.scene.hand_position()
    refused(sim, MoveEntity(id="operator", x=x, y=y), ErrorKind.INVALID_REQUEST, "arm", "operator")
    # Close behind the base (8 cm from its back edge), where safety's person-near stop is for.
    behind = START[0] - 0.3 - 0.2 - 0.08
    moved = sim.scene.move(MoveEntity(id="operator", x=behind, y=START[1]))
    assert moved == Moved(id="operator", position=Vec3(x=behind, y=START[1], z=0.0))


@pytest.mark.parametrize(
    ("request_", "words"),
    [
        # Their centre 10 cm from the outer wall's face (x = 0.05): their body (0.2 m around it) in the wall.
        (MoveEntity(id="operator", x=0.15, y=2.0), "outer wall"),
        # Beside the kitchen table, 5 cm from its west edge (x = 1.8): half inside its top.
        (MoveEntity(id="operator", x=1.75, y=3.9), "kitchen table"),
    ],
)
def test_a_person_is_not_put_into_a_wall_or_furniture(sim: Simulation, request_: MoveEntity, words: str) -> None:
    # Before: done; people have no collision body, so the operator stood in the wall or the table.
    refused(sim, request_, ErrorKind.INVALID_REQUEST, "operator", "would stand in", words)


def test_an_object_is_not_set_down_where_a_person_stands(sim: Simulation) -> None:
    # Before: done, the cup dropped at the operator's feet, inside their body.
    operator = sim.scene.human_poses["operator"]
    at_their_feet = MoveEntity(id="red_cup", x=operator.x + 0.1, y=operator.y)
    refused(sim, at_their_feet, ErrorKind.INVALID_REQUEST, "red cup", "operator")
    # Nor let go over their head (z 1.75 m, they are 1.7 m tall): it fell through them and came to rest inside.
    over_their_head = MoveEntity(id="apple", x=operator.x, y=operator.y, z=1.75)
    refused(sim, over_their_head, ErrorKind.INVALID_REQUEST, "apple", "operator")
    # Nor a person moved onto it where it stands on the floor.
    cup = moved(sim, MoveEntity(id="red_cup", x=8.5, y=1.5)).position
    refused(sim, MoveEntity(id="operator", x=cup.x + 0.15, y=cup.y), ErrorKind.INVALID_REQUEST, "red cup")


def test_a_faults_box_is_not_put_up_where_a_person_stands(sim: Simulation) -> None:
    # Before: put up, standing inside the operator (people have no collision body to push it off).
    blocked = sim.faults.inject(InjectFault(kind=FaultKind.BLOCK, target="office"))
    assert isinstance(blocked, FaultInjected) and blocked.position is not None
    box = blocked.position
    assert isinstance(sim.faults.inject(InjectFault(kind=FaultKind.CLEAR)), FaultInjected)
    assert sim.scene.move(MoveEntity(id="operator", x=box.x, y=box.y)) == Moved(
        id="operator", position=Vec3(x=box.x, y=box.y, z=0.0)
    )
    refusal = sim.faults.inject(InjectFault(kind=FaultKind.BLOCK, target="office"))
    assert isinstance(refusal, ServiceError) and refusal.kind is ErrorKind.PRECONDITION, refusal
    assert "operator stands where a box" in refusal.message, refusal
    assert not sim.scene.blocks


def test_a_person_and_an_object_close_to_things_but_clear_of_them_still_move(sim: Simulation) -> None:
    # 2 cm from the outer wall's face; a cup set down 2 cm beside the operator's body.
    near_wall = 0.05 + 0.2 + 0.02
    assert sim.scene.move(MoveEntity(id="operator", x=near_wall, y=2.0)) == Moved(
        id="operator", position=Vec3(x=near_wall, y=2.0, z=0.0)
    )
    beside = near_wall + 0.2 + 0.03 + 0.02
    assert moved(sim, MoveEntity(id="red_cup", x=beside, y=2.0)).position.x == pytest.approx(beside, abs=0.005)


@pytest.mark.parametrize("entity", ["kitchen_table", "wall_south", "robot", "charging_dock", "kitchen"])
def test_what_is_neither_an_object_nor_a_person_is_not_moved(sim: Simulation, entity: str) -> None:
    # Not a defect before: refused as unknown, the movable ones listed.
    refused(sim, MoveEntity(id=entity, x=7.0, y=1.5), ErrorKind.INVALID_REQUEST, f"no object or person {entity!r}")


def test_an_object_moved_again_while_it_falls_ends_the_earlier_move(sim: Simulation) -> None:
    first = sim.scene.move(MoveEntity(id="red_cup", x=7.0, y=1.5, z=2.0))
    assert isinstance(first, Drop)
    sim.step(2)
    assert first.running
    second = moved(sim, MoveEntity(id="red_cup", x=8.0, y=1.0))
    # Before: both said the cup had come to rest at (8, 1), the first as if it had fallen there.
    assert not first.running and first.message and "moved again" in first.message
    assert (second.position.x, second.position.y) == pytest.approx((8.0, 1.0), abs=0.01)


def test_the_earlier_caller_of_an_object_moved_again_while_it_falls_is_told_so(loop: SimLoop) -> None:
    replies: list[Moved | ServiceError | CallError] = []

    def first() -> None:
        try:
            replies.append(loop.move(MoveEntity(id="red_cup", x=7.0, y=1.5, z=2.0)))
        except CallError as error:
            replies.append(error)

    thread = threading.Thread(target=first)
    thread.start()
    try:
        # Falling 2 m takes 0.64 s at real time: the second move comes while it falls.
        assert wait_until(lambda: bool(loop.answer(lambda sim: sim.scene.settling, changes=False)), 5.0)
        second = loop.move(MoveEntity(id="red_cup", x=8.0, y=1.0))
    finally:
        thread.join(10.0)
    assert isinstance(second, Moved) and (second.position.x, second.position.y) == pytest.approx((8.0, 1.0), abs=0.01)
    assert len(replies) == 1 and isinstance(replies[0], CallError), f"the first caller was told {replies}"
    error = replies[0].error
    assert error.kind is ErrorKind.CANCELED and "moved again" in error.message


GIVEN_UP = {
    "move": lambda loop: loop.move(MoveEntity(id="red_cup", x=7.0, y=1.5)),
    "fault": lambda loop: loop.fault(InjectFault(kind=FaultKind.HIDE, target="red_cup")),
}


@pytest.mark.parametrize("change", GIVEN_UP.values(), ids=GIVEN_UP.keys())
def test_a_change_given_up_on_is_not_done_later(
    loop: SimLoop, monkeypatch: pytest.MonkeyPatch, change: Callable[[SimLoop], object]
) -> None:
    """sim/move and sim/fault: the caller heard "unavailable" (the sim thread held up past its wait),
    and the cup was moved or hidden once the thread got to it, behind their back."""
    monkeypatch.setattr(loop_module, "ANSWER_TIMEOUT", 0.2)
    before = loop.answer(lambda sim: sim.scene.object_position("red_cup"), changes=False)
    busy = threading.Event()
    release = threading.Event()

    def hold(_sim: Simulation) -> None:
        busy.set()
        release.wait(10.0)

    assert loop.submit(hold)
    assert busy.wait(5.0)
    try:
        with pytest.raises(CallError) as raised:
            change(loop)
        assert raised.value.error.kind is ErrorKind.UNAVAILABLE
    finally:
        release.set()
    after, settling = loop.answer(lambda sim: (sim.scene.object_position("red_cup"), sim.scene.settling), changes=False)
    # Where it was, to within the millimetre a cup at rest may still creep in the physics (0.1 mm seen
    # once in CI); done, the change would have put it 4.8 m away, or outside the house.
    assert (after.x, after.y, after.z) == pytest.approx((before.x, before.y, before.z), abs=0.001)
    assert not settling
