"""Review 41 of safety's checks of commands: each case a command that passed before and must not."""

from __future__ import annotations

import math

import msgspec
import pytest

from schemas.common import Pose2D, ServiceError
from schemas.plan import GroundedPlan, NavigateStep, Plan, PlanApproved, Step
from schemas.robot import JointState, Odometry, Twist
from schemas.safety import Decision, Rule
from services.footprint import footprint, nearest
from services.robotmodel import ArmModel
from services.safety.errors import Vetoed
from services.safety.gate import SafetyGate
from services.safety.latch import EstopLatch
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world

WORLD = load_world()
STAIRS = next(zone for zone in WORLD.keep_out if zone.id == "stairs")
STAIRS_WEST = min(x for x, _ in STAIRS.polygon)  # 10.5
STAIRS_SOUTH = min(y for _, y in STAIRS.polygon)  # 7.0


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    arm = ArmModel(WORLD.robot.arm_urdf)
    return SafetyPolicy(WorldModel(WORLD), load_policy(None, WORLD.robot, arm, WORLD.keep_out), arm)


def _south_of_the_stairs(policy: SafetyPolicy) -> Pose2D:
    """Facing east, 10 cm south of where the footprint would touch the stairs: straight on passes by."""
    return Pose2D(x=STAIRS_WEST - 0.5, y=STAIRS_SOUTH - policy.radius - 0.1, yaw=0.0)


def test_a_cmd_vel_whose_arc_curves_into_the_stairs_is_refused(policy: SafetyPolicy) -> None:
    # At both limits (0.6 m/s, 1.2 rad/s) the base drives a 0.5 m radius arc: held for the horizon
    # it curves 0.3 m to the left, into the stairs, although straight ahead is clear.
    pose = _south_of_the_stairs(policy)
    v, w = policy.max_linear, policy.max_angular
    assert policy.check_cmd_vel(Twist(linear_x=v), pose).command == Twist(linear_x=v)
    assert policy.check_cmd_vel(Twist(linear_x=v, angular_z=-w), pose).command.angular_z == -w
    with pytest.raises(Vetoed) as info:
        policy.check_cmd_vel(Twist(linear_x=v, angular_z=w), pose)
    assert info.value.rule is Rule.CMD_VEL_HORIZON
    assert "keep-out zone 'stairs'" in str(info.value)
    assert f"{w:g} rad/s" in str(info.value)
    horizon = policy.policy.base.cmd_vel_horizon
    # Where the arc ends, not where the chord along the heading would.
    assert info.value.values["x"] == pytest.approx(pose.x + v / w * math.sin(w * horizon))
    assert info.value.values["y"] == pytest.approx(pose.y + v / w * (1 - math.cos(w * horizon)))
    assert info.value.values["turn_rps"] == w


def test_teleop_whose_arc_curves_into_the_stairs_is_refused(policy: SafetyPolicy) -> None:
    pose = _south_of_the_stairs(policy)
    v, w = policy.max_linear, policy.max_angular
    running = Twist(linear_x=v, angular_z=w)
    with pytest.raises(Vetoed) as info:
        policy.check_teleop(running, pose, running, 0.1)
    assert info.value.rule is Rule.CMD_VEL_HORIZON


def test_a_cmd_vel_whose_arc_leaves_the_map_is_refused(policy: SafetyPolicy) -> None:
    # In the living room 25 cm from its south wall, facing east: straight on stays in, the arc to
    # the right crosses the wall within the horizon.
    pose = Pose2D(x=7.0, y=0.25, yaw=0.0)
    v, w = policy.max_linear, policy.max_angular
    assert policy.check_cmd_vel(Twist(linear_x=v), pose)
    with pytest.raises(Vetoed) as info:
        policy.check_cmd_vel(Twist(linear_x=v, angular_z=-w), pose)
    assert info.value.rule is Rule.CMD_VEL_HORIZON
    assert "would leave the map" in str(info.value)


# The hand held out beyond the base, driven by cmd_vel

ARM = [f"panda_joint{i}" for i in range(1, 8)]
# The arm held out forward: the grasp point some 0.8 m ahead of the base's centre.
HELD_OUT = [0.0, 0.3, 0.0, -1.5, 0.0, 1.8, 0.785]


def test_a_cmd_vel_that_takes_the_held_out_hand_into_the_stairs_is_refused(policy: SafetyPolicy) -> None:
    # The base stops 10 cm short of the stairs within the horizon; the hand, 0.8 m ahead, would be in.
    reach = policy.reach(dict(zip(ARM, HELD_OUT, strict=True)))
    assert reach > policy.radius + 0.3
    horizon = policy.policy.base.cmd_vel_horizon
    pose = Pose2D(x=STAIRS_WEST - policy.radius - 0.5, y=8.0, yaw=0.0)
    twist = Twist(linear_x=0.4 / horizon)
    assert policy.check_cmd_vel(twist, pose).command == twist
    stowed = policy.reach(dict(zip(ARM, WORLD.robot.home_joints, strict=True)))
    assert policy.check_cmd_vel(twist, pose, reach=stowed).command == twist
    for check in (
        lambda: policy.check_cmd_vel(twist, pose, reach=reach),
        lambda: policy.check_teleop(twist, pose, twist, 0.1, reach=reach),
    ):
        with pytest.raises(Vetoed) as info:
            check()
        assert info.value.rule is Rule.CMD_VEL_HORIZON
        assert f"hand ({reach:.2f} m from the base's centre)" in str(info.value)
        assert "keep-out zone 'stairs'" in str(info.value)
        assert info.value.values["reach_m"] == reach
    # Driving away from the stairs, the hand leaves them behind.
    assert policy.check_cmd_vel(Twist(linear_x=-0.4), pose, reach=reach)


def test_turning_in_place_with_the_hand_held_out_near_the_stairs_is_refused(policy: SafetyPolicy) -> None:
    # Facing away from the stairs, 0.5 m from them: the hand swings round into them.
    reach = policy.reach(dict(zip(ARM, HELD_OUT, strict=True)))
    pose = Pose2D(x=STAIRS_WEST - 0.5, y=8.0, yaw=math.pi)
    turn = Twist(angular_z=0.5)
    assert policy.check_cmd_vel(turn, pose).command == turn
    with pytest.raises(Vetoed) as info:
        policy.check_cmd_vel(turn, pose, reach=reach)
    assert info.value.rule is Rule.CMD_VEL_HORIZON
    assert "keep-out zone 'stairs'" in str(info.value)
    # Far from every zone it turns as before, and a turn without a pose is let through as before.
    assert policy.check_cmd_vel(turn, Pose2D(x=6.0, y=1.2), reach=reach).command == turn
    assert policy.check_cmd_vel(turn, None, reach=reach).command == turn


def test_the_gate_drives_cmd_vel_with_the_hand_where_the_joint_states_put_it(policy: SafetyPolicy) -> None:
    now = [0.0]
    gate = SafetyGate(policy, EstopLatch("operator-token"), lambda: now[0], lambda: 1_700_000_000.0)
    pose = Pose2D(x=STAIRS_WEST - policy.radius - 0.5, y=8.0, yaw=0.0)
    gate.odometry(Odometry(stamp=0.0, sim_time=0.0, pose=pose, linear_x=0.0, angular_z=0.0))
    twist = Twist(linear_x=0.4 / policy.policy.base.cmd_vel_horizon)

    def arm_at(q: list[float]) -> None:
        gate.joint_state(JointState(stamp=0.0, name=list(ARM), position=q, velocity=[0.0] * len(ARM)))

    arm_at(list(WORLD.robot.home_joints))
    assert gate.cmd_vel(twist).forward == twist
    arm_at(HELD_OUT)
    refused = gate.cmd_vel(twist)
    # A person's twist, a moment after that stop, ramps up to 0.15 m/s: the hand still reaches the stairs.
    now[0] = 0.2
    for ruling in (refused, gate.teleop(twist)):
        assert ruling.forward == Twist()  # refused, and the base stopped
        assert ruling.events[0].decision is Decision.VETOED
        assert ruling.events[0].rule is Rule.CMD_VEL_HORIZON
        assert "hand" in ruling.events[0].reason


# A world without walls or furniture (an open floor: the schema's default)


def test_a_plan_in_a_world_without_walls_or_furniture_is_checked_not_crashed() -> None:
    open_floor = msgspec.structs.replace(WORLD, walls=[], furniture=[], objects=[])
    arm = ArmModel(open_floor.robot.arm_urdf)
    policy = SafetyPolicy(WorldModel(open_floor), load_policy(None, open_floor.robot, arm, open_floor.keep_out), arm)
    assert nearest(footprint(6.0, 1.2, 0.0, 0.6, 0.5), []) == ("nothing", math.inf)
    gate = SafetyGate(policy, EstopLatch("operator-token"), lambda: 0.0, lambda: 1_700_000_000.0)
    gate.odometry(Odometry(stamp=0.0, sim_time=0.0, pose=Pose2D(x=6.0, y=1.2), linear_x=0.0, angular_z=0.0))
    source = Plan(steps=[Step(action="stop")])  # type: ignore[arg-type]
    fine = GroundedPlan(steps=[NavigateStep(target="sofa", goal=Pose2D(x=8.0, y=2.0))], source=source)
    assert isinstance(gate.check_plan(fine).forward, PlanApproved)
    stairs = GroundedPlan(steps=[NavigateStep(target="stairs", goal=Pose2D(x=11.2, y=8.0))], source=source)
    refusal = gate.check_plan(stairs).forward
    assert isinstance(refusal, ServiceError) and "keep-out zone 'stairs'" in refusal.message
