"""Safety's rule for a route leaving its start (footprint.clearance_problem, which the executor's base
planner also keeps): near something at the start, the base may stay as close to *that* as it is, never
closer; one it touches or overlaps (a bump, odometry's drift) it may not overlap more; everything else
keeps the margin from the first sweep on.

Before, the start's distance to the nearest obstacle was the allowance for all of them: from a start
touching a wall (0 away) every leaving sweep passed, even one driven into the wall or through a table
across the room, and from 2 cm off a wall a leg could pass 2 cm from anything else.
"""

from __future__ import annotations

import math

import pytest
from shapely.geometry import LineString, box
from shapely.geometry.base import BaseGeometry

from schemas.common import Pose2D
from services.footprint import TRACKING_TOLERANCE, clearance_problem, route_sweeps
from services.robotmodel import ArmModel
from services.safety.errors import Vetoed
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world

LENGTH, WIDTH = 0.6, 0.5
NORTH, SOUTH = math.pi / 2, -math.pi / 2
# A wall whose face is y = 0, and a table 1 m north of it.
WALL = ("the wall", box(-5.0, -0.1, 5.0, 0.0))
TABLE = ("the table", box(-0.5, 1.0, 0.5, 1.5))


def problem(start: Pose2D, point: tuple[float, float], obstacles: list[tuple[str, BaseGeometry]]) -> str | None:
    sweeps = route_sweeps(start, [point], start.yaw, LENGTH, WIDTH)
    found = clearance_problem(start, sweeps, obstacles, TRACKING_TOLERANCE, LENGTH, WIDTH)
    return None if found is None else found[1]


@pytest.mark.parametrize(
    ("start", "point", "why"),
    [
        # Its back against the wall, facing north: on through the table.
        (Pose2D(x=0.0, y=LENGTH / 2, yaw=NORTH), (0.0, 2.5), "would hit the table"),
        # Its front against the wall, facing it: 10 cm on, into the wall.
        (Pose2D(x=0.0, y=LENGTH / 2, yaw=SOUTH), (0.0, LENGTH / 2 - 0.1), "would go further into the wall"),
        # 1 cm into the wall already: further in.
        (Pose2D(x=0.0, y=LENGTH / 2 - 0.01, yaw=SOUTH), (0.0, 0.2), "would go further into the wall"),
        # 2 cm off the wall, along it 2.5 cm from a low table beside it.
        (
            Pose2D(x=-2.0, y=0.02 + WIDTH / 2, yaw=0.0),
            (2.0, 0.02 + WIDTH / 2),
            "2.5 cm from the low table (it keeps 3 cm)",
        ),
    ],
)
def test_a_start_near_one_thing_is_no_licence_to_come_near_another_nor_into_it(
    start: Pose2D, point: tuple[float, float], why: str
) -> None:
    low_table = ("the low table", box(1.0, 0.02 + WIDTH + 0.025, 2.0, 1.0))
    assert why in (problem(start, point, [WALL, TABLE, low_table]) or "accepted")


@pytest.mark.parametrize(
    ("start", "point"),
    [
        (Pose2D(x=0.0, y=LENGTH / 2, yaw=NORTH), (0.0, 0.6)),  # touching the wall, away from it
        (Pose2D(x=0.0, y=LENGTH / 2 - 0.01, yaw=SOUTH), (0.0, 0.6)),  # 1 cm into it, backing out
        (Pose2D(x=0.0, y=WIDTH / 2, yaw=0.0), (0.3, WIDTH / 2)),  # touching it, sliding along
        (Pose2D(x=0.0, y=0.02 + WIDTH / 2, yaw=0.0), (-0.3, 0.02 + WIDTH / 2)),  # 2 cm off, along it
    ],
)
def test_a_base_touching_or_near_a_wall_may_still_leave_it(start: Pose2D, point: tuple[float, float]) -> None:
    assert problem(start, point, [WALL, TABLE]) is None


def test_safety_refuses_a_navigation_into_the_wall_the_base_touches() -> None:
    world = WorldModel(load_world())
    robot = world.world.robot
    arm = ArmModel(robot.arm_urdf)
    policy = SafetyPolicy(world, load_policy(None, robot, arm, world.world.keep_out), arm)
    # Facing the living room's south outer wall (its face at y = 0.05), the front against it.
    start = Pose2D(x=8.0, y=0.05 + robot.base_size.x / 2, yaw=SOUTH)
    with pytest.raises(Vetoed, match="further into the outer wall"):
        policy.check_route(start, [], Pose2D(x=8.0, y=start.y - 0.1, yaw=SOUTH))


def test_a_turn_first_does_not_trade_one_part_of_an_overlap_for_another() -> None:
    # A corner 11 mm into the wall; the turn lifts it out, and the drive after it would enter the wall
    # 0.7 m along, 3 mm deep: the area the drive covers alone is no more than the start's was.
    start = Pose2D(x=0.0, y=0.2714, yaw=0.1152)
    sweeps = route_sweeps(start, [(0.72, 0.254)], -0.024, LENGTH, WIDTH)
    found = clearance_problem(start, sweeps, [WALL], TRACKING_TOLERANCE, LENGTH, WIDTH)
    assert found is not None and "further into the wall" in found[1], found


def test_a_wall_drawn_as_a_line_is_not_driven_through_from_touching_it() -> None:
    # Its overlap has no area: the length of it tells.
    wall = [("the wall", LineString([(-5.0, 0.0), (5.0, 0.0)]))]
    assert "further into the wall" in (problem(Pose2D(x=0.0, y=LENGTH / 2, yaw=SOUTH), (0.0, -0.5), wall) or "")


@pytest.mark.parametrize("deep", [0.015, 0.04])
def test_backing_straight_off_an_overlap_passes_from_a_start_read_a_hair_off(deep: float) -> None:
    # Planned facing north from a base `deep` into the wall; safety reads its yaw 0.9 mrad off, so the
    # leg runs that far off the base's axis and covers a sliver more of the wall (0.2 mm^2 at 2 cm).
    planned = Pose2D(x=0.0, y=LENGTH / 2 - deep, yaw=NORTH)
    read = Pose2D(x=planned.x, y=planned.y, yaw=NORTH + 9e-4)
    sweeps = route_sweeps(read, [(0.0, planned.y + 0.5)], NORTH, LENGTH, WIDTH)
    assert clearance_problem(read, sweeps, [WALL], TRACKING_TOLERANCE, LENGTH, WIDTH) is None
