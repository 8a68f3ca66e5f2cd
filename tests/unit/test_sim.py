"""The sim's controllers without Zenoh: driving, stopping, arm and gripper, a full pick and place."""

from __future__ import annotations

import functools
import itertools
import math
import re
from collections.abc import Iterator
from pathlib import Path

import msgspec
import numpy as np
import pybullet
import pytest
import shapely

from schemas.actions import GoalState
from schemas.common import Pose2D, Vec3
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    GripperCommandResult,
    NavigateToPoseGoal,
    TrajectoryPoint,
    Twist,
)
from schemas.world import World
from services.executor.kinematics import ArmKinematics, joint_trajectory
from services.executor.navigation import BasePlanner
from services.footprint import TRACKING_TOLERANCE, footprint, route_sweeps
from services.robotmodel import world_to_arm
from services.runtime import ConfigError, load_config
from services.sim.config import SimConfig
from services.sim.controllers import STALL_TIME, Navigation
from services.sim.simulation import Simulation
from services.worldmodel import WorldModel, drive_route, load_world
from tests.fastsim import FAST_PHYSICS_HZ

# A stowed arm that carries the hand (and what it holds) high above the base, clear of counters.
# household.yaml is to adopt these as home_joints; until then the tests put them in.
CARRY_JOINTS = [0.0, -1.3, 0.0, -2.35, 0.0, 1.05, 0.785]
PREGRASP_HEIGHT = 0.12
PLACE_CLEARANCE = 0.01
JOINT_SPEED = 1.0


@pytest.fixture(scope="module")
def world() -> World:
    household = load_world("household")
    robot = msgspec.structs.replace(household.robot, home_joints=CARRY_JOINTS)
    return msgspec.structs.replace(household, robot=robot)


@pytest.fixture
def sim(world: World) -> Iterator[Simulation]:
    # Physics at 120 Hz, as the integration stacks run it (FAST_SIM), and no visual meshes (nothing
    # here renders): a third of the time. The default 240 Hz is the robot contract's and the
    # wall-clock tests'.
    simulation = Simulation(world, physics_hz=FAST_PHYSICS_HZ, visuals=False)
    yield simulation
    simulation.close()


@pytest.fixture(scope="module")
def kin() -> ArmKinematics:
    return ArmKinematics()


def approach(world: World, furniture_id: str) -> Pose2D:
    return next(f.approach for f in world.furniture if f.id == furniture_id)


@functools.cache
def _planner(world_name: str) -> BasePlanner:
    return BasePlanner(WorldModel(load_world(world_name)))


def route_planner(sim: Simulation) -> BasePlanner:
    return _planner(sim.world.name)


def drive(sim: Simulation, pose: Pose2D) -> None:
    # Through the doorways, as the executor would plan it.
    path = route_planner(sim).plan(sim.robot.base_pose(), pose)
    motion = sim.run(sim.controllers.navigate(NavigateToPoseGoal(pose=pose, path=path)), timeout=120.0)
    assert motion.state is GoalState.SUCCEEDED, motion.message
    here = sim.robot.base_pose()
    assert math.hypot(here.x - pose.x, here.y - pose.y) < 0.05
    assert abs(math.remainder(here.yaw - pose.yaw, math.tau)) < 0.05


def move_arm(sim: Simulation, q: list[float] | np.ndarray) -> None:
    points = joint_trajectory(sim.robot.arm_positions(), q, JOINT_SPEED)
    goal = FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=points)
    motion = sim.run(sim.controllers.follow_trajectory(goal), timeout=20.0)
    assert motion.state is GoalState.SUCCEEDED, motion.message


def reach(sim: Simulation, kin: ArmKinematics, point: Vec3) -> None:
    target = world_to_arm(sim.robot.base_pose(), sim.world.robot.arm_mount, point)
    move_arm(sim, kin.solve_top_down(target, sim.robot.arm_positions()))


def gripper(sim: Simulation, position: float) -> GripperCommandResult:
    motion = sim.run(sim.controllers.gripper(GripperCommandGoal(position=position)), timeout=5.0)
    assert motion.state is GoalState.SUCCEEDED, motion.message
    assert motion.result is not None
    return motion.result


def above(point: Vec3, height: float) -> Vec3:
    return Vec3(x=point.x, y=point.y, z=point.z + height)


def test_config_defaults_and_unknown_fields_are_errors(tmp_path: Path) -> None:
    assert load_config(SimConfig, None, "sim").heartbeat_timeout == 0.2
    bad = tmp_path / "tether.toml"
    bad.write_text("[sim]\nrealtime_factor = 3\nphysic_hz = 100\n")
    with pytest.raises(ConfigError, match="physic_hz"):
        load_config(SimConfig, bad, "sim")
    bad.write_text("[sim]\nsolver_iterations = 0\n")
    with pytest.raises(ConfigError, match="solver_iterations"):
        load_config(SimConfig, bad, "sim")
    # A cmd_vel held longer than safety checked its path for (the policy's cmd_vel_horizon, 1 s).
    bad.write_text("[sim]\ncmd_vel_timeout = 5\n")
    with pytest.raises(ConfigError, match="cmd_vel_timeout"):
        load_config(SimConfig, bad, "sim")


def test_the_solver_makes_the_passes_configured(world: World) -> None:
    assert SimConfig().solver_iterations == 50  # pybullet's default

    def passes(sim: Simulation) -> int:
        try:
            return int(sim.scene.bullet.getPhysicsEngineParameters()["numSolverIterations"])
        finally:
            sim.close()

    assert passes(Simulation(world, visuals=False)) == 50
    assert passes(Simulation(world, solver_iterations=20, visuals=False)) == 20


def test_base_drives_to_the_kitchen_counter_approach(sim: Simulation, world: World) -> None:
    goal = approach(world, "kitchen_counter")
    motion = sim.controllers.navigate(NavigateToPoseGoal(pose=goal, max_speed=0.6))
    sim.step(24)
    assert motion.feedback is not None and motion.feedback.distance_remaining > 3.0
    drive(sim, goal)
    assert sim.robot.base_speed() < 0.05


def test_stop_brings_the_base_to_rest_within_100_ms(sim: Simulation, world: World) -> None:
    motion = sim.controllers.navigate(NavigateToPoseGoal(pose=Pose2D(x=10.0, y=1.2, yaw=0.0), max_speed=0.6))
    sim.settle(2.0)
    assert sim.robot.base_speed() > 0.5
    sim.controllers.stop("e-stop latched by test: stop now")
    assert motion.state is GoalState.ABORTED and "e-stop" in motion.message
    sim.settle(0.1)
    assert sim.robot.base_speed() < 0.01
    assert sim.scene.ground_truth().linear_speed < 0.01


def test_a_goal_preempting_a_moving_base_brakes_first_and_drives_from_where_it_stopped(sim: Simulation) -> None:
    first = sim.controllers.navigate(NavigateToPoseGoal(pose=Pose2D(x=10.0, y=1.2, yaw=0.0), max_speed=0.6))
    sim.settle(2.0)
    assert sim.robot.base_speed() > 0.5
    goal = Pose2D(x=sim.robot.base_pose().x + 1.0, y=1.2, yaw=0.0)
    second = sim.run(sim.controllers.navigate(NavigateToPoseGoal(pose=goal)), timeout=30.0)
    assert first.state is GoalState.CANCELED and "preempted" in first.message
    assert second.state is GoalState.SUCCEEDED, second.message
    here = sim.robot.base_pose()
    assert math.hypot(here.x - goal.x, here.y - goal.y) < 0.05


def test_stop_holds_the_fingers_where_they_are(sim: Simulation) -> None:
    closing = sim.controllers.gripper(GripperCommandGoal(position=0.0))
    sim.settle(0.1)
    gap = sim.robot.gripper_gap()
    assert 0.01 < gap < 0.07
    sim.controllers.stop("e-stop latched by test: stop now")
    assert closing.state is GoalState.ABORTED
    sim.settle(0.5)
    assert sim.robot.gripper_gap() == pytest.approx(gap, abs=0.003)


def test_canceling_a_gripper_goal_holds_the_fingers_where_they_are(sim: Simulation) -> None:
    closing = sim.controllers.gripper(GripperCommandGoal(position=0.0))
    sim.settle(0.1)
    sim.controllers.cancel(closing)
    gap = sim.robot.gripper_gap()
    assert 0.01 < gap < 0.07 and closing.state is GoalState.CANCELED
    sim.settle(0.5)
    assert sim.robot.gripper_gap() == pytest.approx(gap, abs=0.003)


def test_a_gripper_goal_preempting_a_closing_one_reaches_its_own_gap(sim: Simulation) -> None:
    closing = sim.controllers.gripper(GripperCommandGoal(position=0.0))
    sim.settle(0.05)
    opening = sim.run(sim.controllers.gripper(GripperCommandGoal(position=0.08)), timeout=5.0)
    assert closing.state is GoalState.CANCELED and "preempted" in closing.message
    assert opening.state is GoalState.SUCCEEDED and opening.result is not None
    assert opening.result.reached_goal, opening.result


def test_a_refused_navigation_leaves_cmd_vel_to_expire(sim: Simulation) -> None:
    # Safety fills `start` from odometry; while cmd_vel turns the base it is soon elsewhere.
    assert sim.controllers.set_cmd_vel(Twist(angular_z=0.8), hold_for=0.5)
    start = sim.robot.base_pose()
    sim.settle(0.3)
    refused = sim.controllers.navigate(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2, yaw=0.0), start=start))
    assert refused.state is GoalState.ABORTED and "checked from" in refused.message
    sim.settle(0.2 + 1.0)  # past the hold, and braking from 0.8 rad/s
    assert sim.robot.base_speed() < 0.01
    _, angular = sim.robot.base_velocity()
    assert abs(angular) < 0.01, angular


def test_cmd_vel_drives_and_expires(sim: Simulation) -> None:
    start = sim.robot.base_pose()
    assert sim.controllers.set_cmd_vel(Twist(linear_x=0.4), hold_for=1.0)
    sim.settle(0.8)
    linear, _ = sim.robot.base_velocity()
    assert linear == pytest.approx(0.4, abs=0.02)
    sim.settle(0.6)
    assert sim.robot.base_speed() < 0.01
    assert sim.robot.base_pose().x > start.x + 0.2


def test_cmd_vel_is_limited_by_the_speed_scale(sim: Simulation) -> None:
    robot = sim.world.robot
    sim.controllers.set_speed_scale(0.5)
    assert sim.controllers.set_cmd_vel(
        Twist(linear_x=robot.max_linear_speed, angular_z=robot.max_angular_speed), hold_for=1.0
    )
    sim.settle(0.8)
    linear, angular = sim.robot.base_velocity()
    assert linear == pytest.approx(0.5 * robot.max_linear_speed, abs=0.01)
    assert angular == pytest.approx(0.5 * robot.max_angular_speed, abs=0.02)


def test_the_heartbeats_limits_never_raise_the_scaled_ones(sim: Simulation) -> None:
    robot = sim.world.robot
    sim.controllers.set_speed_scale(0.5, linear=robot.max_linear_speed, angular=10.0)
    assert sim.controllers.base.limits == (0.5 * robot.max_linear_speed, 0.5 * robot.max_angular_speed)
    sim.controllers.set_speed_scale(0.5, linear=0.1, angular=0.2)
    assert sim.controllers.base.limits == (0.1, 0.2)


# Two metres straight ahead of the start pose, with nothing in the way.
AHEAD = NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2, yaw=0.0), max_speed=0.6)


def largest_drop(speeds: list[float]) -> float:
    return max(a - b for a, b in itertools.pairwise(speeds))


def speeds_over(sim: Simulation, seconds: float) -> list[float]:
    speeds = []
    for _ in range(round(seconds / sim.dt)):
        sim.step()
        speeds.append(sim.robot.base_speed())
    return speeds


def test_navigation_slows_to_the_speed_scale_and_still_arrives(sim: Simulation) -> None:
    limit = 0.5 * sim.world.robot.max_linear_speed
    motion = sim.controllers.navigate(AHEAD)
    sim.settle(1.5)
    before = sim.robot.base_speed()
    assert before > 0.55
    sim.controllers.set_speed_scale(0.5)
    ramp = (before - limit) / sim.world.robot.max_linear_acceleration
    speeds = [before, *speeds_over(sim, 2.0)]
    # Slowed down at the normal deceleration, not at once, then held to the limit.
    assert largest_drop(speeds) < 1.2 * sim.world.robot.max_linear_acceleration * sim.dt
    settled = round((ramp + 0.05) / sim.dt)
    assert max(speeds[settled:]) < limit + 0.01
    assert speeds[settled] > limit - 0.02, "slowed down further than asked"
    while motion.running:
        sim.step()
        assert sim.robot.base_speed() < limit + 0.01
    assert motion.state is GoalState.SUCCEEDED, motion.message
    assert sim.robot.base_pose().x == pytest.approx(AHEAD.pose.x, abs=0.05)


def test_a_pause_stops_the_base_gently_and_keeps_the_goal_running(sim: Simulation) -> None:
    motion = sim.controllers.navigate(AHEAD)
    sim.settle(1.2)
    assert sim.robot.base_speed() > 0.3
    sim.controllers.set_speed_scale(0.0)
    speeds = [sim.robot.base_speed(), *speeds_over(sim, 1.0)]
    assert largest_drop(speeds) < 1.2 * sim.world.robot.max_linear_acceleration * sim.dt
    stopped_after = next(k for k, v in enumerate(speeds) if v < 0.01) * sim.dt
    assert stopped_after > 0.8 * 0.3 / sim.world.robot.max_linear_acceleration
    assert speeds[-1] < 0.001
    # Long past the stall time, the paused goal runs on: the stall and deadline clocks stand still.
    assert isinstance(motion, Navigation)
    clock, here = motion.clock, sim.robot.base_pose()
    sim.settle(3.0 * STALL_TIME)
    assert motion.running
    assert motion.clock == clock
    assert math.dist((here.x, here.y), (sim.robot.base_pose().x, sim.robot.base_pose().y)) < 0.005
    sim.controllers.set_speed_scale(1.0)
    drive(sim, AHEAD.pose)


def trajectory_time(sim: Simulation, q: list[float]) -> float:
    start = sim.sim_time
    move_arm(sim, q)
    return sim.sim_time - start


ELSEWHERE_JOINTS = [0.3, -1.0, 0.2, -2.0, 0.1, 1.3, 0.5]


def test_trajectories_at_half_speed_take_twice_as_long(sim: Simulation) -> None:
    full = trajectory_time(sim, ELSEWHERE_JOINTS)
    sim.controllers.set_speed_scale(0.5)
    # The way back: the same joint distances, so the same trajectory timing.
    half = trajectory_time(sim, CARRY_JOINTS)
    assert half == pytest.approx(2.0 * full, rel=0.05)


def test_a_paused_trajectory_holds_the_arm_and_keeps_the_goal_running(sim: Simulation) -> None:
    points = joint_trajectory(sim.robot.arm_positions(), ELSEWHERE_JOINTS, JOINT_SPEED)
    goal = FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=points)
    motion = sim.controllers.follow_trajectory(goal)
    sim.settle(0.2)
    sim.controllers.set_speed_scale(0.0)
    sim.settle(0.2)
    held = sim.robot.arm_positions()
    # Paused for longer than the trajectory and its settle time together.
    for _ in range(round(2.0 / sim.dt)):
        sim.step()
        arm = sim.sensors.joint_state(0.0).velocity[: len(ARM_JOINTS)]
        assert max(abs(v) for v in arm) < 1e-3
    assert motion.running
    assert sim.robot.arm_positions() == pytest.approx(held, abs=1e-3)
    assert sim.robot.arm_positions() != pytest.approx(ELSEWHERE_JOINTS, abs=0.05)
    sim.controllers.set_speed_scale(1.0)
    assert sim.run(motion, timeout=5.0).state is GoalState.SUCCEEDED, motion.message
    assert sim.robot.arm_positions() == pytest.approx(ELSEWHERE_JOINTS, abs=0.01)


def gripper_time(sim: Simulation, position: float) -> float:
    start = sim.sim_time
    assert gripper(sim, position).reached_goal
    return sim.sim_time - start


def test_the_gripper_is_not_slowed_but_pauses_with_the_robot(sim: Simulation) -> None:
    closing = gripper_time(sim, 0.0)
    sim.controllers.set_speed_scale(0.2)
    assert gripper_time(sim, 0.08) == pytest.approx(closing, rel=0.1)
    # Paused (a person too close): the fingers hold where they are, and the goal waits.
    motion = sim.controllers.gripper(GripperCommandGoal(position=0.0))
    sim.settle(0.1)
    sim.controllers.set_speed_scale(0.0)
    sim.settle(0.05)
    held = sim.robot.gripper_gap()
    assert 0.01 < held < 0.075, held
    sim.settle(3.0)  # longer than the gripper's own timeout
    assert motion.running
    assert sim.robot.gripper_gap() == pytest.approx(held, abs=0.002)
    sim.controllers.set_speed_scale(1.0)
    sim.run(motion, timeout=5.0)
    assert motion.state is GoalState.SUCCEEDED and sim.robot.gripper_gap() < 0.002


def test_navigation_into_furniture_aborts_with_a_reason(sim: Simulation, world: World) -> None:
    # Head on into the coffee table: the base stops against it and makes no more progress.
    inside_the_table = Pose2D(x=8.0, y=2.5, yaw=math.pi / 2)
    path = [Pose2D(x=8.0, y=1.2)]
    motion = sim.run(sim.controllers.navigate(NavigateToPoseGoal(pose=inside_the_table, path=path)), timeout=60.0)
    assert motion.state is GoalState.ABORTED
    assert "stalled" in motion.message and "is the way blocked?" in motion.message
    assert sim.robot.base_speed() < 0.05


@pytest.mark.parametrize("furniture_id", ["kitchen_counter", "shelf", "bed"])
def test_the_base_as_driven_stays_within_the_sweeps_safety_checked(sim: Simulation, furniture_id: str) -> None:
    # Out of the living room, through doorways, and straight in to park by the furniture.
    goal = approach(sim.world, furniture_id)
    start = sim.robot.base_pose()
    path = route_planner(sim).plan(start, goal)
    size = sim.world.robot.base_size
    checked = shapely.union_all(
        [s.shape for s in route_sweeps(start, drive_route(start, path, goal), goal.yaw, size.x, size.y)]
    ).buffer(TRACKING_TOLERANCE + 1e-6)
    shapely.prepare(checked)  # covers() is then quick; the area outside is computed only when not covered
    motion = sim.controllers.navigate(NavigateToPoseGoal(pose=goal, path=path, start=start))
    worst = 0.0
    while motion.running:
        sim.step()
        here = sim.robot.base_pose()
        driven = footprint(here.x, here.y, here.yaw, size.x, size.y)
        if not checked.covers(driven):
            worst = max(worst, driven.difference(checked).area)
    assert motion.state is GoalState.SUCCEEDED, motion.message
    assert worst == 0.0, f"the footprint left the checked sweeps (grown by the tracking tolerance) by {worst} m^2"


def test_a_base_pushed_off_its_route_aborts_the_goal(sim: Simulation) -> None:
    start = sim.robot.base_pose()
    motion = sim.controllers.navigate(NavigateToPoseGoal(pose=Pose2D(x=start.x + 2.0, y=start.y)))
    sim.step(round(1.5 / sim.dt))
    assert motion.running
    # Shoved 0.2 m sideways: no longer on the route safety checked.
    y_joint = sim.robot.joint_index["base_y"]
    sim.scene.bullet.resetJointState(sim.robot.id, y_joint, start.y + 0.2)
    sim.run(motion, timeout=5.0)
    assert motion.state is GoalState.ABORTED
    assert "cm off its route (tolerance 3 cm): pushed or blocked?" in motion.message


def test_an_arm_blocked_on_its_way_aborts_the_trajectory_and_holds_there(sim: Simulation) -> None:
    # A box in front of the robot, in the way of the arm reaching forward and down.
    base = sim.robot.base_pose()
    box = sim.scene.bullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[0.15, 0.4, 0.15])
    sim.scene.bullet.createMultiBody(0.0, box, -1, [base.x + 0.75, base.y, 0.75])
    start = sim.robot.arm_positions()
    forward = [start[0], 1.7, start[2], -0.3, *start[4:]]
    points = [
        TrajectoryPoint(positions=start, time_from_start=0.0),
        TrajectoryPoint(positions=forward, time_from_start=3.0),
    ]
    goal = FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=points, path_tolerance=0.1)
    motion = sim.run(sim.controllers.follow_trajectory(goal), timeout=10.0)
    assert motion.state is GoalState.ABORTED
    assert re.search(r"panda_joint\d was 0\.1\d\d rad from the trajectory at \d", motion.message), motion.message
    assert motion.message.endswith("(path tolerance 0.1 rad): blocked or pushed")
    stopped = sim.robot.arm_positions()
    assert stopped[1] < 1.0, "stopped at the box, far short of the goal"
    sim.settle(0.5)
    assert np.max(np.abs(np.array(sim.robot.arm_positions()) - stopped)) < 0.02, "and it holds there"


def test_trajectory_goals_are_checked(sim: Simulation) -> None:
    unknown = FollowJointTrajectoryGoal(
        joint_names=["panda_joint1", "elbow"], points=[TrajectoryPoint(positions=[0.0, 0.0], time_from_start=1.0)]
    )
    assert "unknown joints ['elbow']" in (sim.controllers.arm.check_trajectory(unknown) or "")
    short = FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=[0.0] * 6, time_from_start=1.0)]
    )
    assert "6 positions for 7 joints" in (sim.controllers.arm.check_trajectory(short) or "")
    beyond = FollowJointTrajectoryGoal(
        joint_names=["panda_joint4"], points=[TrajectoryPoint(positions=[0.5], time_from_start=1.0)]
    )
    assert "outside" in (sim.controllers.arm.check_trajectory(beyond) or "")
    motion = sim.controllers.follow_trajectory(short)
    assert motion.state is GoalState.ABORTED


def test_closing_on_nothing_holds_nothing(sim: Simulation) -> None:
    result = gripper(sim, 0.0)
    assert result.holding is None and not result.stalled and result.reached_goal


def test_pick_red_cup_from_counter_and_place_it_on_the_coffee_table(
    sim: Simulation, world: World, kin: ArmKinematics
) -> None:
    drive(sim, approach(world, "kitchen_counter"))
    cup = sim.scene.object_position("red_cup")
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    reach(sim, kin, cup)
    grasp = gripper(sim, 0.0)
    assert grasp.holding == "red_cup" and grasp.stalled
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    move_arm(sim, world.robot.home_joints)
    assert sim.scene.ground_truth().holding == "red_cup"

    table = next(f for f in world.furniture if f.id == "coffee_table")
    drive(sim, table.approach)
    cup_half_height = next(o for o in world.objects if o.id == "red_cup").size.z / 2
    spot = Vec3(x=table.center[0] - 0.2, y=table.center[1] - 0.1, z=table.size.z + cup_half_height + PLACE_CLEARANCE)
    reach(sim, kin, above(spot, PREGRASP_HEIGHT))
    reach(sim, kin, spot)
    released = gripper(sim, 0.08)
    assert released.holding is None
    reach(sim, kin, above(spot, PREGRASP_HEIGHT))
    move_arm(sim, world.robot.home_joints)
    sim.settle(0.5)

    truth = sim.scene.ground_truth()
    cup_now = next(o for o in truth.objects if o.id == "red_cup")
    assert truth.holding is None
    assert (cup_now.on, cup_now.room) == ("coffee_table", "living_room")
    # The fingers centre the cup as they close, so it may sit up to the finger gap off the spot.
    assert math.hypot(cup_now.position.x - spot.x, cup_now.position.y - spot.y) < 0.045


def test_a_held_object_kept_still_for_seconds_still_goes_with_the_hand(
    sim: Simulation, world: World, kin: ArmKinematics
) -> None:
    """Objects at rest sleep in the physics (world.py); one in the gripper must not, however long the
    arm waits (Bullet puts a body to sleep after 2 s still), or the hand would move on without it."""
    drive(sim, approach(world, "kitchen_counter"))
    cup = sim.scene.object_position("red_cup")
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    reach(sim, kin, cup)
    assert gripper(sim, 0.0).holding == "red_cup"
    sim.settle(5.0)  # the arm waits, still, well past Bullet's 2 s
    reach(sim, kin, above(cup, PREGRASP_HEIGHT))
    sim.settle(5.0)
    move_arm(sim, world.robot.home_joints)
    hand = np.array(sim.scene.hand_position())
    held = sim.scene.object_position("red_cup")
    assert np.linalg.norm(hand - np.array([held.x, held.y, held.z])) < 0.15, "the cup stayed behind"
    released = gripper(sim, 0.08)
    assert released.holding is None
    sim.settle(3.0)
    landed = sim.scene.object_position("red_cup")
    assert landed.z < held.z - 0.05, "let go, the cup falls"
