"""The resolver grounds names in what the robot saw, over real processes: a moved object is found
where the camera saw it, not where the world file put it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time

from schemas import keys
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.world import Empty, Moved, MoveEntity, SceneDescription
from tests.integration.conftest import Stack
from tests.watch import Watch
from tether.client import PlanSender

PERCEPTION_TIMEOUT = 30.0
# On the coffee table, in front of the robot's start and clear of the blue book.
NEW_SPOT = (8.0, 2.35)


def scene_until(stack: Stack, seen: str, on: str, timeout: float) -> SceneDescription | None:
    """The resolver's scene once it has `seen` on `on`, or None at the deadline."""
    frames = Watch(stack.node, keys.OBJECTS)
    deadline = time.monotonic() + timeout
    while True:
        after = len(frames)
        scene = stack.node.call(keys.SCENE, Empty(), timeout=5.0)
        if any(o.id == seen and o.on == on and o.stamp > 0 for o in scene.objects):
            return scene
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        frames.wait_for(lambda _: True, remaining, after=after)  # ask again once a new frame is out


def run(stack: Stack, text: str, *, dry_run: bool = False) -> tuple[PlanStatus, str, list[str]]:
    outcome = PlanSender(stack.node).run(ExecutePlanGoal(text=text, dry_run=dry_run), 300.0)
    assert outcome.result is not None
    return outcome.result.status, outcome.result.reason, outcome.result.warnings


def test_a_moved_object_is_picked_where_the_camera_saw_it(stack: Stack) -> None:
    scene = stack.node.call(keys.SCENE, Empty(), timeout=5.0)
    cup = next(o for o in scene.objects if o.id == "red_cup")
    assert (cup.on, cup.stamp) == ("kitchen_counter", 0.0), "out of view at the start: known from the world file"

    moved = stack.node.call(keys.SIM_MOVE, MoveEntity(id="red_cup", x=NEW_SPOT[0], y=NEW_SPOT[1]), timeout=10.0)
    assert isinstance(moved, Moved), moved
    assert math.dist((moved.position.x, moved.position.y), NEW_SPOT) < 0.02

    seen = scene_until(stack, "red_cup", "coffee_table", PERCEPTION_TIMEOUT)
    assert seen is not None, "the camera never showed the resolver the red cup on the coffee table"
    assert "red cup" in seen.text and "coffee table" in seen.text

    # Named by where it is now, which only perception knows.
    status, reason, _ = run(stack, "pick up the cup on the coffee table", dry_run=True)
    assert status is PlanStatus.SUCCEEDED, reason
    status, reason, _ = run(stack, "pick up the cup on the kitchen counter", dry_run=True)
    assert status is PlanStatus.REJECTED and "nothing called 'cup' is" in reason, reason

    status, reason, _ = run(stack, json.dumps({"plan": [{"action": "pick", "target": "red cup"}]}))
    assert status is PlanStatus.SUCCEEDED, reason
    truth = stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)
    assert truth.holding == "red_cup"
    approach = (8.0, 1.75)  # the coffee table's, not the kitchen counter's
    assert math.dist((truth.robot.x, truth.robot.y), approach) < 0.2, truth.robot


def test_the_scene_command_describes_what_the_resolver_knows(stack: Stack) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "tether", "world", "scene", "--json"],
        env=stack.supervisor.env(),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    scene = json.loads(done.stdout)
    assert scene["text"].startswith("The robot is in the living room")
    book = next(o for o in scene["objects"] if o["id"] == "blue_book")
    assert book["on"] == "coffee_table"
    assert {"subject": "blue_book", "relation": "on", "object": "coffee_table"} in scene["relations"]
