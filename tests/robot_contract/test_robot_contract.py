"""docs/robot.md as tests: what any robot backend must do for safety, checked over real Zenoh against a real process."""

from __future__ import annotations

import itertools
import math
import time
import uuid
from collections.abc import Callable
from typing import Any, TypeVar

import msgspec
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
from services.safety.policyfile import MonitorPolicy
from tests.robot_contract.conftest import REPORTS, RunningBackend
from tests.watch import Watch

# Bounds in wall-clock time: `make test` runs these one at a time at normal priority (tests/suite.py).
# `alone` (tests/suite.py): the played safety's heartbeat comes from this test process, and beside the
# rest of the suite one came 200 ms late now and then, which (rightly) stops the robot mid-test.
pytestmark = [pytest.mark.realtime, pytest.mark.alone]

G = TypeVar("G")
F = TypeVar("F")
R = TypeVar("R")

# Goals keep this far from the lane's ends (metres).
LANE_MARGIN = 0.3
# safety's monitor: odometry or joint states older than this count as unknown, and the watchdog
# latches the e-stop if the robot was moving (the policy's monitor.state_max_age).
STATE_MAX_AGE = MonitorPolicy().state_max_age
STILL = 0.02  # m/s, rad/s: at rest
# Generous: two cores shared with other work, and a result or a sample has to cross Zenoh too.
SLACK = 1.0
# A halt (e-stop latched, heartbeat lost) shows in every report stamped this long after it is due:
# the robot stops at once, the rest is a heartbeat crossing Zenoh and the backend's next loop on a
# loaded machine (the sim measured a few milliseconds on two idle cores).
HALT_WITHIN = 0.15
# ... and the base and arm then stay where they stopped for this long.
HELD = 0.5
HELD_TOLERANCE = 0.005  # metres, radians
RESULT_TIMEOUT = 60.0


def here(robot: RunningBackend) -> Odometry:
    latest = robot.odom.latest(timeout=5.0)
    assert latest is not None, "no odometry"
    return latest


def arm(robot: RunningBackend) -> list[float]:
    latest = robot.joint_states.latest(timeout=5.0)
    assert latest is not None, "no joint states"
    return [latest.position[latest.name.index(name)] for name in ARM_JOINTS]


def lane_goal(robot: RunningBackend, s: float, backwards: bool = False) -> NavigateToPoseGoal:
    lane = robot.backend.lane
    x, y = lane.point(s)
    return NavigateToPoseGoal(pose=Pose2D(x=x, y=y, yaw=lane.heading + (math.pi if backwards else 0.0)))


def near_goal(robot: RunningBackend) -> NavigateToPoseGoal:
    """Half a metre along the lane, facing along it."""
    lane, pose = robot.backend.lane, here(robot).pose
    s = lane.along(pose.x, pose.y)
    return lane_goal(robot, s + 0.5 if s < lane.length - 1.5 else s - 0.5)


def far_goal(robot: RunningBackend) -> NavigateToPoseGoal:
    """The other end of the lane: a few seconds of driving, for goals to be canceled on the way."""
    lane, pose = robot.backend.lane, here(robot).pose
    if lane.along(pose.x, pose.y) < lane.length / 2:
        return lane_goal(robot, lane.length - LANE_MARGIN)
    return lane_goal(robot, LANE_MARGIN, backwards=True)


def from_here(robot: RunningBackend, goal: NavigateToPoseGoal) -> NavigateToPoseGoal:
    """`goal` with the start safety fills in: the pose odometry reports now."""
    return msgspec.structs.replace(goal, start=here(robot).pose)


def swing(robot: RunningBackend, seconds: float) -> FollowJointTrajectoryGoal:
    """Every arm joint where it is, but the first swung by 0.6 rad, over `seconds` of trajectory time."""
    q = arm(robot)
    target = [0.6 if q[0] < 0.3 else 0.0, *q[1:]]
    return FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=target, time_from_start=seconds)]
    )


def send(
    robot: RunningBackend, action: ActionKeys[G, F, R], goal: G, goal_id: str | None = None
) -> ClientGoal[G, F, R]:
    return ActionClient(robot.node, action).send(goal, timeout=15.0, goal_id=goal_id)


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


def halted_from(robot: RunningBackend, due: float) -> None:
    """Base and arm report still in every sample stamped from `due` + HALT_WITHIN on (wall seconds),
    and stay where they are for HELD after."""
    since = due + HALT_WITHIN
    until = since + HELD
    assert robot.odom.wait_for(lambda o: o.stamp > until, timeout=until - time.time() + 5.0), "no odometry"
    assert robot.joint_states.wait_for(lambda j: j.stamp > until, timeout=5.0), "no joint states"
    odom = [o for o in robot.odom.messages if since <= o.stamp <= until]
    joints = [j for j in robot.joint_states.messages if since <= j.stamp <= until]
    assert odom and joints, "no reports in the halt window"
    moving = [o for o in odom if abs(o.linear_x) >= STILL or abs(o.angular_z) >= STILL]
    assert not moving, f"the base still moved {moving[0].stamp - due:.3f} s after the halt was due"
    first, last = odom[0].pose, odom[-1].pose
    drift = math.hypot(last.x - first.x, last.y - first.y) + abs(math.remainder(last.yaw - first.yaw, math.tau))
    assert drift < HELD_TOLERANCE, f"the base drifted {drift:.4f} after the halt"
    n = len(ARM_JOINTS)
    swinging = [j for j in joints if max(abs(v) for v in j.velocity[:n]) >= STILL]
    assert not swinging, f"the arm still moved {swinging[0].stamp - due:.3f} s after the halt was due"
    arm_drift = max(abs(a - b) for a, b in zip(joints[0].position[:n], joints[-1].position[:n], strict=True))
    assert arm_drift < HELD_TOLERANCE, f"the arm drifted {arm_drift:.4f} rad after the halt"


def stream(robot: RunningBackend, twist: Twist, beats: int) -> None:
    """cmd_vel once per heartbeat, as safety relays a stream it approved."""
    for _ in range(beats):
        robot.node.publish(keys.ROBOT_CMD_VEL, twist)
        robot.safety.beats(1)


# Reports


@pytest.mark.parametrize("topic", REPORTS)
def test_the_robots_reports_come_at_their_configured_rates(robot: RunningBackend, topic: str) -> None:
    watch: Watch[Any] = getattr(robot, topic)
    hz: float = getattr(robot.backend, f"{topic}_hz")
    count = max(10, int(hz))  # a second's worth, or ten
    start = robot.rate_start(topic)  # the same moment for the four reports: measured side by side
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


def test_a_new_trajectory_preempts_the_running_one_which_ends_canceled_first(robot: RunningBackend) -> None:
    first = send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 12.0))
    moving_arm(robot)
    second_id = uuid.uuid4().hex
    second = send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0), goal_id=second_id)
    # Accepted only once the first had ended: two goals never drive the same joints at once.
    ended_first(robot, keys.ROBOT_TRAJECTORY, first, second_id)
    finished = result(second)
    assert finished.state is GoalState.SUCCEEDED, finished.message


def test_a_new_navigation_preempts_the_running_one_checked_from_where_the_base_then_stood(
    robot: RunningBackend,
) -> None:
    first = send(robot, keys.ROBOT_NAVIGATE, far_goal(robot))
    assert robot.odom.wait_for(lambda o: abs(o.linear_x) > 0.45, timeout=20.0, after=len(robot.odom)), "never drove"
    # As safety sends it: checked from where odometry has the base now, while it is still driving.
    second_id = uuid.uuid4().hex
    second = send(robot, keys.ROBOT_NAVIGATE, from_here(robot, near_goal(robot)), goal_id=second_id)
    ended_first(robot, keys.ROBOT_NAVIGATE, first, second_id)
    # The first braked to rest away from where the second was checked from: the second is refused.
    refused = result(second)
    assert refused.state is GoalState.ABORTED and "checked from" in refused.message, refused.message
    # The executor's way on: the next goal checked from where the base stands still.
    assert base_at_rest(robot, timeout=SLACK + 1.0), "the base did not come to rest"
    again = result(send(robot, keys.ROBOT_NAVIGATE, from_here(robot, near_goal(robot))))
    assert again.state is GoalState.SUCCEEDED, again.message


def ended_first(
    robot: RunningBackend, action: ActionKeys[Any, Any, Any], first: ClientGoal[Any, Any, Any], by: str
) -> None:
    """Right after the preempting goal `by` was accepted, `first` has ended canceled, naming it."""
    status = robot.node.call(action.get_status, GetResult(goal_id=first.goal_id), timeout=5.0)
    assert status.state is GoalState.CANCELED, (status.state, status.message)
    assert f"preempted by goal {by}" in status.message, status.message


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
    assert robot.safety.beats(1)
    for handle in (drive, swinging):
        stopped = result(handle)
        assert stopped.state is GoalState.ABORTED and "e-stop" in stopped.message, stopped.message
    halted_from(robot, robot.safety.applied)

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
    swinging = send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 12.0))
    moving_base(robot)
    moving_arm(robot)
    last_beat = robot.safety.silence()
    for handle in (drive, swinging):
        stopped = result(handle)
        assert stopped.state is GoalState.ABORTED and "heartbeat" in stopped.message, stopped.message
    halted_from(robot, last_beat + robot.backend.heartbeat_timeout)
    with pytest.raises(GoalRejected, match="heartbeat"):
        send(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0))

    robot.safety.set()
    assert succeeds_with_heartbeats(robot, lambda: send_once_ready(robot, keys.ROBOT_TRAJECTORY, swing(robot, 1.0)))


def succeeds_with_heartbeats(robot: RunningBackend, start: Callable[[], ClientGoal[Any, Any, Any]]) -> bool:
    """Whether the goal `start` sends succeeds now that the heartbeat flows again. The stand-in
    safety's beats come from this test process: on a loaded machine one may come late and the
    robot (rightly) aborts; such a goal is sent again, at most twice more."""
    for _ in range(3):
        done = result(start())
        if done.state is GoalState.SUCCEEDED:
            return True
        assert "heartbeat" in done.message, done
        robot.safety.beats(2)
    return False


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
