"""The stand-in robot as a real process, behaving as a real ROS 2 robot where it used not to.

Nav2's controller_server reads speed_limit and limits the velocities it commands while it
navigates; cmd_vel from anyone else (teleop, the ros2 backend) goes to the base controller past
it, unlimited. A stand-in that limited cmd_vel too would hide a backend that relies on it. So
with the rest: a preempted goal ends as Nav2 and ros2_control end it, a goal it cannot carry out is
taken and aborted where their servers take every goal, and a stamped cmd_vel holds from its stamp
as diff_drive_controller's does.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest

from services.ros2.rmw import GoalStatus
from services.ros2sim import messages
from services.ros2sim import node as standin
from tests.integration import test_ros2sim as base
from tests.integration.test_ros2sim import GOAL_TIMEOUT, Robot, ahead, speed

pytestmark = [pytest.mark.realtime, pytest.mark.alone]

robot = base.robot  # the module's own stand-in process, driven as the ros2 backend would

LIMIT = 0.1  # m/s, well under the base's top speed and the cmd_vel below
COMMAND = 0.3  # m/s
SLACK = 0.03  # m/s: odometry's noise and the ramp's last step


@pytest.fixture
def speed_limit(robot: Robot) -> Iterator[Any]:
    publisher = robot.ros.publisher(standin.NAMES.speed_limit, "nav2_msgs/msg/SpeedLimit")

    def put(metres_per_second: float) -> None:
        message = robot.types.new("nav2_msgs/msg/SpeedLimit", percentage=False, speed_limit=metres_per_second)
        publisher.put(message)

    try:
        yield put
    finally:
        put(0.0)  # no limit, for the module's other tests


def test_speed_limit_slows_a_navigation(robot: Robot, speed_limit: Any) -> None:
    speed_limit(LIMIT)
    x, y = ahead(robot, 0.3)  # long enough to reach the limit, short enough to be quick
    start = len(robot.odom)
    goal = robot.navigate(x, y)
    status, result = goal.result(timeout=40.0)
    assert status == GoalStatus.SUCCEEDED, result.error_msg
    fastest = max(speed(m) for m in robot.odom.messages[start:])
    assert 0.5 * LIMIT < fastest < LIMIT + SLACK


def test_speed_limit_leaves_cmd_vel_alone(robot: Robot, speed_limit: Any) -> None:
    speed_limit(LIMIT)
    forward = robot.types.new("geometry_msgs/msg/Vector3", x=COMMAND)
    twist = robot.types.new("geometry_msgs/msg/Twist", linear=forward)
    start = len(robot.odom)
    # Sent until the base is past the limit, or 20 times (2 s at 10 Hz: ample to reach COMMAND).
    for _ in range(20):
        speed_limit(LIMIT)  # the limit stays in force all along
        robot.cmd_vel.put(twist)
        if robot.odom.wait_for(lambda m: speed(m) > COMMAND - SLACK, 0.1, after=start):
            break
    fastest = max(speed(m) for m in robot.odom.messages[start:])
    assert fastest > COMMAND - SLACK, f"cmd_vel held to {fastest:.2f} m/s by speed_limit, which is Nav2's alone"
    assert robot.odom.wait_for(lambda m: speed(m) < 0.01, 5.0, after=len(robot.odom) - 1), "the base did not stop"


# A new goal on an action whose goal still runs: Nav2's SimpleActionServer aborts the old goal with
# an empty result (accept_pending_goal); ros2_control's joint_trajectory_controller cancels it with
# INVALID_GOAL and says why (preempt_active_goal). A cancel the client asked for stays canceled.


def test_a_navigation_preempted_by_a_new_one_is_aborted_as_nav2_does(robot: Robot) -> None:
    x, y = ahead(robot, 1.5)
    first = robot.navigate(x, y)
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 10.0, after=len(robot.odom)), "the base never got going"
    here = robot.odom_pose()
    second = robot.navigate(*here)
    status, result = first.result(timeout=GOAL_TIMEOUT)
    assert (status, result.error_code, result.error_msg) == (GoalStatus.ABORTED, messages.NAV_NONE, "")
    status, result = second.result(timeout=30.0)
    assert status == GoalStatus.SUCCEEDED, result.error_msg


def test_a_trajectory_preempted_by_a_new_one_is_canceled_as_the_joint_trajectory_controller_does(
    robot: Robot,
) -> None:
    joints = robot.joint_states.wait_for(lambda _m: True, 5.0)
    assert joints is not None
    home = float(joints.position[0])
    first = robot.trajectory(["panda_joint1"], [home + 0.4], at=5.0)
    moving = robot.joint_states.wait_for(
        lambda m: float(m.position[0]) > home + 0.01, 5.0, after=len(robot.joint_states)
    )
    assert moving is not None, "the arm never got going"
    second = robot.trajectory(["panda_joint1"], [home], at=0.5)
    status, result = first.result(timeout=GOAL_TIMEOUT)
    assert (status, result.error_code) == (GoalStatus.CANCELED, messages.TRAJECTORY_INVALID_GOAL)
    assert result.error_string == messages.TRAJECTORY_PREEMPTED
    status, result = second.result(timeout=20.0)
    assert (status, result.error_code) == (GoalStatus.SUCCEEDED, messages.TRAJECTORY_SUCCESSFUL), result.error_string


def test_a_goal_the_client_cancels_is_canceled(robot: Robot) -> None:
    x, y = ahead(robot, 1.5)
    goal = robot.navigate(x, y)
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 10.0, after=len(robot.odom)), "the base never got going"
    assert goal.cancel(timeout=GOAL_TIMEOUT)
    status, result = goal.result(timeout=GOAL_TIMEOUT)
    assert (status, result.error_code) == (GoalStatus.CANCELED, messages.NAV_NONE)


def test_a_navigation_through_poses_while_one_to_a_pose_runs_is_aborted_as_nav2_does(robot: Robot) -> None:
    through = robot.ros.action_client(standin.NAMES.navigate_through_poses, messages.NAVIGATE_THROUGH_POSES)
    x, y = ahead(robot, 1.0)
    running = robot.navigate(x, y)
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 10.0, after=len(robot.odom)), "the base never got going"
    types = robot.types
    here = types.new(
        "geometry_msgs/msg/PoseStamped",
        header=messages.header(types, 0.0, "odom"),
        pose=messages.pose(types, *robot.pose()),
    )
    other = through.send_goal(types.new(f"{messages.NAVIGATE_THROUGH_POSES}_Goal", poses=[here]), timeout=GOAL_TIMEOUT)
    status, result = other.result(timeout=GOAL_TIMEOUT)
    assert (status, result.error_code) == (GoalStatus.ABORTED, messages.NAV_NONE)
    status, result = running.result(timeout=30.0)
    assert status == GoalStatus.SUCCEEDED, result.error_msg
    assert robot.pose() == pytest.approx((x, y), abs=0.05)


@pytest.fixture(scope="module")
def stamped_robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    """A stand-in taking geometry_msgs/TwistStamped on cmd_vel, as Jazzy's diff_drive_controller."""
    with base.running_standin(tmp_path_factory.mktemp("stamped"), "stamped_cmd_vel = true\n") as stamped:
        yield stamped


def test_a_stamped_cmd_vel_older_than_the_timeout_is_ignored_as_diff_drive_controller_does(
    stamped_robot: Robot,
) -> None:
    robot = stamped_robot
    cmd_vel = robot.ros.publisher(standin.NAMES.cmd_vel, "geometry_msgs/msg/TwistStamped")
    types = robot.types

    def forward(stamp: float) -> Any:
        twist = types.new("geometry_msgs/msg/Twist", linear=types.new("geometry_msgs/msg/Vector3", x=COMMAND))
        return types.new("geometry_msgs/msg/TwistStamped", header=messages.header(types, stamp), twist=twist)

    start = len(robot.odom)
    for _ in range(5):  # a stream of them, each stamped two timeouts ago
        cmd_vel.put(forward(time.time() - 2 * base.CMD_VEL_TIMEOUT))
    moved = robot.odom.wait_for(lambda m: speed(m) > 0.05, 1.0, after=start)
    if moved is not None:
        pytest.fail(f"a cmd_vel stamped past its timeout moved the base at {speed(moved):.2f} m/s")
    start = len(robot.odom)
    cmd_vel.put(forward(time.time()))
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 5.0, after=start), "a fresh stamped cmd_vel did not move it"
    assert robot.odom.wait_for(lambda m: speed(m) < 0.01, 5.0, after=len(robot.odom) - 1), "the base did not stop"


def test_a_gripper_goal_it_cannot_carry_out_is_taken_then_aborted_as_the_gripper_controller_does(
    robot: Robot,
) -> None:
    joints = robot.joint_states.wait_for(lambda _m: True, 5.0)
    assert joints is not None
    fingers = list(joints.position[-2:])
    command = robot.types.new("control_msgs/msg/GripperCommand", position=0.5, max_effort=20.0)  # wider than it opens
    goal = robot.gripper.send_goal(
        robot.types.new(f"{messages.GRIPPER_COMMAND}_Goal", command=command), timeout=GOAL_TIMEOUT
    )
    status, result = goal.result(timeout=GOAL_TIMEOUT)
    assert (status, result.reached_goal, result.stalled) == (GoalStatus.ABORTED, False, False)
    later = robot.joint_states.wait_for(lambda _m: True, 5.0, after=len(robot.joint_states))
    assert later is not None and list(later.position[-2:]) == pytest.approx(fingers, abs=0.001)
