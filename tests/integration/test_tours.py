"""Tours over real processes, judged by the sim: the base through every pair of rooms, and every
graspable object picked and placed on every surface.

Its own module (apart from tests/integration/test_executor.py) so that its fast sim (conftest's FAST,
twice the executor's: neither tour puts an object back to a spot seen by the camera) lives only while
the tours run, and a parallel worker can take it while another runs the executor's other tests."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator

import pytest

from schemas import keys
from schemas.executor import PlanStatus
from schemas.world import WorldObject
from services.footprint import footprint
from tests.fastsim import FAST_SIM
from tests.integration.conftest import FAST, Stack, start_stack, stop_stack
from tests.integration.test_executor import GRASPABLE, ROBOT, WITHOUT_RECORDER, WORLD, chain, execute, plan, truth
from tests.watch import Watch

# Odometry samples this close (metres, radians) are two of a row, none lost between them.
MAX_SAMPLE_GAP = 0.3
MAX_SAMPLE_TURN = 0.6


@pytest.fixture(scope="module")
def tour_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """One stack for the tours: each leaves the world as it found it, the robot aside."""
    s = start_stack(
        tmp_path_factory.mktemp("tours"), realtime_factor=FAST, services=WITHOUT_RECORDER, sim_options=FAST_SIM
    )
    try:
        yield s
    finally:
        stop_stack(s)


@pytest.mark.parametrize("obj", GRASPABLE, ids=[o.id for o in GRASPABLE])
def test_every_graspable_object_is_picked_and_placed_on_every_surface(tour_stack: Stack, obj: WorldObject) -> None:
    stack = tour_stack
    for surface in chain(obj.support):
        name = WORLD.furniture[surface].name
        result = execute(stack, plan({"action": "pick", "target": obj.name}, {"action": "place", "target": name}))
        # Judged by the simulator, not by what the executor says.
        now = truth(stack)
        placed = next(o for o in now.objects if o.id == obj.id)
        where = f"the sim has it on {placed.on} at {placed.position}, held: {now.holding}"
        assert result.status is PlanStatus.SUCCEEDED, f"{obj.name} onto the {name}: {result.reason}; {where}"
        assert now.holding is None
        assert placed.on == surface, f"{obj.name} is on {placed.on}, not on the {name}"
        resting = WORLD.furniture[surface].size.z + obj.size.z / 2
        assert placed.position.z == pytest.approx(resting, abs=0.01), f"{obj.name} on the {name} is not upright"


def test_the_base_goes_between_every_pair_of_rooms_round_walls_and_furniture(tour_stack: Stack) -> None:
    """Last, from wherever the objects' tours left the robot, so that they run as on a stack of their own,
    the first from the start pose (the red cup's, begun from the kitchen instead, lost the cup on its first place)."""
    stack = tour_stack
    rooms = [room.id for room in WORLD.world.rooms]
    # A round trip through every pair of the five rooms once (each room has four others: even degree).
    tour = ["kitchen", "living_room", "hallway", "office", "bedroom", "kitchen"]
    tour += ["hallway", "bedroom", "living_room", "office", "kitchen"]
    pairs = {frozenset(p) for p in itertools.pairwise(tour)}
    assert pairs == {frozenset(p) for p in itertools.combinations(rooms, 2)}
    odom = Watch(stack.node, keys.ODOM)
    names = {room.id: room.name for room in WORLD.world.rooms}
    result = execute(stack, plan(*({"action": "navigate_to", "target": names[room]} for room in tour)))
    assert result.status is PlanStatus.SUCCEEDED, result.reason
    assert [s.status for s in result.steps] == ["succeeded"] * len(tour)
    end = truth(stack).robot
    goal = WORLD.room_pose("kitchen")
    assert math.hypot(end.x - goal.x, end.y - goal.y) < 0.05
    # Never touching a wall or a piece of furniture on the way: the base where odometry measured it,
    # and between each two samples. Odometry comes at 50 Hz of wall time, so at 20x a sample every
    # 24 cm at top speed (0.6 m/s) and 0.48 rad turning (1.2 rad/s): the hull of two footprints
    # holds what the base covered between them, but for the corners' arcs of a turn (about 1 cm).
    # Samples farther apart (one lost on the way) are checked each by itself.
    size = ROBOT.base_size
    poses = [m.pose for m in odom.messages]
    assert len(poses) > 100
    shapes = [footprint(pose.x, pose.y, pose.yaw, size.x, size.y) for pose in poses]
    for k, (pose, here) in enumerate(zip(poses, shapes, strict=True)):
        swept = here
        if k + 1 < len(poses):
            after = poses[k + 1]
            turn = abs(math.remainder(after.yaw - pose.yaw, math.tau))
            if math.hypot(after.x - pose.x, after.y - pose.y) <= MAX_SAMPLE_GAP and turn <= MAX_SAMPLE_TURN:
                swept = here.union(shapes[k + 1]).convex_hull
        hit = next((o for o in WORLD.obstacles if swept.intersects(o.shape)), None)
        assert hit is None, f"from ({pose.x:.2f}, {pose.y:.2f}) the base touched the {hit.name}"
    visited = {WORLD.room_of(p.x, p.y) for p in poses}
    assert visited == set(rooms)
