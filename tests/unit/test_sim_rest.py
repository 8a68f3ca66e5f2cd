"""A sim at rest is not stepped (Simulation.step with rest=True): it rests only once everything has
stood still with nothing commanded, anything commanded or changed wakes it, and its thread then
wakes for reports and commands only (SimLoop)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from shapely.geometry import Point

from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal
from schemas.world import MoveEntity
from services.footprint import distance_to_footprint, footprint
from services.sim.loop import SimLoop
from services.sim.simulation import REST_AFTER, Simulation
from services.sim.world import Drop
from services.worldmodel import load_world
from tests.fastsim import FAST_PHYSICS_HZ

WORLD = load_world("household")
HZ = FAST_PHYSICS_HZ


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(WORLD, physics_hz=HZ, visuals=False, rest=True)
    yield simulation
    simulation.close()


def rest(sim: Simulation) -> None:
    """Step until the sim rests; it must within a few sim seconds of standing still."""
    for _ in range(round(5.0 * HZ)):
        sim.step()
        if sim.resting:
            return
    pytest.fail("the sim never came to rest")


def test_a_world_at_rest_keeps_every_pose_and_time_goes_on(sim: Simulation) -> None:
    assert not sim.resting  # not before it has stood still for REST_AFTER
    sim.step(round(REST_AFTER * HZ / 2))
    assert not sim.resting
    rest(sim)
    before, at = sim.scene.poses(0.0), sim.sim_time
    sim.step(round(20 * HZ))
    assert sim.resting
    assert sim.sim_time == pytest.approx(at + 20.0)
    assert sim.scene.poses(0.0) == before  # exactly: nothing was stepped (a stepped base creeps)


def test_a_goal_wakes_it_and_it_rests_again_once_the_goal_is_done(sim: Simulation) -> None:
    rest(sim)
    start = sim.robot.base_pose()
    goal = Pose2D(x=start.x + 0.3 * math.cos(start.yaw), y=start.y + 0.3 * math.sin(start.yaw), yaw=start.yaw)
    motion = sim.controllers.navigate(NavigateToPoseGoal(pose=goal, max_speed=0.4))
    sim.step()
    assert not sim.resting
    sim.run(motion, timeout=20.0)
    assert motion.result is not None and motion.result.pose is not None, motion.message
    here = sim.robot.base_pose()
    assert math.dist((here.x, here.y), (goal.x, goal.y)) < 0.05
    rest(sim)
    here = sim.robot.base_pose()
    sim.step(round(5 * HZ))
    assert sim.robot.base_pose() == here


def test_an_object_moved_falls_and_settles_though_nobody_woke_the_sim(sim: Simulation) -> None:
    rest(sim)
    drop = sim.scene.move(MoveEntity(id="red_cup", x=0.6, y=0.6, z=0.5))  # above the floor, nothing under it
    assert isinstance(drop, Drop), drop
    sim.run(drop, timeout=5.0)
    assert drop.result is not None
    assert drop.result.position.z < 0.1  # it fell: physics was stepped


def test_a_command_wakes_a_resting_loop_and_a_read_does_not() -> None:
    simulation = Simulation(WORLD, physics_hz=HZ, visuals=False, rest=True)
    obeyed = [0]

    def obey() -> str | None:
        obeyed[0] += 1
        return None

    loop, stop = SimLoop(simulation, 20.0, obey), threading.Event()
    thread = threading.Thread(target=loop.run, args=(stop,))
    thread.start()
    try:
        deadline = time.monotonic() + 10.0
        while not loop.ask(lambda s: s.resting, 2.0, changes=False):
            assert time.monotonic() < deadline, "the loop's sim never came to rest"
        # At rest the thread wakes for reports and commands (none here): not once a tick (2,400 a
        # second at 20x). 50 ms passes at most, and the asks below.
        counted = obeyed[0]
        time.sleep(1.0)
        assert obeyed[0] - counted < 100, obeyed[0] - counted
        assert loop.ask(lambda s: s.resting, 2.0, changes=False) is True
        assert loop.ask(lambda s: s.resting, 2.0) is False  # woken before it ran
    finally:
        stop.set()
        thread.join(10.0)
        simulation.close()


def test_the_distance_to_the_footprint_is_shapelys() -> None:
    # The sim's contact check and safety's separation from people both measure with it.
    rng = np.random.default_rng(7)
    for _ in range(500):
        x, y, yaw = rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-math.pi, math.pi)
        length, width = rng.uniform(0.2, 1.0), rng.uniform(0.2, 1.0)
        point = (x + rng.uniform(-1.5, 1.5), y + rng.uniform(-1.5, 1.5))
        expected = footprint(x, y, yaw, length, width).distance(Point(point))
        assert distance_to_footprint(x, y, yaw, length, width, point) == pytest.approx(expected, abs=1e-9)
