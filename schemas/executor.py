"""The execute_plan action: raw plan text in, progress per step out, a result per step."""

from __future__ import annotations

import enum
from typing import Annotated

from msgspec import Meta

from schemas.common import Frozen, Stage, Text
from schemas.plan import MAX_PLAN_BYTES, PlanFormat


class PlanStatus(enum.StrEnum):
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    REJECTED = "rejected"
    CANCELED = "canceled"


class StepStatus(enum.StrEnum):
    PENDING = "pending"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"
    SKIPPED = "skipped"


class ExecutePlanGoal(Frozen):
    text: Annotated[str, Meta(max_length=MAX_PLAN_BYTES)]
    format: PlanFormat = "auto"
    dry_run: bool = False


class ExecutePlanFeedback(Frozen):
    stage: Stage
    step: int | None = None
    action: str = ""
    status: StepStatus = StepStatus.RUNNING
    message: Text = ""


class StepResult(Frozen):
    index: int
    action: str
    status: StepStatus
    message: Text = ""


class ExecutePlanResult(Frozen):
    status: PlanStatus
    stage: Stage
    reason: Text = ""
    steps: list[StepResult] = []
