"""A caller stopping its own request (plan/ask_cancel): the planner's bookkeeping of the requests in
flight, pure, and the Planner's sends and recoveries around a cancel, with a stand-in node, executor
and model (no Zenoh)."""

from __future__ import annotations

import threading
from types import SimpleNamespace
from typing import Any

import msgspec
import pytest

from schemas.actions import CancelResponse, GoalState, ResultResponse
from schemas.common import Stage
from schemas.executor import ExecutePlanGoal, ExecutePlanResult, FailureKind, PlanStatus, StepResult, StepStatus
from schemas.planner import AskCancel, AskReply, AskRequest, AskStatus, RecoveryOutcome
from services.planner.config import PlannerConfig
from services.planner.llm import ChatReply
from services.planner.node import MAX_ENDED, Planner, Requests
from services.planner.recovery import Ended
from tests.plannerparts import PlannerNode

PLAN = '{"plan": [{"action": "navigate_to", "target": "kitchen"}]}'
WAIT = 10.0  # s: a deadline for what must happen at once


class StandInNode(PlannerNode):
    """The executor alive, the scene answered, cancels kept (and `canceled` set); every other query
    unanswered."""

    def __init__(self) -> None:
        super().__init__("a kitchen")
        self.cancels: list[str] = []
        self.canceled = threading.Event()

    def alive_services(self, timeout: float) -> set[str]:
        return {"executor"}

    def answer(self, service: Any, request: Any, timeout: float) -> Any:
        if service == "cancel_goal":
            self.cancels.append(request.goal_id)
            self.canceled.set()
            return CancelResponse(goal_id=request.goal_id, accepted=True)
        return super().answer(service, request, timeout)


class StandInExecutor:
    """Dry runs pass; real sends are kept (`sent` set at each)."""

    def __init__(self, node: StandInNode) -> None:
        self._node = node
        self._action = SimpleNamespace(cancel_goal="cancel_goal", get_result="get_result")
        self.sent: list[tuple[str, str]] = []
        self.sending = threading.Event()

    def run(self, goal: ExecutePlanGoal, *, timeout: float) -> ResultResponse[ExecutePlanResult]:
        result = ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.SAFETY, reason="dry run: approved")
        return ResultResponse(goal_id="dry", state=GoalState.SUCCEEDED, result=result)

    def send(self, goal: ExecutePlanGoal, *, timeout: float, goal_id: str) -> Any:
        self.sent.append((goal_id, goal.text))
        self.sending.set()
        return SimpleNamespace(goal_id=goal_id)


class StandInChat:
    """The model: each call waits for `answer`, once `asked` is set, then gives the plan."""

    def __init__(self, hold: bool = False) -> None:
        self.calls = 0
        self.asked = threading.Event()
        self.answer = threading.Event()
        if not hold:
            self.answer.set()

    def chat(self, conversation: list[dict[str, Any]], tools: Any) -> ChatReply:
        self.calls += 1
        self.asked.set()
        assert self.answer.wait(WAIT)
        return ChatReply(PLAN)


def planner_with(chat: StandInChat) -> tuple[Planner, StandInNode, StandInExecutor]:
    node = StandInNode()
    executor = StandInExecutor(node)
    planner = Planner(node, PlannerConfig(), None, client=chat)  # type: ignore[arg-type]
    planner._executor = executor  # type: ignore[assignment]
    planner._tool_schemas = []
    return planner, node, executor


def asking(planner: Planner, request: AskRequest) -> tuple[threading.Thread, list[AskReply]]:
    replies: list[AskReply] = []
    thread = threading.Thread(target=lambda: replies.append(planner.ask(request)))
    thread.start()
    return thread, replies


def failed_at_a_step() -> Ended:
    """A failure a recovery would be asked for (not a cancel, not a veto)."""
    step = StepResult(
        index=0,
        action="navigate_to",
        status=StepStatus.FAILED,
        message="the way is blocked",
        failure=FailureKind.PLANNING,
    )
    result = ExecutePlanResult(
        status=PlanStatus.FAILED, stage=Stage.EXECUTE, reason="step 1 failed", steps=[step], failure=step.failure
    )
    return Ended(result, "aborted", "step 1 failed")


# The bookkeeping, pure.


def test_a_caller_chosen_id_is_refused_while_it_is_in_flight_and_after_it_ended() -> None:
    requests = Requests()
    assert requests.start("req-1") is None
    assert "in flight already" in (requests.start("req-1") or "")
    requests.end("req-1")
    requests.end("req-1")  # again: nothing
    assert "ended lately" in (requests.start("req-1") or "")


def test_an_unknown_id_is_answered_clearly_and_a_request_arriving_with_it_later_is_refused() -> None:
    """The cancel may overtake its request (or the request may wait for a worker): it must not start then."""
    requests = Requests()
    said = requests.cancel("never-seen")
    assert (said.known, said.running, said.goal_id) == (False, False, "")
    assert "nothing was canceled" in said.reason
    assert "canceled before it arrived" in (requests.start("never-seen") or "")


def test_a_cancel_names_the_goal_the_request_sent_last_and_marks_it_canceled() -> None:
    requests = Requests()
    requests.start("req-1")
    said = requests.cancel("req-1")
    assert (said.known, said.running, said.goal_id) == (True, True, "") and requests.canceled("req-1")
    requests.sending("req-1", "goal-a")  # a send that does not look (the planner's does) still names it
    requests.sending("req-1", "goal-b")
    assert requests.cancel("req-1").goal_id == "goal-b"
    requests.end("req-1")
    ended = requests.cancel("req-1")  # answered at acceptance: its plan may still run
    assert (ended.known, ended.running, ended.goal_id) == (True, False, "goal-b"), ended
    assert "ended lately" in (requests.start("req-1") or "")


def test_the_requests_in_flight_and_those_remembered_are_bounded() -> None:
    requests = Requests(max_in_flight=2, max_ended=2, max_early=2)
    assert requests.start("a") is None and requests.start("b") is None
    assert "2 requests in flight" in (requests.start("c") or "")
    requests.end("a")
    assert requests.start("c") is None
    requests.end("b")
    requests.end("c")
    # Only the last two that ended are remembered: "a" is forgotten, and its id free again.
    assert requests.cancel("b").known and requests.cancel("c").known
    assert requests.start("a") is None
    # Cancels of ids never seen are remembered apart, the last two: they push out no request.
    for request_id in ("x", "y", "z"):
        assert not requests.cancel(request_id).known
    assert requests.cancel("b").known and requests.cancel("c").known
    assert requests.start("x") is None
    assert "canceled before it arrived" in (requests.start("y") or "")
    assert "canceled before it arrived" in (requests.start("z") or "")


def test_a_caller_chosen_id_is_checked() -> None:
    assert msgspec.convert({"text": "go", "request_id": "0123abcdEF_-"}, AskRequest).request_id == "0123abcdEF_-"
    assert msgspec.convert({"text": "go"}, AskRequest).request_id == ""
    for bad in ("../x", "a b", "x" * 65, "a\n"):
        with pytest.raises(msgspec.ValidationError, match="request_id"):
            msgspec.convert({"text": "go", "request_id": bad}, AskRequest)
    for bad in ("", "a\n", "x" * 65):
        with pytest.raises(msgspec.ValidationError, match="request_id"):
            msgspec.convert({"request_id": bad}, AskCancel)


# The planner around a cancel.


def test_a_cancel_before_the_plan_is_sent_means_nothing_is_sent() -> None:
    """Canceled while the model thinks: the plan it then gives passes its dry run and is not sent."""
    chat = StandInChat(hold=True)
    planner, node, executor = planner_with(chat)
    thread, replies = asking(planner, AskRequest(text="go to the kitchen", request_id="req-1", wait=True))
    try:
        assert chat.asked.wait(WAIT)
        said = planner.ask_cancel(AskCancel(request_id="req-1"))
        assert (said.known, said.running, said.goal_id) == (True, True, ""), said
    finally:
        chat.answer.set()
        thread.join(WAIT)
    [reply] = replies
    assert reply.status is AskStatus.REJECTED and "canceled" in reply.reason and not reply.goal_id, reply
    assert executor.sent == [] and node.cancels == []


def test_a_cancel_while_the_plan_runs_cancels_it_and_no_recovery_is_sent() -> None:
    """The plan fails at a step as the cancel comes: a recovery was due, but the request is canceled."""
    chat = StandInChat()
    planner, node, executor = planner_with(chat)

    def fails_once_canceled(goal_id: str) -> Ended:
        assert node.canceled.wait(WAIT)
        return failed_at_a_step()

    planner._follow_goal = fails_once_canceled  # type: ignore[method-assign]
    request = AskRequest(text="go to the kitchen", request_id="req-1", wait=True, max_recoveries=2)
    thread, replies = asking(planner, request)
    try:
        assert executor.sending.wait(WAIT)
        said = planner.ask_cancel(AskCancel(request_id="req-1"))
    finally:
        node.canceled.set()
        thread.join(WAIT)
    [(goal_id, _)] = executor.sent
    assert (said.known, said.running, said.goal_id) == (True, True, goal_id), said
    assert node.cancels == [goal_id]
    [reply] = replies
    assert reply.status is AskStatus.FAILED and reply.goal_id == goal_id, reply
    [stopped] = reply.recoveries
    assert stopped.outcome is RecoveryOutcome.STOPPED and "canceled" in stopped.reason, stopped
    assert chat.calls == 1, "the model was asked for a recovery of a canceled request"
    # And a recovery the model gave as the cancel came is not sent either: looked at under the lock.
    assert planner._send_recovery(PLAN, request_id="req-1").stop and len(executor.sent) == 1


def test_a_second_request_with_an_id_in_flight_is_refused_and_the_first_goes_on() -> None:
    chat = StandInChat(hold=True)
    planner, _, executor = planner_with(chat)
    thread, replies = asking(planner, AskRequest(text="go to the kitchen", request_id="req-1"))
    try:
        assert chat.asked.wait(WAIT)
        twin = planner.ask(AskRequest(text="go to the hall", request_id="req-1"))
        assert twin.status is AskStatus.REJECTED and "in flight already" in twin.reason, twin
    finally:
        chat.answer.set()
        thread.join(WAIT)
    [reply] = replies
    assert reply.status is AskStatus.ACCEPTED and [text for _, text in executor.sent] == [PLAN], reply


def test_a_cancel_of_an_unknown_request_is_answered_and_the_request_never_starts() -> None:
    chat = StandInChat()
    planner, node, executor = planner_with(chat)
    said = planner.ask_cancel(AskCancel(request_id="req-late"))
    assert said.known is False and "nothing was canceled" in said.reason, said
    reply = planner.ask(AskRequest(text="go to the kitchen", request_id="req-late"))
    assert reply.status is AskStatus.REJECTED and "canceled before it arrived" in reply.reason, reply
    assert chat.calls == 0 and executor.sent == [] and node.cancels == []


def test_a_cancel_of_a_request_answered_at_acceptance_cancels_its_plan() -> None:
    """Without recoveries the reply goes at acceptance and the request ends; its plan runs on."""
    planner, node, executor = planner_with(StandInChat())
    reply = planner.ask(AskRequest(text="go to the kitchen", request_id="req-1", max_recoveries=0))
    assert reply.status is AskStatus.ACCEPTED, reply
    said = planner.ask_cancel(AskCancel(request_id="req-1"))
    assert (said.known, said.running, said.goal_id) == (True, False, reply.goal_id), said
    assert node.cancels == [reply.goal_id] and len(executor.sent) == 1


class HeldExecutor(StandInExecutor):
    """The first real send is held until `release` (a preempt that takes its time, an executor slow
    to answer); the others go at once."""

    def __init__(self, node: StandInNode) -> None:
        super().__init__(node)
        self.release = threading.Event()

    def send(self, goal: ExecutePlanGoal, *, timeout: float, goal_id: str) -> Any:
        held = not self.sent
        handle = super().send(goal, timeout=timeout, goal_id=goal_id)
        if held:
            assert self.release.wait(3 * WAIT)  # released by the test, which waits WAIT at most for anything
        return handle


def finished_within(what: Any, seconds: float = WAIT) -> bool:
    """Whether `what()` returned within `seconds` (its thread is left to end on its own)."""
    thread = threading.Thread(target=what, daemon=True)
    thread.start()
    thread.join(seconds)
    return not thread.is_alive()


def test_a_slow_send_holds_up_neither_other_requests_nor_their_cancels_nor_close() -> None:
    """One request's send waits on the executor (up to SEND_TIMEOUT + PREEMPT_TIMEOUT): another
    request is answered, a cancel of another id answered, and close() keeps to its bound meanwhile."""
    planner, node, _ = planner_with(StandInChat())
    executor = HeldExecutor(node)
    planner._executor = executor  # type: ignore[assignment]
    thread, replies = asking(planner, AskRequest(text="go to the kitchen", request_id="slow", max_recoveries=0))
    try:
        assert executor.sending.wait(WAIT)
        other: list[AskReply] = []
        asked = finished_within(
            lambda: other.append(planner.ask(AskRequest(text="look", request_id="b", dry_run=True)))
        )
        assert asked and other[0].status is AskStatus.APPROVED, other
        assert finished_within(lambda: planner.ask_cancel(AskCancel(request_id="c")))
        assert finished_within(lambda: planner.close(timeout=0.5), 0.5 + WAIT / 2), "close() waited for the send"
    finally:
        executor.release.set()
        thread.join(WAIT)
    [reply] = replies
    assert reply.status is AskStatus.ACCEPTED, reply


def test_a_cancel_during_the_send_waits_for_it_and_cancels_the_goal_sent() -> None:
    """The send under way is the request's own: the cancel answers once the executor took the goal,
    and cancels it (not before: a goal the executor is deciding on would be unknown to it)."""
    planner, node, _ = planner_with(StandInChat())
    executor = HeldExecutor(node)
    planner._executor = executor  # type: ignore[assignment]
    thread, replies = asking(planner, AskRequest(text="go to the kitchen", request_id="req-1", max_recoveries=0))
    said: list[Any] = []
    canceling = threading.Thread(target=lambda: said.append(planner.ask_cancel(AskCancel(request_id="req-1"))))
    try:
        assert executor.sending.wait(WAIT)
        canceling.start()
        canceling.join(0.3)
        assert canceling.is_alive() and node.cancels == [], "canceled before the executor took the goal"
    finally:
        executor.release.set()
        thread.join(WAIT)
        canceling.join(WAIT)
    [(goal_id, _)] = executor.sent
    [reply] = replies
    assert reply.status is AskStatus.ACCEPTED and reply.goal_id == goal_id, reply
    assert said[0].goal_id == goal_id and node.cancels == [goal_id], said


def test_a_request_reusing_a_forgotten_id_after_a_follower_ended_is_not_kept_in_flight() -> None:
    """A follower's request, once it ended and was forgotten, leaves nothing behind: a later request
    with that id ends when it is answered (kept in flight, it took a place for good, and at the most
    every request was refused)."""
    planner, _, _ = planner_with(StandInChat())
    planner._requests = Requests(max_in_flight=1, max_ended=1)
    done = ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.EXECUTE, reason="done")
    planner._follow_goal = lambda goal_id, until=0.0: Ended(done, "succeeded", "")  # type: ignore[method-assign]
    followed = planner.ask(AskRequest(text="go to the kitchen", request_id="a", max_recoveries=1))
    assert followed.status is AskStatus.ACCEPTED, followed
    follower = planner._followers.get("a")  # gone already when it ended before this line
    if follower is not None:
        follower.join(WAIT)
    assert "a" not in planner._followers
    for request_id in ("b", "a", "c"):  # "b" pushes "a" out of those remembered; "a" comes again
        reply = planner.ask(AskRequest(text="look", request_id=request_id, dry_run=True))
        assert reply.status is AskStatus.APPROVED, reply


def test_a_flood_of_cancels_of_unknown_ids_forgets_no_request() -> None:
    """Cancels of ids no request had (a caller trying ids, or flooding) are remembered apart: a
    request answered at acceptance is still found by its id, and its plan canceled."""
    planner, node, _ = planner_with(StandInChat())
    reply = planner.ask(AskRequest(text="go to the kitchen", request_id="req-1", max_recoveries=0))
    assert reply.status is AskStatus.ACCEPTED, reply
    for number in range(MAX_ENDED + 1):
        assert not planner.ask_cancel(AskCancel(request_id=f"junk-{number}")).known
    said = planner.ask_cancel(AskCancel(request_id="req-1"))
    assert (said.known, said.goal_id) == (True, reply.goal_id), said
    assert node.cancels == [reply.goal_id]
    # The cancels remembered are bounded too; the last ones still refuse their request.
    refused = planner.ask(AskRequest(text="look", request_id=f"junk-{MAX_ENDED}", dry_run=True))
    assert "canceled before it arrived" in refused.reason, refused


def test_close_waits_within_its_bound_for_a_send_under_way() -> None:
    """The lock is let go during a send, yet close() still waits for that send's end: after it, no
    send is under way."""
    planner, node, _ = planner_with(StandInChat())
    executor = HeldExecutor(node)
    planner._executor = executor  # type: ignore[assignment]
    thread, _ = asking(planner, AskRequest(text="go to the kitchen", request_id="slow", max_recoveries=0))
    closing = threading.Thread(target=planner.close, kwargs={"timeout": WAIT})
    try:
        assert executor.sending.wait(WAIT)
        closing.start()
        closing.join(0.3)
        assert closing.is_alive(), "close() did not wait for the send under way"
    finally:
        executor.release.set()
        closing.join(WAIT)
        thread.join(WAIT)
    assert not closing.is_alive()
