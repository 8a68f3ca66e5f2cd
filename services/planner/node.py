"""The planner on Zenoh: serves plan/ask, reads the scene, dry-runs through the executor, publishes attempts."""

from __future__ import annotations

import logging
import time
import uuid
from typing import Any

import msgspec

from schemas import keys
from schemas.common import Stage
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.planner import (
    MAX_RECORDED_CHARS,
    MAX_REQUEST_CHARS,
    AskReply,
    AskRequest,
    AskStatus,
    AttemptOutcome,
    PlannerAttempt,
)
from schemas.safety import SafetyStatus
from schemas.world import Empty
from services.actionlib import PREEMPT_TIMEOUT, ActionClient
from services.errors import CallError, GoalRejected
from services.planner.config import HOW_TO_CONFIGURE, Endpoint, PlannerConfig
from services.planner.errors import ExecutorUnreachable, LLMError
from services.planner.llm import ChatClient, ChatReply
from services.planner.loop import Attempt, DryRunVerdict, LoopStatus, plan_loop
from services.planner.prompt import initial_messages
from services.runtime import Node

log = logging.getLogger(__name__)

SCENE_TIMEOUT = 5.0
# How long the executor may take to accept a goal (longer when it preempts a running plan).
SEND_TIMEOUT = 5.0
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


def past_deadline(request: AskRequest) -> bool:
    return request.deadline > 0 and time.time() > request.deadline


def bounded(text: str, limit: int = MAX_RECORDED_CHARS) -> str:
    marker = " ...(cut)"
    return text if len(text) <= limit else text[: limit - len(marker)] + marker


def tool_schemas() -> list[dict[str, Any]]:
    """The action tools in OpenAI's shape (imported when first asked, not at start)."""
    from services.agent.tools import all_tools, render

    tools = all_tools()
    # The step tools and execute_plan; not plan_and_execute (this planner itself), reads or controls.
    actions = [t for t in tools if t.kind == "action" and t.name != "plan_and_execute"] or tools
    rendered: list[dict[str, Any]] = render(actions, "openai")
    return rendered


class Planner:
    """Words to a checked plan for one robot, on one node; used by the service and by `tether ask`."""

    def __init__(self, node: Node, config: PlannerConfig, endpoint: Endpoint | None, client: Any = None) -> None:
        self.node = node
        self.config = config
        self.endpoint = endpoint
        self._chat = client if client is not None else (ChatClient(endpoint) if endpoint is not None else None)
        self._executor: ActionClient[Any, Any, Any] = ActionClient(node, keys.EXECUTE_PLAN)
        self._attempts = node.publisher(keys.PLANNER_ATTEMPTS)
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

    def close(self) -> None:
        if isinstance(self._chat, ChatClient):
            self._chat.close()

    def scene_text(self) -> str:
        try:
            return self.node.call(keys.SCENE, Empty(), timeout=SCENE_TIMEOUT).text
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
        request_id = uuid.uuid4().hex[:16]
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
        max_attempts = request.max_attempts or self.config.max_attempts
        tools = tool_schemas()
        native = self.config.native_tools
        messages = initial_messages(request.text, tools, native, self.scene_text())
        model = self.endpoint.model if self.endpoint is not None else ""
        chat = self._chat

        def call_model(conversation: list[dict[str, Any]]) -> ChatReply:
            if past_deadline(request):
                raise LLMError(DEADLINE_PASSED)
            reply: ChatReply = chat.chat(conversation, tools if native else None)
            return reply

        def record(attempt: Attempt) -> None:
            log.info("request %s attempt %d: %s %s", request_id, attempt.number, attempt.status, attempt.reason)
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
                )
            )

        try:
            result = plan_loop(messages, call_model, self.check, max_attempts, record)
        except ExecutorUnreachable as exc:
            return AskReply(status=AskStatus.UNREACHABLE, request_id=request_id, reason=str(exc))
        reply = AskReply(
            status=LOOP_STATUS[result.status],
            request_id=request_id,
            attempts=len(result.attempts),
            stage=result.stage,
            reason=bounded(result.reason, 4000),
            plan=bounded(result.plan),
        )
        if result.status is not LoopStatus.APPROVED or request.dry_run:
            return reply
        if past_deadline(request):
            return msgspec.structs.replace(
                reply, status=AskStatus.REJECTED, stage=Stage.EXECUTE, reason=DEADLINE_PASSED
            )
        return self.send(reply, result.plan, request.preempt)

    def send(self, approved: AskReply, plan: str, preempt: bool) -> AskReply:
        """The approved plan for real: the goal id once the executor has accepted it."""
        try:
            handle = self._executor.send(
                ExecutePlanGoal(text=plan, preempt=preempt), timeout=SEND_TIMEOUT + PREEMPT_TIMEOUT
            )
        except GoalRejected as exc:
            return msgspec.structs.replace(
                approved, status=AskStatus.REJECTED, stage=Stage.EXECUTE, reason=bounded(exc.reason, 4000)
            )
        except CallError as exc:
            return msgspec.structs.replace(
                approved, status=AskStatus.UNREACHABLE, reason=bounded(f"executor unreachable: {exc}", 4000)
            )
        log.info("request %s: plan sent as goal %s", approved.request_id, handle.goal_id)
        return msgspec.structs.replace(
            approved, status=AskStatus.ACCEPTED, goal_id=handle.goal_id, reason="approved by a dry run and sent"
        )


def declare(node: Node, planner: Planner) -> None:
    node.serve(keys.PLAN_ASK, planner.ask)
