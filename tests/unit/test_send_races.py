"""`tether send`'s client (tether.client.PlanSender) against a stand-in for the executor's session:
what it makes of a result with none in it, a cancel that did not reach the executor, and feedback
told while the result comes."""

from __future__ import annotations

import io
import threading
from collections.abc import Callable
from typing import Any

import pytest
from rich.console import Console

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalState, ResultResponse
from schemas.common import ErrorKind, ServiceError, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepStatus
from services.errors import CallError
from tether import cli, client
from tether.client import PlanSender, plan_result

WAIT = 5.0  # a deadline for each condition, never a pause
GOAL = "a" * 32
CANCELED = ExecutePlanResult(status=PlanStatus.CANCELED, stage=Stage.EXECUTE, reason="stopped")


class Session:
    """The node PlanSender uses, its calls answered by `answer(service, request)`."""

    def __init__(self, answer: Callable[[Any, Any], Any]) -> None:
        self.answer = answer
        self.feedback: Callable[[ExecutePlanFeedback], None] | None = None

    def subscribe(self, topic: Any, callback: Callable[[Any], None], **_: Any) -> None:
        self.feedback = callback

    def call(self, service: Any, request: Any, *, timeout: float) -> Any:
        return self.answer(service, request)


def unavailable(what: str) -> CallError:
    return CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=f"no reply from {what}"))


def test_a_goal_that_ended_without_a_result_ends_as_its_state_says() -> None:
    """The executor's run of the plan raised: the goal ended aborted with no result, which send took
    for a plan still moving ('accepted', exit 0)."""
    aborted = ResultResponse[ExecutePlanResult](goal_id=GOAL, state=GoalState.ABORTED, message="execute failed: boom")
    result = plan_result(GOAL, aborted)
    assert (result.status, result.stage, result.reason) == (PlanStatus.FAILED, Stage.EXECUTE, "execute failed: boom")
    canceled = ResultResponse[ExecutePlanResult](goal_id=GOAL, state=GoalState.CANCELED)
    assert plan_result(GOAL, canceled).status is PlanStatus.CANCELED


@pytest.mark.parametrize(
    "response",
    [
        ResultResponse[ExecutePlanResult](goal_id="b" * 32, state=GoalState.SUCCEEDED, result=CANCELED),
        ResultResponse[ExecutePlanResult](goal_id=GOAL, state=GoalState.EXECUTING, message="still running"),
    ],
)
def test_an_answer_that_is_no_end_of_this_goal_is_no_outcome(response: ResultResponse[ExecutePlanResult]) -> None:
    with pytest.raises(CallError):
        plan_result(GOAL, response)


def test_a_cancel_that_did_not_reach_the_executor_is_asked_again() -> None:
    """Ctrl-C while waiting: the cancel's first call went unanswered. send raised the CallError out of
    its Ctrl-C handling (a traceback, no JSON) and the plan drove on."""
    cancels: list[str] = []
    ended = threading.Event()

    def answer(service: Any, request: Any) -> Any:
        if service is keys.EXECUTE_PLAN.cancel_goal:
            assert isinstance(request, CancelGoal)
            cancels.append(request.goal_id)
            if len(cancels) == 1:
                raise unavailable("cancel_goal")
            ended.set()
            return CancelResponse(goal_id=request.goal_id, accepted=True)
        assert isinstance(request, GetResult)
        assert ended.wait(WAIT), "the result was asked for before the plan was canceled"
        return ResultResponse[ExecutePlanResult](goal_id=request.goal_id, state=GoalState.CANCELED, result=CANCELED)

    sender = PlanSender(Session(answer))  # type: ignore[arg-type]
    run = sender.cancel(sender.handle(GOAL), grace=WAIT)
    assert cancels == [GOAL, GOAL]
    assert run.result == CANCELED
    assert sender.following() == []


def test_a_goal_the_executor_never_accepted_ends_canceled_when_canceled() -> None:
    """A Ctrl-C before the executor answered the send: the cancel comes while it decides (it rejects
    the goal for it), and it knows no such goal when asked for its result."""

    def answer(service: Any, request: Any) -> Any:
        if service is keys.EXECUTE_PLAN.cancel_goal:
            return CancelResponse(goal_id=request.goal_id, accepted=False, reason="no such running goal")
        raise CallError(ServiceError(kind=ErrorKind.INVALID_REQUEST, message=f"unknown goal {request.goal_id}"))

    sender = PlanSender(Session(answer))  # type: ignore[arg-type]
    run = sender.cancel(sender.handle(GOAL), grace=WAIT)
    assert run.result is not None and run.result.status is PlanStatus.CANCELED, run


def test_a_cancel_unanswered_for_its_whole_grace_is_no_outcome() -> None:
    def answer(service: Any, request: Any) -> Any:
        raise unavailable(service.path)

    sender = PlanSender(Session(answer))  # type: ignore[arg-type]
    with pytest.raises(CallError):
        sender.cancel(sender.handle(GOAL), grace=0.2)


def test_feedback_being_told_as_the_result_comes_is_told_before_it() -> None:
    """The last step's end, printed on Zenoh's thread as the result came, was printed after the result
    (the run was done, the printing not): `step 1 ... done` below `succeeded at stage execute`."""
    told: list[str] = []
    telling, go_on = threading.Event(), threading.Event()
    succeeded = ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.EXECUTE)

    def answer(service: Any, request: Any) -> Any:
        return ResultResponse[ExecutePlanResult](goal_id=GOAL, state=GoalState.SUCCEEDED, result=succeeded)

    def on_feedback(fb: ExecutePlanFeedback) -> None:
        telling.set()
        assert go_on.wait(WAIT)
        told.append("feedback")

    session = Session(answer)
    sender = PlanSender(session, on_feedback)  # type: ignore[arg-type]
    handle = sender.handle(GOAL)
    sender._follow(GOAL)  # as `send` does before the goal goes out
    end = ExecutePlanFeedback(stage=Stage.EXECUTE, step=0, action="navigate_to", status=StepStatus.SUCCEEDED)
    assert session.feedback is not None
    feedback = session.feedback
    zenoh_thread = threading.Thread(target=lambda: feedback(_wire(end)))
    zenoh_thread.start()
    assert telling.wait(WAIT)

    def waits() -> None:
        sender.wait(handle, WAIT)
        told.append("result")

    waiter = threading.Thread(target=waits)
    waiter.start()
    waiter.join(0.5)  # the old sender returned at once here; this one waits for the telling to end
    go_on.set()
    waiter.join(WAIT)
    zenoh_thread.join(WAIT)
    assert told == ["feedback", "result"]


def _wire(fb: ExecutePlanFeedback) -> Any:
    """The feedback as ActionClient's subscription hands it on: with its goal id."""

    class Message:
        goal_id = GOAL
        feedback = fb

    return Message


def test_a_result_fetch_nothing_answered_is_asked_again() -> None:
    """A get_result lost on the way (a router restarting, the executor's pool for waiting queries
    full): send said 'no outcome', exit 3, of a plan that went on moving."""
    asked: list[str] = []
    succeeded = ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.EXECUTE)

    def answer(service: Any, request: Any) -> Any:
        asked.append(request.goal_id)
        if len(asked) == 1:
            raise unavailable("get_result")
        return ResultResponse[ExecutePlanResult](goal_id=GOAL, state=GoalState.SUCCEEDED, result=succeeded)

    sender = PlanSender(Session(answer))  # type: ignore[arg-type]
    run = sender.wait(sender.handle(GOAL), WAIT)
    assert run.result == succeeded
    assert asked == [GOAL, GOAL]


def test_an_executor_gone_for_good_is_no_outcome_within_its_bound(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(client, "RESULT_GONE", 0.2)
    monkeypatch.setattr(client, "RESULT_RETRY", 0.05)

    def answer(service: Any, request: Any) -> Any:
        raise unavailable("get_result")

    sender = PlanSender(Session(answer))  # type: ignore[arg-type]
    with pytest.raises(CallError, match="no reply"):
        sender.wait(sender.handle(GOAL), WAIT)


def test_a_peers_huge_feedback_is_printed_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Feedback is a publication anyone on the robot's keys can make for a goal id it saw: an action of
    a megabyte and ten thousand places searched (neither bounded by the schema) went to the terminal whole."""
    text = io.StringIO()
    monkeypatch.setattr(cli, "console", Console(file=text, width=400, color_system=None))
    huge = ExecutePlanFeedback(
        stage=Stage.EXECUTE,
        step=0,
        action="[red]x" * 200_000,
        status=StepStatus.FAILED,
        message="m",
        searched=["on the [b]table"] * 10_000,
    )
    cli.print_feedback(huge)
    printed = text.getvalue()
    assert len(printed) < 10_000, len(printed)
    assert "[red]x" in printed and "on the [b]table" in printed  # as written, not as markup


def test_a_send_with_no_answer_cancels_the_goal_by_its_id() -> None:
    """A --preempt waits up to 15 s for its answer: when none came, send said 'executor unreachable'
    while the executor, deciding on it still, went on to accept and run the plan with nobody following."""
    cancels: list[str] = []

    def answer(service: Any, request: Any) -> Any:
        if service is keys.EXECUTE_PLAN.cancel_goal:
            cancels.append(request.goal_id)
            return CancelResponse(goal_id=request.goal_id, accepted=False, reason="no such running goal")
        raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message="no reply from send_goal within 15 s"))

    sender = PlanSender(Session(answer))  # type: ignore[arg-type]
    with pytest.raises(CallError):
        sender.send(ExecutePlanGoal(text="{}", preempt=True), GOAL)
    assert cancels == [GOAL]
    assert sender.following() == []
