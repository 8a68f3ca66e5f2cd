"""The planner's following of a sent plan against the caller's deadline, and the recovery records of a
plan it stops following, with a stand-in node, executor and model (no Zenoh)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace
from typing import Any

from schemas.actions import GoalState, ResultResponse
from schemas.common import ErrorKind, ServiceError, Stage
from schemas.executor import ExecutePlanGoal, ExecutePlanResult, FailureKind, PlanStatus, StepResult, StepStatus
from schemas.planner import AskReply, AskRequest, AskStatus, Recovery, RecoveryOutcome
from services.errors import CallError
from services.planner.config import PlannerConfig
from services.planner.llm import ChatReply
from services.planner.loop import DryRunVerdict, LoopResult, plan_loop
from services.planner.node import Planner
from services.planner.recovery import Ended, Ports, Sent, follow_and_recover
from tests.plannerparts import PlannerNode

REQUEST = "put the red cup on the coffee table"
PLAN = '{"plan": [{"action": "pick", "target": "red cup"}, {"action": "place", "target": "coffee table"}]}'
WAIT = 10.0  # s: a deadline for what must happen at once


class StandInNode(PlannerNode):
    """The scene answered, safety's incidents not; get_result (how the planner follows a goal) blocks
    until `ended` is set."""

    def __init__(self) -> None:
        super().__init__("the red cup is on the kitchen counter")
        self.ended = threading.Event()
        self.asked_result = threading.Event()

    def answer(self, service: Any, request: Any, timeout: float) -> Any:
        if service == "get_result":
            self.asked_result.set()
            self.ended.wait(timeout)
            raise CallError(ServiceError(kind=ErrorKind.TIMEOUT, message="the test ended"))
        return super().answer(service, request, timeout)


class StandInExecutor:
    """Dry runs pass; real sends are kept; results come from the node's get_result."""

    def __init__(self, node: StandInNode) -> None:
        self._node = node
        self._action = SimpleNamespace(get_result="get_result")
        self.sent: list[str] = []

    def run(self, goal: ExecutePlanGoal, *, timeout: float) -> ResultResponse[ExecutePlanResult]:
        result = ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.SAFETY, reason="dry run: approved")
        return ResultResponse(goal_id="dry", state=GoalState.SUCCEEDED, result=result)

    def send(self, goal: ExecutePlanGoal, *, timeout: float) -> Any:
        self.sent.append(goal.text)
        return SimpleNamespace(goal_id=f"goal{len(self.sent)}")


class StandInChat:
    def __init__(self) -> None:
        self.calls = 0

    def chat(self, conversation: list[dict[str, Any]], tools: Any) -> ChatReply:
        self.calls += 1
        return ChatReply(PLAN)


def test_a_caller_waiting_for_the_plans_end_is_answered_at_its_deadline_not_at_the_plans_end() -> None:
    """`wait` with a deadline: past it no one waits for the answer (tether ask has given up; in its own
    process it is tether ask that waits). Following went on until the plan's end, up to an hour,
    holding a worker of the service (or the command) for no one."""
    node = StandInNode()
    chat = StandInChat()
    planner = Planner(node, PlannerConfig(), None, client=chat)  # type: ignore[arg-type]
    planner._executor = StandInExecutor(node)  # type: ignore[assignment]
    planner._tool_schemas = []
    request = AskRequest(text=REQUEST, wait=True, deadline=time.time() + 0.5)
    sent = AskReply(status=AskStatus.ACCEPTED, request_id="req1", goal_id="goal0", plan=PLAN)
    replies: list[AskReply] = []
    follower = threading.Thread(target=lambda: replies.append(planner.follow(request, sent, 2)))
    try:
        follower.start()
        assert node.asked_result.wait(WAIT), "the planner follows the goal"
        follower.join(WAIT)
        assert not follower.is_alive(), "still following a plan past the caller's deadline"
        # Nor is the result asked for longer: no thread left waiting, for an hour, for a result no one reads.
        for fetch in [t for t in threading.enumerate() if t.name == "result:goal0"]:
            fetch.join(WAIT)
            assert not fetch.is_alive(), "the thread asking for the result outlived the deadline"
    finally:
        node.ended.set()
        follower.join(WAIT)
        planner.close()
    [reply] = replies
    # Sent, taken and still running: neither succeeded nor failed.
    assert reply.status is AskStatus.ACCEPTED and reply.goal_id == "goal0", reply
    assert "deadline" in reply.reason and "goal0 goes on" in reply.reason, reply.reason
    [stopped] = node.recoveries()
    assert stopped.outcome is RecoveryOutcome.STOPPED and "deadline" in stopped.reason
    assert chat.calls == 0


def _failed() -> Ended:
    step = StepResult(
        index=1, action="place", status=StepStatus.FAILED, message="the cup slipped", failure=FailureKind.EXECUTION
    )
    result = ExecutePlanResult(
        status=PlanStatus.FAILED, stage=Stage.EXECUTE, reason="step 2 failed", steps=[step], failure=step.failure
    )
    return Ended(result, "aborted", "step 2 failed")


def test_a_recovery_still_running_when_it_is_no_longer_followed_is_not_recorded_as_failed() -> None:
    """planner/recoveries said the recovery plan had failed (and the reply FAILED) while the robot
    still ran it, when the planner stopped following it (shutting down, the caller's deadline)."""
    endings = [_failed(), Ended(None, "unfollowed", "the caller's deadline passed")]
    records: list[Recovery] = []
    sent: list[str] = []

    def send(plan: str) -> Sent:
        sent.append(plan)
        return Sent(goal_id="goal1")

    def plan(messages: list[dict[str, Any]], number: int) -> LoopResult:
        return plan_loop(messages, lambda _: ChatReply(PLAN), lambda _: DryRunVerdict(True, Stage.SAFETY), 3)

    ports = Ports(
        follow=lambda goal_id: endings.pop(0),
        estop=lambda: None,
        scene=lambda: "",
        incidents=lambda: "",
        plan=plan,
        send=send,
        record=records.append,
        clock=lambda: 1000.0,
    )
    followed = follow_and_recover("req1", REQUEST, "goal0", PLAN, 2, [], True, ports)

    assert sent == [PLAN]
    outcomes = [(r.number, r.outcome) for r in records]
    assert outcomes == [(1, RecoveryOutcome.SENT), (2, RecoveryOutcome.STOPPED)], outcomes
    assert not followed.succeeded and followed.running and followed.goal_id == "goal1"
    assert "goal1 goes on" in followed.reason and "deadline" in followed.reason
