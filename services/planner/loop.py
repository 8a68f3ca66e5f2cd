"""Ask the model, dry-run its plan, feed a refusal back, up to N attempts. Pure: chat and check are callables."""

from __future__ import annotations

import enum
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from schemas.common import Stage
from schemas.plan import MAX_PLAN_BYTES
from services.planner.errors import LLMError
from services.planner.llm import ChatReply
from services.planner.prompt import feedback_messages, normalize_calls, plan_text


@dataclass(frozen=True)
class DryRunVerdict:
    """A dry run's answer: approved, or refused at a stage with a reason."""

    approved: bool
    stage: Stage | None = None
    reason: str = ""


class LoopStatus(enum.StrEnum):
    APPROVED = "approved"
    REJECTED = "rejected"
    LLM_ERROR = "llm_error"


@dataclass(frozen=True)
class Attempt:
    """One model call and its verdict. `status` is LLM_ERROR when the call itself failed."""

    number: int
    status: LoopStatus
    reply: str = ""
    plan: str = ""
    stage: Stage | None = None
    reason: str = ""
    duration: float = 0.0


@dataclass(frozen=True)
class LoopResult:
    status: LoopStatus
    attempts: list[Attempt] = field(default_factory=list)
    plan: str = ""
    stage: Stage | None = None
    reason: str = ""


Chat = Callable[[list[dict[str, Any]]], ChatReply]
Check = Callable[[str], DryRunVerdict]
Record = Callable[[Attempt], None]

NO_PLAN = "the answer held no plan (no text and no tool calls)"


def reply_text(reply: ChatReply) -> str:
    """What the model said, for the record: its text, then its tool calls as JSON."""
    if not reply.tool_calls:
        return reply.content
    calls = plan_text("", reply.tool_calls)
    return f"{reply.content}\n{calls}" if reply.content else calls


def plan_loop(
    messages: list[dict[str, Any]],
    chat: Chat,
    check: Check,
    max_attempts: int,
    record: Record = lambda _: None,
    clock: Callable[[], float] = time.monotonic,
) -> LoopResult:
    """Up to `max_attempts` model calls. Each answer becomes plan text and is checked; a refusal goes
    back to the model with its stage and reason. Stops at the first approved plan, at an LLMError
    from `chat` (a broken endpoint does not get better by asking again), or after the last attempt.
    `check` may raise (executor unreachable): that ends the loop and is the caller's to handle."""
    if max_attempts < 1:
        raise ValueError(f"max_attempts must be at least 1, not {max_attempts}")
    conversation = list(messages)
    attempts: list[Attempt] = []
    last: Attempt | None = None
    for number in range(1, max_attempts + 1):
        started = clock()
        try:
            reply = chat(conversation)
        except LLMError as exc:
            attempt = Attempt(number, LoopStatus.LLM_ERROR, reason=str(exc), duration=clock() - started)
            attempts.append(attempt)
            record(attempt)
            return LoopResult(LoopStatus.LLM_ERROR, attempts, reason=str(exc))
        calls = normalize_calls(reply.tool_calls)
        reply = ChatReply(reply.content, calls)
        text = plan_text(reply.content, calls)
        if not text:
            verdict = DryRunVerdict(False, Stage.PARSE, NO_PLAN)
        elif len(text.encode()) > MAX_PLAN_BYTES:
            size = len(text.encode())
            verdict = DryRunVerdict(False, Stage.PARSE, f"the plan is {size} bytes; the limit is {MAX_PLAN_BYTES}")
        else:
            verdict = check(text)
        status = LoopStatus.APPROVED if verdict.approved else LoopStatus.REJECTED
        last = Attempt(
            number, status, reply_text(reply), text, verdict.stage, verdict.reason, duration=clock() - started
        )
        attempts.append(last)
        record(last)
        if verdict.approved:
            return LoopResult(LoopStatus.APPROVED, attempts, plan=text, stage=verdict.stage, reason=verdict.reason)
        conversation.extend(feedback_messages(reply.message(), verdict.stage, verdict.reason))
    assert last is not None, "max_attempts is at least 1"
    reason = f"no plan passed after {max_attempts} attempt{'s' if max_attempts != 1 else ''}; the last: {last.reason}"
    return LoopResult(LoopStatus.REJECTED, attempts, plan=last.plan, stage=last.stage, reason=reason)
