"""The arm and the base never move at once: safety refuses a trajectory while a navigation it forwarded
may still run on the robot, and a navigation while a trajectory may, whatever odometry says (a base
just sent off stands still for a moment, and the arm's check passed then)."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from schemas import keys
from schemas.actions import GetResult, GoalProgress, GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.robot import ARM_JOINTS, FollowJointTrajectoryGoal, JointState, NavigateToPoseGoal, TrajectoryPoint
from schemas.safety import Rule, SafetyEvent
from services.errors import CallError
from tests.unit.test_safety_node import HOME, Recorder, Start, odometry
from tests.unit.test_safety_node import start as start  # the fixture, shared

HOLD = FollowJointTrajectoryGoal(
    joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=HOME[: len(ARM_JOINTS)], time_from_start=1.0)]
)
AHEAD = NavigateToPoseGoal(pose=Pose2D(x=6.5, y=1.2))


def robot_state(node: Recorder) -> None:
    """The base standing still where the goals start, the arm at home."""
    node.callbacks[keys.ODOM.path](odometry(0.0))
    joints = JointState(stamp=0.0, name=list(ARM_JOINTS), position=HOME[: len(ARM_JOINTS)])
    node.callbacks[keys.JOINT_STATES.path](joints)


def robot_says(node: Recorder, states: dict[str, GoalState]) -> None:
    """The robot's action servers: every goal accepted; get_status answered from `states` (a goal
    not in it is one the robot knows nothing of)."""

    def status(request: GetResult) -> GoalProgress[Any, Any]:
        if request.goal_id not in states:
            raise CallError(ServiceError(kind=ErrorKind.INVALID_REQUEST, message=f"unknown goal {request.goal_id}"))
        return GoalProgress(goal_id=request.goal_id, state=states[request.goal_id])

    for action in (keys.ROBOT_NAVIGATE, keys.ROBOT_TRAJECTORY):
        node.answers[action.send_goal.path] = lambda r: GoalResponse(goal_id=r.goal_id, accepted=True)
        node.answers[action.get_status.path] = status


def vetoes(node: Recorder) -> list[SafetyEvent]:
    return [m for _, m in node.sent if isinstance(m, SafetyEvent) and m.rule is Rule.ONE_MOTION]


def test_a_trajectory_while_a_navigation_runs_is_refused_and_once_it_ended_is_not(start: Start) -> None:
    node, safety = start()
    robot_state(node)
    states = {"nav": GoalState.EXECUTING}
    robot_says(node, states)
    assert node.callbacks[keys.CMD_NAVIGATE.send_goal.path](SendGoal(goal_id="nav", goal=AHEAD)).accepted
    refused = node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](SendGoal(goal_id="arm", goal=HOLD))
    assert not refused.accepted and "a navigation (goal nav) is still under way" in refused.reason, refused
    assert (keys.ROBOT_TRAJECTORY.send_goal.path, SendGoal(goal_id="arm", goal=HOLD)) not in node.sent
    assert len(vetoes(node)) == 1
    states["nav"] = GoalState.SUCCEEDED  # ended, its result not fetched yet: the robot's word counts
    assert node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](SendGoal(goal_id="arm2", goal=HOLD)).accepted
    # and it is forgotten: not asked about again with every goal after it.
    assert "nav" not in safety._forwarded


def test_a_navigation_while_a_trajectory_runs_is_refused_until_its_result_is_in(start: Start) -> None:
    node, safety = start()
    robot_state(node)
    states = {"arm": GoalState.EXECUTING}
    robot_says(node, states)
    assert node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](SendGoal(goal_id="arm", goal=HOLD)).accepted
    refused = node.callbacks[keys.CMD_NAVIGATE.send_goal.path](SendGoal(goal_id="nav", goal=AHEAD))
    assert not refused.accepted and "an arm trajectory (goal arm) is still under way" in refused.reason, refused
    node.answers[keys.ROBOT_TRAJECTORY.get_result.path] = lambda r: ResultResponse(
        goal_id=r.goal_id, state=GoalState.SUCCEEDED
    )
    node.callbacks[keys.CMD_TRAJECTORY.get_result.path](GetResult(goal_id="arm"))
    assert "arm" not in safety._forwarded
    assert node.callbacks[keys.CMD_NAVIGATE.send_goal.path](SendGoal(goal_id="nav2", goal=AHEAD)).accepted


@pytest.mark.parametrize("answer", ["no reply", "unknown"])
def test_a_robot_that_cannot_say_refuses_the_other_motion_one_that_knows_no_such_goal_does_not(
    start: Start, answer: str
) -> None:
    node, safety = start()
    robot_state(node)
    robot_says(node, {})
    assert node.callbacks[keys.CMD_NAVIGATE.send_goal.path](SendGoal(goal_id="nav", goal=AHEAD)).accepted
    if answer == "no reply":

        def silent(_request: GetResult) -> Any:
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message="no reply"))

        node.answers[keys.ROBOT_NAVIGATE.get_status.path] = silent
    reply = node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](SendGoal(goal_id="arm", goal=HOLD))
    assert reply.accepted is (answer == "unknown"), reply
    # Either way the navigation stays noted: an e-stop still cancels it.
    assert "nav" in safety._forwarded


@pytest.mark.parametrize("first", ["navigation", "trajectory"])
def test_two_goals_sent_at_once_do_not_both_go(start: Start, first: str) -> None:
    """The second goal is decided while the first is still on its way to the robot, which knows
    nothing of it yet: it waits for the robot's answer to the first, then hears it runs."""
    node, _safety = start()
    robot_state(node)
    states: dict[str, GoalState] = {}
    robot_says(node, states)
    kinds: list[tuple[Any, Any, Any]] = [
        (keys.CMD_NAVIGATE, keys.ROBOT_NAVIGATE, AHEAD),
        (keys.CMD_TRAJECTORY, keys.ROBOT_TRAJECTORY, HOLD),
    ]
    if first == "trajectory":
        kinds.reverse()
    (cmd, robot, goal), (other_cmd, other_robot, other_goal) = kinds
    asked_about_first = threading.Event()
    status = node.answers[robot.get_status.path]

    def asked(request: GetResult) -> Any:
        asked_about_first.set()
        return status(request)

    node.answers[robot.get_status.path] = asked
    second_reply: list[GoalResponse] = []
    second = threading.Thread(
        target=lambda: second_reply.append(
            node.callbacks[other_cmd.send_goal.path](SendGoal(goal_id="second", goal=other_goal))
        )
    )

    def on_its_way(request: SendGoal[Any]) -> GoalResponse:
        # The robot has the first goal but has not answered yet; the second goal is sent now. Decided
        # at once (the defect), it asks about the first here; waiting its turn, it does not.
        second.start()
        asked_about_first.wait(timeout=0.5)
        states[request.goal_id] = GoalState.EXECUTING
        return GoalResponse(goal_id=request.goal_id, accepted=True)

    node.answers[robot.send_goal.path] = on_its_way
    try:
        assert node.callbacks[cmd.send_goal.path](SendGoal(goal_id="first", goal=goal)).accepted
    finally:
        second.join(timeout=10.0)
    assert not second.is_alive()
    assert len(second_reply) == 1 and not second_reply[0].accepted, second_reply
    assert "(goal first) is still under way" in second_reply[0].reason
    assert not [path for path, _ in node.sent if path == other_robot.send_goal.path]
