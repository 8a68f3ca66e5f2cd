"""Pausing and resuming a running plan in supervised mode, in safety's gate on a fake clock: only the
operator's token pauses; a paused plan's motion is refused (its goals canceled) while teleop drives;
a resume checks the plan again from where the robot is now; what cannot be paused or resumed is
refused saying what it is; leaving supervised mode decides a paused plan as a pending one."""

from __future__ import annotations

import msgspec
import pytest

from schemas.actions import GoalState, GoalStatus, SendGoal
from schemas.robot import Twist
from schemas.safety import (
    ApprovalAction,
    ApprovalDecision,
    ApprovalReply,
    ApprovalRequest,
    ApprovalState,
    ControlMode,
    Decision,
    PlanApproval,
    Rule,
)
from services.safety.gate import Ruling, SafetyGate
from tests.unit.test_safety_gate import TOKEN, FakeClock, odom
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared
from tests.unit.test_safety_modes import PLAN, clock, gate, go, refused, set_mode

__all__ = ["clock", "gate", "policy"]  # fixtures


def act(
    gate: SafetyGate, goal_id: str, action: ApprovalAction, token: str = TOKEN, reason: str = ""
) -> Ruling[ApprovalReply]:
    return gate.decide(ApprovalDecision(operator="alice", token=token, goal_id=goal_id, action=action, reason=reason))


def running(gate: SafetyGate, goal_id: str = "p1") -> None:
    """Supervised mode, plan `goal_id` approved by an operator and running."""
    assert set_mode(gate, ControlMode.SUPERVISED)
    assert gate.request_approval(ApprovalRequest(goal_id=goal_id, plan=PLAN)).forward.state is ApprovalState.PENDING
    assert act(gate, goal_id, ApprovalAction.APPROVE).forward.ok


def state(gate: SafetyGate, goal_id: str = "p1") -> ApprovalState:
    approval = gate.approval(goal_id)
    assert approval is not None
    return approval.state


def test_a_pause_refuses_the_plans_motion_and_cancels_its_goals_while_teleop_drives(
    gate: SafetyGate, clock: FakeClock
) -> None:
    running(gate)
    assert isinstance(gate.navigate(go()).forward, SendGoal)
    # Not the operator's token: nothing changes, nothing is canceled.
    wrong = act(gate, "p1", ApprovalAction.PAUSE, token="guess")
    assert not wrong.forward.ok and "pause refused for 'alice': not the operator's token" in wrong.forward.message
    assert not wrong.cancel_goals and state(gate) is ApprovalState.APPROVED
    paused = act(gate, "p1", ApprovalAction.PAUSE, reason="someone in the hall")
    assert paused.forward.ok and paused.cancel_goals and paused.approvals_changed
    assert paused.forward.approval is not None and paused.forward.approval.pauses == 1
    assert paused.forward.message == "paused by operator alice: someone in the hall"
    (event,) = paused.events
    assert (event.decision, event.rule) == (Decision.PAUSED, Rule.APPROVAL) and TOKEN not in repr(event)
    assert state(gate) is ApprovalState.PAUSED
    # The plan's motion is refused, saying who paused it and how to hand back; a stop still passes.
    why = refused(gate.navigate(go("n2")))
    assert "plan p1 paused by operator alice" in why and "`tether resume p1`" in why, why
    program = gate.cmd_vel(Twist(linear_x=0.1))
    assert program.forward == Twist() and program.events[0].rule is Rule.APPROVAL
    assert "paused by operator alice" in program.events[0].reason
    assert gate.cmd_vel(Twist()).events[0].decision is Decision.APPROVED
    # The person takes over: teleop drives, clamped as always.
    clock.advance(0.05)
    gate.odometry(odom())
    teleop = gate.teleop(Twist(linear_x=0.2))
    assert teleop.forward is not None and teleop.forward.linear_x > 0.0, teleop
    # The executor, asking, hears it is paused; the operator's list shows it.
    assert gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward.state is ApprovalState.PAUSED
    assert [p.goal_id for p in gate.pending().paused] == ["p1"] and gate.pending().plans == []
    # Resumed: checked again, approved again, motion passes.
    resumed = act(gate, "p1", ApprovalAction.RESUME)
    assert resumed.forward.ok and resumed.forward.message == "resumed by operator alice"
    assert resumed.events[-1].decision is Decision.RESUMED and not resumed.cancel_goals
    assert any(e.key == "safety/check_plan" for e in resumed.events), "a resume checks the plan again"
    assert state(gate) is ApprovalState.APPROVED
    assert isinstance(gate.navigate(go("n3")).forward, SendGoal)
    assert gate.approval("p1").pauses == 1  # type: ignore[union-attr]


def test_what_cannot_be_paused_or_resumed_is_refused_saying_what_it_is(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    unknown = act(gate, "nope", ApprovalAction.PAUSE)
    assert not unknown.forward.ok and "no plan with goal id nope is known" in unknown.forward.message
    assert not unknown.cancel_goals
    gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN))
    pending = act(gate, "p1", ApprovalAction.PAUSE)
    assert not pending.forward.ok and "plan p1 does not run with an approval: it is pending" in pending.forward.message
    not_paused = act(gate, "p1", ApprovalAction.RESUME)
    assert not not_paused.forward.ok and "does not wait paused: it is pending" in not_paused.forward.message
    assert act(gate, "p1", ApprovalAction.APPROVE).forward.ok
    assert not act(gate, "p1", ApprovalAction.RESUME).forward.ok, "a running plan is not resumed"
    assert act(gate, "p1", ApprovalAction.PAUSE).forward.ok
    again = act(gate, "p1", ApprovalAction.PAUSE)
    assert not again.forward.ok and "it is paused" in again.forward.message and not again.cancel_goals
    assert not act(gate, "p1", ApprovalAction.APPROVE).forward.ok, "a paused plan is resumed, not approved"
    # The plan ends while paused (canceled by its sender): finished; nothing to pause or resume.
    gate.plan_status(GoalStatus(goal_id="p1", state=GoalState.CANCELED))
    assert state(gate) is ApprovalState.FINISHED
    finished = act(gate, "p1", ApprovalAction.RESUME)
    assert not finished.forward.ok and "it is finished" in finished.forward.message
    assert "no plan an operator approved is running" in refused(gate.navigate(go()))


def test_a_resume_checks_the_plan_again_and_one_refused_now_is_denied(gate: SafetyGate) -> None:
    running(gate)
    assert act(gate, "p1", ApprovalAction.PAUSE).forward.ok
    gate.latch.trigger("operator", "test", 0.0)
    blocked = act(gate, "p1", ApprovalAction.RESUME)
    assert not blocked.forward.ok and "safety's check refuses it now" in blocked.forward.message
    assert "e-stop latched" in blocked.forward.message and blocked.events[-1].decision is Decision.DENIED
    asked = gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward
    assert asked.state is ApprovalState.DENIED and "refuses it now" in asked.reason


def test_deny_ends_a_paused_plan_and_pause_is_for_supervised_mode_only(gate: SafetyGate) -> None:
    running(gate)
    assert act(gate, "p1", ApprovalAction.PAUSE).forward.ok
    denied = act(gate, "p1", ApprovalAction.DENY, reason="enough")
    assert denied.forward.ok and denied.forward.message == "denied by operator alice: enough"
    assert state(gate) is ApprovalState.DENIED
    assert "no plan an operator approved is running" in refused(gate.navigate(go()))
    # Approved in supervised mode, running on in autonomous mode: nothing to pause there.
    gate.request_approval(ApprovalRequest(goal_id="p2", plan=PLAN))
    assert act(gate, "p2", ApprovalAction.APPROVE).forward.ok
    assert set_mode(gate, ControlMode.AUTONOMOUS)
    outside = act(gate, "p2", ApprovalAction.PAUSE)
    assert not outside.forward.ok and "pause is for supervised mode; the mode is autonomous" in outside.forward.message


@pytest.mark.parametrize(
    ("mode", "decided"), [(ControlMode.AUTONOMOUS, ApprovalState.APPROVED), (ControlMode.DIRECT, ApprovalState.DENIED)]
)
def test_leaving_supervised_mode_while_paused_decides_as_for_a_pending_plan(
    gate: SafetyGate, mode: ControlMode, decided: ApprovalState
) -> None:
    running(gate)
    assert act(gate, "p1", ApprovalAction.PAUSE).forward.ok
    assert set_mode(gate, mode)
    asked = gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward
    assert asked.state is decided and asked.reason.startswith(f"mode {mode}"), asked


def test_a_decision_names_an_action_or_the_older_approve_exactly_once_and_old_records_read(gate: SafetyGate) -> None:
    running(gate)
    for bad in (
        ApprovalDecision(operator="alice", token=TOKEN, goal_id="p1"),
        ApprovalDecision(operator="alice", token=TOKEN, goal_id="p1", approve=False, action=ApprovalAction.PAUSE),
    ):
        ruling = gate.decide(bad)
        assert not ruling.forward.ok and "exactly one" in ruling.forward.message and not ruling.cancel_goals
    assert state(gate) is ApprovalState.APPROVED
    # Recorded before pause existed: they still decode, as they meant.
    old = b'{"operator":"alice","token":"***","goal_id":"p1","approve":true,"reason":""}'
    assert msgspec.json.decode(old, type=ApprovalDecision).approve is True
    approval = msgspec.json.decode(b'{"goal_id":"p1","state":"approved"}', type=PlanApproval)
    assert approval.pauses == 0
    assert isinstance(gate.navigate(go()).forward, SendGoal), "the plan still runs approved"
