"""The control modes and plan approval in safety's gate, on a fake clock: what each mode lets move,
who may change it and decide on a plan (the operator's token only), and that the mode survives a restart."""

from __future__ import annotations

from pathlib import Path

import pytest

from schemas.actions import GoalResponse, GoalState, GoalStatus, SendGoal
from schemas.common import Pose2D, ServiceError
from schemas.plan import GroundedPlan, NavigateStep, Plan, PlanApproved, SayStep, Step
from schemas.robot import NavigateToPoseGoal, Twist
from schemas.safety import (
    ApprovalDecision,
    ApprovalRequest,
    ApprovalState,
    ControlMode,
    Decision,
    ModeRequest,
    Rule,
)
from services.safety.gate import SafetyGate
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.policy import SafetyPolicy
from tests.unit.test_safety_gate import HERE, TOKEN, FakeClock, nobody, odom
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared

SOURCE = Plan(steps=[Step(action="stop")])  # type: ignore[arg-type]
# A short drive in the office, clear of everything (the gate tests' HERE is (6.0, 1.2)).
NEAR = Pose2D(x=6.5, y=1.2)
PLAN = GroundedPlan(steps=[NavigateStep(target="near", goal=NEAR), SayStep(text="hi")], source=SOURCE)
STAIRS = GroundedPlan(steps=[NavigateStep(target="stairs", goal=Pose2D(x=11.2, y=8.0))], source=SOURCE)


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def gate(policy: SafetyPolicy, clock: FakeClock, tmp_path: Path) -> SafetyGate:
    modes = ModeFile(tmp_path / "m.json")
    g = SafetyGate(policy, EstopLatch(TOKEN), clock, FakeClock(1_700_000_000.0), modes=modes)
    g.odometry(odom())
    nobody(g)
    return g


def set_mode(gate: SafetyGate, mode: ControlMode, token: str = TOKEN, operator: str = "alice") -> bool:
    return gate.set_mode(ModeRequest(operator=operator, token=token, mode=mode)).forward.ok


def go(goal_id: str = "n1") -> SendGoal[NavigateToPoseGoal]:
    return SendGoal(goal_id=goal_id, goal=NavigateToPoseGoal(pose=NEAR))


def refused(ruling: object) -> str:
    forward = ruling.forward  # type: ignore[attr-defined]
    assert isinstance(forward, GoalResponse) and not forward.accepted, forward
    return forward.reason


def decide(gate: SafetyGate, goal_id: str, approve: bool, token: str = TOKEN, reason: str = "") -> object:
    return gate.decide(ApprovalDecision(operator="alice", token=token, goal_id=goal_id, approve=approve, reason=reason))


def test_the_default_is_autonomous_and_plans_and_goals_pass(gate: SafetyGate) -> None:
    assert gate.mode is ControlMode.AUTONOMOUS and gate.status(1, 0.0).mode is ControlMode.AUTONOMOUS
    assert isinstance(gate.check_plan(PLAN).forward, PlanApproved)
    asked = gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward
    assert asked.state is ApprovalState.NOT_NEEDED
    assert isinstance(gate.navigate(go()).forward, SendGoal)


def test_only_the_operators_token_changes_the_mode_and_a_change_is_an_event(gate: SafetyGate) -> None:
    wrong = gate.set_mode(ModeRequest(operator="agent", token="guess", mode=ControlMode.DIRECT))
    assert not wrong.forward.ok and "not the operator's token" in wrong.forward.message
    assert wrong.forward.mode is ControlMode.AUTONOMOUS and gate.mode is ControlMode.AUTONOMOUS
    assert (wrong.events[0].decision, wrong.events[0].rule) == (Decision.VETOED, Rule.OPERATOR)
    assert not wrong.mode_changed
    right = gate.set_mode(ModeRequest(operator="alice", token=TOKEN, mode=ControlMode.DIRECT))
    assert right.forward.ok and right.mode_changed and gate.mode is ControlMode.DIRECT
    (event,) = right.events
    assert event.decision is Decision.MODE and "autonomous -> direct by operator alice" in event.reason
    assert TOKEN not in repr(right.events)
    assert gate.status(2, 0.0).mode is ControlMode.DIRECT


def test_wrong_tokens_for_the_mode_count_against_the_same_limit_as_resets(gate: SafetyGate) -> None:
    for _ in range(5):
        assert not set_mode(gate, ControlMode.DIRECT, token="guess", operator="mallory")
    locked = gate.set_mode(ModeRequest(operator="mallory", token="guess", mode=ControlMode.DIRECT)).forward
    assert "too many attempts" in locked.message
    assert gate.mode is ControlMode.AUTONOMOUS


def test_the_mode_survives_a_restart_and_an_unreadable_file_starts_supervised(gate: SafetyGate, tmp_path: Path) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    gate.modes.save()
    assert ModeFile(tmp_path / "m.json").mode is ControlMode.SUPERVISED
    assert ModeFile(tmp_path / "missing.json").mode is ControlMode.AUTONOMOUS
    (tmp_path / "bad.json").write_text("{not json")
    assert ModeFile(tmp_path / "bad.json").mode is ControlMode.SUPERVISED


def test_direct_refuses_plans_and_a_programs_motion_but_teleop_drives_clamped(
    gate: SafetyGate, clock: FakeClock
) -> None:
    assert set_mode(gate, ControlMode.DIRECT)
    checked = gate.check_plan(PLAN)
    assert isinstance(checked.forward, ServiceError)
    assert checked.forward.message == "mode direct: only the operator drives (teleop); plans are refused"
    assert checked.events[0].rule is Rule.MODE
    assert "mode direct" in refused(gate.navigate(go()))
    program = gate.cmd_vel(Twist(linear_x=0.2))
    assert program.forward == Twist() and program.events[0].rule is Rule.MODE
    stop = gate.cmd_vel(Twist())
    assert stop.forward == Twist() and stop.events[0].decision is Decision.APPROVED
    clock.advance(0.05)
    gate.odometry(odom())
    teleop = gate.teleop(Twist(linear_x=5.0))
    assert teleop.forward is not None and 0.0 < teleop.forward.linear_x < 1.0
    assert teleop.events[0].decision is Decision.CLAMPED


def test_shared_refuses_plans_like_direct_with_its_own_reason(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SHARED)
    checked = gate.check_plan(PLAN)
    assert isinstance(checked.forward, ServiceError) and checked.forward.message.startswith("mode shared")
    denied = gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward
    assert denied.state is ApprovalState.DENIED and denied.reason.startswith("mode shared")


def test_supervised_nothing_moves_before_approval_and_the_approved_plan_moves_until_it_ends(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    asked = gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN))
    assert asked.forward.state is ApprovalState.PENDING
    assert asked.forward.steps[0].startswith("1. navigate_to near") and asked.forward.checks
    assert asked.events[-1].decision is Decision.AWAITING_APPROVAL
    assert [p.goal_id for p in gate.pending().plans] == ["p1"]
    assert "no plan an operator approved is running" in refused(gate.navigate(go()))
    assert gate.cmd_vel(Twist(linear_x=0.1)).events[0].rule is Rule.APPROVAL
    # Asking again is answered from the book, without a second event.
    assert gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).events == ()
    wrong = decide(gate, "p1", True, token="guess")
    assert not wrong.forward.ok and "not the operator's token" in wrong.forward.message  # type: ignore[attr-defined]
    assert gate.approval("p1").state is ApprovalState.PENDING  # type: ignore[union-attr]
    right = decide(gate, "p1", True)
    assert right.forward.ok and right.forward.approval.state is ApprovalState.APPROVED  # type: ignore[attr-defined]
    assert gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward.state is ApprovalState.APPROVED
    assert gate.pending().plans == []
    assert isinstance(gate.navigate(go()).forward, SendGoal)
    gate.plan_status(GoalStatus(goal_id="p1", state=GoalState.SUCCEEDED))
    assert gate.approval("p1").state is ApprovalState.FINISHED  # type: ignore[union-attr]
    assert "no plan an operator approved is running" in refused(gate.navigate(go("n2")))
    again = decide(gate, "p1", True)
    assert not again.forward.ok and "does not wait for approval: it is finished" in again.forward.message  # type: ignore[attr-defined]


def test_a_denied_plan_never_moves_and_unknown_goals_are_named(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN))
    denied = decide(gate, "p1", False, reason="not now")
    assert denied.forward.ok  # type: ignore[attr-defined]
    state = gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward
    assert state.state is ApprovalState.DENIED and state.reason == "denied by operator alice: not now"
    assert "no plan an operator approved is running" in refused(gate.navigate(go()))
    late = decide(gate, "p1", True)
    assert not late.forward.ok and "it is denied" in late.forward.message  # type: ignore[attr-defined]
    unknown = decide(gate, "nope", True)
    assert not unknown.forward.ok and "no plan with goal id nope waits for approval" in unknown.forward.message  # type: ignore[attr-defined]


def test_a_plan_safety_refuses_is_denied_at_once_and_never_waits(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    asked = gate.request_approval(ApprovalRequest(goal_id="p2", plan=STAIRS)).forward
    assert asked.state is ApprovalState.DENIED and "stairs" in asked.reason
    assert gate.pending().plans == []


def test_a_plan_canceled_while_waiting_is_no_longer_pending(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN))
    gate.plan_status(GoalStatus(goal_id="p1", state=GoalState.CANCELED))
    assert gate.pending().plans == []
    assert not decide(gate, "p1", True).forward.ok  # type: ignore[attr-defined]


def test_leaving_supervised_decides_what_waits_and_cancels_what_the_new_mode_refuses(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN))
    to_autonomous = gate.set_mode(ModeRequest(operator="alice", token=TOKEN, mode=ControlMode.AUTONOMOUS))
    assert not to_autonomous.cancel_goals
    assert gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward.state is ApprovalState.APPROVED
    gate.plan_status(GoalStatus(goal_id="p1", state=GoalState.SUCCEEDED))
    assert set_mode(gate, ControlMode.SUPERVISED)
    gate.request_approval(ApprovalRequest(goal_id="p3", plan=PLAN))
    to_direct = gate.set_mode(ModeRequest(operator="alice", token=TOKEN, mode=ControlMode.DIRECT))
    assert to_direct.cancel_goals
    assert gate.request_approval(ApprovalRequest(goal_id="p3", plan=PLAN)).forward.state is ApprovalState.DENIED


def test_an_approval_checks_the_plan_again_from_where_the_robot_is_now(gate: SafetyGate) -> None:
    assert set_mode(gate, ControlMode.SUPERVISED)
    gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN))
    assert set_mode(gate, ControlMode.DIRECT) and set_mode(gate, ControlMode.SUPERVISED)
    # Decided by the mode change on the executor's next ask; a fresh plan waits again.
    gate.request_approval(ApprovalRequest(goal_id="p4", plan=PLAN))
    gate.odometry(odom(pose=Pose2D(x=HERE.x, y=HERE.y)))
    gate.latch.trigger("operator", "test", 0.0)
    blocked = decide(gate, "p4", True)
    assert not blocked.forward.ok and "e-stop latched" in blocked.forward.message  # type: ignore[attr-defined]
    assert gate.approval("p4").state is ApprovalState.DENIED  # type: ignore[union-attr]


def test_an_approval_holds_for_the_plan_it_was_asked_for_only(gate: SafetyGate) -> None:
    """A harmless plan asked about first under a goal id: the real plan under the same id got the
    harmless one's answer, and once approved, its approval (a review's finding). Now it is refused."""
    assert set_mode(gate, ControlMode.SUPERVISED)
    assert gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward.state is ApprovalState.PENDING
    other = gate.request_approval(ApprovalRequest(goal_id="p1", plan=STAIRS))
    assert other.forward.state is ApprovalState.DENIED
    assert "asked about with another plan; an approval is for one plan only" in other.forward.reason
    assert other.events[0].decision is Decision.DENIED
    assert decide(gate, "p1", True).forward.ok  # the plan asked for first, as it was
    assert gate.request_approval(ApprovalRequest(goal_id="p1", plan=STAIRS)).forward.state is ApprovalState.DENIED
    assert gate.request_approval(ApprovalRequest(goal_id="p1", plan=PLAN)).forward.state is ApprovalState.APPROVED
