"""docs/robot.md as tests: what any robot backend must do for safety, checked over real Zenoh against a real process."""

from __future__ import annotations

import itertools
import math
import time
from typing import Any, TypeVar

import pytest

from schemas import keys
from schemas.actions import GetResult, GoalState, ResultResponse
from schemas.common import Pose2D
from schemas.keys import ActionKeys
from schemas.robot import (
    ARM_JOINTS,
    FINGER_JOINTS,
    GRIPPER_MAX_GAP,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    NavigateToPoseGoal,
    Odometry,
    TrajectoryPoint,
    Twist,
)
from services.actionlib import ActionClient, ClientGoal
from services.errors import GoalRejected
from tests.robot_contract.conftest import RunningBackend
from tests.watch import Watch

G = TypeVar("G")
F = TypeVar("F")
R = TypeVar("R")

# On the household's line y = 1.2 from the start pose (6.0, 1.2) east: clear of walls and furniture.
LANE_Y = 1.2
LANE_WEST, LANE_EAST = 6.3, 9.8
# safety's monitor: odometry or joint states older than this count as unknown, and the watchdog
# latches the e-stop if the robot was moving (services/safety/policy.toml, state_max_age).
STATE_MAX_AGE = 0.5
STILL = 0.02  # m/s, rad/s: at rest
# Generous: two cores shared with other work, and a result or a sample has to cross Zenoh too.
SLACK = 1.0
RESULT_TIMEOUT = 60.0


def here(robot: RunningBackend) -> Odometry:
    latest = robot.odom.latest(timeout=5.0)
    assert latest is not None, "no odometry"
    return latest


def arm(robot: RunningBackend) -> list[float]:
    latest = robot.joint_states.latest(timeout=5.0)
    assert latest is not None, "no joint states"
    return [latest.position[latest.name.index(name)] for name in ARM_JOINTS]


def near_goal(robot: RunningBackend) -> NavigateToPoseGoal:
    """Half a metre along the lane, facing east."""
    x = here(robot).pose.x
    return NavigateToPoseGoal(pose=Pose2D(x=x + 0.5 if x < 8.5 else x - 0.5, y=LANE_Y, yaw=0.0))


def far_goal(robot: RunningBackend) -> NavigateToPoseGoal:
    """The other end of the lane: a few seconds of driving, for goals to be canceled on the way."""
    if here(robot).pose.x < 8.0:
        return NavigateToPoseGoal(pose=Pose2D(x=LANE_EAST, y=LANE_Y, yaw=0.0))
    return NavigateToPoseGoal(pose=Pose2D(x=LANE_WEST, y=LANE_Y, yaw=math.pi))


def swing(robot: RunningBackend, seconds: float) -> FollowJointTrajectoryGoal:
    """Every arm joint where it is, but the first swung by 0.6 rad, over `seconds` of trajectory time."""
    q = arm(robot)
    target = [0.6 if q[0] < 0.3 else 0.0, *q[1:]]
    return FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=target, time_from_start=seconds)]
    )


def send(robot: RunningBackend, action: ActionKeys[G, F, R], goal: G) -> ClientGoal[G, F, R]:
    return ActionClient(robot.node, action).send(goal, timeout=15.0)


def send_once_ready(
    robot: RunningBackend, action: ActionKeys[G, F, R], goal: G, timeout: float = 5.0
) -> ClientGoal[G, F, R]:
    """Send `goal`, again after each heartbeat while the robot still refuses it (it has yet to hear
    that it may move again)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return send(robot, action, goal)
        except GoalRejected:
            if time.monotonic() > deadline:
                raise
            robot.safety.beats(1)


def result(handle: ClientGoal[Any, Any, R]) -> ResultResponse[R]:
    return handle.result(timeout=RESULT_TIMEOUT)


def moving_base(robot: RunningBackend) -> None:
    assert robot.odom.wait_for(lambda o: abs(o.linear_x) > 0.1, timeout=20.0, after=len(robot.odom)), "never drove"


def moving_arm(robot: RunningBackend) -> None:
    moving = robot.joint_states.wait_for(
        lambda j: abs(j.velocity[0]) > 0.02, timeout=20.0, after=len(robot.joint_states)
    )
    assert moving, "the arm never moved"


def base_at_rest(robot: RunningBackend, timeout: float = SLACK) -> Odometry | None:
    return robot.odom.wait_for(
        lambda o: abs(o.linear_x) < STILL and abs(o.angular_z) < STILL, timeout=timeout, after=len(robot.odom)
    )


def arm_at_rest(robot: RunningBackend, timeout: float = SLACK) -> bool:
    def still(j: Any) -> bool:
        return max(abs(v) for v in j.velocity[: len(ARM_JOINTS)]) < STILL

    return robot.joint_states.wait_for(still, timeout=timeout, after=len(robot.joint_states)) is not None


def stream(robot: RunningBackend, twist: Twist, beats: int) -> None:
    """cmd_vel once per heartbeat, as safety relays a stream it approved."""
    for _ in range(beats):
        robot.node.publish(keys.ROBOT_CMD_VEL, twist)
        robot.safety.beats(1)


# Reports


@pytest.mark.parametrize("topic", ["odom", "joint_states", "objects", "humans"])
def test_the_robots_reports_come_at_their_configured_rates(robot: RunningBackend, topic: str) -> None:
    watch: Watch[Any] = getattr(robot, topic)
    hz: float = getattr(robot.backend, f"{topic}_hz")
    count = max(10, int(hz))  # a second's worth, or ten
    start = len(watch)
    assert watch.wait_for(lambda _: True, timeout=10.0, after=start + count - 1), f"fewer than {count} {topic}"
    samples = watch.messages[start : start + count]
    stamps = [m.stamp for m in samples]
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert all(g > 0 for g in gaps), f"{topic} stamps must increase"
    rate = (count - 1) / (stamps[-1] - stamps[0])
    # Tolerant below (a machine under load wakes the backend late), strict above: a backend over
    # its rate floods the recorder. What safety needs is the bound on the gaps, below.
    assert 0.3 * hz <= rate <= 1.2 * hz, f"{topic} at {rate:.1f} Hz, configured {hz:g} Hz"
    if topic in ("odom", "joint_states"):
        assert max(gaps) < STATE_MAX_AGE, f"{topic} fell silent for {max(gaps):.2f} s: safety's watchdog would latch"
    if topic == "joint_states":
        names = samples[-1].name
        assert set(ARM_JOINTS) | set(FINGER_JOINTS) <= set(names)
        assert len(samples[-1].position) == len(samples[-1].velocity) == len(names)


# Goals: accepted, feedback, result


def test_a_navigation_goal_reports_feedback_and_status_and_ends_at_the_pose(robot: RunningBackend) -> None:
    status, feedback = Watch(robot.node, keys.ROBOT_NAVIGATE.status), Watch(robot.node, keys.ROBOT_NAVIGATE.feedback)
    goal = near_goal(robot)
    handle = send(robot, keys.ROBOT_NAVIGATE, goal)
    done = result(handle)
    assert done.state is GoalState.SUCCEEDED, done.message
    assert done.result is not None
    pose = done.result.pose
    assert math.hypot(pose.x - goal.pose.x, pose.y - goal.pose.y) < 0.05
    assert abs(math.remainder(pose.yaw - goal.pose.yaw, math.tau)) < 0.05
    ours = [f.feedback for f in feedback.messages if f.goal_id == handle.goal_id]
    assert ours, "no feedback"
    assert ours[-1].distance_remaining < ours[0].distance_remaining
    assert status.wait_for(lambda s: s.goal_id == handle.goal_id and s.state is GoalState.SUCCEEDED, timeout=5.0)
    states = [s.state for s in status.messages if s.goal_id == handle.goal_id]
    assert states[0] is GoalState.ACCEPTED and GoalState.EXECUTING in states and states[-1] is GoalState.SUCCEEDED
    odom = here(robot).pose
    assert math.hypot(odom.x - goal.pose.x, odom.y - goal.pose.y) < 0.05, "odometry disagrees with the result"


def test_a_trajectory_goal_reports_feedback_and_ends_within_its_tolerance(robot: RunningBackend) -> None:
    feedback = Watch(robot.node, keys.ROBOT_TRAJECTORY.feedback)
    goal = swing(robot, 1.0)
    handle = send(robot, keys.ROBOT_TRAJECTORY, goal)
    done = result(handle)
    assert done.state is GoalState.SUCCEEDED, done.message
    assert done.result is not None and done.result.error < goal.goal_tolerance
    ours = [f.feedback for f in feedback.messages if f.goal_id == handle.goal_id]
    assert ours and len(ours[-1].desired) == len(ours[-1].actual) == len(ARM_JOINTS)
    target = goal.points[-1].positions
    assert robot.joint_states.wait_for(
        lambda j: abs(j.position[j.name.index(ARM_JOINTS[0])] - target[0]) < goal.goal_tolerance,
        timeout=5.0,
        after=max(0, len(robot.joint_states) - 1),
    ), "joint states disagree with the result"


def test_the_gripper_closes_and_opens_to_the_goal_gap(robot: RunningBackend) -> None:
    closed = result(send(robot, keys.ROBOT_GRIPPER, GripperCommandGoal(position=0.0)))
    assert closed.state is GoalState.SUCCEEDED, closed.message
    assert closed.result is not None and closed.result.position < 0.005 and closed.result.holding is None
    opened = result(send(robot, keys.ROBOT_GRIPPER, GripperCommandGoal(position=GRIPPER_MAX_GAP)))
    assert opened.state is GoalState.SUCCEEDED, opened.message
    assert opened.result is not None and opened.result.reached_goal
    assert opened.result.position > GRIPPER_MAX_GAP - 0.005


# Goals: rejected, canceled, preempted


def test_a_trajectory_the_arm_cannot_follow_is_rejected_with_the_reason(robot: RunningBackend) -> None:
    q = arm(robot)
    unknown = FollowJointTrajectoryGoal(
        joint_names=["panda_joint9"], points=[TrajectoryPoint(positions=[0.0], time_from_start=1.0)]
    )
    with pytest.raises(GoalRejected, match="panda_joint9"):
        send(robot, keys.ROBOT_TRAJECTORY, unknown)
    beyond = FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=[5.0, *q[1:]], time_from_start=1.0)]
    )
    with pytest.raises(GoalRejected, match=ARM_JOINTS[0]):
        send(robot, keys.ROBOT_TRAJECTORY, beyond)


def test_a_navigation_checked_from_elsewhere_ends_at_once_and_the_base_stays(robot: RunningBackend) -> None:
    start = here(robot).pose
    elsewhere = Pose2D(x=start.x + 1.0, y=start.y, yaw=start.yaw)
    done = result(send(robot, keys.ROBOT_NAVIGATE, NavigateToPoseGoal(pose=elsewhere, start=elsewhere)))
    assert done.state is GoalState.ABORTED and done.message
    now = here(robot).pose
    assert math.hypot(now.x - start.x, now.y - start.y) < 0.01


def test_a_canceled_goal_ends_canceled_and_the_robot_comes_to_rest(robot: RunningBackend) -> None:
    drive = send(robot, keys.ROBOT_NAVIGATE, far_goal(robot))
    moving_base(robot)
    assert drive.cancel().accepted
    canceled = result(drive)
    assert canceled.state is GoalState.CANCELED, canceled.message
    assert canceled.result is not None, "a canceled goal still reports where it ended"
    assert base_at_rest(robot), "the base kept moving after the cancel"

    slow = send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 12.0))
    moving_arm(robot)
    assert slow.cancel().accepted
    assert result(slow).state is GoalState.CANCELED
    assert arm_at_rest(robot), "the arm kept moving after the cancel"


@pytest.mark.parametrize("action", ["navigate", "trajectory"])
def test_a_new_goal_preempts_the_running_one(robot: RunningBackend, action: str) -> None:
    if action == "navigate":
        first = send(robot, keys.ROBOT_NAVIGATE, far_goal(robot))
        moving_base(robot)
        # Accepted only once the first has ended: two goals never drive the robot at once.
        second: ClientGoal[Any, Any, Any] = send(robot, keys.ROBOT_NAVIGATE, near_goal(robot))
    else:
        first = send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 12.0))
        moving_arm(robot)
        second = send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0))
    preempted = result(first)
    assert preempted.state in (GoalState.CANCELED, GoalState.ABORTED), preempted.state
    assert "preempted" in preempted.message
    finished = result(second)
    assert finished.state is GoalState.SUCCEEDED, finished.message


# Safety: e-stop, heartbeat, cmd_vel, speed limits


def test_until_the_first_heartbeat_the_robot_refuses_goals_and_ignores_cmd_vel(unheard_robot: RunningBackend) -> None:
    robot = unheard_robot
    asked = time.monotonic()
    with pytest.raises(GoalRejected, match="heartbeat"):
        send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0))
    waited = time.monotonic() - asked
    # It waits for a heartbeat a while, as after start-up the peers may still be connecting.
    assert waited > 0.5 * robot.backend.first_heartbeat_wait, f"refused after {waited:.2f} s"
    n = len(robot.odom)
    for _ in range(10):
        robot.node.publish(keys.ROBOT_CMD_VEL, Twist(angular_z=0.6))
        assert robot.odom.wait_for(lambda _: True, timeout=2.0, after=len(robot.odom)), "no odometry"
    assert robot.odom.wait_for(lambda _: True, timeout=2.0, after=n + 20)
    assert all(abs(o.angular_z) < STILL for o in robot.odom.messages[n:]), "cmd_vel moved an unheard robot"

    robot.safety.set()
    started = send_once_ready(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0))
    assert result(started).state is GoalState.SUCCEEDED


def test_an_estop_in_the_heartbeat_halts_base_and_arm_and_refuses_everything(robot: RunningBackend) -> None:
    drive = send(robot, keys.ROBOT_NAVIGATE, far_goal(robot))
    swinging = send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 12.0))
    moving_base(robot)
    moving_arm(robot)
    robot.safety.set(latched=True)
    for handle in (drive, swinging):
        stopped = result(handle)
        assert stopped.state is GoalState.ABORTED and "e-stop" in stopped.message, stopped.message
    assert base_at_rest(robot), "the base still moves under a latched e-stop"
    assert arm_at_rest(robot), "the arm still moves under a latched e-stop"

    with pytest.raises(GoalRejected, match="e-stop"):
        send(robot, keys.ROBOT_NAVIGATE, near_goal(robot))
    n = len(robot.odom)
    stream(robot, Twist(angular_z=0.6), beats=15)
    assert robot.odom.wait_for(lambda _: True, timeout=2.0, after=n + 10)
    assert all(abs(o.angular_z) < STILL for o in robot.odom.messages[n:]), "cmd_vel moved a latched robot"

    robot.safety.set()
    again = send_once_ready(robot, keys.ROBOT_GRIPPER, GripperCommandGoal(position=GRIPPER_MAX_GAP))
    assert result(again).state is GoalState.SUCCEEDED


def test_losing_the_heartbeat_halts_the_robot_within_the_timeout(robot: RunningBackend) -> None:
    drive = send(robot, keys.ROBOT_NAVIGATE, far_goal(robot))
    moving_base(robot)
    last_beat = robot.safety.silence()
    stopped = result(drive)
    noticed = time.monotonic() - last_beat
    assert stopped.state is GoalState.ABORTED and "heartbeat" in stopped.message, stopped.message
    assert noticed < robot.backend.heartbeat_timeout + SLACK, f"stopped {noticed:.2f} s after the last heartbeat"
    assert base_at_rest(robot), "the base still moves without a heartbeat"
    with pytest.raises(GoalRejected, match="heartbeat"):
        send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0))

    robot.safety.set()
    again = send_once_ready(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0))
    assert result(again).state is GoalState.SUCCEEDED


def test_cmd_vel_drives_the_base_and_holds_only_until_its_timeout(robot: RunningBackend) -> None:
    stream(robot, Twist(angular_z=0.6), beats=10)
    assert robot.odom.wait_for(lambda o: o.angular_z > 0.3, timeout=5.0, after=len(robot.odom)), (
        "cmd_vel never turned it"
    )
    stopped_sending = time.time()
    rest = base_at_rest(robot, timeout=robot.backend.cmd_vel_timeout + SLACK)
    assert rest is not None, "the base kept turning after cmd_vel stopped"
    held = rest.stamp - stopped_sending
    assert held > 0.5 * robot.backend.cmd_vel_timeout, f"stopped {held:.2f} s after the last cmd_vel: too soon"


def test_the_base_keeps_to_the_heartbeats_speed_limit(robot: RunningBackend) -> None:
    limit = 0.3
    robot.safety.set(max_angular_speed=limit)
    assert robot.safety.beats(3)
    n = len(robot.odom)
    stream(robot, Twist(angular_z=1.0), beats=40)
    turning = [abs(o.angular_z) for o in robot.odom.messages[n:]]
    assert max(turning) > 0.5 * limit, "cmd_vel never turned the base"
    assert max(turning) < limit + 0.05, f"turned at {max(turning):.2f} rad/s under a {limit} rad/s limit"


def test_speed_scale_zero_pauses_a_goal_and_it_resumes(robot: RunningBackend) -> None:
    drive = send(robot, keys.ROBOT_NAVIGATE, far_goal(robot))
    moving_base(robot)
    robot.safety.set(speed_scale=0.0)
    assert base_at_rest(robot, timeout=robot.backend.heartbeat_timeout + SLACK), "the base did not pause"
    paused = robot.node.call(keys.ROBOT_NAVIGATE.get_status, GetResult(goal_id=drive.goal_id), timeout=5.0)
    assert paused.state is GoalState.EXECUTING, paused.message
    robot.safety.set()
    moving_base(robot)  # and on to the goal: no need to wait for it
    assert drive.cancel().accepted
