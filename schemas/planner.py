"""The natural-language planner: a request in words, its outcome, and each attempt the model made."""

from __future__ import annotations

import enum
from typing import Annotated

from msgspec import Meta

from schemas.common import Frozen, Stage, Text

# What a person asks for, in words ("bring me the red cup").
MAX_REQUEST_CHARS = 2000
# The most attempts a request may ask for; each is one model call and one dry run.
MAX_ATTEMPTS = 10
# A model's reply and the plan text are kept up to this many characters in attempt records.
MAX_RECORDED_CHARS = 8000
# The most recovery plans one request may ask the model for after its plan failed at execution.
MAX_RECOVERIES = 5

RecordedText = Annotated[str, Meta(max_length=MAX_RECORDED_CHARS)]
RequestId = Annotated[str, Meta(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:-]+(?!\n)$")]
# An id a caller chooses for its request (a uuid's hex, say), to cancel it by: empty, the planner picks
# one. (?!\n): Python's `$` also matches before a last newline, which would let "id\n" through.
CallerRequestId = Annotated[str, Meta(max_length=64, pattern=r"^[A-Za-z0-9_-]*(?!\n)$")]


class AskStatus(enum.StrEnum):
    """approved: a dry run passed (nothing sent); accepted: the approved plan was sent and the executor
    took it; rejected: every attempt was refused, or the executor refused the approved plan;
    llm_error: the model's endpoint failed or misbehaved; unconfigured: no endpoint is configured;
    unreachable: no executor answered."""

    APPROVED = "approved"
    ACCEPTED = "accepted"
    REJECTED = "rejected"
    LLM_ERROR = "llm_error"
    UNCONFIGURED = "unconfigured"
    UNREACHABLE = "unreachable"
    # Only when the request waited for the plan's end (`wait`): the plan, or a recovery plan, succeeded;
    # or it failed and no recovery (or none allowed) made it succeed.
    SUCCEEDED = "succeeded"
    FAILED = "failed"


class AttemptOutcome(enum.StrEnum):
    APPROVED = "approved"
    REJECTED = "rejected"
    LLM_ERROR = "llm_error"


class AskRequest(Frozen):
    """A request in words. `max_attempts` 0 means the planner's configured number. `deadline` (wall
    clock, seconds; 0 for none) is when the caller stops waiting: no model call starts and no plan is
    sent after it, so a caller that gave up never has a plan started behind its back."""

    text: Annotated[str, Meta(min_length=1, max_length=MAX_REQUEST_CHARS)]
    dry_run: bool = False
    max_attempts: Annotated[int, Meta(ge=0, le=MAX_ATTEMPTS)] = 0
    preempt: bool = False
    deadline: Annotated[float, Meta(ge=0.0)] = 0.0
    # A plan given as is (`tether send --recover`): dry-run and sent without asking the model; the
    # model is asked only for recoveries. `text` then says what the plan is for.
    plan: RecordedText = ""
    # Recovery plans the model may be asked for when the sent plan fails at execution (None: the
    # planner's `max_recoveries`; 0: none). Each is dry-run and checked like any plan.
    max_recoveries: Annotated[int, Meta(ge=0, le=MAX_RECOVERIES)] | None = None
    # Answer only once the plan (and any recovery) has ended, with SUCCEEDED or FAILED.
    wait: bool = False
    # The caller's name for the request (plan/ask_cancel stops it by this; refused while one with the
    # same id is in flight or ended lately); empty: the planner picks one.
    request_id: CallerRequestId = ""


class AskCancel(Frozen):
    """Stop the request the caller started with this `request_id`: no plan, nor recovery, is sent for
    it after this, and the goal it sent last is canceled."""

    request_id: Annotated[CallerRequestId, Meta(min_length=1)]


class AskCancelReply(Frozen):
    """What a cancel found. `known`: the planner had the request (in flight, or ended lately);
    `running`: it was still in flight (now canceled); `goal_id`: its last goal, which the planner asked
    the executor to cancel (a caller follows it to its end); empty when it sent none."""

    request_id: RequestId
    known: bool
    running: bool = False
    goal_id: Annotated[str, Meta(max_length=64)] = ""
    reason: Text = ""


class RecoveryOutcome(enum.StrEnum):
    """sent: the recovery plan passed its dry run and was sent; succeeded, failed: how it ended (when
    followed); rejected: no plan the model gave passed; llm_error; stopped: not attempted, because the
    failure was an e-stop or a veto (not something to work around), or the bound was reached."""

    SENT = "sent"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    REJECTED = "rejected"
    LLM_ERROR = "llm_error"
    STOPPED = "stopped"


class Recovery(Frozen):
    """One recovery: the failure that asked for it and what became of it. Published on
    planner/recoveries for the recorder and listed in AskReply.recoveries. `number` counts from 1
    within the request; `failed_goal` is the goal that failed, `goal_id` the recovery plan's goal."""

    request_id: RequestId
    number: Annotated[int, Meta(ge=1, le=MAX_RECOVERIES + 1)]
    stamp: float
    outcome: RecoveryOutcome
    failed_goal: Annotated[str, Meta(max_length=64)] = ""
    failure: Annotated[str, Meta(max_length=32)] = ""
    step: Annotated[int, Meta(ge=0)] | None = None
    failure_reason: Text = ""
    reason: Text = ""
    attempts: Annotated[int, Meta(ge=0, le=MAX_ATTEMPTS)] = 0
    plan: RecordedText = ""
    goal_id: Annotated[str, Meta(max_length=64)] = ""


class AskReply(Frozen):
    """The outcome. `plan` is the last plan text the model gave (the approved one when approved);
    `stage` and `reason` say why it was refused; `goal_id` names the goal sent, when one was."""

    status: AskStatus
    request_id: RequestId
    attempts: Annotated[int, Meta(ge=0, le=MAX_ATTEMPTS)] = 0
    stage: Stage | None = None
    reason: Text = ""
    plan: RecordedText = ""
    goal_id: Annotated[str, Meta(max_length=64)] = ""
    # The recoveries asked for after the plan failed at execution, in order (when the request waited,
    # or as far as they got before the reply).
    recoveries: Annotated[list[Recovery], Meta(max_length=MAX_RECOVERIES + 1)] = []


class PlannerAttempt(Frozen):
    """One model call and the dry run of its plan, published on planner/attempts for the recorder.
    `reply` is what the model answered (text and tool calls, cut to a bound), `plan` the plan text
    derived from it."""

    request_id: RequestId
    attempt: Annotated[int, Meta(ge=1, le=MAX_ATTEMPTS)]
    max_attempts: Annotated[int, Meta(ge=1, le=MAX_ATTEMPTS)]
    stamp: float
    outcome: AttemptOutcome
    stage: Stage | None = None
    reason: Text = ""
    request: Annotated[str, Meta(max_length=MAX_REQUEST_CHARS)] = ""
    model: Annotated[str, Meta(max_length=200)] = ""
    reply: RecordedText = ""
    plan: RecordedText = ""
    duration: Annotated[float, Meta(ge=0.0)] = 0.0
    # 0: an attempt at the request's plan; N: an attempt at the Nth recovery plan.
    recovery: Annotated[int, Meta(ge=0, le=MAX_RECOVERIES + 1)] = 0
