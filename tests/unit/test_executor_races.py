"""Races in the executor, each made to happen at its worst moment by a stand-in that acts at that
moment (no sleeps): pure logic, the plan runner, its Supervision (against safety's real gate where an
operator pauses) and the execute_plan server's goal function."""

from __future__ import annotations

import threading
from typing import Any

from schemas.actions import GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.common import Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepStatus
from schemas.plan import Fallback, SayStep, WaitStep
from schemas.robot import NavigateToPoseGoal
from schemas.safety import ApprovalAction, ApprovalRequest, ApprovalState, PlanApproval
from services.actionlib import GoalHandle
from services.errors import GoalRejected
from services.executor.config import ExecutorConfig
from services.executor.node import Supervision, serve_execute_plan
from services.runtime import decoder, encode
from services.safety.gate import SafetyGate
from tests.unit.test_executor_pause import NO_RETRIES, RobotBehindSafety, Run
from tests.unit.test_executor_pause import gate as gate  # the fixture: safety's gate in supervised mode
from tests.unit.test_executor_review41 import LongWinded
from tests.unit.test_runner import KITCHEN, ScriptedPlanServices, ScriptedRobot, go, grounded, runner
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared
from tests.unit.test_safety_modes import NEAR

__all__ = ["gate", "policy"]  # fixtures

WAIT = 10.0  # a deadline for each condition, never a pause


class ResumedAsRefused(RobotBehindSafety):
    """Safety refuses the first navigation goal (the plan is paused) and the operator resumes the plan
    just after, before the executor asks whether it was paused; later goals arrive at once."""

    refused = 0

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        ruled = self.gate.navigate(SendGoal(goal_id=f"n{len(self.goals)}", goal=goal)).forward
        if isinstance(ruled, GoalResponse):
            self.refused += 1
            if self.refused == 1:
                assert self.safety.decide("p1", ApprovalAction.RESUME)
            raise GoalRejected(ruled.reason, ruled.kind)
        self.forwarded += 1
        return self.ended(goal, GoalState.SUCCEEDED)


class PausedAsStepEnds(Run):
    """The operator pauses the plan as its first step ends, before the next step's attempt begins."""

    def _on_feedback(self, fb: ExecutePlanFeedback) -> None:
        if fb.step == 0 and fb.status is StepStatus.SUCCEEDED:
            assert self.safety.decide("p1", ApprovalAction.PAUSE, "a look")
        super()._on_feedback(fb)


def test_a_step_begun_while_paused_and_refused_as_it_is_resumed_runs_again(gate: SafetyGate) -> None:
    """The attempt began while the plan was paused, so its count of pauses took that pause in: the
    refusal it met was then taken for a veto of its own (the plan failed), not for the pause."""
    run = PausedAsStepEnds(gate, grounded([SayStep(text="ready"), go(NEAR, "near")]), ResumedAsRefused)
    try:
        run.thread.start()
        run.wait_feedback(StepStatus.AWAITING_APPROVAL, None)
        assert run.safety.decide("p1", ApprovalAction.APPROVE)
        result = run.ended()
    finally:
        run.cancel.set()
        run.thread.join(WAIT)
    robot = run.robot
    assert isinstance(robot, ResumedAsRefused) and robot.refused == 1, "no goal was refused: the race did not happen"
    assert result.status is PlanStatus.SUCCEEDED, result
    assert [(s.status, s.attempts) for s in result.steps] == [(StepStatus.SUCCEEDED, 1), (StepStatus.SUCCEEDED, 1)]
    assert robot.forwarded == 1


class Autonomous:
    """Safety's node outside supervised mode: every plan may move at once."""

    def __init__(self) -> None:
        self.asked = 0

    def call(self, key: Any, request: ApprovalRequest, timeout: float) -> PlanApproval:
        self.asked += 1
        return PlanApproval(goal_id=request.goal_id, state=ApprovalState.NOT_NEEDED)


class CanceledWhileChecked(ScriptedPlanServices):
    """The plan is canceled while safety checks it."""

    def __init__(self, cancel: threading.Event) -> None:
        super().__init__(resolve=grounded([go(NEAR, "near")]))
        self.cancel = cancel

    def check(self, plan: Any) -> Any:
        self.cancel.set()
        return super().check(plan)


def test_a_plan_canceled_before_its_first_motion_outside_supervised_mode_says_so() -> None:
    """Canceled while it was checked, the plan said it was canceled "while awaiting an operator's
    approval" though no operator was ever asked (autonomous mode)."""
    cancel = threading.Event()
    robot = ScriptedRobot()
    safety = Autonomous()
    supervision = Supervision(safety, "p1", NO_RETRIES)  # type: ignore[arg-type]
    feedback: list[ExecutePlanFeedback] = []
    result = runner(CanceledWhileChecked(cancel), robot).run(
        ExecutePlanGoal(text="..."), cancel, feedback.append, supervision.approve, supervision
    )
    assert (result.status, result.stage) == (PlanStatus.CANCELED, Stage.SAFETY), result
    assert "operator" not in result.reason and "nothing moved" in result.reason, result.reason
    assert robot.goals == [] and not any(f.status is StepStatus.AWAITING_APPROVAL for f in feedback)


class NodeStandIn(Autonomous):
    """What serve_execute_plan asks of a node to set up its action server (nothing is served), and
    safety outside supervised mode."""

    def publisher(self, key: Any) -> Any:
        return self

    def put(self, message: Any) -> None:
        pass

    def serve(self, *args: Any, **kwargs: Any) -> None:
        pass


def test_a_preempted_plan_with_a_long_reason_has_a_result_its_client_can_read() -> None:
    """A step failed with the robot's long words, its on_failure ran and the plan was preempted
    meanwhile: the result's reason, clipped to fit, then got "preempted by goal ..." put before it,
    so it no longer fit and the client's decoder refused the result: the plan's outcome was lost."""
    alternative = Fallback(first=0, last=0, steps=[WaitStep(duration=60.0)], labels=["1 on_failure 1"])
    plan = grounded([go(KITCHEN, "kitchen")], fallbacks=[alternative])
    config = ExecutorConfig()
    server = serve_execute_plan(NodeStandIn(), runner(ScriptedPlanServices(resolve=plan), LongWinded()), config)  # type: ignore[arg-type]

    def feedback(goal_id: str, fb: ExecutePlanFeedback) -> None:
        if fb.action == "wait" and fb.status is StepStatus.RUNNING:  # the alternative started: preempted
            handle.cancel_reason = f"preempted by goal {'b' * 32}"
            handle.cancel_requested.set()

    handle: GoalHandle[Any, Any] = GoalHandle("a" * 32, ExecutePlanGoal(text="..."), feedback)
    outcome = server._execute(handle)
    assert outcome.state is GoalState.CANCELED and outcome.result is not None, outcome
    assert len(outcome.result.steps) == 2 and outcome.result.steps[1].status is StepStatus.CANCELED, outcome.result
    result = decoder(ExecutePlanResult).decode(encode(outcome.result))
    assert result.status is PlanStatus.CANCELED and result.reason.startswith(handle.cancel_reason), result.reason
    response = ResultResponse(goal_id=handle.goal_id, state=outcome.state, result=result, message=outcome.message)
    decoder(ResultResponse[ExecutePlanResult]).decode(encode(response))
