"""A route the base planner gives from a few centimetres off a wall is one safety accepts from where
the base stands when it checks it, not only from the very pose the planner read; and there is one
from where teleop can leave the base, along a wall, whenever it can leave without coming closer.

The executor plans from its latest odometry; safety checks the goal a moment later from its own
(services/safety/gate.py, SafetyGate.navigate). A base standing under its motors creeps (about 2e-5
rad a second, services/sim/simulation.py) and a turn by teleop dies out over a few ticks, so the two
poses may differ by a hair, and the design allows them to (robotrules.away_from: the robot drives a
goal checked from up to TRACKING_TOLERANCE off). Closer than TRACKING_TOLERANCE to a wall, safety's
rule (footprint.clearance_problem) lets the base leave only as close as it starts, never closer; the
planner's way out ties with that rule exactly, so a start a micrometre or 1e-6 rad off had it
refused: "backing from (7.12, 0.39) to (7.22, 0.41) the base would come 2.5 cm from the outer wall,
closer than it starts" (test_modes.py's supervised pause, once in CI, after teleop had turned the
base by the south wall and the plan was resumed). From so close to a wall the planner now turns
first (BasePlanner._way_out): safety draws that turn from its own start, beginning with exactly the
footprint it measures there, so its rule holds from whatever pose it reads.
"""

from __future__ import annotations

import itertools
import math

import pytest
from shapely.geometry import LineString

from schemas.common import Pose2D
from services.executor.errors import PlanningFailed
from services.executor.navigation import BasePlanner
from services.footprint import TRACKING_TOLERANCE, Sweep, clearance_problem, footprint
from services.robotmodel import ArmModel
from services.safety.errors import Vetoed
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world

WORLD = WorldModel(load_world())
ROBOT = WORLD.world.robot
ARM = ArmModel(ROBOT.arm_urdf)
# The real default policy, as the safety service loads it.
POLICY = SafetyPolicy(WORLD, load_policy(None, ROBOT, ARM, WORLD.world.keep_out), ARM)
# The executor's defaults (ExecutorConfig.base_clearance, planning_time).
CLEARANCE = 0.04
# test_modes.py's pause drives to whichever table is farther: from the living room's south wall, this one.
KITCHEN_TABLE = next(f.approach for f in WORLD.world.furniture if f.id == "kitchen_table")
# How far safety's pose may be from the planner's a moment later: a few seconds' creep of a base
# standing still, far inside what the robot accepts (TRACKING_TOLERANCE).
DRIFT_YAW = 1e-4
DRIFT_XY = 1e-5
# Bases by the living room's south outer wall (its face at y = 0.05), their front turned toward it,
# each closer to it than TRACKING_TOLERANCE: the way out is a short leg backwards.
NEAR_WALL = [
    Pose2D(x=7.125, y=0.3885, yaw=-2.905),
    Pose2D(x=6.476, y=0.3931, yaw=-0.262),
    # Square to the wall, facing it and facing away: no turn out keeps clear, so the way out is a leg
    # straight back or ahead, which safety draws facing as the base does (footprint.route_sweeps).
    Pose2D(x=8.0, y=0.37, yaw=-math.pi / 2),
    Pose2D(x=8.0, y=0.37, yaw=math.pi / 2),
]


# Bases teleop can leave (its guard stops the footprint 1 to 5 cm short, services/safety/shared.py)
# from which no straight leg reaches where the base can turn: nearly along the living room's south
# wall (facing west; 4 cm off, so it may turn, but only by a hair); in its south-east corner; along
# the kitchen table; at an angle to the kitchen counter. Each needs a few legs out, turning a little
# before each, coming no closer to anything than it starts ("cannot drive straight out", or OMPL
# finding nothing, before).
ALONG_A_WALL = [
    Pose2D(x=10.36, y=0.3255, yaw=3.118),
    Pose2D(x=6.401, y=0.3573, yaw=3.096),
    Pose2D(x=11.088, y=0.3842, yaw=0.278),
    Pose2D(x=1.975, y=3.228, yaw=0.034),
    Pose2D(x=3.893, y=0.4253, yaw=2.855),
]


def gap_of(start: Pose2D) -> float:
    """How far the base's footprint at `start` is from the nearest wall or piece of furniture."""
    shape = footprint(start.x, start.y, start.yaw, ROBOT.base_size.x, ROBOT.base_size.y)
    return min(shape.distance(o.shape) for o in WORLD.obstacles)


def drifted(pose: Pose2D) -> list[Pose2D]:
    """`pose` and the poses around it within the drift, every combination of the extremes."""
    yaws = (-DRIFT_YAW, 0.0, DRIFT_YAW)
    offsets = (-DRIFT_XY, 0.0, DRIFT_XY)
    return [
        Pose2D(x=pose.x + dx, y=pose.y + dy, yaw=pose.yaw + dyaw)
        for dx, dy, dyaw in itertools.product(offsets, offsets, yaws)
    ]


def refusals(start: Pose2D, path: list[Pose2D]) -> list[str]:
    """Safety's refusals of `path` to the kitchen table, checked from each of the poses `drifted` from `start`."""
    refused = []
    for there in drifted(start):
        try:
            POLICY.check_route(there, path, KITCHEN_TABLE)
        except Vetoed as exc:
            refused.append(f"from ({there.x}, {there.y}, {there.yaw}): {exc}")
    return refused


@pytest.fixture(scope="module")
def planner() -> BasePlanner:
    return BasePlanner(WORLD, clearance=CLEARANCE, time_limit=1.0)


@pytest.mark.parametrize("start", NEAR_WALL, ids=lambda p: f"{p.x}-{p.y}-{p.yaw}")
def test_the_way_out_from_beside_a_wall_is_accepted_from_a_hair_away(planner: BasePlanner, start: Pose2D) -> None:
    gap = gap_of(start)
    assert gap < TRACKING_TOLERANCE, f"the start is {gap:.4f} m from the nearest wall: not the situation tested"
    path = planner.plan(start, KITCHEN_TABLE)
    # From the planner's own start the route passes (the planner verifies every route with safety's
    # rule), and it must pass from where safety may find the base a moment later too.
    POLICY.check_route(start, path, KITCHEN_TABLE)
    assert not (refused := refusals(start, path)), "\n".join(refused)


@pytest.mark.parametrize("start", ALONG_A_WALL, ids=lambda p: f"{p.x}-{p.y}-{p.yaw}")
def test_a_base_left_along_a_wall_leaves_by_a_few_legs_safety_accepts(planner: BasePlanner, start: Pose2D) -> None:
    assert 0.01 <= gap_of(start) <= 0.05, "not where teleop leaves the base"
    path = planner.plan(start, KITCHEN_TABLE)
    assert not (refused := refusals(start, path)), "\n".join(refused)


def test_a_base_exactly_along_a_wall_says_why_it_cannot_leave(planner: BasePlanner) -> None:
    # Any turn swings a corner closer to the wall, and no leg along it gets farther: safety's rule
    # (leaving, no closer than it starts) leaves no way out, and the reason says so.
    start = Pose2D(x=8.0, y=0.05 + 0.02 + ROBOT.base_size.y / 2, yaw=0.0)
    reason = r"is 2 cm from the outer wall and cannot drive out of there, in up to \d legs coming no closer to anything"
    with pytest.raises(PlanningFailed, match=reason):
        planner.plan(start, KITCHEN_TABLE)


@pytest.mark.parametrize(
    ("gap", "closer", "why"), [(0.02, 0.0, None), (0.02, 1e-4, "closer than it starts"), (5e-4, 0.1, "would hit")]
)
def test_safetys_rule_leaving_a_wall_has_no_slack(gap: float, closer: float, why: str | None) -> None:
    # A base `gap` from a wall (its face at y = 0) leaving by a piece of route that comes `closer` to it:
    # not even a tenth of a millimetre, and not into it from half a millimetre off. A slack here (tried,
    # 1 mm) let each goal come that much closer than the last, and one from within it drive into the wall.
    length, width = ROBOT.base_size.x, ROBOT.base_size.y
    wall = [("the wall", LineString([(-5.0, 0.0), (5.0, 0.0)]))]
    start = Pose2D(x=0.0, y=gap + width / 2, yaw=0.0)
    dipped = footprint(start.x + 0.1, start.y - closer, 0.0, length, width)
    problem = clearance_problem(
        start, [Sweep("driving", (dipped,), start.x + 0.2, start.y)], wall, TRACKING_TOLERANCE, length, width
    )
    if why is None:
        assert problem is None, problem
    else:
        assert problem is not None and why in problem[1], problem
