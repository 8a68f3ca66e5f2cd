"""How a plan goal ends when something other than its steps ends it: the executor shutting down
(over two real Zenoh sessions in one process), a dry run canceled while it is checked."""

from __future__ import annotations

import threading
import uuid
from typing import Any

from schemas import keys
from schemas.actions import GoalState
from schemas.common import Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, PlanStatus
from schemas.plan import GroundedPlan
from schemas.safety import ApprovalRequest, ApprovalState, PlanApproval
from services.actionlib import ActionClient
from services.executor.config import ExecutorConfig
from services.executor.node import serve_execute_plan
from services.runtime import Node, NodeSettings
from tests.sessions import free_port
from tests.unit.test_runner import KITCHEN, ScriptedPlanServices, ScriptedRobot, go, grounded, runner

WAIT = 10.0  # a deadline for each condition, never a pause


class CanceledWhileChecked(ScriptedPlanServices):
    """The plan is canceled while safety checks it."""

    def __init__(self, cancel: threading.Event) -> None:
        super().__init__(resolve=grounded([go(KITCHEN, "kitchen")]))
        self.cancel = cancel

    def check(self, plan: GroundedPlan) -> Any:
        self.cancel.set()
        return super().check(plan)


def not_needed(request: ApprovalRequest) -> PlanApproval:
    """Safety outside supervised mode: every plan may move at once."""
    return PlanApproval(goal_id=request.goal_id, state=ApprovalState.NOT_NEEDED)


def test_a_plan_stopped_by_the_executor_shutting_down_says_so_in_its_result_and_its_state() -> None:
    """Its result said "canceled" with the step's words only, while its goal ended aborted with
    "executor shutting down": a client reading the result could not tell why, nor that no one canceled it."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    robot = ScriptedRobot(block=True)  # drives until its motion is canceled
    plan = runner(ScriptedPlanServices(resolve=grounded([go(KITCHEN, "kitchen")])), robot)
    with Node("executor", settings) as executor, Node("test", settings) as test:
        server = serve_execute_plan(executor, plan, ExecutorConfig())
        test.serve(keys.APPROVAL_REQUEST, not_needed)
        executor.declare_alive()
        assert not test.wait_alive({"executor"}, WAIT), "the two sessions did not find each other"
        goal = ActionClient(test, keys.EXECUTE_PLAN).send(ExecutePlanGoal(text="..."))
        assert robot.started.wait(WAIT), "the plan never moved"
        server.abort_all("executor shutting down")
        ended = goal.result(WAIT)
    assert ended.state is GoalState.ABORTED and ended.result is not None, ended
    assert ended.result.status is PlanStatus.FAILED, ended.result
    assert ended.result.reason.startswith("executor shutting down; step 1 (navigate_to) canceled"), ended.result.reason
    assert ended.message == ended.result.reason


def test_a_dry_run_canceled_while_it_is_checked_ends_canceled() -> None:
    cancel = threading.Event()
    feedback: list[ExecutePlanFeedback] = []
    robot = ScriptedRobot()
    result = runner(CanceledWhileChecked(cancel), robot).run(
        ExecutePlanGoal(text="...", dry_run=True), cancel, feedback.append
    )
    assert (result.status, result.stage) == (PlanStatus.CANCELED, Stage.SAFETY), result
    assert "nothing moved" in result.reason and result.steps == [], result
    assert robot.goals == []
