"""Review 46 of safety: a twist on robot/cmd_vel and an arm trajectory never move the robot at once.

A trajectory's path is checked from where the base stands, and a program's cmd_vel with the hand's
reach measured now: a base driven while the arm moves takes the hand where neither check looked.
Odometry alone let a trajectory through the moment after a cmd_vel (the base had not started yet),
and a program's cmd_vel went through while a trajectory ran."""

from __future__ import annotations

from typing import Any

import pytest

from schemas import keys
from schemas.actions import GetResult, GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.robot import Twist
from schemas.safety import Decision, Rule, SafetyEvent
from services.safety.gate import SafetyGate
from services.safety.latch import EstopLatch
from services.safety.policy import SafetyPolicy, Verdict
from tests.unit.test_safety_gate import HOME, TOKEN, FakeClock, arm_at, odom
from tests.unit.test_safety_gate import policy as policy  # the fixture, shared
from tests.unit.test_safety_node import Recorder, Start
from tests.unit.test_safety_node import start as start  # the fixture, shared
from tests.unit.test_safety_one_motion import HOLD, robot_says, robot_state

DRIVE = Twist(linear_x=0.3)


@pytest.fixture
def gate(policy: SafetyPolicy) -> tuple[SafetyGate, FakeClock]:
    clock = FakeClock(100.0)
    gate = SafetyGate(policy, EstopLatch(TOKEN), clock, FakeClock(1_700_000_000.0))
    return gate, clock


def still(gate: SafetyGate) -> None:
    """Odometry of a base standing still, the arm at home: both fresh."""
    gate.odometry(odom())
    gate.joint_state(arm_at(HOME[:7]))


def arm_goal(goal_id: str = "arm") -> SendGoal[Any]:
    return SendGoal(goal_id=goal_id, goal=HOLD)


def test_a_trajectory_just_after_a_cmd_vel_is_refused_while_the_base_may_still_move(
    gate: tuple[SafetyGate, FakeClock],
) -> None:
    safety, clock = gate
    still(safety)
    assert safety.cmd_vel(DRIVE).forward == DRIVE
    # The base has not started yet: its odometry says it stands still.
    still(safety)
    refused = safety.trajectory(arm_goal())
    assert isinstance(refused.forward, GoalResponse) and not refused.forward.accepted, refused.forward
    (event,) = refused.events
    assert event.rule is Rule.ONE_MOTION and event.decision is Decision.VETOED
    assert "sent a cmd_vel of 0.3 m/s, 0 rad/s 0.00 s ago and may still be moving" in refused.forward.reason
    assert event.values["speed_mps"] == 0.3
    # Once the robot's hold of it is over, odometry tells (still, here: the trajectory goes).
    clock.advance(safety.policy.policy.base.cmd_vel_horizon + 0.01)
    still(safety)
    assert isinstance(safety.trajectory(arm_goal("arm2")).forward, SendGoal)


def test_a_trajectory_after_a_stop_is_not_held_back(gate: tuple[SafetyGate, FakeClock]) -> None:
    safety, _clock = gate
    still(safety)
    assert safety.cmd_vel(DRIVE).forward == DRIVE
    assert safety.cmd_vel(Twist()).forward == Twist()
    assert isinstance(safety.trajectory(arm_goal()).forward, SendGoal)


def test_a_programs_cmd_vel_while_a_trajectory_may_run_is_refused_and_the_base_stopped(
    gate: tuple[SafetyGate, FakeClock],
) -> None:
    safety, _clock = gate
    still(safety)
    safety.noted = lambda action: "arm" if action is keys.ROBOT_TRAJECTORY else None
    refused = safety.cmd_vel(DRIVE)
    assert refused.forward == Twist(), "refused, and the base stopped"
    (event,) = refused.events
    assert event.rule is Rule.ONE_MOTION and event.decision is Decision.VETOED
    assert "an arm trajectory (goal arm) may still be under way" in event.reason
    # A stop is never refused for it.
    stop = safety.cmd_vel(Twist())
    assert stop.forward == Twist() and stop.events[0].decision is Decision.APPROVED


def driven(node: Recorder) -> list[Twist]:
    return [m for path, m in node.sent if path == keys.ROBOT_CMD_VEL.path]


def one_motion_vetoes(node: Recorder, key: str) -> list[SafetyEvent]:
    return [m for _, m in node.sent if isinstance(m, SafetyEvent) and m.rule is Rule.ONE_MOTION and m.key == key]


def test_through_the_node_a_cmd_vel_waits_for_the_trajectorys_result(start: Start) -> None:
    node, safety = start()
    robot_state(node)
    robot_says(node, {"arm": GoalState.EXECUTING})
    assert node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](arm_goal()).accepted
    node.callbacks[keys.CMD_VEL.path](DRIVE)
    assert DRIVE not in driven(node) and driven(node)[-1] == Twist()
    assert len(one_motion_vetoes(node, keys.CMD_VEL.path)) == 1
    node.answers[keys.ROBOT_TRAJECTORY.get_result.path] = lambda r: ResultResponse(
        goal_id=r.goal_id, state=GoalState.SUCCEEDED
    )
    node.callbacks[keys.CMD_TRAJECTORY.get_result.path](GetResult(goal_id="arm"))
    node.callbacks[keys.CMD_VEL.path](DRIVE)
    assert driven(node)[-1] == DRIVE
    # And the other way round: the trajectory after it is refused, never forwarded.
    robot_state(node)
    refused = node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](arm_goal("arm2"))
    assert not refused.accepted and "may still be moving" in refused.reason, refused
    assert (keys.ROBOT_TRAJECTORY.send_goal.path, arm_goal("arm2")) not in node.sent
    assert "arm2" not in safety._forwarded


def test_a_trajectory_decided_while_a_cmd_vel_is_checked_leaves_only_one_of_them_moving(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The race: the twist's checks pass, a trajectory is noted and decided (no twist sent yet, so it
    goes), then the twist would be sent. It is refused instead: one of the two moves, never both."""
    node, safety = start()
    robot_state(node)
    robot_says(node, {"arm": GoalState.EXECUTING})
    replies: list[GoalResponse] = []
    checked = safety.gate.policy.check_cmd_vel

    def meanwhile(*args: Any, **kwargs: Any) -> Verdict[Twist]:
        verdict = checked(*args, **kwargs)
        replies.append(node.callbacks[keys.CMD_TRAJECTORY.send_goal.path](arm_goal()))
        return verdict

    monkeypatch.setattr(safety.gate.policy, "check_cmd_vel", meanwhile)
    node.callbacks[keys.CMD_VEL.path](DRIVE)
    (reply,) = replies
    assert reply.accepted, reply
    assert DRIVE not in driven(node), "the trajectory went: the twist may not"
    assert len(one_motion_vetoes(node, keys.CMD_VEL.path)) == 1
