"""The shortcuts of the trajectory check decide as the plain checks do: one point at a time (in plain
floats) and all at once (numpy, shapely) give the same decisions, messages and values, and a point
is in a keep-out zone exactly when shapely has it there (the zone's bounding box first)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shapely.geometry import Point

from schemas.common import Pose2D
from schemas.robot import ARM_JOINTS, FollowJointTrajectoryGoal, TrajectoryPoint
from schemas.safety import Rule
from schemas.world import KeepOut
from services.robotmodel import ArmModel
from services.safety import policy as policy_module
from services.safety.errors import Vetoed
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world
from tests.unit.test_safety_rules import decision

WORLD = load_world()
STAIRS = next(zone for zone in WORLD.keep_out if zone.id == "stairs")
WEST, SOUTH = min(x for x, _ in STAIRS.polygon), min(y for _, y in STAIRS.polygon)
EAST, NORTH = max(x for x, _ in STAIRS.polygon), max(y for _, y in STAIRS.polygon)
# A triangle in the living room: half of its bounding box is outside it.
WEDGE = KeepOut(id="wedge", name="wedge", polygon=[[7.0, 2.0], [8.0, 2.0], [7.0, 3.0]])
NOW = dict(zip(ARM_JOINTS, WORLD.robot.home_joints, strict=True))


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    arm = ArmModel(WORLD.robot.arm_urdf)
    world = WorldModel(WORLD)
    return SafetyPolicy(world, load_policy(None, WORLD.robot, arm, [*WORLD.keep_out, WEDGE], WORLD.rooms), arm)


def trajectory(rng: np.random.Generator, policy: SafetyPolicy) -> tuple[FollowJointTrajectoryGoal, Pose2D]:
    """1 to 40 points over all the arm's joints or some of them in any order, wandering in small or
    large steps or on a line to anywhere in the limits (a joint over its limit or its speed now and
    then, a time repeated or going back, the first point at time 0), from the open floor or facing
    the stairs."""
    names = (
        list(ARM_JOINTS) if rng.random() < 0.6 else [ARM_JOINTS[i] for i in rng.permutation(7)[: rng.integers(1, 8)]]
    )
    n = int(rng.integers(1, 41))
    lower = np.array([policy.joint_limits[name].lower for name in names])
    upper = np.array([policy.joint_limits[name].upper for name in names])
    q = np.array([NOW[name] for name in names])
    if rng.random() < 0.3:  # on a straight line to anywhere in the limits, the hand in or out of the workspace
        target = rng.uniform(lower + 0.02, upper - 0.02)
        rows = q + (target - q) * np.arange(1, n + 1)[:, np.newaxis] / n
    else:
        walk = np.cumsum(rng.normal(0.0, rng.choice([0.02, 0.2, 0.8]), (n, len(names))), axis=0)
        rows = np.clip(q + walk, lower - 0.05, upper + 0.05)
    times = np.cumsum(rng.choice([-0.1, 0.0, 0.3, 1.0, 4.0], n, p=[0.02, 0.03, 0.15, 0.3, 0.5]))
    if rng.random() < 0.2:
        times[0] = 0.0
    spot = Pose2D(x=6.0, y=1.2) if rng.random() < 0.4 else Pose2D(x=WEST - rng.uniform(0.1, 0.6), y=8.0)
    base = Pose2D(x=spot.x, y=spot.y, yaw=float(rng.uniform(-0.6, 0.6)))
    points = [
        TrajectoryPoint(positions=row.tolist(), time_from_start=float(t)) for row, t in zip(rows, times, strict=True)
    ]
    return FollowJointTrajectoryGoal(joint_names=names, points=points), base


def test_trajectories_checked_point_by_point_and_all_at_once_are_decided_alike(
    policy: SafetyPolicy, monkeypatch: pytest.MonkeyPatch
) -> None:
    rng = np.random.default_rng(43)
    cases = [trajectory(rng, policy) for _ in range(300)]
    monkeypatch.setattr(policy_module, "FEW_POINTS", 0)
    monkeypatch.setattr(policy_module, "FEW_ARM_POINTS", 0)
    at_once = [decision(policy, goal, base, NOW) for goal, base in cases]
    monkeypatch.setattr(policy_module, "FEW_POINTS", 10**9)
    monkeypatch.setattr(policy_module, "FEW_ARM_POINTS", 10**9)
    assert [decision(policy, goal, base, NOW) for goal, base in cases] == at_once
    assert sum(d[0] == "approved" for d in at_once) > 30
    rules = {d[2] for d in at_once if d[0] == "vetoed"}
    assert {Rule.JOINT_LIMITS, Rule.JOINT_SPEED, Rule.WORKSPACE, Rule.ARM_KEEP_OUT} <= rules, rules


@pytest.mark.parametrize(
    ("x", "y"),
    [
        (WEST, 8.0),  # on an edge: in (intersects counts the boundary)
        (EAST, NORTH),  # a corner
        (11.0, SOUTH),
        (math.nextafter(WEST, -math.inf), 8.0),  # the closest double outside
        (11.0, math.nextafter(NORTH, math.inf)),
        (7.2, 2.2),  # inside the wedge
        (7.5, 2.5),  # on its slanted edge
        (7.9, 2.9),  # in its bounding box, outside it
        (math.nan, 8.0),
        (math.inf, 8.0),
        (6.0, 1.2),  # nowhere near
    ],
)
def test_a_point_is_in_a_keep_out_zone_exactly_when_shapely_has_it_there(
    policy: SafetyPolicy, x: float, y: float
) -> None:
    expected = next(
        (zone for zone in policy.limits.keep_out if Point(x, y).intersects(policy.zone_shapes[zone.id])), None
    )
    assert policy.zone_at(x, y) == expected


@pytest.mark.parametrize("broken", [math.nan, math.inf, -math.inf])
def test_a_joint_state_that_is_not_a_number_refuses_the_trajectory_naming_the_joint(
    policy: SafetyPolicy, broken: float
) -> None:
    """A robot's joint_states may carry NaN or infinity (a failed encoder): the arm does not move, and
    the refusal says which joint, rather than the check failing on the arithmetic."""
    current = {**NOW, "panda_joint4": broken}
    goal = FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS),
        points=[TrajectoryPoint(positions=[NOW[n] for n in ARM_JOINTS], time_from_start=0.3)],
    )
    with pytest.raises(Vetoed, match=r"no position for panda_joint4$") as refused:
        policy.check_trajectory(goal, current, Pose2D(x=1.0, y=1.0, yaw=0.0))
    assert refused.value.rule is Rule.POSE_KNOWN
