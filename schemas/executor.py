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


class FailureKind(enum.StrEnum):
    """Why a step failed, as pyrobosim names it: each asks for a different next move.

    precondition: the world is not as the step needs (the hand already full, the object not found);
    planning: no collision-free path for the base or the arm, no grasp that reaches;
    execution: a motion did not complete (blocked, timed out, ended by the robot);
    postcondition: the motions went through but perception shows otherwise (not in the hand after
    closing, not on the surface after placing); canceled; vetoed: safety refused a command or
    stopped the robot (e-stop).
    """

    PRECONDITION = "precondition"
    PLANNING = "planning"
    EXECUTION = "execution"
    POSTCONDITION = "postcondition"
    CANCELED = "canceled"
    VETOED = "vetoed"


class StepStatus(enum.StrEnum):
    PENDING = "pending"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"
    SKIPPED = "skipped"
    # The whole plan (step None, stage safety) waits for an operator's approval (supervised mode).
    AWAITING_APPROVAL = "awaiting_approval"


class ExecutePlanGoal(Frozen):
    """A plan to run. With `preempt`, a plan already running is canceled (and the robot brought to a
    stop) before this one starts; without it, this one is rejected while another runs, unless the
    executor is configured to preempt (`[executor] when_busy = "preempt"`)."""

    text: Annotated[str, Meta(max_length=MAX_PLAN_BYTES)]
    format: PlanFormat = "auto"
    dry_run: bool = False
    preempt: bool = False


# A place a search looked ("around in the kitchen", "on the kitchen table").
Place = Annotated[str, Meta(max_length=200)]
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
    failure: FailureKind | None = None
    attempt: int = 1
    # Where the step has looked for its object so far (see StepResult.searched).
    searched: list[Place] = []


class StepResult(Frozen):
    """One step's outcome. `index` as ExecutePlanFeedback.step; `label` names the step in the plan.
    A failed step says what kind of failure it was, and `attempts` how often it was tried (a retry
    follows a re-detection and a new plan, see the executor's README)."""

    index: int
    action: str
    status: StepStatus
    message: Text = ""
    label: Label | None = None
    failure: FailureKind | None = None
    attempts: int = 1
    # Where a detect or a pick looked for an object that was not in view, in order, in its last
    # attempt ("on the kitchen counter", "around in the kitchen", "on the kitchen table"); empty
    # when it saw the object at once.
    searched: list[Place] = []
    # Seconds (the executor's clock) the step spent searching, over all its attempts.
    search_s: Annotated[float, Meta(ge=0.0)] = 0.0


class ExecutePlanResult(Frozen):
    """`warnings` are the parser's and the resolver's: what they read differently from how it was
    written (a near-miss name, ignored parameters, coordinates overruled by a named entity); and
    safety's: earlier incidents near where the plan goes, caution zones it enters."""

    status: PlanStatus
    stage: Stage
    reason: Text = ""
    steps: list[StepResult] = []
    warnings: list[Text] = []
    # The kind of the failure that ended the plan, when a step's failure did.
    failure: FailureKind | None = None
