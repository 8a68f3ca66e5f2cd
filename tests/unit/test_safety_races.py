"""Safety's node on several threads at once: a decision taken on state another thread changes in
between. Each race is made to happen every time with events (a hook where one thread is, the other
thread's input delivered there), on the Recorder stand-in of test_safety_node."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from schemas import keys
from schemas.actions import CancelGoal, GetResult, GoalResponse, GoalState, SendGoal
from schemas.common import ErrorKind, ServiceError
from schemas.robot import GripperCommandGoal, Twist
from schemas.safety import (
    ApprovalAction,
    ApprovalRequest,
    ApprovalState,
    ControlMode,
    ModeRequest,
    PendingPlans,
    PlanApproval,
    ResetRequest,
    SafetyStatus,
)
from schemas.world import Empty
from services.errors import CallError
from tests.unit.test_safety_modes import PLAN
from tests.unit.test_safety_node import WAIT, FakeClock, Start, approved_in_supervised_mode, odometry
from tests.unit.test_safety_node import start as start  # the fixture, shared
from tests.unit.test_safety_one_motion import AHEAD, HOLD, robot_says, robot_state


def last_twist(sent: list[tuple[str, Any]]) -> Twist:
    return [m for path, m in sent if path == keys.ROBOT_CMD_VEL.path][-1]


def set_mode(mode: ControlMode) -> ModeRequest:
    return ModeRequest(operator="alice", token="token", mode=mode)


@pytest.mark.parametrize("stop", ["pause", "mode direct"])
def test_teleop_speeds_up_from_the_stop_a_pause_or_mode_change_put_on_robot_cmd_vel(start: Start, stop: str) -> None:
    """The stop was put on robot/cmd_vel but not noted as sent: teleop, which speeds up from what the
    robot was last told, went on from the program's 0.3 m/s, so the base went from the stop to 0.3
    m/s at once."""
    clock = FakeClock(0.0)
    node, safety = start(clock=clock)
    decide = approved_in_supervised_mode(node)
    node.callbacks[keys.CMD_VEL.path](Twist(linear_x=0.3))
    assert last_twist(node.sent) == Twist(linear_x=0.3)
    clock.now = 0.05
    if stop == "pause":
        assert decide(ApprovalAction.PAUSE)
    else:
        assert node.callbacks[keys.SET_MODE.path](set_mode(ControlMode.DIRECT)).ok
    assert last_twist(node.sent) == Twist()
    clock.now = 0.1
    node.callbacks[keys.TELEOP_CMD_VEL.path](Twist(linear_x=0.3))
    ramped = safety.gate.policy.policy.base.max_linear_acceleration * 0.05
    assert 0.0 < last_twist(node.sent).linear_x <= ramped + 1e-9, node.sent[-3:]


def test_a_twist_decided_as_the_estop_latches_leaves_teleop_ramping_from_the_stop(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A teleop twist checked just before the latch and noted as sent after it: the latch's stop came
    last on robot/cmd_vel, yet the gate remembered the twist, and after a reset teleop went on from it
    instead of from standstill."""
    clock = FakeClock(0.0)
    node, safety = start(clock=clock)
    node.callbacks[keys.ODOM.path](odometry())
    estop_key = keys.ESTOP.key(node.robot)
    estop = threading.Thread(target=node.callbacks[estop_key], args=(estop_key, b'{"source": "operator"}'))
    told = threading.Event()

    def look(_path: str, message: Any) -> None:
        if isinstance(message, SafetyStatus) and threading.current_thread() is estop:
            told.set()  # the latch's heartbeat: its stop waits for the twist being checked now

    node.on_put = look
    check = safety.gate.policy.check_teleop

    def latch_while_checking(*args: Any) -> Any:
        estop.start()
        assert told.wait(WAIT)
        return check(*args)

    monkeypatch.setattr(safety.gate.policy, "check_teleop", latch_while_checking)
    node.callbacks[keys.TELEOP_CMD_VEL.path](Twist(linear_x=0.1))
    estop.join(WAIT)
    assert last_twist(node.sent) == Twist(), "the latch's stop came last"
    monkeypatch.setattr(safety.gate.policy, "check_teleop", check)
    assert node.callbacks[keys.RESET.path](ResetRequest(operator="alice", token="token")).ok
    clock.now = 0.1
    node.callbacks[keys.TELEOP_CMD_VEL.path](Twist(linear_x=0.3))
    ramped = safety.gate.policy.policy.base.max_linear_acceleration * 0.1
    assert 0.0 < last_twist(node.sent).linear_x <= ramped + 1e-9, node.sent[-3:]


@pytest.mark.parametrize("mode", [ControlMode.AUTONOMOUS, ControlMode.DIRECT])
def test_a_mode_change_wakes_an_executor_waiting_for_approval(start: Start, mode: ControlMode) -> None:
    """The wait ended only on a change of the plan's own approval: a mode that lets it run (or refuses
    it) was applied only when the executor's `wait` ran out."""
    node, safety = start()
    node.callbacks[keys.ODOM.path](odometry())
    assert node.callbacks[keys.SET_MODE.path](set_mode(ControlMode.SUPERVISED)).ok
    looked = threading.Event()
    approval = safety.gate.approval

    def looking(goal_id: str) -> PlanApproval | None:
        looked.set()  # under the condition's lock: a notify now comes once it waits
        return approval(goal_id)

    safety.gate.approval = looking  # type: ignore[method-assign]
    replies: list[PlanApproval] = []
    ask = ApprovalRequest(goal_id="p1", plan=PLAN, wait=5.0)
    waiter = threading.Thread(target=lambda: replies.append(node.callbacks[keys.APPROVAL_REQUEST.path](ask)))
    waiter.start()
    try:
        assert looked.wait(WAIT)
        assert node.callbacks[keys.SET_MODE.path](set_mode(mode)).ok
    finally:
        waiter.join(timeout=2.5)  # half the wait: woken, not timed out
    assert not waiter.is_alive(), "the executor waited out its wait"
    expected = ApprovalState.APPROVED if mode is ControlMode.AUTONOMOUS else ApprovalState.DENIED
    assert [r.state for r in replies] == [expected], replies


def test_an_ask_being_checked_when_the_executor_goes_away_does_not_wait_for_an_operator(start: Start) -> None:
    """Held after the executor's approvals were ended, the ask waited for an operator; approved, it
    let every program's motion pass in supervised mode, with no executor to report its end."""
    node, safety = start()
    node.callbacks[keys.ODOM.path](odometry())
    assert node.callbacks[keys.SET_MODE.path](set_mode(ControlMode.SUPERVISED)).ok
    check = safety.gate.check_plan

    def executor_goes_while_checking(plan: Any) -> Any:
        node.callbacks["alive/executor"](False)
        return check(plan)

    safety.gate.check_plan = executor_goes_while_checking  # type: ignore[method-assign]
    reply = node.callbacks[keys.APPROVAL_REQUEST.path](ApprovalRequest(goal_id="p1", plan=PLAN))
    assert reply.state is ApprovalState.DENIED and "executor went away" in reply.reason, reply
    pending: PendingPlans = node.callbacks[keys.PENDING_PLANS.path](Empty())
    assert not pending.plans


def test_a_gripper_goal_under_a_running_navigations_id_does_not_make_safety_forget_the_navigation(
    start: Start,
) -> None:
    """Goals were noted by id alone: a gripper goal sent under the id of a navigation under way took
    its place, so the navigation was no longer one a trajectory had to wait for, nor one an e-stop
    canceled."""
    node, _safety = start()
    robot_state(node)
    robot_says(node, {"g": GoalState.EXECUTING})
    node.answers[keys.ROBOT_GRIPPER.send_goal.path] = lambda r: GoalResponse(goal_id=r.goal_id, accepted=True)
    assert node.callbacks[keys.CMD_NAVIGATE.send_goal.path](SendGoal(goal_id="g", goal=AHEAD)).accepted
    gripper = SendGoal(goal_id="g", goal=GripperCommandGoal(position=0.04))
    assert node.callbacks[keys.CMD_GRIPPER.send_goal.path](gripper).accepted
    refused = node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](SendGoal(goal_id="arm", goal=HOLD))
    assert not refused.accepted and "a navigation (goal g) is still under way" in refused.reason, refused
    node.callbacks[keys.ESTOP.key(node.robot)](keys.ESTOP.key(node.robot), b'{"source": "operator"}')
    canceled = [
        (action.cancel_goal.path, CancelGoal(goal_id="g")) for action in (keys.ROBOT_NAVIGATE, keys.ROBOT_GRIPPER)
    ]
    node.wait_for(lambda sent: all(cancel in sent for cancel in canceled))


def test_two_gripper_goals_sent_at_once_under_one_id_leave_the_one_the_robot_runs_noted(start: Start) -> None:
    """The first reached the robot after the second, which the robot took; the first, refused (an id
    already used), forgot the id, and the gripper goal running was one no e-stop canceled."""
    node, safety = start()
    taken: list[str] = []
    second_at_robot = threading.Event()
    second_reply: list[GoalResponse] = []
    goal = SendGoal(goal_id="g", goal=GripperCommandGoal(position=0.04))
    send = node.callbacks[keys.CMD_GRIPPER.send_goal.path]
    second = threading.Thread(target=lambda: second_reply.append(send(goal)))

    def robot(request: SendGoal[Any]) -> GoalResponse:
        if threading.current_thread() is second:
            second_at_robot.set()
        else:
            # The first is on its way; the second is sent now. Decided at once (the defect), it
            # reaches the robot first; waiting its turn, it does not.
            second.start()
            second_at_robot.wait(timeout=0.5)
        accepted = request.goal_id not in taken
        taken.append(request.goal_id)
        return GoalResponse(goal_id=request.goal_id, accepted=accepted, reason="" if accepted else "id already used")

    node.answers[keys.ROBOT_GRIPPER.send_goal.path] = robot
    try:
        send(goal)
    finally:
        second.join(timeout=WAIT)
    assert not second.is_alive() and len(second_reply) == 1
    assert "g" in safety._forwarded, "the goal the robot runs was forgotten"
    node.callbacks[keys.ESTOP.key(node.robot)](keys.ESTOP.key(node.robot), b'{"source": "operator"}')
    node.wait_for(lambda sent: (keys.ROBOT_GRIPPER.cancel_goal.path, CancelGoal(goal_id="g")) in sent)


def test_a_result_asked_for_while_the_goal_is_on_its_way_does_not_forget_it(start: Start) -> None:
    """The robot, asked for the result of a goal it had not yet received, knew no such goal, and safety
    forgot it: accepted a moment later, the navigation ran unnoted, so a trajectory went with it (and
    no pause or e-stop would have canceled it)."""
    node, safety = start()
    robot_state(node)
    states: dict[str, GoalState] = {}
    robot_says(node, states)

    def result(request: Any) -> Any:
        if request.goal_id not in states:
            raise CallError(ServiceError(kind=ErrorKind.INVALID_REQUEST, message=f"unknown goal {request.goal_id}"))
        raise AssertionError("not asked once the robot has it")

    node.answers[keys.ROBOT_NAVIGATE.get_result.path] = result
    asked: list[BaseException] = []

    def ask_for_result() -> None:
        try:
            node.callbacks[keys.CMD_NAVIGATE.get_result.path](GetResult(goal_id="g"))
        except CallError as exc:
            asked.append(exc)

    def on_its_way(request: SendGoal[Any]) -> GoalResponse:
        # The client asks for the result before the robot has the goal (and has answered).
        asker = threading.Thread(target=ask_for_result)
        asker.start()
        asker.join(WAIT)
        states[request.goal_id] = GoalState.EXECUTING
        return GoalResponse(goal_id=request.goal_id, accepted=True)

    node.answers[keys.ROBOT_NAVIGATE.send_goal.path] = on_its_way
    assert node.callbacks[keys.CMD_NAVIGATE.send_goal.path](SendGoal(goal_id="g", goal=AHEAD)).accepted
    assert len(asked) == 1, "the robot knew no such goal then"
    assert "g" in safety._forwarded
    refused = node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](SendGoal(goal_id="arm", goal=HOLD))
    assert not refused.accepted and "a navigation (goal g) is still under way" in refused.reason, refused
