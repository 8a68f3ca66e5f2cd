"""Supervised mode's book of plans under pressure, in safety's gate on a fake clock: a flood of plans
past MAX_WAITING is refused naming why while the plans that wait stay as the operator sees them; and
what a plan, a peer or a timing must not get past it: a plan asked for under a goal id while another
is being checked under it, a plan the mode let run without an operator when supervised mode is back,
another plan's approval while one is paused, a plan that ended before safety held it."""

from __future__ import annotations

from collections.abc import Callable

from schemas.actions import GoalState, GoalStatus, SendGoal
from schemas.common import Pose2D
from schemas.plan import GroundedPlan, NavigateStep, PlanCheckReply, SayStep
from schemas.robot import Twist
from schemas.safety import ApprovalAction, ApprovalRequest, ApprovalState, ControlMode, Decision, ModeRequest, Rule
from services.safety.gate import Ruling, SafetyGate
from services.safety.modes import MAX_WAITING
from tests.unit.test_safety_gate import TOKEN, FakeClock
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared
from tests.unit.test_safety_modes import PLAN, SOURCE, clock, gate, go, refused, set_mode
from tests.unit.test_safety_pause import act, state

__all__ = ["clock", "gate", "policy"]  # fixtures

OTHER = GroundedPlan(steps=[NavigateStep(target="there", goal=Pose2D(x=6.2, y=1.4)), SayStep(text="ho")], source=SOURCE)


def ask(gate: SafetyGate, goal_id: str, plan: GroundedPlan = PLAN) -> ApprovalState:
    return gate.request_approval(ApprovalRequest(goal_id=goal_id, plan=plan)).forward.state


def during_check(gate: SafetyGate, meanwhile: Callable[[], object]) -> None:
    """The next plan check of `gate` lets `meanwhile` happen first (another thread's input arriving
    while it checks), once."""
    real = gate.check_plan

    def check(plan: GroundedPlan) -> Ruling[PlanCheckReply]:
        gate.check_plan = real  # type: ignore[method-assign]
        meanwhile()
        return real(plan)

    gate.check_plan = check  # type: ignore[method-assign]


# A flood of plans


def test_past_max_waiting_a_plan_is_refused_naming_why_and_the_waiting_ones_stay(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    for i in range(MAX_WAITING):
        assert ask(gate, f"w{i}") is ApprovalState.PENDING
    seen = [(p.goal_id, p.steps) for p in gate.pending().plans]
    for i in range(3 * MAX_WAITING):
        flood = gate.request_approval(ApprovalRequest(goal_id=f"f{i}", plan=OTHER))
        assert flood.forward.state is ApprovalState.DENIED
        assert flood.forward.reason == f"{MAX_WAITING} plans already wait for an operator: decide those first"
        assert flood.events[-1].decision is Decision.DENIED and flood.events[-1].rule is Rule.APPROVAL
    # Asked again, still refused (not taken in later, unseen); the operator's view is as it was.
    assert ask(gate, "f0", OTHER) is ApprovalState.DENIED
    assert [(p.goal_id, p.steps) for p in gate.pending().plans] == seen
    assert act(gate, "w0", ApprovalAction.APPROVE).forward.ok
    assert isinstance(gate.navigate(go()).forward, SendGoal)
    assert ask(gate, "late", OTHER) is ApprovalState.PENDING  # one decided: room for one more


# Timings and peers


def test_a_plan_asked_for_while_another_is_checked_under_its_goal_id_does_not_replace_it(gate: SafetyGate) -> None:
    """Two plans asked for at once under one goal id: both found the book empty, and the one whose
    check ended last replaced the other, also after the operator had seen (or approved) the first."""
    assert set_mode(gate, ControlMode.SUPERVISED)
    during_check(gate, lambda: ask(gate, "p1", PLAN))
    late = gate.request_approval(ApprovalRequest(goal_id="p1", plan=OTHER)).forward
    assert late.state is ApprovalState.DENIED and "another plan" in late.reason
    (waiting,) = gate.pending().plans
    assert waiting.steps[0].startswith("1. navigate_to near")
    assert act(gate, "p1", ApprovalAction.APPROVE).forward.ok
    assert ask(gate, "p1", PLAN) is ApprovalState.APPROVED
    assert ask(gate, "p1", OTHER) is ApprovalState.DENIED


def test_the_same_plan_asked_twice_at_once_keeps_an_approval_given_meanwhile(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)

    def asked_and_approved() -> None:
        ask(gate, "p1")
        assert act(gate, "p1", ApprovalAction.APPROVE).forward.ok

    during_check(gate, asked_and_approved)
    assert ask(gate, "p1") is ApprovalState.APPROVED
    assert state(gate) is ApprovalState.APPROVED


def test_a_plan_the_mode_let_run_needs_an_operator_when_supervised_mode_is_back(gate: SafetyGate) -> None:
    """Pending, then autonomous (the executor's next ask: approved by the mode), then supervised
    again: it went on moving the robot as if an operator had approved it."""
    assert set_mode(gate, ControlMode.SUPERVISED)
    assert ask(gate, "p1") is ApprovalState.PENDING
    assert set_mode(gate, ControlMode.AUTONOMOUS)
    assert ask(gate, "p1") is ApprovalState.APPROVED
    assert isinstance(gate.navigate(go()).forward, SendGoal)
    ruling = gate.set_mode(ModeRequest(operator="alice", token=TOKEN, mode=ControlMode.SUPERVISED))
    assert ruling.forward.ok and ruling.cancel_goals
    assert "no plan an operator approved is running" in refused(gate.navigate(go("n2")))
    assert gate.cmd_vel(Twist(linear_x=0.1)).forward == Twist()
    now = gate.approval("p1")
    assert now is not None and now.state is ApprovalState.DENIED and "not an operator" in now.reason
    assert any(e.decision is Decision.DENIED and "p1" in e.reason for e in ruling.events)
    # An operator's approval is one still.
    assert ask(gate, "p2") is ApprovalState.PENDING and act(gate, "p2", ApprovalAction.APPROVE).forward.ok
    assert set_mode(gate, ControlMode.AUTONOMOUS) and set_mode(gate, ControlMode.SUPERVISED)
    assert isinstance(gate.navigate(go("n3")).forward, SendGoal)


def test_a_paused_plan_stops_a_programs_motion_whatever_else_is_approved(gate: SafetyGate) -> None:
    """Two plans approved (one of them the executor's, one asked for by anyone and approved, or one
    whose end was never heard): pausing the running one left the other's approval letting every
    program's motion pass."""
    assert set_mode(gate, ControlMode.SUPERVISED)
    for goal_id in ("p1", "p2"):
        assert ask(gate, goal_id) is ApprovalState.PENDING
        assert act(gate, goal_id, ApprovalAction.APPROVE).forward.ok
    paused = act(gate, "p1", ApprovalAction.PAUSE)
    assert paused.forward.ok and paused.cancel_goals
    assert "plan p1 paused by operator alice" in refused(gate.navigate(go()))
    assert gate.cmd_vel(Twist(linear_x=0.1)).forward == Twist()
    assert act(gate, "p1", ApprovalAction.RESUME).forward.ok
    assert isinstance(gate.navigate(go("n2")).forward, SendGoal)


def test_a_plan_that_ended_before_safety_held_it_is_never_approved(gate: SafetyGate, clock: FakeClock) -> None:
    """The executor gave up asking (its call timed out while safety checked the plan) and reported
    the plan ended before safety put it in the book: it then waited, an operator could approve it,
    and as no end would ever come again it let every program's motion pass for as long as safety ran."""
    assert set_mode(gate, ControlMode.SUPERVISED)
    during_check(gate, lambda: gate.plan_status(GoalStatus(goal_id="p1", state=GoalState.ABORTED)))
    asked = gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward
    assert asked.state is ApprovalState.DENIED and "ended" in asked.reason
    assert gate.pending().plans == []
    assert not act(gate, "p1", ApprovalAction.APPROVE).forward.ok
    assert "no plan an operator approved is running" in refused(gate.navigate(go()))
