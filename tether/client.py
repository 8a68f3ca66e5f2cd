"""Client-side helpers shared by the CLI, the demo and the tests: send plans, read robot state."""

from __future__ import annotations

import getpass
import threading
import time
import uuid
from collections.abc import Callable
from concurrent import futures
from dataclasses import dataclass, field
from typing import Any, TypeVar

import msgspec

from schemas import keys
from schemas.actions import GoalState, ResultResponse
from schemas.common import ErrorKind, ServiceError, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepStatus
from schemas.keys import Topic
from schemas.safety import EStop, EstopSource, ResetReply, ResetRequest, SafetyStatus
from services.actionlib import CANCEL_GRACE, CANCEL_POLL, CANCEL_RESEND, PREEMPT_TIMEOUT, ActionClient, ClientGoal
from services.errors import CallError, GoalRejected
from services.robotlink import NOT_SIGNED, Refusal, unpack
from services.runtime import Node
from services.safety.operator import read_token, token_path

T = TypeVar("T")

EXIT_CODES = {
    PlanStatus.SUCCEEDED: 0,
    PlanStatus.FAILED: 1,
    PlanStatus.CANCELED: 1,
    PlanStatus.REJECTED: 2,
}
EXIT_UNREACHABLE = 3
# How long the executor may take to accept or reject a plan.
SEND_TIMEOUT = 5.0
# How long a Ctrl-C waits for the canceled plan to end: beyond the executor's own grace for a motion
# that does not stop (10 s, then it latches the e-stop and ends the plan failed).
CANCEL_WAIT = 30.0
# A get_result that nothing answered (a router restarting, the executor's pool for waiting queries
# full) is asked again this often while the plan runs on; for this long, then the executor is gone.
RESULT_RETRY = 0.5
RESULT_GONE = 5.0
STEP_ENDS = (StepStatus.SUCCEEDED, StepStatus.FAILED, StepStatus.CANCELED)
# A plan's steps end at most MAX_STEPS times each (with their sub-steps and retries, a few times more):
# the ends a run notes are bounded, whatever an executor sends.
MAX_TOLD_ENDS = 4096
# The plan's status for a goal that ended with no result (the executor's run of it raised, no thread to
# run it on): what the goal's state says, its message the reason.
ENDED_WITHOUT_RESULT = {
    GoalState.SUCCEEDED: PlanStatus.SUCCEEDED,
    GoalState.CANCELED: PlanStatus.CANCELED,
    GoalState.ABORTED: PlanStatus.FAILED,
    GoalState.REJECTED: PlanStatus.REJECTED,
}


def next_message(node: Node, topic: Topic[T], timeout: float) -> T | None:
    """The next message published on `topic`, or None if none arrives by the deadline."""
    box: list[T] = []
    arrived = threading.Event()

    def on_message(msg: T) -> None:
        if not box:
            box.append(msg)
            arrived.set()

    subscription = node.subscribe(topic, on_message)
    try:
        arrived.wait(timeout)
    finally:
        subscription.undeclare()
    return box[0] if box else None


def signature_shaped(key_expr: str, payload: bytes, attachment: bytes | None) -> Refusal | None:
    """A subscription's `verify` for safety's heartbeat where there is no robot key (the CLI, the view):
    refused without a signature-shaped robot-link attachment. It screens out unsigned forgeries, not
    a forger's own MAC."""
    return None if unpack(attachment) is not None else Refusal(NOT_SIGNED)


class HeartbeatWait:
    """The first heartbeat that can be safety's and is fresh: it carries a signature-shaped robot-link
    attachment (the CLI has no robot key: this screens out unsigned forgeries, not a forger's own
    MAC) and is stamped within `fresh` seconds of `clock` (a beat buffered across a stalled link and
    delivered late is not fresh), and, given `wanted`, one it passes (a latched e-stop). `why_not` says
    what came instead, when nothing did."""

    def __init__(
        self, fresh: float, clock: Callable[[], float] = time.time, wanted: Callable[[SafetyStatus], bool] | None = None
    ) -> None:
        self.fresh = fresh
        self._clock = clock
        self._wanted = wanted
        self._lock = threading.Lock()
        self._arrived = threading.Event()
        self.status: SafetyStatus | None = None
        self._unsigned = 0
        self._stale: float | None = None  # the age of the latest stale beat

    def verify(self, key_expr: str, payload: bytes, attachment: bytes | None) -> Refusal | None:
        """Before decoding: refused without a signature-shaped attachment (signature_shaped), counted."""
        refusal = signature_shaped(key_expr, payload, attachment)
        if refusal is not None:
            with self._lock:
                self._unsigned += 1
        return refusal

    def take(self, status: SafetyStatus) -> None:
        age = self._clock() - status.stamp
        with self._lock:
            if self.status is not None:
                return
            if not abs(age) < self.fresh:  # also NaN
                self._stale = age
                return
            if self._wanted is not None and not self._wanted(status):
                return
            self.status = status
        self._arrived.set()

    def wait(self, timeout: float) -> SafetyStatus | None:
        self._arrived.wait(timeout)
        with self._lock:
            return self.status

    def why_not(self, timeout: float) -> str:
        with self._lock:
            stale, unsigned = self._stale, self._unsigned
        if stale is not None:
            when = f"{stale:.1f} s ago" if stale > 0 else f"{-stale:.1f} s ahead of this clock"
            return f"no fresh heartbeat from safety within {timeout:g} s (one stamped {when}: stale)"
        if unsigned:
            return f"no heartbeat from safety within {timeout:g} s ({unsigned} without a robot-link MAC: not safety's)"
        return f"no heartbeat from safety within {timeout:g} s"


def next_heartbeat(node: Node, timeout: float) -> HeartbeatWait:
    """Wait up to `timeout` for a fresh heartbeat that may be safety's (HeartbeatWait)."""
    waiting = HeartbeatWait(fresh=timeout)
    subscription = node.subscribe(keys.HEARTBEAT, waiting.take, verify=waiting.verify)
    try:
        waiting.wait(timeout)
    finally:
        subscription.undeclare()
    return waiting


def operator_name() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "operator"


def trigger_estop(node: Node, source: EstopSource, reason: str, timeout: float = 2.0) -> SafetyStatus | None:
    """Publish an e-stop and wait for a heartbeat that shows it latched; None if safety never confirms.

    Only a beat that can be safety's and is fresh confirms it (HeartbeatWait): a latched one without a
    robot-link MAC, or one stamped long ago (a replay, a beat held on a stalled link), said "latched"
    while safety, unreachable, never heard of this e-stop and the robot went on."""
    waiting = HeartbeatWait(fresh=timeout, wanted=lambda status: status.estop.latched)
    subscription = node.subscribe(keys.HEARTBEAT, waiting.take, verify=waiting.verify)
    try:
        node.publish(keys.ESTOP, EStop(source=source, reason=reason))
        return waiting.wait(timeout)
    finally:
        subscription.undeclare()


def within_schema(request: T) -> T:
    """`request` as safety will read it: msgspec.ValidationError, naming the field, for a value out of
    its schema's bounds (a Struct's constructor checks none). An operator's token file that holds no
    token (a certificate given by mistake) is refused so, not taken for safety unreachable."""
    return msgspec.json.decode(msgspec.json.encode(request), type=type(request))


def reset_estop(node: Node, token_file: str | None = None, timeout: float = 3.0) -> ResetReply:
    """Ask safety to clear its latch with the operator token: OSError for a token file that cannot be
    read, msgspec.ValidationError for one that holds no token, CallError when safety does not answer."""
    request = within_schema(ResetRequest(operator=operator_name(), token=read_token(token_path(token_file))))
    return node.call(keys.RESET, request, timeout=timeout)


def plan_result(goal_id: str, response: ResultResponse[Any]) -> ExecutePlanResult:
    """The plan's result in the executor's answer to get_result. A goal that ended with none ends as
    its state says, the executor's message its reason (it was taken for a plan still moving: 'accepted',
    exit 0). CallError when the answer is no end of this goal (another goal's, a state it goes on
    from): it may still be running."""
    if response.goal_id != goal_id:
        message = f"the executor answered goal {goal_id}'s result with goal {response.goal_id}'s"
    elif not response.state.terminal:
        message = f"the executor answered goal {goal_id}'s result with no end: state {response.state}"
    elif response.result is not None:
        return response.result  # type: ignore[no-any-return]
    else:
        return ended_without_result(response.state, response.message)
    raise CallError(ServiceError(kind=ErrorKind.INTERNAL, message=message))


def ended_without_result(state: GoalState, message: str) -> ExecutePlanResult:
    """A plan goal that ended (`state`, terminal) with no result: what its state says, `message` the reason."""
    return ExecutePlanResult(status=ENDED_WITHOUT_RESULT[state], stage=Stage.EXECUTE, reason=message)


@dataclass
class PlanRun:
    """One execute_plan goal as the client sees it: feedback as it comes, then the result."""

    goal_id: str = ""
    result: ExecutePlanResult | None = None
    # What the feedback said, not the feedback itself: a plan that runs for hours sends it for hours.
    latest: ExecutePlanFeedback | None = None
    executing: bool = False  # some feedback said the plan was being carried out
    # (step, label) of the steps whose end some feedback showed
    told_ends: set[tuple[int | None, str | None]] = field(default_factory=set)

    def heard(self, fb: ExecutePlanFeedback) -> None:
        self.latest = fb
        self.executing = self.executing or fb.stage is Stage.EXECUTE
        if fb.status in STEP_ENDS and len(self.told_ends) < MAX_TOLD_ENDS:
            self.told_ends.add((fb.step, fb.label))

    @property
    def awaiting_approval(self) -> ExecutePlanFeedback | None:
        """The feedback saying the plan waits for an operator (supervised mode), while that is the latest."""
        latest = self.latest
        if self.result is None and latest is not None and latest.status is StepStatus.AWAITING_APPROVAL:
            return latest
        return None

    def as_json(self) -> dict[str, Any]:
        r = self.result
        if r is None and (waiting := self.awaiting_approval) is not None:
            return {
                "status": StepStatus.AWAITING_APPROVAL,
                "stage": waiting.stage,
                "reason": waiting.message,
                "goal_id": self.goal_id,
                "steps": [],
            }
        if r is None:
            return {"status": "accepted", "stage": Stage.EXECUTE, "reason": "", "goal_id": self.goal_id, "steps": []}
        out: dict[str, Any] = msgspec.to_builtins(r)
        out["goal_id"] = self.goal_id
        return out


class PlanSender:
    """Sends plans to the executor and follows them; `on_feedback` hears the progress of the plans
    this sender sent (not other clients'). A run is forgotten once its result is in, or by `forget`:
    no feedback of it is told after that (its result is printed then, and after it nothing of the run)."""

    def __init__(self, node: Node, on_feedback: Any = None) -> None:
        self.node = node
        self._runs: dict[str, PlanRun] = {}
        self._started: dict[str, threading.Event] = {}
        self._on_feedback = on_feedback
        self._client = ActionClient(node, keys.EXECUTE_PLAN, self._feedback)
        self._lock = threading.Lock()
        # Held while a feedback is told, and by `forget`: a run forgotten is told nothing more.
        self._telling = threading.Lock()

    def _feedback(self, goal_id: str, fb: ExecutePlanFeedback) -> None:
        with self._telling:
            with self._lock:
                run = self._runs.get(goal_id)
                if run is None:  # another client's plan, or one this sender is done with
                    return
                run.heard(fb)
                started = self._started[goal_id]
            # Moving, or waiting for an operator (supervised mode): either way the sender may return now.
            if fb.stage is Stage.EXECUTE or fb.status is StepStatus.AWAITING_APPROVAL:
                started.set()
            if self._on_feedback is not None:
                self._on_feedback(fb)

    def _follow(self, goal_id: str) -> tuple[PlanRun, threading.Event]:
        with self._lock:
            run = self._runs.setdefault(goal_id, PlanRun(goal_id=goal_id))
            return run, self._started.setdefault(goal_id, threading.Event())

    def following(self) -> list[str]:
        """The goals this sender still keeps feedback for."""
        with self._lock:
            return list(self._runs)

    def forget(self, goal_id: str) -> None:
        """Stop keeping `goal_id`'s feedback (a caller that will not wait for its result)."""
        with self._telling, self._lock:
            self._runs.pop(goal_id, None)
            self._started.pop(goal_id, None)

    def handle(self, goal_id: str) -> ClientGoal[Any, Any, Any]:
        """The goal `goal_id` as sent by this sender, whether or not its send was answered."""
        return ClientGoal(self._client, goal_id)

    def send(self, goal: ExecutePlanGoal, goal_id: str | None = None) -> ClientGoal[Any, Any, Any]:
        """Raises GoalRejected when the executor is busy, CallError when it is unreachable. A goal
        that preempts (its own `preempt`, or the executor's `when_busy`) is answered only once the
        plan it preempts has stopped: the wait allows for that. `goal_id` (default: a new one) lets
        a caller interrupted before the answer cancel the goal (`cancel`)."""
        goal_id = goal_id or uuid.uuid4().hex
        self._follow(goal_id)  # before it is sent: its first feedback may come before the reply
        try:
            return self._client.send(goal, timeout=SEND_TIMEOUT + PREEMPT_TIMEOUT, goal_id=goal_id)
        except GoalRejected:
            self.forget(goal_id)
            raise
        except CallError:
            # No answer, or an error instead of one: the goal may have been accepted all the same and
            # move the robot. Canceled by its id; an executor still deciding on it rejects it then.
            self.forget(goal_id)
            cancel_reached(self.handle(goal_id))
            raise
        except BaseException:
            self.forget(goal_id)
            raise

    def wait(self, handle: ClientGoal[Any, Any, Any], timeout: float, until_started: bool = False) -> PlanRun:
        """Wait for the result, or with `until_started` only until execution begins (the run is then
        kept, to wait on again or to `forget`)."""
        run, started = self._follow(handle.goal_id)
        future = result_future(handle, timeout)
        future.add_done_callback(lambda _: started.set())
        if until_started:
            started.wait(timeout)
            if not future.done():
                return run
        # The fetch gives up after `timeout` itself, failing the future with CallError.
        return self._ended(run, future)

    def cancel(self, handle: ClientGoal[Any, Any, Any], grace: float = CANCEL_GRACE) -> PlanRun:
        """Cancel the goal (sent, or being sent: one the executor is still deciding on is rejected) and
        wait up to `grace` for its end. A cancel that did not reach the executor (no answer, or too
        busy to take it) is asked again meanwhile. CallError when no end came: the goal may still be
        moving the robot. A goal the executor knows nothing of ends canceled: it never ran."""
        run, _ = self._follow(handle.goal_id)
        deadline = time.monotonic() + grace
        # The cancel first: asked for the result of a goal still being decided, the executor says it knows none.
        while not cancel_reached(handle, max(CANCEL_POLL, deadline - time.monotonic())):
            if time.monotonic() + CANCEL_RESEND >= deadline:
                break
            time.sleep(CANCEL_RESEND)
        future = result_future(handle, max(CANCEL_POLL, deadline - time.monotonic()))
        try:
            return self._ended(run, future)
        except CallError as exc:
            if exc.error.kind is not ErrorKind.INVALID_REQUEST:
                raise
        # No such goal: the executor was still deciding on it (it rejects it for the cancel) or never had it.
        run.result = ExecutePlanResult(
            status=PlanStatus.CANCELED, stage=Stage.EXECUTE, reason="canceled before the executor accepted it"
        )
        return run

    def _ended(self, run: PlanRun, future: futures.Future[ResultResponse[Any]]) -> PlanRun:
        try:
            result = plan_result(run.goal_id, future.result())
        except CallError:
            self.forget(run.goal_id)  # given up on: its feedback is not kept any longer
            raise
        self.forget(run.goal_id)  # before the result is set: every feedback told is told before it
        run.result = result
        return run

    def run(self, goal: ExecutePlanGoal, timeout: float) -> PlanRun:
        return self.wait(self.send(goal), timeout)


def cancel_interrupted(sender: PlanSender, goal_id: str) -> PlanRun | str:
    """A Ctrl-C's cancel of `goal_id` (sent, or being sent) and the wait for its end, CANCEL_WAIT at
    most: the run with its end, or why none came (the plan may still be moving), a second Ctrl-C too."""
    try:
        return sender.cancel(sender.handle(goal_id), CANCEL_WAIT)
    except CallError as exc:
        return f"no outcome: canceled (Ctrl-C), but goal {goal_id} did not end: {exc}"
    except KeyboardInterrupt:
        return f"no outcome: interrupted while canceling goal {goal_id} (`tether goal` follows it)"


def cancel_reached(handle: ClientGoal[Any, Any, Any], timeout: float = 2.0) -> bool:
    """Ask the executor to cancel the goal; False when the cancel did not reach it (no answer, or too
    busy to take it): worth asking again. An answer that it knows no such running goal is an answer."""
    try:
        handle.cancel(min(timeout, 2.0))
    except CallError as exc:
        return exc.error.kind is not ErrorKind.UNAVAILABLE
    return True


def result_future(handle: ClientGoal[Any, Any, Any], timeout: float) -> futures.Future[ResultResponse[Any]]:
    """The goal's result, fetched on a thread of its own within `timeout`. A fetch nothing answered is
    asked again (RESULT_RETRY) for up to RESULT_GONE: one lost on the way said 'no outcome' of a plan
    still moving. The future fails with the last CallError, or whatever else ended the call."""
    future: futures.Future[ResultResponse[Any]] = futures.Future()
    deadline = time.monotonic() + timeout

    def fetch() -> None:
        unanswered_since: float | None = None
        while True:
            asked = time.monotonic()
            try:
                future.set_result(handle.result(max(CANCEL_POLL, deadline - asked)))
                return
            except CallError as exc:
                now = time.monotonic()
                if unanswered_since is None or now - asked >= RESULT_GONE:  # the first, or after a long wait
                    unanswered_since = now
                gone = now - unanswered_since >= RESULT_GONE or now + RESULT_RETRY >= deadline
                if exc.error.kind is not ErrorKind.UNAVAILABLE or gone:
                    future.set_exception(exc)
                    return
            except Exception as exc:  # the node closed under the call: the waiter learns it
                future.set_exception(exc)
                return
            time.sleep(RESULT_RETRY)

    threading.Thread(target=fetch, name=f"result:{handle.goal_id}", daemon=True).start()
    return future
