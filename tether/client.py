"""Client-side helpers shared by the CLI, the demo and the tests: send plans, read robot state."""

from __future__ import annotations

import getpass
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import msgspec

from schemas import keys
from schemas.common import Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepStatus
from schemas.keys import Topic
from schemas.safety import EStop, EstopSource, ResetReply, ResetRequest, SafetyStatus
from services.actionlib import PREEMPT_TIMEOUT, ActionClient, ClientGoal
from services.errors import CallError
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
STEP_ENDS = (StepStatus.SUCCEEDED, StepStatus.FAILED, StepStatus.CANCELED)
# A plan's steps end at most MAX_STEPS times each (with their sub-steps and retries, a few times more):
# the ends a run notes are bounded, whatever an executor sends.
MAX_TOLD_ENDS = 4096


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


def reset_estop(node: Node, token_file: str | None = None, timeout: float = 3.0) -> ResetReply:
    token = read_token(token_path(token_file))
    return node.call(keys.RESET, ResetRequest(operator=operator_name(), token=token), timeout=timeout)


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
    this sender sent (not other clients'). A run is forgotten once its result is in, or by `forget`."""

    def __init__(self, node: Node, on_feedback: Any = None) -> None:
        self.node = node
        self._runs: dict[str, PlanRun] = {}
        self._started: dict[str, threading.Event] = {}
        self._on_feedback = on_feedback
        self._client = ActionClient(node, keys.EXECUTE_PLAN, self._feedback)
        self._lock = threading.Lock()

    def _feedback(self, goal_id: str, fb: ExecutePlanFeedback) -> None:
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
        with self._lock:
            self._runs.pop(goal_id, None)
            self._started.pop(goal_id, None)

    def send(self, goal: ExecutePlanGoal) -> ClientGoal[Any, Any, Any]:
        """Raises GoalRejected when the executor is busy, CallError when it is unreachable. A goal
        that preempts (its own `preempt`, or the executor's `when_busy`) is answered only once the
        plan it preempts has stopped: the wait allows for that."""
        goal_id = uuid.uuid4().hex
        self._follow(goal_id)  # before it is sent: its first feedback may come before the reply
        try:
            return self._client.send(goal, timeout=SEND_TIMEOUT + PREEMPT_TIMEOUT, goal_id=goal_id)
        except BaseException:
            self.forget(goal_id)
            raise

    def wait(self, handle: ClientGoal[Any, Any, Any], timeout: float, until_started: bool = False) -> PlanRun:
        """Wait for the result, or with `until_started` only until execution begins (the run is then
        kept, to wait on again or to `forget`)."""
        run, started = self._follow(handle.goal_id)
        future = handle.result_future(timeout)
        future.add_done_callback(lambda _: started.set())
        if until_started:
            started.wait(timeout)
            if not future.done():
                return run
        # The fetch gives up after `timeout` itself, failing the future with CallError.
        try:
            run.result = future.result().result
        except CallError:
            self.forget(handle.goal_id)  # given up on: its feedback is not kept any longer
            raise
        self.forget(handle.goal_id)
        return run

    def run(self, goal: ExecutePlanGoal, timeout: float) -> PlanRun:
        return self.wait(self.send(goal), timeout)
