"""The executor's side of an operator's pause, pure: the plan runner and its Supervision (the node's)
against safety's real gate, with the queries and goals handed across in memory instead of Zenoh.

A pause makes safety cancel the plan's goal: the step does not fail; the executor reports
`awaiting_approval` on it and waits; resumed, the step runs again (a new route from where the robot
is), not counted as an attempt. Denied while paused, the plan ends with the reason; canceled, at
once. A goal canceled while no one paused (an e-stop) stays a failure."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from schemas import keys
from schemas.actions import GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, FailureKind, PlanStatus, StepStatus
from schemas.plan import GroundedPlan, SayStep, WaitStep
from schemas.robot import NavigateToPoseGoal
from schemas.safety import ApprovalAction, ApprovalDecision, ApprovalRequest, ApprovalState, ControlMode, PlanApproval
from services.errors import GoalRejected
from services.executor.config import ExecutorConfig, StepRetries
from services.executor.node import Supervision
from services.safety.gate import SafetyGate
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.policy import SafetyPolicy
from tests.unit.test_runner import ScriptedPlanServices, ScriptedRobot, go, grounded, runner
from tests.unit.test_safety_gate import TOKEN, FakeClock, nobody, odom
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared
from tests.unit.test_safety_modes import NEAR, set_mode

__all__ = ["policy"]  # fixture

WAIT = 10.0  # a deadline for each condition, never a pause
PLAN = grounded([go(NEAR, "near"), SayStep(text="done")])
NO_RETRIES = ExecutorConfig(
    retries=StepRetries(navigate_to=0, pick=0, place=0, detect=0, gripper=0, say=0, wait=0, stop=0)
)


class SafetyInMemory:
    """Safety's node as the executor meets it: `safety/approval/request` answered by the gate, waiting
    (up to the request's `wait`) while the plan is pending or paused, as safety's node waits."""

    def __init__(self, gate: SafetyGate) -> None:
        self.gate = gate
        self.changed = threading.Condition()
        self.canceled = threading.Event()  # safety canceled the goals it forwarded

    def call(self, key: Any, request: ApprovalRequest, timeout: float) -> PlanApproval:
        assert key is keys.APPROVAL_REQUEST
        asked = self.gate.request_approval(request).forward
        if asked.state in (ApprovalState.PENDING, ApprovalState.PAUSED) and request.wait > 0.0:
            with self.changed:
                self.changed.wait_for(lambda: self.gate.approval(request.goal_id) != asked, request.wait)
            asked = self.gate.request_approval(request).forward
        return asked

    def decide(self, goal_id: str, action: ApprovalAction, reason: str = "") -> bool:
        ruling = self.gate.decide(
            ApprovalDecision(operator="alice", token=TOKEN, goal_id=goal_id, action=action, reason=reason)
        )
        if ruling.cancel_goals:
            self.canceled.set()
        with self.changed:
            self.changed.notify_all()
        return ruling.forward.ok


class RobotBehindSafety(ScriptedRobot):
    """Navigation goals go through the gate; one it forwards drives until safety cancels it (the first)
    or arrives at once (the later ones)."""

    def __init__(self, gate: SafetyGate, safety: SafetyInMemory) -> None:
        super().__init__()
        self.gate = gate
        self.safety = safety
        self.forwarded = 0

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        ruled = self.gate.navigate(SendGoal(goal_id=f"n{len(self.goals)}", goal=goal)).forward
        if isinstance(ruled, GoalResponse):
            raise GoalRejected(ruled.reason, ruled.kind)
        self.forwarded += 1
        self.started.set()
        if self.forwarded > 1:
            return self.ended(goal, GoalState.SUCCEEDED)
        return self.first(cancel)

    def first(self, cancel: threading.Event) -> ResultResponse[Any]:
        """How the first goal forwarded ends: it drives until safety (or the executor) cancels it."""
        while not cancel.wait(0.01):
            if self.safety.canceled.is_set():
                return ResultResponse(goal_id="g", state=GoalState.CANCELED, message="canceled")
        return ResultResponse(goal_id="g", state=GoalState.CANCELED, message="canceled")


@pytest.fixture
def gate(policy: SafetyPolicy, tmp_path: Path) -> SafetyGate:
    g = SafetyGate(policy, EstopLatch(TOKEN), FakeClock(), FakeClock(1_700_000_000.0), modes=ModeFile(None))
    g.odometry(odom())
    nobody(g)
    assert set_mode(g, ControlMode.SUPERVISED)
    return g


class Run:
    """One plan run in a thread of its own, approved by the operator once it waits."""

    def __init__(
        self, gate: SafetyGate, plan: GroundedPlan = PLAN, robot: type[RobotBehindSafety] | None = None
    ) -> None:
        self.safety = SafetyInMemory(gate)
        self.robot = (robot or RobotBehindSafety)(gate, self.safety)
        self.cancel = threading.Event()
        self.feedback: list[ExecutePlanFeedback] = []
        self.heard = threading.Condition()
        self.result: Any = None
        self.supervision = Supervision(self.safety, "p1", NO_RETRIES)  # type: ignore[arg-type]
        planner = ScriptedPlanServices(resolve=plan)
        self.runner = runner(planner, self.robot)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _on_feedback(self, fb: ExecutePlanFeedback) -> None:
        with self.heard:
            self.feedback.append(fb)
            self.heard.notify_all()

    def _run(self) -> None:
        goal = ExecutePlanGoal(text="...")
        self.result = self.runner.run(goal, self.cancel, self._on_feedback, self.supervision.approve, self.supervision)

    def wait_feedback(self, status: StepStatus, step: int | None) -> ExecutePlanFeedback:
        def found() -> ExecutePlanFeedback | None:
            return next((f for f in self.feedback if f.status is status and f.step == step), None)

        with self.heard:
            assert self.heard.wait_for(lambda: found() is not None, WAIT), (status, step, self.feedback)
        fb = found()
        assert fb is not None
        return fb

    def approved_and_driving(self) -> None:
        """Start the plan, approve it when it asks, and wait until its first step drives."""
        self.thread.start()
        self.wait_feedback(StepStatus.AWAITING_APPROVAL, None)
        assert self.safety.decide("p1", ApprovalAction.APPROVE)
        assert self.robot.started.wait(WAIT)

    def ended(self) -> Any:
        self.thread.join(WAIT)
        assert not self.thread.is_alive(), "the plan did not end"
        return self.result


@pytest.fixture
def paused_run(gate: SafetyGate) -> Iterator[Run]:
    """A plan approved, driving its first step, then paused by the operator."""
    run = Run(gate)
    try:
        run.approved_and_driving()
        assert run.safety.decide("p1", ApprovalAction.PAUSE, "someone in the hall")
        yield run
    finally:
        run.cancel.set()
        run.thread.join(WAIT)


def test_a_paused_step_waits_and_runs_again_from_where_the_robot_is_once_resumed(paused_run: Run) -> None:
    run = paused_run
    waiting = run.wait_feedback(StepStatus.AWAITING_APPROVAL, 0)
    assert waiting.message.startswith("paused by operator alice: someone in the hall"), waiting.message
    assert "`tether resume p1`" in waiting.message and waiting.label == "1"
    assert run.thread.is_alive() and run.robot.forwarded == 1, "the plan must wait, not fail or move"
    assert run.safety.decide("p1", ApprovalAction.RESUME)
    result = run.ended()
    assert result.status is PlanStatus.SUCCEEDED, result
    assert [(s.status, s.attempts) for s in result.steps] == [(StepStatus.SUCCEEDED, 1), (StepStatus.SUCCEEDED, 1)]
    assert run.robot.forwarded == 2, "the step drives again once handed back"
    assert any("resumed by the operator" in f.message for f in run.feedback if f.step == 0)


def test_denied_while_paused_the_plan_ends_with_the_reason(paused_run: Run) -> None:
    run = paused_run
    run.wait_feedback(StepStatus.AWAITING_APPROVAL, 0)
    assert run.safety.decide("p1", ApprovalAction.DENY, "enough")
    result = run.ended()
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.VETOED), result
    assert result.reason == "step 1 (navigate_to) stopped while paused: denied by operator alice: enough"
    assert [s.status for s in result.steps] == [StepStatus.FAILED, StepStatus.SKIPPED]
    assert run.robot.forwarded == 1


def test_canceled_while_paused_the_plan_ends_canceled(paused_run: Run) -> None:
    run = paused_run
    run.wait_feedback(StepStatus.AWAITING_APPROVAL, 0)
    run.cancel.set()
    result = run.ended()
    assert result.status is PlanStatus.CANCELED and "canceled while paused" in result.reason, result
    assert run.robot.forwarded == 1


def e_stopped(run: Run) -> Any:
    """The plan's result after the e-stop latches while it drives: safety cancels its goal (no pause)."""
    assert run.robot.started.wait(WAIT)
    run.safety.gate.latch.trigger("operator", "test", 0.0)
    run.safety.canceled.set()
    return run.ended()


def test_an_e_stop_after_the_approval_fails_the_step_as_before(gate: SafetyGate) -> None:
    run = Run(gate)
    try:
        run.approved_and_driving()
        result = e_stopped(run)  # the step fails at once, no waiting
    finally:
        run.cancel.set()
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.VETOED), result
    assert "canceled by the robot side" in result.reason
    assert not any(f.status is StepStatus.AWAITING_APPROVAL for f in run.feedback if f.step is not None)
    assert run.robot.forwarded == 1


# A wait first: an operator may pause and resume the plan while no motion runs.
WAIT_FIRST = grounded([WaitStep(duration=1.0), go(NEAR, "near")])


class AbortedFirst(RobotBehindSafety):
    """The first navigation goal safety forwards ends aborted by the robot (a failure of its own)."""

    def first(self, cancel: threading.Event) -> ResultResponse[Any]:
        return ResultResponse(goal_id="g", state=GoalState.ABORTED, message="navigation aborted: stalled")


def paused_and_resumed_while_waiting(run: Run) -> None:
    """Approve the plan, then pause and resume it while its first step waits: nothing was canceled."""
    run.thread.start()
    run.wait_feedback(StepStatus.AWAITING_APPROVAL, None)
    assert run.safety.decide("p1", ApprovalAction.APPROVE)
    run.wait_feedback(StepStatus.RUNNING, 0)
    assert run.safety.decide("p1", ApprovalAction.PAUSE, "a look")
    assert run.safety.decide("p1", ApprovalAction.RESUME)
    run.safety.canceled.clear()


def test_a_pause_resumed_while_nothing_moved_is_not_taken_for_a_later_e_stop(gate: SafetyGate) -> None:
    """The e-stop fails the next step as it would without the pause: no second goal is sent."""
    run = Run(gate, WAIT_FIRST)
    try:
        paused_and_resumed_while_waiting(run)
        result = e_stopped(run)
    finally:
        run.cancel.set()
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.VETOED), result
    assert len(run.robot.goals) == 1, "a navigation goal was sent after the e-stop latched"


def test_a_pause_resumed_while_nothing_moved_is_not_taken_for_a_later_failure(gate: SafetyGate) -> None:
    """A step that fails on its own later is not run again as if the pause had stopped it (no retries here)."""
    run = Run(gate, WAIT_FIRST, AbortedFirst)
    try:
        paused_and_resumed_while_waiting(run)
        result = run.ended()
    finally:
        run.cancel.set()
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.EXECUTION), result
    assert [(s.status, s.attempts) for s in result.steps] == [(StepStatus.SUCCEEDED, 1), (StepStatus.FAILED, 1)]
    assert run.robot.forwarded == 1, "the failed step drove again"
