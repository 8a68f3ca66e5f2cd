"""Every rule the pure checks enforce, at its boundary: just inside passes, just outside is refused.

Each refusal is checked for its rule, for a message that names the measured value and the limit
(told apart), and for `values` carrying both. The limits come from the default policy and world
files, so the tests follow the files when those change. Monitors and rate limits are in
test_safety_monitor.py, the policy file itself in test_policyfile.py.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import msgspec
import numpy as np
import pytest

from schemas.common import Pose2D, Vec3
from schemas.plan import (
    Fallback,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    Step,
)
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, TrajectoryPoint, Twist
from schemas.safety import Rule
from schemas.world import World
from services.footprint import MAX_REVERSE, TRACKING_TOLERANCE
from services.robotmodel import ArmModel
from services.safety import policy as policy_module
from services.safety.errors import Vetoed
from services.safety.policy import JOINT_LIMIT_MARGIN, START_TOLERANCE, SafetyPolicy
from services.safety.policyfile import Limits, PayloadPolicy, load_policy, resolve
from services.worldmodel import WorldModel, load_world

WORLD = load_world()
ROBOT = WORLD.robot
# How far outside and inside a limit the two cases of each pair are (metres, radians, seconds, kg, N).
EPS = 1e-3
# Keep-out zones are grown by the base's half-diagonal (plus base.footprint_margin, 0 by default).
RADIUS = math.hypot(ROBOT.base_size.x, ROBOT.base_size.y) / 2
STAIRS = next(zone for zone in WORLD.keep_out if zone.id == "stairs")
STAIRS_WEST = min(x for x, _ in STAIRS.polygon)  # 10.5
STAIRS_SOUTH = min(y for _, y in STAIRS.polygon)  # 7.0
STAIRS_MID_Y = (STAIRS_SOUTH + max(y for _, y in STAIRS.polygon)) / 2  # 8.0
MAP_WEST = min(x for room in WORLD.rooms for x, _ in room.polygon)  # 0.0, the kitchen's and bedroom's wall

ARM = [f"panda_joint{i}" for i in range(1, 8)]
HOME = [0.0, -1.2, 0.0, -2.7, 0.0, 1.5, 0.785]
NOW = dict(zip(ARM, HOME, strict=True))
START = Pose2D(x=6.0, y=1.2)  # the living room, facing east, nothing near
# The coffee table's approach pose: from START the base drives there in a straight line.
COFFEE_TABLE = Pose2D(x=8.0, y=1.75, yaw=math.pi / 2)
# The flat with its walls and furniture taken away, for the map's own edge.
OPEN_FLOOR = msgspec.structs.replace(WORLD, walls=[], furniture=[], objects=[])
SOURCE = Plan(steps=[Step(action="stop")])  # type: ignore[arg-type]

# The rules this file tests at their boundaries, and those tested elsewhere or not by pure checks.
PURE = {
    Rule.POSE_KNOWN,
    Rule.MAP,
    Rule.KEEP_OUT,
    Rule.OBSTACLE,
    Rule.BASE_SPEED,
    Rule.BASE_ACCELERATION,
    Rule.CMD_VEL_HORIZON,
    Rule.JOINT_LIMITS,
    Rule.JOINT_SPEED,
    Rule.WORKSPACE,
    Rule.ARM_KEEP_OUT,
    Rule.BASE_STILL,
    Rule.PAYLOAD,
    Rule.GRIPPER_FORCE,
    Rule.GRIPPER_DROP,
    Rule.HUMAN_SEPARATION,  # the teleop clamp here; separation() in test_safety_monitor.py
    Rule.PLAN,
    Rule.MONITOR_KEEP_OUT,  # zone_at here
}
ELSEWHERE = {
    Rule.COMMAND_RATE,  # RateLimit: test_safety_monitor.py
    Rule.MONITOR_SPEED,  # MotionMonitor: test_safety_monitor.py
    Rule.MONITOR_JOINT_SPEED,
    Rule.ESTOP,  # the latch and the node, not a limit
    Rule.OPERATOR,
    Rule.WATCHDOG,
    Rule.MODE,  # the control mode, not a limit: test_safety_modes.py, test_modes.py
    Rule.APPROVAL,  # supervised plans: test_safety_modes.py, test_modes.py
    Rule.CAUTION_ZONE,  # safety's memory of incidents: test_gate_incidents.py, test_caution_zone.py
    Rule.ONE_MOTION,  # the goals the node forwarded: test_safety_one_motion.py
}


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel(ROBOT.arm_urdf)


@pytest.fixture(scope="module")
def limits(arm: ArmModel) -> Limits:
    return load_policy(None, ROBOT, arm, WORLD.keep_out)


@pytest.fixture(scope="module")
def policy(limits: Limits, arm: ArmModel) -> SafetyPolicy:
    return SafetyPolicy(WorldModel(WORLD), limits, arm)


def tightened(limits: Limits, arm: ArmModel, world: World = WORLD, **sections: object) -> SafetyPolicy:
    """The default policy with some sections replaced, resolved against the robot like a file."""
    changed = msgspec.structs.replace(limits.policy, **sections)
    return SafetyPolicy(
        WorldModel(world), resolve(changed, limits.path, limits.hash, world.robot, arm, world.keep_out), arm
    )


def refused(check: Callable[[], object], rule: Rule) -> Vetoed:
    with pytest.raises(Vetoed) as info:
        check()
    assert info.value.rule is rule, f"refused by {info.value.rule}, not {rule}: {info.value}"
    return info.value


NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?")


def shown_as(message: str, x: float) -> set[float]:
    """The numbers printed in `message` that are `x` at their printed precision."""
    found = set()
    for text in NUMBER.findall(message):
        decimals = len(text.partition(".")[2])
        if round(x, decimals) == float(text):
            found.add(float(text))
    return found


def assert_names(message: str, measured: float, limit: float) -> None:
    """The message names the measured value and the limit, and a reader can tell them apart."""
    as_measured, as_limit = shown_as(message, measured), shown_as(message, limit)
    assert as_measured, f"the measured {measured} is not in: {message}"
    assert as_limit, f"the limit {limit} is not in: {message}"
    assert any(a != b for a in as_measured for b in as_limit), f"{measured} and its limit {limit} read alike: {message}"


def trajectory(*points: tuple[list[float], float]) -> FollowJointTrajectoryGoal:
    return FollowJointTrajectoryGoal(
        joint_names=ARM, points=[TrajectoryPoint(positions=list(q), time_from_start=t) for q, t in points]
    )


def with_joint(q: list[float], name: str, value: float) -> list[float]:
    out = list(q)
    out[ARM.index(name)] = value
    return out


def test_every_rule_is_covered_here_or_elsewhere() -> None:
    # A new rule must get its boundary tests (and be listed above) before this passes.
    assert set(Rule) == PURE | ELSEWHERE
    assert not PURE & ELSEWHERE


# pose_known


def test_without_odometry_or_joint_states_motion_is_refused(policy: SafetyPolicy) -> None:
    goal = NavigateToPoseGoal(pose=COFFEE_TABLE)
    assert policy.check_navigation(goal, START).command.pose == goal.pose
    refused(lambda: policy.check_navigation(goal, None), Rule.POSE_KNOWN)
    refused(lambda: policy.check_cmd_vel(Twist(linear_x=0.01), None), Rule.POSE_KNOWN)
    refused(lambda: policy.check_teleop(Twist(linear_x=0.01), None, Twist(linear_x=0.01), 0.1), Rule.POSE_KNOWN)
    plan = GroundedPlan(steps=[NavigateStep(target="counter", goal=goal.pose)], source=SOURCE)
    assert "unknown" in str(refused(lambda: policy.check_plan(plan, None), Rule.POSE_KNOWN))
    still = trajectory((HOME, 1.0))
    assert policy.check_trajectory(still, NOW, START).command == still
    refused(lambda: policy.check_trajectory(still, None, START), Rule.POSE_KNOWN)
    refused(
        lambda: policy.check_trajectory(still, {n: q for n, q in NOW.items() if n != "panda_joint7"}, START),
        Rule.POSE_KNOWN,
    )
    refused(lambda: policy.check_trajectory(still, NOW, None), Rule.POSE_KNOWN)


# map


def test_a_goal_just_inside_the_map_passes_and_just_outside_is_off_the_map(limits: Limits, arm: ArmModel) -> None:
    # Without the outer wall in the way, which would stop the base first (obstacle, below).
    policy = tightened(limits, arm, OPEN_FLOOR)
    start = Pose2D(x=2.5, y=2.5)
    facing_west = math.pi  # the base drives in from 0.4 m east of the goal: inside the kitchen
    inside = NavigateToPoseGoal(pose=Pose2D(x=MAP_WEST + 0.01, y=2.5, yaw=facing_west))
    assert policy.check_navigation(inside, start).command.pose == inside.pose
    outside = NavigateToPoseGoal(pose=Pose2D(x=MAP_WEST - 0.01, y=2.5, yaw=facing_west))
    exc = refused(lambda: policy.check_navigation(outside, start), Rule.MAP)
    assert "(-0.01, 2.50) is outside every room" in str(exc)
    assert exc.values == {"x": pytest.approx(MAP_WEST - 0.01), "y": 2.5}
    # A waypoint off the map is refused like the goal.
    via = NavigateToPoseGoal(pose=Pose2D(x=2.5, y=4.0), path=[Pose2D(x=MAP_WEST - 0.01, y=3.0)])
    assert refused(lambda: policy.check_navigation(via, start), Rule.MAP).values["x"] == pytest.approx(-0.01)


# keep_out


@pytest.mark.parametrize(
    ("start", "pose_at"),
    [
        # From the west, facing east: the goal's x runs up to the zone's west edge.
        (Pose2D(x=9.0, y=STAIRS_MID_Y), lambda d: Pose2D(x=STAIRS_WEST - d, y=STAIRS_MID_Y, yaw=0.0)),
        # From the south, facing north: the goal's y runs up to the zone's south edge.
        (Pose2D(x=11.2, y=5.5), lambda d: Pose2D(x=11.2, y=STAIRS_SOUTH - d, yaw=math.pi / 2)),
    ],
    ids=["west-edge", "south-edge"],
)
def test_a_goal_a_footprint_away_from_the_stairs_passes_and_closer_is_refused(
    policy: SafetyPolicy, start: Pose2D, pose_at: Callable[[float], Pose2D]
) -> None:
    clear = NavigateToPoseGoal(pose=pose_at(RADIUS + EPS))
    assert policy.check_navigation(clear, start).command.pose == clear.pose
    close = pose_at(RADIUS - EPS)
    exc = refused(lambda: policy.check_navigation(NavigateToPoseGoal(pose=close), start), Rule.KEEP_OUT)
    assert str(exc) == (
        f"at the goal ({close.x:.2f}, {close.y:.2f}) the base's footprint would be in keep-out zone 'stairs': "
        "the robot could fall down the stairs"
    )
    assert exc.values == {"x": pytest.approx(close.x), "y": pytest.approx(close.y)}


# From here the base drives across the stairs' south-west corner, though every point of its route,
# the pre-goal (11.10, 6.50) and the goal, is CORNER_GAP clear of the stairs.
CORNER_START = Pose2D(x=10.0, y=8.5)
CORNER_GOAL = NavigateToPoseGoal(pose=Pose2D(x=11.5, y=6.5))
CORNER_GAP = 0.5


def test_a_leg_of_the_route_that_takes_the_footprint_into_the_stairs_is_refused_naming_the_leg(
    policy: SafetyPolicy,
) -> None:
    assert RADIUS < CORNER_GAP
    # Around the corner, through the hallway, the same goal is reached.
    around = msgspec.structs.replace(CORNER_GOAL, path=[Pose2D(x=9.5, y=8.5), Pose2D(x=9.5, y=6.5)])
    assert policy.check_navigation(around, CORNER_START).command.path == around.path
    exc = refused(lambda: policy.check_navigation(CORNER_GOAL, CORNER_START), Rule.KEEP_OUT)
    assert str(exc) == (
        "path from (10.00, 8.50) to (11.10, 6.50) takes the base's footprint into keep-out zone 'stairs': "
        "the robot could fall down the stairs"
    )
    assert exc.values == {"x": pytest.approx(11.1), "y": pytest.approx(6.5)}


# keep_out with the arm out: the zones grown by how far the hand sticks out, when beyond the footprint


@pytest.mark.parametrize("reach", [RADIUS + 0.2, 0.85])
def test_with_the_hand_out_a_goal_its_reach_away_from_the_stairs_passes_and_closer_is_refused(
    policy: SafetyPolicy, reach: float
) -> None:
    start = Pose2D(x=8.5, y=STAIRS_MID_Y)
    clear = NavigateToPoseGoal(pose=Pose2D(x=STAIRS_WEST - reach - EPS, y=STAIRS_MID_Y))
    verdict = policy.check_navigation(clear, start, reach)
    assert verdict.command.pose == clear.pose
    assert verdict.values["reach_m"] == reach
    close = Pose2D(x=STAIRS_WEST - reach + EPS, y=STAIRS_MID_Y)
    assert policy.check_navigation(NavigateToPoseGoal(pose=close), start).command.pose == close, "clear of the base"
    exc = refused(lambda: policy.check_navigation(NavigateToPoseGoal(pose=close), start, reach), Rule.KEEP_OUT)
    assert str(exc) == (
        f"at the goal ({close.x:.2f}, {close.y:.2f}) the hand ({reach:.2f} m from the base's centre) would be in "
        "keep-out zone 'stairs': the robot could fall down the stairs"
    )
    assert exc.values == {"x": pytest.approx(close.x), "y": pytest.approx(close.y)}


@pytest.mark.parametrize("reach", [0.1, RADIUS], ids=["tucked", "at-the-footprint"])
def test_a_hand_within_the_footprint_changes_nothing(policy: SafetyPolicy, reach: float) -> None:
    start = Pose2D(x=9.0, y=STAIRS_MID_Y)
    clear = NavigateToPoseGoal(pose=Pose2D(x=STAIRS_WEST - RADIUS - EPS, y=STAIRS_MID_Y))
    assert policy.check_navigation(clear, start, reach).values["reach_m"] == reach
    close = NavigateToPoseGoal(pose=Pose2D(x=STAIRS_WEST - RADIUS + EPS, y=STAIRS_MID_Y))
    exc = refused(lambda: policy.check_navigation(close, start, reach), Rule.KEEP_OUT)
    assert "the base's footprint would be in keep-out zone 'stairs'" in str(exc)


def test_a_leg_that_takes_the_hand_into_the_stairs_is_refused_naming_the_hand(limits: Limits, arm: ArmModel) -> None:
    # Without walls: turning by the hallway's north wall, the hand out would reach it (obstacle, below).
    policy = tightened(limits, arm, OPEN_FLOOR)
    reach = (RADIUS + CORNER_GAP) / 2  # beyond the footprint, short of every point's gap
    around = msgspec.structs.replace(CORNER_GOAL, path=[Pose2D(x=9.5, y=8.5), Pose2D(x=9.5, y=6.5)])
    assert policy.check_navigation(around, CORNER_START, reach)
    exc = refused(lambda: policy.check_navigation(CORNER_GOAL, CORNER_START, reach), Rule.KEEP_OUT)
    assert str(exc) == (
        f"path from (10.00, 8.50) to (11.10, 6.50) takes the hand ({reach:.2f} m from the base's centre) into "
        "keep-out zone 'stairs': the robot could fall down the stairs"
    )
    # Reaching as far as the points' gap, the pre-goal point is refused first.
    exc = refused(lambda: policy.check_navigation(around, CORNER_START, CORNER_GAP + EPS), Rule.KEEP_OUT)
    assert str(exc).startswith("at the route point (11.10, 6.50) the hand (0.50 m from the base's centre) would be in")


def test_the_footprint_margin_grows_the_zones_further(limits: Limits, arm: ArmModel) -> None:
    margin = 0.2
    wider = tightened(limits, arm, base=msgspec.structs.replace(limits.policy.base, footprint_margin=margin))
    start = Pose2D(x=9.0, y=STAIRS_MID_Y)
    clear = NavigateToPoseGoal(pose=Pose2D(x=STAIRS_WEST - RADIUS - margin - EPS, y=STAIRS_MID_Y))
    assert wider.check_navigation(clear, start).command.pose == clear.pose
    for d in (RADIUS + margin - EPS, RADIUS + EPS):  # the second passes with no margin (above)
        with pytest.raises(Vetoed) as info:
            wider.check_navigation(NavigateToPoseGoal(pose=Pose2D(x=STAIRS_WEST - d, y=STAIRS_MID_Y)), start)
        assert info.value.rule is Rule.KEEP_OUT


# obstacle: the footprint, driving the route as the sim does, touches no wall or furniture

COUNTER = next(f for f in WORLD.furniture if f.id == "kitchen_counter")
COUNTER_FRONT = COUNTER.center[1] + COUNTER.size.y / 2  # 0.7: the counter's edge facing the kitchen
HALF_LENGTH = ROBOT.base_size.x / 2
FACING_COUNTER = -math.pi / 2


def test_a_goal_parked_a_tracking_tolerance_from_the_counter_passes_and_closer_is_refused(
    policy: SafetyPolicy,
) -> None:
    start = Pose2D(x=2.5, y=2.5, yaw=FACING_COUNTER)  # drives straight in, no turning
    keep = TRACKING_TOLERANCE  # the sim keeps within it of the route: safety keeps the route that far clear
    clear = NavigateToPoseGoal(pose=Pose2D(x=2.5, y=COUNTER_FRONT + HALF_LENGTH + keep + EPS, yaw=FACING_COUNTER))
    assert policy.check_navigation(clear, start).command.pose == clear.pose
    close = Pose2D(x=2.5, y=COUNTER_FRONT + HALF_LENGTH + keep - EPS, yaw=FACING_COUNTER)
    exc = refused(lambda: policy.check_navigation(NavigateToPoseGoal(pose=close), start), Rule.OBSTACLE)
    assert str(exc) == (
        f"driving from (2.50, {close.y + 0.4:.2f}) to (2.50, {close.y:.2f}) the base would come 2.9 cm from the "
        "kitchen counter (it keeps 3 cm); plan a path around it"
    )
    assert exc.values == {"x": 2.5, "y": pytest.approx(close.y)}
    inside = Pose2D(x=2.5, y=COUNTER_FRONT + HALF_LENGTH - EPS, yaw=FACING_COUNTER)
    exc = refused(lambda: policy.check_navigation(NavigateToPoseGoal(pose=inside), start), Rule.OBSTACLE)
    assert "the base would hit the kitchen counter" in str(exc)
    # A plan may not send the base there either.
    plan = GroundedPlan(steps=[NavigateStep(target="counter", goal=close)], source=SOURCE)
    exc = refused(lambda: policy.check_plan(plan, start), Rule.OBSTACLE)
    assert str(exc) == (
        f"step 1 (navigate_to): at the goal (2.50, {close.y:.2f}) the base would stand 3 cm from the kitchen counter "
        "(it keeps 3 cm)"
    )
    assert policy.check_plan(
        GroundedPlan(steps=[NavigateStep(target="counter", goal=clear.pose)], source=SOURCE), start
    )


def test_a_base_parked_closer_than_that_may_still_leave_but_never_get_closer(policy: SafetyPolicy) -> None:
    parked = Pose2D(x=2.5, y=COUNTER_FRONT + HALF_LENGTH + 0.01, yaw=FACING_COUNTER)  # 1 cm from the counter
    away = NavigateToPoseGoal(pose=Pose2D(x=2.5, y=parked.y + 0.3, yaw=FACING_COUNTER))  # backs straight out
    assert policy.check_navigation(away, parked).command.pose == away.pose
    nearer = NavigateToPoseGoal(pose=Pose2D(x=2.5, y=parked.y - 0.005, yaw=FACING_COUNTER))  # 5 mm in
    exc = refused(lambda: policy.check_navigation(nearer, parked), Rule.OBSTACLE)
    assert str(exc) == (
        "driving from (2.50, 1.01) to (2.50, 1.01) the base would come 0.5 cm from the kitchen counter, closer than "
        "it starts; plan a path around it"
    )


def test_parked_at_the_counter_the_base_backs_away_before_turning_round(policy: SafetyPolicy) -> None:
    parked = COUNTER.approach  # 5 cm from the counter: the corners, 0.39 m out, would hit it turning
    goal = Pose2D(x=2.5, y=2.5, yaw=math.pi / 2)
    backing = NavigateToPoseGoal(pose=goal, path=[Pose2D(x=2.5, y=parked.y + MAX_REVERSE)])
    assert policy.check_navigation(backing, parked).command.path == backing.path
    exc = refused(lambda: policy.check_navigation(NavigateToPoseGoal(pose=goal), parked), Rule.OBSTACLE)
    assert str(exc) == "turning at (2.50, 1.05) the base would hit the kitchen counter; plan a path around it"


def test_a_leg_through_a_wall_is_refused_and_through_the_doorway_passes(policy: SafetyPolicy) -> None:
    kitchen = Pose2D(x=4.0, y=2.1, yaw=math.pi)
    exc = refused(lambda: policy.check_navigation(NavigateToPoseGoal(pose=kitchen), START), Rule.OBSTACLE)
    assert str(exc).startswith("driving from (6.00, 1.20) to (4.40, 2.10) the base would hit the wall between")
    doorway = NavigateToPoseGoal(pose=kitchen, path=[Pose2D(x=5.8, y=2.1)])
    assert policy.check_navigation(doorway, START).command.path == doorway.path


# base_speed


def test_a_navigation_speed_at_the_limit_passes_and_just_over_is_refused(policy: SafetyPolicy) -> None:
    limit = policy.max_linear
    at = NavigateToPoseGoal(pose=COFFEE_TABLE, max_speed=limit)
    assert policy.check_navigation(at, START).command.max_speed == limit
    over = msgspec.structs.replace(at, max_speed=limit + EPS)
    exc = refused(lambda: policy.check_navigation(over, START), Rule.BASE_SPEED)
    assert_names(str(exc), limit + EPS, limit)
    assert exc.values == {"speed_mps": limit + EPS, "limit_mps": limit}


def test_a_navigation_turn_rate_at_the_limit_passes_and_just_over_is_refused(policy: SafetyPolicy) -> None:
    limit = policy.max_angular
    at = NavigateToPoseGoal(pose=COFFEE_TABLE, max_turn_rate=limit)
    verdict = policy.check_navigation(at, START)
    assert verdict.command.max_turn_rate == limit
    assert verdict.values["turn_rps"] == limit
    over = msgspec.structs.replace(at, max_turn_rate=limit + EPS)
    exc = refused(lambda: policy.check_navigation(over, START), Rule.BASE_SPEED)
    assert str(exc).startswith("a turn rate of ")
    assert_names(str(exc), limit + EPS, limit)
    assert exc.values == {"turn_rps": limit + EPS, "limit_rps": limit}


def test_navigation_gets_the_limits_filled_in_when_it_asks_for_no_speed_or_turn_rate(policy: SafetyPolicy) -> None:
    goal = NavigateToPoseGoal(pose=COFFEE_TABLE)
    verdict = policy.check_navigation(goal, START)
    # Filled in, with the start the route was checked from: the robot drives the legs that start gives.
    assert verdict.command == msgspec.structs.replace(
        goal, max_speed=policy.max_linear, max_turn_rate=policy.max_angular, start=START
    )
    assert verdict.checks == (Rule.POSE_KNOWN, Rule.MAP, Rule.KEEP_OUT, Rule.OBSTACLE, Rule.BASE_SPEED)
    assert verdict.values == {
        "x": COFFEE_TABLE.x,
        "y": COFFEE_TABLE.y,
        "speed_mps": policy.max_linear,
        "limit_mps": policy.max_linear,
        "limit_rps": policy.max_angular,
        "turn_rps": policy.max_angular,
        "reach_m": 0.0,
    }
    # What was asked for, within the limits, is kept: one filled in leaves the other alone.
    slower = msgspec.structs.replace(goal, max_speed=0.1, max_turn_rate=0.2)
    assert policy.check_navigation(slower, START).command == msgspec.structs.replace(slower, start=START)
    only_speed = policy.check_navigation(msgspec.structs.replace(goal, max_speed=0.1), START).command
    assert (only_speed.max_speed, only_speed.max_turn_rate) == (0.1, policy.max_angular)
    only_turn = policy.check_navigation(msgspec.structs.replace(goal, max_turn_rate=0.2), START).command
    assert (only_turn.max_speed, only_turn.max_turn_rate) == (policy.max_linear, 0.2)


@pytest.mark.parametrize(("field", "sign"), [("linear_x", 1), ("linear_x", -1), ("angular_z", 1), ("angular_z", -1)])
def test_cmd_vel_at_the_limit_passes_and_just_over_is_refused(policy: SafetyPolicy, field: str, sign: int) -> None:
    limit = policy.max_linear if field == "linear_x" else policy.max_angular
    at = Twist(**{field: sign * limit})
    assert policy.check_cmd_vel(at, START).command == at
    over = Twist(**{field: sign * (limit + EPS)})
    exc = refused(lambda: policy.check_cmd_vel(over, START), Rule.BASE_SPEED)
    assert field in str(exc)
    assert_names(str(exc), sign * (limit + EPS), limit)
    measured, bound = ("speed_mps", "limit_mps") if field == "linear_x" else ("turn_rps", "limit_rps")
    assert exc.values == {measured: sign * (limit + EPS), bound: limit}


def test_a_cmd_vel_near_a_person_passes_with_a_note_of_the_speed_the_robot_keeps_to(policy: SafetyPolicy) -> None:
    twist = Twist(linear_x=policy.max_linear, angular_z=-policy.max_angular)
    full = policy.check_cmd_vel(twist, START)
    assert full.command == twist and full.clamped_by is None and full.note == ""
    assert full.checks == (Rule.BASE_SPEED, Rule.CMD_VEL_HORIZON, Rule.HUMAN_SEPARATION)
    assert full.values == {"speed_mps": policy.max_linear, "turn_rps": -policy.max_angular, "scale": 1.0}
    # Just under full scale the note is there; the command is not changed (the robot keeps to the lower speed).
    for scale in (1.0 - EPS, policy.policy.humans.reduced_speed_scale, 0.0):
        near = policy.check_cmd_vel(twist, START, scale)
        assert near.command == twist and near.clamped_by is None
        assert near.values["scale"] == scale
        assert near.note == (
            f"a person is near: the robot moves at most {policy.max_linear * scale:.2f} m/s and "
            f"{policy.max_angular * scale:.2f} rad/s for now"
        )
    # Over the full limit it is still refused, near a person or not.
    over = Twist(linear_x=policy.max_linear + EPS)
    refused(lambda: policy.check_cmd_vel(over, START, policy.policy.humans.reduced_speed_scale), Rule.BASE_SPEED)


def test_a_plan_asking_for_a_speed_just_over_the_limit_is_refused(policy: SafetyPolicy) -> None:
    limit = policy.max_linear
    step = NavigateStep(target="coffee table", goal=COFFEE_TABLE, max_speed=limit)
    assert policy.check_plan(GroundedPlan(steps=[step], source=SOURCE), START)
    faster = msgspec.structs.replace(step, max_speed=limit + EPS)
    exc = refused(lambda: policy.check_plan(GroundedPlan(steps=[faster], source=SOURCE), START), Rule.BASE_SPEED)
    assert str(exc).startswith("step 1 (navigate_to): ")
    assert_names(str(exc), limit + EPS, limit)
    assert exc.values == {"speed_mps": limit + EPS, "limit_mps": limit}


# base_acceleration (teleop: clamped, not refused)


def test_teleop_speeding_up_within_the_acceleration_limit_is_sent_unchanged_and_beyond_is_ramped(
    policy: SafetyPolicy,
) -> None:
    base = policy.policy.base
    dt = 0.1
    before = Twist(linear_x=0.2)
    reachable = 0.2 + base.max_linear_acceleration * dt  # 0.35 m/s
    within = policy.check_teleop(Twist(linear_x=reachable), START, before, dt)
    assert within.clamped_by is None and within.command.linear_x == reachable
    ramped = policy.check_teleop(Twist(linear_x=reachable + EPS), START, before, dt)
    assert ramped.clamped_by is Rule.BASE_ACCELERATION
    assert ramped.command.linear_x == pytest.approx(reachable)
    assert ramped.values["requested_mps"] == reachable + EPS
    assert ramped.values["speed_mps"] == pytest.approx(reachable)
    assert f"acceleration limit {base.max_linear_acceleration:g} m/s^2" in ramped.note
    # Turning: from standing, max_angular_acceleration * dt.
    turn = base.max_angular_acceleration * dt  # 0.3 rad/s
    assert policy.check_teleop(Twist(angular_z=-turn), START, Twist(), dt).clamped_by is None
    turning = policy.check_teleop(Twist(angular_z=-turn - EPS), START, Twist(), dt)
    assert turning.clamped_by is Rule.BASE_ACCELERATION
    assert turning.command.angular_z == pytest.approx(-turn)


@pytest.mark.parametrize(
    ("previous", "wanted"),
    [
        (0.6, 0.0),  # a stop
        (0.6, 0.05),  # slowing down
        (-0.6, -0.1),  # slowing down in reverse
        (0.3, 0.0),  # reversing... to a stop
    ],
)
def test_teleop_slowing_down_is_never_limited(policy: SafetyPolicy, previous: float, wanted: float) -> None:
    verdict = policy.check_teleop(Twist(linear_x=wanted), START, Twist(linear_x=previous), 0.001)
    assert verdict.clamped_by is None
    assert verdict.command.linear_x == wanted


def test_teleop_reversing_brakes_freely_then_ramps_the_other_way(policy: SafetyPolicy) -> None:
    dt = 0.1
    step = policy.policy.base.max_linear_acceleration * dt
    forward = Twist(linear_x=0.3)
    assert policy.check_teleop(Twist(linear_x=-step), START, forward, dt).clamped_by is None
    back = policy.check_teleop(Twist(linear_x=-step - EPS), START, forward, dt)
    assert back.clamped_by is Rule.BASE_ACCELERATION
    assert back.command.linear_x == pytest.approx(-step)


def test_teleop_with_no_time_elapsed_or_a_clock_going_back_gets_no_acceleration(policy: SafetyPolicy) -> None:
    for dt in (0.0, -1.0):
        verdict = policy.check_teleop(Twist(linear_x=0.1), START, Twist(), dt)
        assert verdict.clamped_by is Rule.BASE_ACCELERATION
        assert verdict.command.linear_x == 0.0


# human_separation in teleop: the speed limit times the separation scale


def test_teleop_near_a_person_is_clamped_to_the_reduced_speed(policy: SafetyPolicy) -> None:
    scale = policy.policy.humans.reduced_speed_scale
    v = policy.max_linear * scale
    running = Twist(linear_x=v)  # no acceleration involved
    assert policy.check_teleop(Twist(linear_x=v), START, running, 0.1, scale).clamped_by is None
    slowed = policy.check_teleop(Twist(linear_x=v + EPS), START, running, 0.1, scale)
    assert slowed.clamped_by is Rule.HUMAN_SEPARATION
    assert slowed.command.linear_x == pytest.approx(v)
    assert slowed.values["scale"] == scale
    # Full scale: the same kind of clamp is the base's own speed limit.
    full = policy.check_teleop(Twist(linear_x=policy.max_linear + EPS), START, Twist(linear_x=policy.max_linear), 0.1)
    assert full.clamped_by is Rule.BASE_SPEED
    # Paused: nothing moves, but a stop is not a clamp.
    paused = policy.check_teleop(Twist(linear_x=EPS, angular_z=EPS), START, Twist(), 0.1, 0.0)
    assert paused.clamped_by is Rule.HUMAN_SEPARATION
    assert (paused.command.linear_x, paused.command.angular_z) == (0.0, 0.0)
    assert policy.check_teleop(Twist(), START, running, 0.1, 0.0).clamped_by is None


# cmd_vel_horizon


def facing_stairs(gap: float, yaw: float = 0.0) -> Pose2D:
    """The base `gap` metres short of where its footprint would touch the stairs (from the west)."""
    return Pose2D(x=STAIRS_WEST - RADIUS - gap, y=STAIRS_MID_Y, yaw=yaw)


@pytest.mark.parametrize(("yaw", "sign"), [(0.0, 1), (math.pi, -1)], ids=["forward", "reversing"])
def test_a_cmd_vel_that_stops_short_of_the_stairs_within_the_horizon_passes(
    policy: SafetyPolicy, yaw: float, sign: int
) -> None:
    horizon = policy.policy.base.cmd_vel_horizon
    gap = 0.5
    pose = facing_stairs(gap, yaw)
    short = Twist(linear_x=sign * (gap - EPS) / horizon)
    assert policy.check_cmd_vel(short, pose).command == short
    reaching = Twist(linear_x=sign * (gap + EPS) / horizon)
    exc = refused(lambda: policy.check_cmd_vel(reaching, pose), Rule.CMD_VEL_HORIZON)
    assert f"would enter keep-out zone 'stairs' within {horizon:g} s" in str(exc)
    assert exc.values == {
        "x": pytest.approx(pose.x + sign * math.cos(yaw) * (gap + EPS)),
        "y": pytest.approx(STAIRS_MID_Y),
        "speed_mps": reaching.linear_x,
        "horizon_s": horizon,
    }


def test_a_cmd_vel_that_would_leave_the_map_within_the_horizon_is_refused(policy: SafetyPolicy) -> None:
    horizon = policy.policy.base.cmd_vel_horizon
    pose = Pose2D(x=MAP_WEST + 0.5, y=2.5, yaw=math.pi)  # in the kitchen, facing its west wall
    assert policy.check_cmd_vel(Twist(linear_x=(0.5 - EPS) / horizon), pose)
    exc = refused(lambda: policy.check_cmd_vel(Twist(linear_x=(0.5 + EPS) / horizon), pose), Rule.CMD_VEL_HORIZON)
    assert f"would leave the map within {horizon:g} s" in str(exc)
    assert exc.values["x"] == pytest.approx(MAP_WEST - EPS)


def test_teleop_is_refused_by_the_horizon_only_when_even_the_clamped_command_reaches_the_stairs(
    policy: SafetyPolicy,
) -> None:
    horizon = policy.policy.base.cmd_vel_horizon
    pose = facing_stairs(0.5)
    # Asked for full speed from 0.2 m/s, ramped to 0.35 m/s: short of the zone.
    ramped = policy.check_teleop(Twist(linear_x=0.6), pose, Twist(linear_x=0.2), 0.1)
    assert ramped.clamped_by is Rule.BASE_ACCELERATION
    running = Twist(linear_x=(0.5 + EPS) / horizon)
    refused(lambda: policy.check_teleop(running, pose, running, 0.1), Rule.CMD_VEL_HORIZON)


# joint_limits


JOINT_CASES = [(name, side) for name in ARM for side in ("lower", "upper")]


@pytest.mark.parametrize(("name", "side"), JOINT_CASES, ids=[f"{n}-{s}" for n, s in JOINT_CASES])
def test_a_joint_just_inside_its_limit_passes_and_just_outside_is_refused(
    policy: SafetyPolicy, name: str, side: str
) -> None:
    limit = policy.joint_limits[name]
    sign = 1 if side == "upper" else -1
    bound = (limit.upper if side == "upper" else limit.lower) - sign * JOINT_LIMIT_MARGIN
    rest = list(HOME)
    if (name, side) == ("panda_joint4", "upper"):
        rest[1] = 0.0  # stretched from HOME, the hand would be behind the workspace
    inside = with_joint(rest, name, bound - sign * EPS)
    now = dict(zip(ARM, inside, strict=True))
    assert policy.check_trajectory(trajectory((inside, 1.0)), now, START)
    outside = bound + sign * EPS
    goal = trajectory((with_joint(rest, name, outside), 1.0))
    exc = refused(lambda: policy.check_trajectory(goal, now, START), Rule.JOINT_LIMITS)
    assert f"{name} = {outside:.4f} rad" in str(exc)
    in_force = {"lower_rad": limit.lower + JOINT_LIMIT_MARGIN, "upper_rad": limit.upper - JOINT_LIMIT_MARGIN}
    assert exc.values == {"position_rad": pytest.approx(outside), **{k: pytest.approx(v) for k, v in in_force.items()}}


def test_a_joint_limit_refusal_names_the_limit_in_force(policy: SafetyPolicy) -> None:
    # The limit in force is the URDF's (or the policy's) less JOINT_LIMIT_MARGIN. A position between
    # the two is refused, and the refusal must say so: not "2.958 rad is outside [-2.967, 2.967]".
    limit = policy.joint_limits["panda_joint1"]
    in_force = limit.upper - JOINT_LIMIT_MARGIN
    outside = in_force + EPS
    goal = trajectory((with_joint(HOME, "panda_joint1", outside), 1.0))
    exc = refused(lambda: policy.check_trajectory(goal, NOW, START), Rule.JOINT_LIMITS)
    assert_names(str(exc), outside, in_force)
    low, high = exc.values["lower_rad"], exc.values["upper_rad"]
    assert not low <= exc.values["position_rad"] <= high, f"values say the position is within its limits: {exc.values}"


@pytest.mark.parametrize(
    ("goal", "why"),
    [
        (
            FollowJointTrajectoryGoal(
                joint_names=["panda_joint1", "panda_joint1"],
                points=[TrajectoryPoint(positions=[0.0, 0.0], time_from_start=1.0)],
            ),
            "named twice",
        ),
        (trajectory((HOME[:6], 1.0)), "6 positions for 7 joints"),
        (trajectory((with_joint(HOME, "panda_joint3", math.nan), 1.0)), "not finite"),
    ],
    ids=["twice", "short", "nan"],
)
def test_malformed_trajectories_are_refused(policy: SafetyPolicy, goal: FollowJointTrajectoryGoal, why: str) -> None:
    assert why in str(refused(lambda: policy.check_trajectory(goal, NOW, START), Rule.JOINT_LIMITS))


# joint_speed


def test_a_segment_at_the_joint_speed_limit_passes_and_just_over_is_refused(policy: SafetyPolicy) -> None:
    limit = policy.joint_limits["panda_joint1"].velocity  # the policy's max_joint_speed, 1.5 rad/s
    at = trajectory((with_joint(HOME, "panda_joint1", limit * 1.0), 1.0))
    assert policy.check_trajectory(at, NOW, START).values["fastest_rps"] == pytest.approx(limit)
    # The second segment, not just the first from where the arm is.
    over = trajectory(
        (with_joint(HOME, "panda_joint1", 0.5), 1.0), (with_joint(HOME, "panda_joint1", 0.5 + limit + 2 * EPS), 2.0)
    )
    exc = refused(lambda: policy.check_trajectory(over, NOW, START), Rule.JOINT_SPEED)
    assert str(exc).startswith("point 1: panda_joint1 ")
    assert exc.values == {"speed_rps": pytest.approx(limit + 2 * EPS), "limit_rps": limit}


def test_a_joint_speed_refusal_tells_the_speed_from_the_limit(policy: SafetyPolicy) -> None:
    # At 1.502 rad/s against 1.5, the message must not read "1.50 rad/s, over its limit of 1.50 rad/s".
    limit = policy.joint_limits["panda_joint1"].velocity
    over = trajectory((with_joint(HOME, "panda_joint1", limit + 2 * EPS), 1.0))
    exc = refused(lambda: policy.check_trajectory(over, NOW, START), Rule.JOINT_SPEED)
    assert_names(str(exc), limit + 2 * EPS, limit)


def test_a_first_point_at_time_zero_may_differ_from_the_measured_position_only_a_little(policy: SafetyPolicy) -> None:
    later = with_joint(HOME, "panda_joint1", 0.5)
    near = trajectory((with_joint(HOME, "panda_joint1", START_TOLERANCE - EPS), 0.0), (later, 2.0))
    assert policy.check_trajectory(near, NOW, START)
    jump = trajectory((with_joint(HOME, "panda_joint1", START_TOLERANCE + EPS), 0.0), (later, 2.0))
    exc = refused(lambda: policy.check_trajectory(jump, NOW, START), Rule.JOINT_SPEED)
    assert exc.values == {"jump_rad": pytest.approx(START_TOLERANCE + EPS)}
    assert str(exc) == f"point 0: panda_joint1 would jump {START_TOLERANCE + EPS:.3f} rad at once"
    backwards = trajectory((later, 2.0), (HOME, 1.0))
    exc = refused(lambda: policy.check_trajectory(backwards, NOW, START), Rule.JOINT_SPEED)
    assert str(exc) == "point 1: time_from_start 1 s does not increase from 2 s"


@pytest.mark.parametrize("start", [0.0, 1.0], ids=["at-zero", "later"])
def test_after_the_first_point_each_time_must_increase_so_small_steps_cannot_add_up_to_a_jump(
    policy: SafetyPolicy, start: float
) -> None:
    limit = policy.joint_limits["panda_joint1"].velocity
    step = START_TOLERANCE - EPS  # each point within the start tolerance of the one before
    points = [with_joint(HOME, "panda_joint1", k * step) for k in range(1, 5)]  # 0.196 rad in all
    # Spread out at the joint speed limit, the same points pass; each step a hair apart in time too.
    spread = trajectory(*((q, start + k * step / limit) for k, q in enumerate(points)))
    assert policy.check_trajectory(spread, NOW, START).values["fastest_rps"] == pytest.approx(limit)
    still = trajectory((points[0], start), (points[0], start + EPS))
    assert policy.check_trajectory(still, NOW, START)
    # All at one time: the second point is refused, however small its step.
    at_once = trajectory(*((q, start) for q in points))
    exc = refused(lambda: policy.check_trajectory(at_once, NOW, START), Rule.JOINT_SPEED)
    assert str(exc) == f"point 1: time_from_start {start:g} s does not increase from {start:g} s"
    same = trajectory((points[0], start), (points[0], start))
    refused(lambda: policy.check_trajectory(same, NOW, START), Rule.JOINT_SPEED)


# base_still


def test_a_trajectory_passes_while_the_base_stands_still_and_is_refused_while_it_moves(policy: SafetyPolicy) -> None:
    goal = trajectory((with_joint(HOME, "panda_joint1", 0.5), 1.0))
    verdict = policy.check_trajectory(goal, NOW, START, base_moving=False)
    assert verdict.command == goal
    assert Rule.BASE_STILL in verdict.checks
    exc = refused(lambda: policy.check_trajectory(goal, NOW, START, base_moving=True), Rule.BASE_STILL)
    assert str(exc) == "the base is moving: the arm moves only while the base stands still"
    assert exc.values == {}


# workspace


AXES = [(axis, side) for axis in "xyz" for side in ("min", "max")]


@pytest.mark.parametrize(("axis", "side"), AXES, ids=[f"{a}-{s}" for a, s in AXES])
def test_a_point_just_inside_the_workspace_box_passes_and_just_outside_is_refused(
    policy: SafetyPolicy, axis: str, side: str
) -> None:
    box = policy.policy.workspace
    low, high = getattr(box.min, axis), getattr(box.max, axis)
    bound = high if side == "max" else low
    sign = 1 if side == "max" else -1
    centre = {a: (getattr(box.min, a) + getattr(box.max, a)) / 2 for a in "xyz"}
    policy.check_in_workspace(**{**centre, axis: bound - sign * EPS}, what="the hand")
    exc = refused(
        lambda: policy.check_in_workspace(**{**centre, axis: bound + sign * EPS}, what="the hand"), Rule.WORKSPACE
    )
    assert str(exc).startswith(f"the hand would be at {axis} = ")
    assert_names(str(exc), bound + sign * EPS, bound)
    assert exc.values == {f"{axis}_m": pytest.approx(bound + sign * EPS), "low_m": low, "high_m": high}


@pytest.mark.parametrize(("axis", "side"), [("x", "max"), ("y", "max"), ("y", "min"), ("z", "min")])
def test_reach_is_measured_in_the_frame_of_the_base_at_its_approach_pose(
    policy: SafetyPolicy, axis: str, side: str
) -> None:
    box = policy.policy.workspace
    approach = Pose2D(x=2.0, y=2.0, yaw=math.pi / 2)  # facing north: base x is map +y, base y is map -x
    bound = getattr(getattr(box, side), axis)
    sign = 1 if side == "max" else -1
    base_frame = {"x": 0.5, "y": 0.0, "z": 0.8}

    def spot(offset: float) -> Vec3:
        p = {**base_frame, axis: bound + sign * offset}
        return Vec3(x=approach.x - p["y"], y=approach.y + p["x"], z=p["z"])

    policy.check_reach(approach, spot(-EPS), "the cup")
    exc = refused(lambda: policy.check_reach(approach, spot(EPS), "the cup"), Rule.WORKSPACE)
    assert exc.values[f"{axis}_m"] == pytest.approx(bound + sign * EPS)


def _lowest_q(arm: ArmModel, z: float) -> list[float]:
    """The arm reaching forward and down, its grasp point at height `z` above the floor (bisection on
    panda_joint2, which lowers the hand monotonically here)."""
    mount = ROBOT.arm_mount.z
    lo, hi = 1.2, 1.7
    for _ in range(60):
        mid = (lo + hi) / 2
        q = [0.0, mid, 0.0, -1.5, 0.0, 1.5, 0.785]
        if arm.grasp_point(q)[2] + mount > z:
            lo = mid
        else:
            hi = mid
    return [0.0, (lo + hi) / 2, 0.0, -1.5, 0.0, 1.5, 0.785]


def test_a_trajectory_whose_hand_ends_just_above_the_floor_of_the_workspace_passes_and_just_below_is_refused(
    policy: SafetyPolicy, arm: ArmModel
) -> None:
    floor = policy.policy.workspace.min.z
    above, below = _lowest_q(arm, floor + EPS), _lowest_q(arm, floor - EPS)
    now = dict(zip(ARM, above, strict=True))
    verdict = policy.check_trajectory(trajectory((above, 1.0)), now, START)
    assert verdict.values["lowest_m"] == pytest.approx(floor + EPS)
    exc = refused(lambda: policy.check_trajectory(trajectory((below, 1.0)), now, START), Rule.WORKSPACE)
    assert str(exc).startswith("the end effector would be at z = ")
    assert_names(str(exc), floor - EPS, floor)
    assert exc.values["z_m"] == pytest.approx(floor - EPS)


def test_a_trajectory_whose_hand_dips_out_of_the_workspace_between_its_points_is_refused(
    policy: SafetyPolicy, arm: ArmModel
) -> None:
    a = [-0.45, 1.76, 2.14, -1.6, -2.41, 2.84, 2.61]
    b = [0.39, 1.18, -2.18, -1.08, 0.24, 2.61, 2.45]
    mount = np.array([ROBOT.arm_mount.x, ROBOT.arm_mount.y, ROBOT.arm_mount.z])
    floor = policy.policy.workspace.min.z
    # Both ends well inside the box; half way the hand is below its floor.
    for q in (a, b):
        x, y, z = arm.grasp_point(q) + mount
        policy.check_in_workspace(float(x), float(y), float(z), "an end")
    assert (arm.grasp_point((np.array(a) + b) / 2) + mount)[2] < floor - 0.05
    exc = refused(
        lambda: policy.check_trajectory(trajectory((b, 10.0)), dict(zip(ARM, a, strict=True)), START), Rule.WORKSPACE
    )
    assert exc.values["z_m"] < floor


# arm_keep_out


def test_reaching_just_short_of_the_stairs_passes_and_just_over_them_is_refused(policy: SafetyPolicy) -> None:
    approach = facing_stairs(0.01)  # parked just clear of the (grown) zone, facing it
    policy.check_reach(approach, Vec3(x=STAIRS_WEST - EPS, y=STAIRS_MID_Y, z=0.8), "the cup")
    over = Vec3(x=STAIRS_WEST + EPS, y=STAIRS_MID_Y, z=0.8)  # the zone itself, not grown
    exc = refused(lambda: policy.check_reach(approach, over, "the cup"), Rule.ARM_KEEP_OUT)
    assert str(exc).startswith("the cup at (10.50, 8.00) is inside keep-out zone 'stairs'")


def test_a_reach_into_a_keep_out_zone_is_refused_with_where(policy: SafetyPolicy) -> None:
    # As check_trajectory's ARM_KEEP_OUT refusals carry x and y, so must check_reach's.
    over = Vec3(x=STAIRS_WEST + EPS, y=STAIRS_MID_Y, z=0.8)
    exc = refused(lambda: policy.check_reach(facing_stairs(0.01), over, "the cup"), Rule.ARM_KEEP_OUT)
    assert exc.values == {"x": pytest.approx(over.x), "y": pytest.approx(over.y)}


REACH = [0.0, 0.5, 0.0, -1.5, 0.0, 2.0, 0.785]  # hand forward, about 0.85 m ahead of the base centre


def test_a_trajectory_reaching_just_short_of_the_stairs_passes_and_just_over_is_refused(policy: SafetyPolicy) -> None:
    goal = trajectory((REACH, 5.0))
    farthest = policy.check_trajectory(goal, NOW, START).values["farthest_m"]
    assert farthest > 0.7
    short = Pose2D(x=STAIRS_WEST - farthest - EPS, y=STAIRS_MID_Y)
    assert policy.check_trajectory(goal, NOW, short).command == goal
    over = Pose2D(x=STAIRS_WEST - farthest + EPS, y=STAIRS_MID_Y)
    exc = refused(lambda: policy.check_trajectory(goal, NOW, over), Rule.ARM_KEEP_OUT)
    assert "reach into keep-out zone 'stairs'" in str(exc)
    assert exc.values == {"x": pytest.approx(STAIRS_WEST + EPS), "y": pytest.approx(STAIRS_MID_Y, abs=1e-6)}


def random_trajectory(rng: np.random.Generator, policy: SafetyPolicy) -> tuple[FollowJointTrajectoryGoal, Pose2D]:
    """A trajectory of 1 to 30 points from NOW over all the arm's joints or some of them in any order,
    some to a random configuration in the limits (the hand in or out of the workspace), some wandering
    (a joint over its limit or its speed now and then, a time repeated or going back); some start with
    a point at time 0 where the arm is. From a spot near the stairs or in the open, facing any way."""
    names = list(ARM) if rng.random() < 0.7 else [ARM[i] for i in rng.permutation(7)[: int(rng.integers(1, 8))]]
    n = int(rng.integers(1, 31))
    q = np.array([NOW[name] for name in names])
    if rng.random() < 0.5:
        lower = np.array([policy.joint_limits[name].lower for name in names]) + 0.02
        upper = np.array([policy.joint_limits[name].upper for name in names]) - 0.02
        target = rng.uniform(lower, upper)
        rows = [q + (target - q) * k / n for k in range(1, n + 1)]
        times = np.cumsum(rng.uniform(3.0, 6.0, n))
    else:
        rows = list(q + np.cumsum(rng.normal(0.0, rng.choice([0.05, 0.3]), (n, len(names))), axis=0))
        times = np.cumsum(rng.choice([-0.1, 0.0, 0.2, 1.0], n, p=[0.02, 0.03, 0.25, 0.7]))
    if rng.random() < 0.3:  # first where the arm is, at time 0
        rows, times = [q + rng.normal(0.0, 0.02, len(names)), *rows], np.concatenate(([0.0], times))
    yaw = float(rng.uniform(-math.pi, math.pi))
    spot = (START.x, START.y) if rng.random() < 0.5 else (STAIRS_WEST - rng.uniform(0.2, 1.2), STAIRS_MID_Y)
    goal = FollowJointTrajectoryGoal(
        joint_names=names,
        points=[
            TrajectoryPoint(positions=list(row), time_from_start=float(t)) for row, t in zip(rows, times, strict=True)
        ],
    )
    return goal, Pose2D(x=spot[0], y=spot[1], yaw=yaw)


def decision(
    policy: SafetyPolicy, goal: FollowJointTrajectoryGoal, base: Pose2D, now: dict[str, float] = NOW
) -> tuple[object, ...]:
    """check_trajectory's verdict or refusal, as values to compare (the arm standing at `now`)."""
    try:
        verdict = policy.check_trajectory(goal, now, base)
    except Vetoed as exc:
        return ("vetoed", str(exc), exc.rule, exc.values)
    return ("approved", verdict.values)


def test_a_long_trajectory_checked_all_at_once_is_decided_as_point_by_point(
    policy: SafetyPolicy, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Past FEW_POINTS points (FEW_ARM_POINTS hand positions), the checks run on all of them at once and
    # point by point only to name the first that fails: the same decisions, messages and values.
    rng = np.random.default_rng(21)
    cases = [random_trajectory(rng, policy) for _ in range(300)]
    monkeypatch.setattr(policy_module, "FEW_POINTS", 0)  # all at once, whatever the thresholds
    monkeypatch.setattr(policy_module, "FEW_ARM_POINTS", 0)
    at_once = [decision(policy, goal, base) for goal, base in cases]
    monkeypatch.setattr(policy_module, "FEW_POINTS", 10**9)
    monkeypatch.setattr(policy_module, "FEW_ARM_POINTS", 10**9)
    assert [decision(policy, goal, base) for goal, base in cases] == at_once
    rules = {d[2] for d in at_once if d[0] == "vetoed"}
    assert sum(d[0] == "approved" for d in at_once) > 50
    assert {Rule.JOINT_LIMITS, Rule.JOINT_SPEED, Rule.WORKSPACE, Rule.ARM_KEEP_OUT} <= rules, rules


# payload


BOOK = next(obj for obj in WORLD.objects if obj.id == "blue_book")


@pytest.mark.parametrize("offset", [EPS, 0.0])
def test_an_object_at_or_under_the_payload_passes(limits: Limits, arm: ArmModel, offset: float) -> None:
    payload = BOOK.mass + offset
    rules = tightened(limits, arm, payload=PayloadPolicy(max_mass=payload))
    verdict = rules.check_gripper(GripperCommandGoal(position=0.0, object_id=BOOK.id))
    assert verdict.values["mass_kg"] == BOOK.mass
    assert verdict.values["payload_kg"] == payload
    assert verdict.checks == (Rule.GRIPPER_FORCE, Rule.PAYLOAD)
    assert verdict.command.payload_limit == payload


def test_the_gripper_gets_the_payload_filled_in_as_its_limit_and_a_limit_over_it_is_refused(
    policy: SafetyPolicy,
) -> None:
    payload = policy.policy.payload.max_mass
    force = policy.policy.gripper.max_force
    # With no object named, the payload still applies: the robot lets anything heavier slip.
    verdict = policy.check_gripper(GripperCommandGoal(position=0.0))
    assert verdict.command == GripperCommandGoal(position=0.0, payload_limit=payload)
    assert verdict.checks == (Rule.GRIPPER_FORCE, Rule.PAYLOAD)
    assert verdict.values == {"force_n": 40.0, "limit_n": force, "payload_kg": payload}
    for limit in (payload, 0.5):  # at the payload, and lighter: kept as asked
        asked = GripperCommandGoal(position=0.0, payload_limit=limit)
        assert policy.check_gripper(asked).command == asked
    over = GripperCommandGoal(position=0.0, object_id="red_cup", payload_limit=payload + EPS)
    exc = refused(lambda: policy.check_gripper(over), Rule.PAYLOAD)
    assert str(exc).startswith("a payload limit of ")
    assert_names(str(exc), payload + EPS, payload)
    assert exc.values == {"mass_kg": payload + EPS, "payload_kg": payload}


def test_an_object_just_over_the_payload_is_refused_by_its_mass_in_the_world_file(
    limits: Limits, arm: ArmModel
) -> None:
    payload = BOOK.mass - EPS
    rules = tightened(limits, arm, payload=PayloadPolicy(max_mass=payload))
    exc = refused(lambda: rules.check_gripper(GripperCommandGoal(position=0.0, object_id=BOOK.id)), Rule.PAYLOAD)
    assert f"'{BOOK.name}'" in str(exc)
    assert_names(str(exc), BOOK.mass, payload)
    assert exc.values == {"mass_kg": BOOK.mass, "payload_kg": payload}
    # In a plan, too, whatever mass the step claims.
    table = next(f for f in WORLD.furniture if f.id == BOOK.support)
    pick = PickStep(
        object_id=BOOK.id,
        object_name=BOOK.name,
        position=Vec3(x=table.center[0] + BOOK.offset[0], y=table.center[1] + BOOK.offset[1], z=table.size.z + 0.015),
        mass=0.01,
        support_id=table.id,
        approach=table.approach,
    )
    plan = GroundedPlan(steps=[pick], source=SOURCE)
    exc = refused(lambda: rules.check_plan(plan, START), Rule.PAYLOAD)
    assert str(exc).startswith("step 1 (pick): ")
    at = tightened(limits, arm, payload=PayloadPolicy(max_mass=BOOK.mass))
    assert at.check_plan(plan, START)


# gripper_force


def test_a_gripper_force_at_the_limit_passes_and_just_over_is_refused(policy: SafetyPolicy) -> None:
    limit = policy.policy.gripper.max_force
    assert policy.check_gripper(GripperCommandGoal(position=0.0, max_effort=limit)).values["force_n"] == limit
    over = limit + 0.01
    exc = refused(lambda: policy.check_gripper(GripperCommandGoal(position=0.0, max_effort=over)), Rule.GRIPPER_FORCE)
    assert_names(str(exc), over, limit)
    assert exc.values == {"force_n": over, "limit_n": limit}


# gripper_drop


def test_opening_the_gripper_is_refused_only_while_it_holds_something(policy: SafetyPolicy) -> None:
    counter = next(f for f in WORLD.furniture if f.id == "kitchen_counter")
    cup = PickStep(
        object_id="red_cup",
        object_name="red cup",
        position=Vec3(x=2.2, y=0.55, z=0.95),
        mass=0.25,
        support_id=counter.id,
        approach=counter.approach,
    )
    put = PlaceStep(surface_id=counter.id, surface_name=counter.name, position=cup.position, approach=counter.approach)
    start = Pose2D(x=2.5, y=2.0)
    opened = GripperStep(open=True)
    assert policy.check_plan(GroundedPlan(steps=[opened, cup, put, opened], source=SOURCE), start)
    held = GroundedPlan(steps=[cup, GripperStep(open=False), opened], source=SOURCE)
    exc = refused(lambda: policy.check_plan(held, start), Rule.GRIPPER_DROP)
    assert str(exc).startswith("step 3 (gripper): opening the gripper would drop red cup")


# plan


def test_an_on_failure_range_within_the_plan_passes_and_one_past_its_end_is_refused(policy: SafetyPolicy) -> None:
    steps: list[GroundedStep] = [
        NavigateStep(target="a", goal=Pose2D(x=7.0, y=1.2)),
        NavigateStep(target="b", goal=START),
    ]
    back: list[GroundedStep] = [NavigateStep(target="back", goal=START)]
    fits = GroundedPlan(steps=steps, source=SOURCE, fallbacks=[Fallback(first=0, last=1, steps=back)])
    assert policy.check_plan(fits, START)
    for fallback in (
        Fallback(first=0, last=2, steps=back),
        Fallback(first=1, last=0, steps=back),
        Fallback(first=0, last=1, steps=[]),
        Fallback(first=0, last=1, steps=back, labels=["1", "2"]),
    ):
        with pytest.raises(Vetoed) as info:
            policy.check_plan(msgspec.structs.replace(fits, fallbacks=[fallback]), START)
        assert info.value.rule is Rule.PLAN, fallback
    exc = refused(lambda: policy.check_plan(msgspec.structs.replace(fits, labels=["1", "2", "3"]), START), Rule.PLAN)
    assert "2 steps but 3 labels" in str(exc)
    assert policy.check_plan(msgspec.structs.replace(fits, labels=["1", "2"]), START)


# monitor_keep_out: the base's centre in a zone, not grown


def test_zone_at_finds_the_zone_the_base_centre_stands_in(policy: SafetyPolicy) -> None:
    assert policy.zone_at(STAIRS_WEST - EPS, STAIRS_MID_Y) is None
    zone = policy.zone_at(STAIRS_WEST + EPS, STAIRS_MID_Y)
    assert zone is not None and zone.id == "stairs"
    assert policy.zone_at(11.2, STAIRS_SOUTH - EPS) is None
    assert policy.zone_at(START.x, START.y) is None
