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


# Where a step came from in the parsed plan: "2", "3.1" (first sub-step of step 3), "2 on_failure 1".
Label = Annotated[str, Meta(max_length=64)]


class ExecutePlanFeedback(Frozen):
    """Progress. `step` indexes GroundedPlan.steps, or for an on_failure step its fallback's steps;
    `label` says which."""

    stage: Stage
    step: int | None = None
    action: str = ""
    status: StepStatus = StepStatus.RUNNING
    message: Text = ""
    label: Label | None = None


class StepResult(Frozen):
    """One step's outcome. `index` as ExecutePlanFeedback.step; `label` names the step in the plan."""

    index: int
    action: str
    status: StepStatus
    message: Text = ""
    label: Label | None = None


class ExecutePlanResult(Frozen):
    """`warnings` are the parser's and the resolver's: what they read differently from how it was
    written (a near-miss name, ignored parameters, coordinates overruled by a named entity)."""

    status: PlanStatus
    stage: Stage
    reason: Text = ""
    steps: list[StepResult] = []
    warnings: list[Text] = []
