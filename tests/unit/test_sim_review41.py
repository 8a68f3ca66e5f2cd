"""The sim against hostile or ill-timed input: a gripper goal while paused, sim/move's height, the
camera's process killed for hanging."""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Iterator

import numpy as np
import pytest

from schemas.common import ErrorKind, ServiceError
from schemas.robot import GripperCommandGoal
from schemas.world import FaultInjected, FaultKind, InjectFault, Moved, MoveEntity, World
from services.executor.kinematics import ArmKinematics
from services.sim import renderer as renderer_module
from services.sim.config import CameraConfig
from services.sim.loop import SimLoop
from services.sim.renderer import Renderer
from services.sim.simulation import Simulation
from services.sim.world import Drop
from tests.procs import wait_until
from tests.simthread import sim_thread
from tests.unit.test_sim import PREGRASP_HEIGHT, above, approach, drive, gripper, reach
from tests.unit.test_sim import sim as sim  # the fixtures, shared
from tests.unit.test_sim import world as world


def cup_from_hand(sim: Simulation) -> float:
    cup = sim.scene.object_position("red_cup")
    return float(np.linalg.norm(np.array(sim.scene.hand_position()) - np.array([cup.x, cup.y, cup.z])))


def test_an_open_goal_while_paused_keeps_hold_of_the_object_until_the_robot_may_move(
    sim: Simulation, world: World
) -> None:
    drive(sim, approach(world, "kitchen_counter"))
    kin = ArmKinematics()
    cup = sim.scene.object_position("red_cup")
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    reach(sim, kin, cup)
    assert gripper(sim, 0.0).holding == "red_cup"
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    held = cup_from_hand(sim)
    # A person too close: the gripper's goal waits with the fingers where they are, and so does the cup.
    sim.controllers.set_speed_scale(0.0)
    motion = sim.controllers.gripper(GripperCommandGoal(position=0.08))
    sim.settle(1.0)
    assert motion.running
    assert sim.scene.holding == "red_cup", "the paused gripper let go"
    assert cup_from_hand(sim) == pytest.approx(held, abs=0.01)
    # Allowed to move again, it opens and lets go.
    sim.controllers.set_speed_scale(1.0)
    sim.run(motion, timeout=5.0)
    assert motion.result is not None and motion.result.holding is None and motion.result.reached_goal


def process_state(pid: int) -> str | None:
    """The process's state letter (Z for a zombie), or None once it is gone (reaped)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return None


def test_a_camera_process_killed_for_hanging_is_reaped_not_left_a_zombie(
    sim: Simulation, world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(renderer_module, "FRAME_TIMEOUT", 1.0)
    renderer = Renderer(world, CameraConfig())
    try:
        seen: list[object] = []
        renderer.detect(sim.scene.poses(time.time()), seen.append)
        assert wait_until(lambda: bool(seen), 60.0), "the renderer never drew a frame"
        os.kill(renderer.pid, signal.SIGSTOP)  # hangs, as a child stuck in a frame would
        renderer.detect(sim.scene.poses(time.time()), seen.append)
        assert wait_until(lambda: renderer.failure is not None, 10.0), "the hanging renderer was never noticed"
        assert "killed" in (renderer.failure or "")
        assert wait_until(lambda: process_state(renderer.pid) is None, 5.0), (
            f"the killed renderer is left in state {process_state(renderer.pid)}"
        )
    finally:
        renderer.close()


@pytest.mark.parametrize("z", [-3.0, -0.01, 2.5, 1000.0])
def test_sim_move_refuses_a_height_below_the_floor_or_to_throw_from(sim: Simulation, z: float) -> None:
    # Below the floor Bullet shot the cup metres up; from 1000 m it was still falling when the reply came.
    before = sim.scene.ground_truth()
    refused = sim.scene.move(MoveEntity(id="red_cup", x=3.0, y=3.0, z=z))
    assert isinstance(refused, ServiceError), refused
    assert refused.kind is ErrorKind.INVALID_REQUEST and f"z = {z:g} m" in refused.message, refused
    assert sim.scene.ground_truth() == before


def test_sim_move_sets_an_object_down_from_up_to_two_metres(sim: Simulation) -> None:
    drop = sim.scene.move(MoveEntity(id="red_cup", x=3.0, y=3.0, z=2.0))
    assert isinstance(drop, Drop), drop
    sim.run(drop, timeout=5.0)
    assert drop.message == "red_cup at rest"
    assert sim.scene.object_position("red_cup").z < 0.1


@pytest.fixture
def loop(sim: Simulation) -> Iterator[SimLoop]:
    """The sim thread as the services run it, without Zenoh: sim/move and sim/fault answered by it."""
    with sim_thread(sim, 4.0) as looping:
        yield looping


def test_an_object_moved_out_of_hiding_is_hidden_no_more(loop: SimLoop) -> None:
    hide = InjectFault(kind=FaultKind.HIDE, target="red_cup")
    assert isinstance(loop.fault(hide), FaultInjected)
    assert isinstance(loop.fault(InjectFault(kind=FaultKind.HIDE, target="apple")), FaultInjected)
    moved = loop.move(MoveEntity(id="red_cup", x=2.5, y=3.9))  # onto the kitchen table
    assert isinstance(moved, Moved), moved
    # It can be hidden again, at a spot of its own, not on the apple's.
    again = loop.fault(hide)
    assert isinstance(again, FaultInjected), again
    assert again.position is not None and (again.position.x, again.position.y) == pytest.approx((2.5, 3.9), abs=0.05)
    hidden = loop.answer(lambda sim: (sim.scene.object_position("red_cup"), sim.scene.object_position("apple")))
    assert math.dist((hidden[0].x, hidden[0].y), (hidden[1].x, hidden[1].y)) > 0.3
    # Moved out of hiding again, `clear` leaves it where it was moved (it put it back on the counter).
    moved = loop.move(MoveEntity(id="red_cup", x=2.5, y=3.9))
    assert isinstance(moved, Moved), moved
    cleared = loop.fault(InjectFault(kind=FaultKind.CLEAR))
    assert isinstance(cleared, FaultInjected) and "red cup" not in cleared.message, cleared
    cup = loop.answer(lambda sim: sim.scene.object_position("red_cup"))
    assert (cup.x, cup.y) == pytest.approx((2.5, 3.9), abs=0.05)
