"""The planner on Zenoh: serves plan/ask, reads the scene, dry-runs through the executor, publishes attempts."""

from __future__ import annotations

import functools
import logging
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from concurrent import futures
from dataclasses import dataclass
from typing import Any

import msgspec

from schemas import keys
from schemas.common import ErrorKind, Pose2D, Stage
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.incidents import IncidentList
from schemas.planner import (
    MAX_RECORDED_CHARS,
    MAX_RECOVERIES,
    MAX_REQUEST_CHARS,
    AskCancel,
    AskCancelReply,
    AskReply,
    AskRequest,
    AskStatus,
    AttemptOutcome,
    PlannerAttempt,
    Recovery,
)
from schemas.safety import SafetyStatus
from schemas.world import Empty
from services.actionlib import MAX_RESULT_WAIT, PREEMPT_TIMEOUT, ActionClient, ClientGoal
from services.errors import CallError, GoalRejected
from services.planner.config import HOW_TO_CONFIGURE, Endpoint, PlannerConfig
from services.planner.errors import ExecutorUnreachable, LLMError
from services.planner.llm import ChatClient, ChatReply
from services.planner.loop import Attempt, DryRunVerdict, LoopResult, LoopStatus, plan_loop
from services.planner.prompt import hazard_lines, hazards_block, hazards_query, initial_messages
from services.planner.recovery import UNFOLLOWED, Ended, Ports, Sent, follow_and_recover
from services.runtime import BUILDING_TYPES, Node, prepare_types

log = logging.getLogger(__name__)

SCENE_TIMEOUT = 5.0
# How long the executor may take to accept a goal (longer when it preempts a running plan).
SEND_TIMEOUT = 5.0
INCIDENTS_TIMEOUT = 3.0
# Plans followed behind a reply at once (each until its end); the executor runs one plan at a time,
# so more than a few means plans preempted while their followers wait for the result.
MAX_FOLLOWERS = 8
# How often a follower looks whether the planner is closing while it waits for a plan's end.
FOLLOW_POLL = 0.25
# Requests in flight at once (plan/ask's workers and the followers behind replies are fewer), and the
# ended ones remembered (a cancel still finds their last goal; their ids are not taken again).
MAX_IN_FLIGHT = 128
MAX_ENDED = 256
# Cancels of ids no request had, remembered apart (their request is refused if it comes): a caller
# flooding plan/ask_cancel with made-up ids pushes out only these, never a request's own record.
MAX_EARLY_CANCELS = 256
# How long a cancel waits for the executor to take the cancel of a request's goal.
CANCEL_TIMEOUT = 2.0
# How long a dry run whose end could not be learned is canceled for before it is given up on
# (actionlib's CANCEL_GRACE, 10 s, is for motions).
DRY_RUN_CANCEL_GRACE = 1.0
LOOP_STATUS = {
    LoopStatus.APPROVED: AskStatus.APPROVED,
    LoopStatus.REJECTED: AskStatus.REJECTED,
    LoopStatus.LLM_ERROR: AskStatus.LLM_ERROR,
}
ATTEMPT_OUTCOME = {
    LoopStatus.APPROVED: AttemptOutcome.APPROVED,
    LoopStatus.REJECTED: AttemptOutcome.REJECTED,
    LoopStatus.LLM_ERROR: AttemptOutcome.LLM_ERROR,
}


DEADLINE_PASSED = "the caller's deadline passed: nothing more was asked of the model and no plan was sent"
CANCELED = "the request was canceled (plan/ask_cancel)"


@dataclass
class InFlight:
    """A request as a cancel sees it: the goal it sent last (the plan, then each recovery), whether
    the executor is still deciding on it (`sending`), and whether its caller canceled it."""

    goal_id: str = ""
    sending: bool = False
    canceled: bool = False


class Requests:
    """The requests in flight by id, the ones that ended lately with their last goal (a plan
    answered at acceptance runs on after its request ended), and the ids canceled before any request
    had them. Pure bookkeeping, bounded, used under the planner's lock: a send looks at the cancel
    and names its goal in one hold of that lock, so a cancel either comes first and no goal is sent,
    or finds the goal named (and waits for the send's end before canceling it)."""

    def __init__(
        self, max_in_flight: int = MAX_IN_FLIGHT, max_ended: int = MAX_ENDED, max_early: int = MAX_EARLY_CANCELS
    ) -> None:
        self._in_flight: dict[str, InFlight] = {}
        self._ended: OrderedDict[str, InFlight] = OrderedDict()
        self._early: OrderedDict[str, None] = OrderedDict()
        self._max_in_flight = max_in_flight
        self._max_ended = max_ended
        self._max_early = max_early

    def start(self, request_id: str) -> str | None:
        """Take the request in: None, or why it is refused."""
        if request_id in self._in_flight:
            return f"request id {request_id} is in flight already: each request needs an id of its own"
        if request_id in self._early:
            return f"request {request_id} was canceled before it arrived: nothing was asked or sent"
        if request_id in self._ended:
            return f"request id {request_id} was used by a request that ended lately: each needs an id of its own"
        if len(self._in_flight) >= self._max_in_flight:
            return f"the planner has {len(self._in_flight)} requests in flight, its most: ask again later"
        self._in_flight[request_id] = InFlight()
        return None

    def end(self, request_id: str) -> None:
        """The request is over (its last goal may still run); again, or for an unknown id, nothing."""
        entry = self._in_flight.pop(request_id, None)
        if entry is not None:
            self._remember(request_id, entry)

    def sending(self, request_id: str, goal_id: str) -> None:
        """The request's next goal, named before it goes: a send that got no answer may have been taken."""
        entry = self._in_flight.get(request_id)
        if entry is not None:
            entry.goal_id = goal_id
            entry.sending = True

    def sent(self, request_id: str) -> None:
        """The executor answered the send (or it failed): a cancel need not wait for it any longer."""
        entry = self._in_flight.get(request_id)
        if entry is not None:
            entry.sending = False

    def in_send(self, request_id: str | None = None) -> bool:
        """Whether the request (None: any) has a send the executor has not answered yet."""
        if request_id is None:
            return any(entry.sending for entry in self._in_flight.values())
        entry = self._in_flight.get(request_id)
        return entry is not None and entry.sending

    def canceled(self, request_id: str) -> bool:
        entry = self._in_flight.get(request_id) or self._ended.get(request_id)
        return entry is not None and entry.canceled

    def cancel(self, request_id: str) -> AskCancelReply:
        """Mark the request canceled; the answer names the goal to cancel, if it sent one. An id not
        known is remembered as canceled: a request arriving with it later (the cancel overtook it, or
        it waited for a worker) is refused."""
        entry = self._in_flight.get(request_id)
        if entry is not None:
            entry.canceled = True
            if entry.goal_id:
                said = f"canceled: goal {entry.goal_id} is canceled and no recovery is sent after it"
            else:
                said = "canceled before any plan was sent: none is sent"
            return AskCancelReply(request_id=request_id, known=True, running=True, goal_id=entry.goal_id, reason=said)
        entry = self._ended.get(request_id)
        if entry is not None:
            entry.canceled = True
            if entry.goal_id:
                said = f"the request had ended; its last goal {entry.goal_id} is canceled (it may have ended already)"
            else:
                said = "the request had ended without sending a plan: nothing to cancel"
            return AskCancelReply(request_id=request_id, known=True, goal_id=entry.goal_id, reason=said)
        self._early[request_id] = None
        self._early.move_to_end(request_id)
        while len(self._early) > self._max_early:
            self._early.popitem(last=False)
        said = (
            f"no request {request_id} is in flight or ended lately: nothing was canceled; "
            "a request with this id arriving later is refused"
        )
        return AskCancelReply(request_id=request_id, known=False, reason=said)

    def _remember(self, request_id: str, entry: InFlight) -> None:
        self._ended[request_id] = entry
        self._ended.move_to_end(request_id)
        while len(self._ended) > self._max_ended:
            self._ended.popitem(last=False)


def past_deadline(request: AskRequest) -> bool:
    return request.deadline > 0 and time.time() > request.deadline


def bounded(text: str, limit: int = MAX_RECORDED_CHARS) -> str:
    marker = " ...(cut)"
    return text if len(text) <= limit else text[: limit - len(marker)] + marker


def tool_schemas() -> list[dict[str, Any]]:
    """The action tools in OpenAI's shape (imported when first asked, not at start). The import brings
    struct types (the vocabulary's) first used here, maybe on two workers at once: built one at a time
    (runtime.prepare_types; two threads using a new struct type at once crashed the planner)."""
    from services.agent.tools import all_tools, render

    prepare_types()
    tools = all_tools()
    # The step tools and execute_plan; not plan_and_execute (this planner itself), reads or controls.
    actions = [t for t in tools if t.kind == "action" and t.name != "plan_and_execute"] or tools
    rendered: list[dict[str, Any]] = render(actions, "openai")
    return rendered


class Planner:
    """Words to a checked plan for one robot, on one node; used by the service and by `tether ask`."""

    def __init__(
        self,
        node: Node,
        config: PlannerConfig,
        endpoint: Endpoint | None,
        client: Any = None,
        on_send: Callable[[str], None] | None = None,
    ) -> None:
        self.node = node
        # Told each goal's id right before it is sent (the plan, then any recovery): `tether ask`,
        # interrupted, cancels the last by id, whether or not the executor had answered its send.
        self._on_send = on_send
        self.config = config
        self.endpoint = endpoint
        self._chat = client if client is not None else (ChatClient(endpoint) if endpoint is not None else None)
        # Its `run` is only the dry run's, which moves nothing: a goal whose end cannot be learned is
        # given up on after a short try at canceling it (an executor that is down fails the ask at once).
        self._executor: ActionClient[Any, Any, Any] = ActionClient(
            node, keys.EXECUTE_PLAN, cancel_grace=DRY_RUN_CANCEL_GRACE
        )
        self._attempts = node.publisher(keys.PLANNER_ATTEMPTS)
        self._recoveries = node.publisher(keys.PLANNER_RECOVERIES)
        self._tool_schemas: list[dict[str, Any]] | None = None
        # Where the scene last put the robot: the recovery prompt lists the incidents near it.
        self._last_robot: Pose2D | None = None
        # Followers of plans sent without waiting (request id -> thread, each started before it is
        # listed, each taking itself off as it ends); closing stops them. `_closing` is set under
        # `_lock`, and a recovery goes only if its send saw it unset under `_lock`: no recovery is
        # sent once close() has begun, but the one whose send was under way (close waits for it).
        self._lock = threading.Lock()
        self._followers: dict[str, threading.Thread] = {}
        self._closing = threading.Event()
        # The requests in flight, for plan/ask_cancel, under `_lock`. A send names its goal under it,
        # then lets it go while the executor decides (up to SEND_TIMEOUT + PREEMPT_TIMEOUT; held that
        # long, it kept every other request, cancel and close() waiting); `_sends_ended` is notified
        # as each send ends, for a cancel of that request and close() to wait on.
        self._requests = Requests()
        self._sends_ended = threading.Condition(self._lock)
        # The e-stop as the heartbeat last said: while it is latched no plan can pass, and asking the
        # model to "fix" one would spend attempts on what only an operator can change.
        self._heartbeat: SafetyStatus | None = None
        node.subscribe(keys.HEARTBEAT, self._on_heartbeat)

    def _on_heartbeat(self, status: SafetyStatus) -> None:
        self._heartbeat = status

    def estop_latched(self) -> str | None:
        """Why nothing may move now, when the e-stop is latched; None otherwise."""
        beat = self._heartbeat
        if beat is None or not beat.estop.latched:
            return None
        return (
            f"the e-stop is latched (by {beat.estop.source}: {beat.estop.reason}); only a human operator can "
            "reset it, so no plan was asked for or sent"
        )

    def close(self, timeout: float = 5.0) -> None:
        """Stop following: no model call starts and no recovery is sent after this; the plans go on.
        Waits (up to `timeout` in all) for a send already under way, and for the followers to end."""
        deadline = time.monotonic() + timeout
        with self._lock:
            self._closing.set()
            followers = list(self._followers.values())
            self._sends_ended.wait_for(lambda: not self._requests.in_send(), timeout)
        for thread in followers:
            thread.join(max(0.0, deadline - time.monotonic()))
        if isinstance(self._chat, ChatClient):
            self._chat.close()

    def scene_text(self) -> str:
        try:
            scene = self.node.call(keys.SCENE, Empty(), timeout=SCENE_TIMEOUT)
            if scene.robot is not None:
                self._last_robot = scene.robot
            return scene.text
        except CallError as exc:
            log.warning("no scene for the prompt: %s", exc)
            return f"(the scene is not available: {exc.error.message})"

    def check(self, text: str) -> DryRunVerdict:
        """A dry run through the executor: parse, resolve, safety check; nothing moves."""
        try:
            response = self._executor.run(ExecutePlanGoal(text=text, dry_run=True), timeout=self.config.check_timeout)
        except GoalRejected as exc:
            return DryRunVerdict(False, Stage.EXECUTE, exc.reason)
        except CallError as exc:
            raise ExecutorUnreachable(f"executor unreachable: {exc}") from None
        result = response.result
        if result is None:
            return DryRunVerdict(False, Stage.EXECUTE, response.message or f"the dry run ended {response.state}")
        if result.status is PlanStatus.SUCCEEDED:
            return DryRunVerdict(True, result.stage, result.reason)
        return DryRunVerdict(False, result.stage, result.reason)

    def ask(self, request: AskRequest) -> AskReply:
        request_id = request.request_id or uuid.uuid4().hex[:16]
        with self._lock:
            refused = self._requests.start(request_id)
        if refused is not None:
            return AskReply(status=AskStatus.REJECTED, request_id=request_id, reason=refused)
        try:
            return self._ask(request, request_id)
        finally:
            with self._lock:
                if request_id not in self._followers:  # else its follower ends it, as it takes itself off
                    self._requests.end(request_id)

    def _ask(self, request: AskRequest, request_id: str) -> AskReply:
        if self._chat is None:
            return AskReply(status=AskStatus.UNCONFIGURED, request_id=request_id, reason=HOW_TO_CONFIGURE)
        if "executor" not in self.node.alive_services(timeout=2.0):
            return AskReply(
                status=AskStatus.UNREACHABLE,
                request_id=request_id,
                reason="no executor reachable: start the services with `tether up`",
            )
        if (latched := self.estop_latched()) is not None:
            return AskReply(status=AskStatus.REJECTED, request_id=request_id, stage=Stage.SAFETY, reason=latched)
        try:
            reply, approved = self._given(request, request_id) if request.plan else self._asked(request, request_id)
        except ExecutorUnreachable as exc:
            return AskReply(status=AskStatus.UNREACHABLE, request_id=request_id, reason=str(exc))
        if reply.status is not AskStatus.APPROVED or request.dry_run:
            return reply
        if past_deadline(request):
            return msgspec.structs.replace(
                reply, status=AskStatus.REJECTED, stage=Stage.EXECUTE, reason=DEADLINE_PASSED
            )
        if (latched := self.estop_latched()) is not None:
            return msgspec.structs.replace(reply, status=AskStatus.REJECTED, stage=Stage.SAFETY, reason=latched)
        # The whole plan the dry run approved: the reply's copy is cut for the records (RecordedText).
        sent = self.send(reply, approved, request.preempt)
        if sent.status is not AskStatus.ACCEPTED:
            return sent
        recoveries = self.config.max_recoveries if request.max_recoveries is None else request.max_recoveries
        if request.wait:
            return self.follow(request, sent, recoveries)
        if recoveries > 0:
            self._follow_behind(request, sent, recoveries)
        return sent

    def _asked(self, request: AskRequest, request_id: str) -> tuple[AskReply, str]:
        """The model's plan for the request, dry-run checked (APPROVED), or why there is none; and
        the plan's whole text (the reply holds it cut to what a record keeps)."""
        max_attempts = request.max_attempts or self.config.max_attempts
        scene = self.scene_text()  # first: it says where the robot is, for the hazards near it
        hazards = hazards_block(self.incidents())
        messages = initial_messages(request.text, self._tools(), self.config.native_tools, scene, hazards)
        result = plan_loop(
            messages,
            self._model_call(request_id, request.deadline),
            self.check,
            max_attempts,
            self._recorder(request, request_id, max_attempts, 0),
        )
        status, stage, reason = LOOP_STATUS[result.status], result.stage, result.reason
        if result.status is LoopStatus.LLM_ERROR and (latched := self.estop_latched()) is not None:
            status, stage, reason = AskStatus.REJECTED, Stage.SAFETY, latched  # it latched during the loop
        reply = AskReply(
            status=status,
            request_id=request_id,
            attempts=len(result.attempts),
            stage=stage,
            reason=bounded(reason, 4000),
            plan=bounded(result.plan),
        )
        return reply, result.plan

    def _given(self, request: AskRequest, request_id: str) -> tuple[AskReply, str]:
        """A plan given as is (`tether send --recover`): its dry run, with no model call; and the plan."""
        verdict = self.check(request.plan)
        log.info("request %s: the given plan's dry run: %s %s", request_id, verdict.approved, verdict.reason)
        reply = AskReply(
            status=AskStatus.APPROVED if verdict.approved else AskStatus.REJECTED,
            request_id=request_id,
            stage=verdict.stage,
            reason=bounded(verdict.reason, 4000),
            plan=bounded(request.plan),
        )
        return reply, request.plan

    def _tools(self) -> list[dict[str, Any]]:
        if self._tool_schemas is None:
            with BUILDING_TYPES:  # once, and the vocabulary read by one worker at a time
                if self._tool_schemas is None:
                    self._tool_schemas = tool_schemas()
        return self._tool_schemas

    def _model_call(self, request_id: str, deadline: float) -> Callable[[list[dict[str, Any]]], ChatReply]:
        """One model call, not started after `deadline` (0: none), once the planner is closing, nor
        once the request was canceled."""
        chat = self._chat
        assert chat is not None, "asked only with an endpoint"
        tools = self._tools() if self.config.native_tools else None

        def call_model(conversation: list[dict[str, Any]]) -> ChatReply:
            if deadline > 0 and time.time() > deadline:
                raise LLMError(DEADLINE_PASSED)
            if self._closing.is_set():
                raise LLMError("the planner is shutting down")
            if self._requests.canceled(request_id):  # a read of a flag: the send looks again under the lock
                raise LLMError(CANCELED)
            if (latched := self.estop_latched()) is not None:
                raise LLMError(latched)  # latched since the loop began: no model is asked to fix anything
            reply: ChatReply = chat.chat(conversation, tools)
            return reply

        return call_model

    def _recorder(
        self, request: AskRequest, request_id: str, max_attempts: int, recovery: int
    ) -> Callable[[Attempt], None]:
        model = self.endpoint.model if self.endpoint is not None else ""

        def record(attempt: Attempt) -> None:
            which = f" (recovery {recovery})" if recovery else ""
            log.info(
                "request %s attempt %d%s: %s %s", request_id, attempt.number, which, attempt.status, attempt.reason
            )
            self._attempts.put(
                PlannerAttempt(
                    request_id=request_id,
                    attempt=attempt.number,
                    max_attempts=max_attempts,
                    stamp=time.time(),
                    outcome=ATTEMPT_OUTCOME[attempt.status],
                    stage=attempt.stage,
                    reason=bounded(attempt.reason, 4000),
                    request=bounded(request.text, MAX_REQUEST_CHARS),
                    model=model[:200],
                    reply=bounded(attempt.reply),
                    plan=bounded(attempt.plan),
                    duration=attempt.duration,
                    recovery=recovery,
                )
            )

        return record

    def send(self, approved: AskReply, plan: str, preempt: bool) -> AskReply:
        """The approved plan for real: the goal id once the executor has accepted it. Not sent once the
        request was canceled: looked at under the lock a cancel takes, as the goal is named."""
        request_id = approved.request_id
        with self._lock:
            if self._requests.canceled(request_id):
                said = f"{CANCELED}: no plan was sent"
                return msgspec.structs.replace(approved, status=AskStatus.REJECTED, stage=Stage.EXECUTE, reason=said)
            goal_id = self._name_goal(request_id)
        try:
            goal = ExecutePlanGoal(text=plan, preempt=preempt)
            handle = self._send_named(request_id, goal, goal_id, SEND_TIMEOUT + PREEMPT_TIMEOUT)
        except GoalRejected as exc:
            return msgspec.structs.replace(
                approved, status=AskStatus.REJECTED, stage=Stage.EXECUTE, reason=bounded(exc.reason, 4000)
            )
        except CallError as exc:
            return msgspec.structs.replace(
                approved, status=AskStatus.UNREACHABLE, reason=bounded(f"executor unreachable: {exc}", 4000)
            )
        log.info("request %s: plan sent as goal %s", request_id, handle.goal_id)
        return msgspec.structs.replace(
            approved, status=AskStatus.ACCEPTED, goal_id=handle.goal_id, reason="approved by a dry run and sent"
        )

    def _name_goal(self, request_id: str) -> str:
        """The next goal's id, under `_lock`, named before the send (to the request, for a cancel, and
        to `on_send` when it wants it): an unanswered send may have been taken."""
        goal_id = uuid.uuid4().hex
        self._requests.sending(request_id, goal_id)
        if self._on_send is not None:
            self._on_send(goal_id)
        return goal_id

    def _send_named(
        self, request_id: str, goal: ExecutePlanGoal, goal_id: str, timeout: float
    ) -> ClientGoal[Any, Any, Any]:
        """Send for real, `_lock` let go; its end is told to a cancel of the request, and to close()."""
        try:
            return self._executor.send(goal, timeout=timeout, goal_id=goal_id)
        finally:
            with self._lock:
                self._requests.sent(request_id)
                self._sends_ended.notify_all()

    # Following a sent plan to its end, and recovering when it failed at a step.

    def follow(self, request: AskRequest, sent: AskReply, max_recoveries: int) -> AskReply:
        """Follow the sent plan (and any recovery) to its end: SUCCEEDED or FAILED, with the recoveries.
        The caller's deadline, when it waits, bounds what is asked and sent after the failure."""
        deadline = request.deadline if request.wait else 0.0
        max_attempts = request.max_attempts or self.config.max_attempts
        request_id = sent.request_id

        def stopped() -> str | None:
            if self._closing.is_set():
                return "the planner is shutting down"
            if self._requests.canceled(request_id):
                return CANCELED
            if deadline > 0 and time.time() > deadline:
                return DEADLINE_PASSED
            return None

        def plan(messages: list[dict[str, Any]], number: int) -> LoopResult:
            record = self._recorder(request, request_id, max_attempts, number)
            try:
                return plan_loop(messages, self._model_call(request_id, deadline), self.check, max_attempts, record)
            except ExecutorUnreachable as exc:
                return LoopResult(LoopStatus.REJECTED, reason=str(exc))

        # The caller stops waiting at its deadline: the plan is not followed longer than that (a worker,
        # or `tether ask` itself, held until the plan's end, up to MAX_RESULT_WAIT, for no one).
        follow = functools.partial(self._follow_goal, until=deadline) if deadline > 0 else self._follow_goal
        ports = Ports(
            follow=follow,
            estop=self.estop_latched,
            scene=self.scene_text,
            incidents=self.incidents_text,
            plan=plan,
            send=functools.partial(self._send_recovery, request_id=request_id),
            record=self._publish_recovery,
            stopped=stopped,
        )
        followed = follow_and_recover(
            request_id,
            request.text,
            sent.goal_id,
            sent.plan,
            max_recoveries,
            self._tools(),
            self.config.native_tools,
            ports,
        )
        log.info("request %s: %s", request_id, followed.reason)
        status = AskStatus.SUCCEEDED if followed.succeeded else AskStatus.FAILED
        if followed.running:
            status = AskStatus.ACCEPTED  # sent, taken, and still running: not failed
        return msgspec.structs.replace(
            sent,
            status=status,
            stage=Stage.EXECUTE,
            reason=bounded(followed.reason, 4000),
            plan=bounded(followed.plan),
            goal_id=followed.goal_id,
            recoveries=followed.recoveries[: MAX_RECOVERIES + 1],
        )

    def _follow_behind(self, request: AskRequest, sent: AskReply, max_recoveries: int) -> None:
        """Follow and recover on a thread of its own, the reply having gone at acceptance: one per
        request, at most MAX_FOLLOWERS at once (past that the plan runs, but is not recovered)."""
        with self._lock:
            # Every listed thread was started before it was listed: one not alive has ended.
            self._followers = {k: t for k, t in self._followers.items() if t.is_alive()}
            if self._closing.is_set():
                log.warning("request %s: not followed (the planner is shutting down)", sent.request_id)
                return
            if len(self._followers) >= MAX_FOLLOWERS:
                log.warning("request %s: not followed (%d followers already)", sent.request_id, len(self._followers))
                return
            thread = threading.Thread(
                target=self._follow_quietly,
                args=(request, sent, max_recoveries),
                name=f"follow:{sent.request_id}",
                daemon=True,
            )
            # Started under the lock, so that close() (which lists the followers under it) joins it.
            thread.start()
            self._followers[sent.request_id] = thread

    def _follow_quietly(self, request: AskRequest, sent: AskReply, max_recoveries: int) -> None:
        try:
            self.follow(request, sent, max_recoveries)
        except Exception:
            log.exception("request %s: following goal %s failed", sent.request_id, sent.goal_id)
        finally:
            with self._lock:
                # Off the list as it ends: a listed follower that ended kept a later request with the
                # same id (its own forgotten) in flight for good, since ask() leaves the end to it.
                if self._followers.get(sent.request_id) is threading.current_thread():
                    del self._followers[sent.request_id]
                self._requests.end(sent.request_id)

    def _follow_goal(self, goal_id: str, until: float = 0.0) -> Ended:
        """Wait for the goal's end (get_result); give up when the planner closes, or at `until`
        (wall clock; 0: none), the caller's deadline."""
        wait = MAX_RESULT_WAIT
        if until > 0:  # the thread asking for the result ends soon after the deadline too, not an hour later
            wait = min(MAX_RESULT_WAIT, max(0.0, until - time.time()) + FOLLOW_POLL)
        future = ClientGoal(self._executor, goal_id).result_future(wait)
        while not futures.wait([future], FOLLOW_POLL).done:
            if self._closing.is_set():
                return Ended(None, UNFOLLOWED, "the planner is shutting down")
            if until > 0 and time.time() > until:
                return Ended(None, UNFOLLOWED, "the caller's deadline passed")
        try:
            response = future.result()
        except CallError as exc:
            if until > 0 and time.time() > until:
                return Ended(None, UNFOLLOWED, "the caller's deadline passed")
            return Ended(None, "unknown", f"no result from the executor: {exc}")
        return Ended(response.result, str(response.state), response.message)

    def _send_recovery(self, plan: str, request_id: str = "") -> Sent:
        """A recovery plan for real; never preempting: whatever runs now was started by someone else.
        Looked at again right before it goes, under the lock close() and a cancel take: not sent once
        the planner is closing or the request was canceled, nor while the e-stop is latched (the
        executor would refuse it; it is not asked)."""
        with self._lock:
            if self._closing.is_set():
                return Sent(refused="the planner is shutting down", stop=True)
            if self._requests.canceled(request_id):
                return Sent(refused=CANCELED, stop=True)
            if (latched := self.estop_latched()) is not None:
                return Sent(refused=latched, kind=ErrorKind.ESTOP, stop=True)
            goal_id = self._name_goal(request_id)
        try:
            handle = self._send_named(request_id, ExecutePlanGoal(text=plan), goal_id, SEND_TIMEOUT)
        except GoalRejected as exc:
            return Sent(refused=exc.reason, kind=exc.kind)
        except CallError as exc:
            return Sent(refused=f"executor unreachable: {exc}")
        return Sent(goal_id=handle.goal_id)

    def ask_cancel(self, cancel: AskCancel) -> AskCancelReply:
        """Stop a request by the id its caller chose: nothing more is asked or sent for it, and its
        last goal is canceled here (the reply names it, for the caller to follow to its end)."""
        with self._lock:  # each send names its goal under it: no goal goes after this but the one named here
            found = self._requests.cancel(cancel.request_id)
            # A send of it under way ends first (its own timeout bounds it): the goal is canceled once
            # the executor has decided on it, not while it may not know it yet.
            self._sends_ended.wait_for(
                lambda: not self._requests.in_send(cancel.request_id), SEND_TIMEOUT + PREEMPT_TIMEOUT
            )
        log.info("request %s: %s", cancel.request_id, found.reason)
        if not found.goal_id:
            return found
        try:
            ClientGoal(self._executor, found.goal_id).cancel(CANCEL_TIMEOUT)
        except CallError as exc:
            said = f"{found.reason}; but the executor did not take the cancel: {exc}"
            return msgspec.structs.replace(found, reason=bounded(said, 4000))
        return found

    def _publish_recovery(self, recovery: Recovery) -> None:
        log.info(
            "request %s recovery %d: %s %s", recovery.request_id, recovery.number, recovery.outcome, recovery.reason
        )
        self._recoveries.put(recovery)

    def incidents(self) -> IncidentList | None:
        """The incidents safety remembers near the robot (where the scene last put it; the latest
        anywhere when it did not say); None when safety does not answer."""
        query = hazards_query(self._last_robot)
        try:
            found: IncidentList = self.node.call(keys.INCIDENTS, query, timeout=INCIDENTS_TIMEOUT)
        except CallError as exc:
            log.warning("no incidents from safety: %s", exc)
            return None
        return found

    def incidents_text(self) -> str:
        return "\n".join(hazard_lines(self.incidents()))


def declare(node: Node, planner: Planner) -> None:
    # A request that waits for its plan's end takes as long as the plan runs: the pool for such waits.
    node.serve(keys.PLAN_ASK, planner.ask, waits=True)
    # Quick (a send under way may hold it a few seconds), on the other pool: never behind the waits.
    node.serve(keys.PLAN_ASK_CANCEL, planner.ask_cancel)
