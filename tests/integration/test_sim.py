"""The sim as a real process over Zenoh: sim/move changes the world, ground truth and the camera follow."""

from __future__ import annotations

import itertools
import math
import os
import signal
import statistics
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.world import CameraImage, Empty, Moved, MoveEntity
from services.sim.config import CameraConfig, SimConfig
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli
from tests.procs import children, gone, wait_until
from tests.watch import Watch

# On the coffee table, which the camera sees from the robot's start pose.
IN_VIEW = (7.8, 2.4)


@pytest.fixture
def sim_stack(tmp_path: Path) -> Iterator[Stack]:
    stack = start_stack(tmp_path, realtime_factor=4.0, services=("sim",))
    try:
        yield stack
    finally:
        stop_stack(stack)


def test_a_moved_object_shows_in_ground_truth_and_then_in_perception(sim_stack: Stack) -> None:
    node = sim_stack.node
    objects = Watch(node, keys.OBJECTS)
    assert objects.wait_for(lambda m: True, timeout=10.0), "no perception from the sim"
    assert not any(o.id == "red_cup" for o in objects.messages[-1].objects), "the kitchen is out of view"

    moved = node.call(keys.SIM_MOVE, MoveEntity(id="red_cup", x=IN_VIEW[0], y=IN_VIEW[1]), timeout=10.0)
    assert isinstance(moved, Moved), moved
    truth = node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)
    cup = next(o for o in truth.objects if o.id == "red_cup")
    assert (cup.on, cup.room) == ("coffee_table", "living_room")
    assert math.dist((cup.position.x, cup.position.y), IN_VIEW) < 0.005

    n = len(objects)
    seen = objects.wait_for(lambda m: any(o.id == "red_cup" for o in m.objects), timeout=10.0, after=n)
    assert seen is not None, "the camera never reported the moved cup"
    perceived = next(o for o in seen.objects if o.id == "red_cup")
    assert perceived.on == "coffee_table"
    # Camera estimate plus the default 3 mm of noise per axis.
    p, q = perceived.position, cup.position
    assert math.dist((p.x, p.y, p.z), (q.x, q.y, q.z)) < 0.025


def test_a_moved_person_shows_in_world_humans(sim_stack: Stack) -> None:
    humans = Watch(sim_stack.node, keys.HUMANS)
    moved = sim_stack.node.call(keys.SIM_MOVE, MoveEntity(id="operator", x=2.0, y=2.0, yaw=0.5), timeout=10.0)
    assert isinstance(moved, Moved), moved
    there = humans.wait_for(
        lambda m: any(h.id == "operator" and (h.pose.x, h.pose.y) == (2.0, 2.0) for h in m.humans), timeout=10.0
    )
    assert there is not None, "world/humans never showed the operator at (2, 2)"
    assert there.humans[0].room == "kitchen" and there.humans[0].pose.yaw == 0.5


def test_tether_world_move_prints_the_result_or_the_refusal_with_exit_codes(sim_stack: Stack) -> None:
    moved = tether_cli(sim_stack, "world", "move", "apple", "7.0", "1.5")
    assert moved.returncode == 0, moved.stderr
    assert "apple now at (7.000, 1.500" in moved.stdout
    unknown = tether_cli(sim_stack, "world", "move", "unicorn", "7.0", "1.5")
    assert unknown.returncode == 2
    assert "unicorn" in unknown.stderr and "red_cup" in unknown.stderr
    outside = tether_cli(sim_stack, "world", "move", "apple", "70", "1.5")
    assert outside.returncode == 2 and "outside every room" in outside.stderr
    unreachable = tether_cli(sim_stack, "--base-port", "1100", "--robot", "nobody", "world", "move", "apple", "7", "1")
    assert unreachable.returncode == 3, unreachable.stderr


def test_the_camera_renders_in_a_child_at_the_objects_rate_and_dies_with_the_sim(sim_stack: Stack) -> None:
    sim = sim_stack.supervisor.procs["sim"].pid
    renderers = [p for p in children(sim) if "services.sim.renderer" in Path(f"/proc/{p}/cmdline").read_text()]
    assert len(renderers) == 1, f"the sim (pid {sim}) has no renderer process"
    # Detections come from it at objects_hz per wall second, stamped by the sim's schedule.
    objects = Watch(sim_stack.node, keys.OBJECTS)
    assert objects.wait_for(lambda m: True, timeout=10.0, after=0)
    assert objects.wait_for(lambda m: True, timeout=10.0, after=len(objects) + 5), "detections stopped"
    stamps = [m.stamp for m in objects.messages]
    gap = statistics.median(b - a for a, b in itertools.pairwise(stamps))
    assert gap == pytest.approx(1.0 / SimConfig().objects_hz, rel=0.25), f"stamps {stamps}"
    assert any(o.id == "blue_book" for o in objects.messages[-1].objects), "the coffee table's book is in view"
    # The MCP camera tool's picture, drawn there too.
    image = sim_stack.node.call(keys.CAMERA_IMAGE, Empty(), timeout=10.0)
    assert isinstance(image, CameraImage)
    assert (image.width, image.height) == (2 * CameraConfig().width, 2 * CameraConfig().height)

    os.kill(sim, signal.SIGKILL)  # the sim alone, as a crash: nothing of it runs, the child is not told
    assert wait_until(lambda: gone(renderers[0]), 10.0), f"renderer {renderers[0]} outlived the killed sim"
