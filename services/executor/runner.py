"""Runs one execute_plan goal: parse, resolve, check the whole plan, then each step in order."""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import msgspec

from schemas.common import ServiceError, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepResult, StepStatus
from schemas.plan import (
    DetectStep,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    SayStep,
    StopStep,
    WaitStep,
    fallback_labels,
    step_kind,
    step_labels,
)
from schemas.robot import Twist
from services.executor.errors import Canceled, ExecutionError, Interrupted, Vetoed
from services.executor.manipulation import Manipulator
from services.executor.ports import Planner, Robot
from services.runtime import CallError

log = logging.getLogger(__name__)

FeedbackSink = Callable[[ExecutePlanFeedback], None]


@dataclass(frozen=True)
class _Failure:
    """Why the plan stopped or a step failed. `final` says why no on_failure may run, if so."""

    reason: str
    status: PlanStatus
    final: str | None = None


class PlanRunner:
    def __init__(self, planner: Planner, robot: Robot, manipulator: Manipulator) -> None:
        self.planner = planner
        self.robot = robot
        self.manipulator = manipulator

    def run(self, goal: ExecutePlanGoal, cancel: threading.Event, feedback: FeedbackSink) -> ExecutePlanResult:
        warnings: list[str] = []
        result = self._run(goal, cancel, feedback, warnings)
        return msgspec.structs.replace(result, warnings=warnings) if warnings else result

    def _run(
        self, goal: ExecutePlanGoal, cancel: threading.Event, feedback: FeedbackSink, warnings: list[str]
    ) -> ExecutePlanResult:
        grounded = self._prepare(goal, feedback, warnings)
        if isinstance(grounded, ExecutePlanResult):
            return grounded
        if goal.dry_run:
            return ExecutePlanResult(
                status=PlanStatus.SUCCEEDED,
                stage=Stage.SAFETY,
                reason="dry run: parsed, resolved and approved by safety; nothing moved",
                steps=dry_run_steps(grounded),
            )
        return self._execute(grounded, cancel, feedback)

    def _prepare(
        self, goal: ExecutePlanGoal, feedback: FeedbackSink, warnings: list[str]
    ) -> GroundedPlan | ExecutePlanResult:
        """Parse, resolve and check the whole plan before anything moves; `warnings` collects what
        the parser and the resolver said back."""
        try:
            feedback(ExecutePlanFeedback(stage=Stage.PARSE, message="parsing"))
            parsed = self.planner.parse(goal.text, goal.format)
            if isinstance(parsed, ServiceError):
                return rejected(Stage.PARSE, parsed)
            warnings.extend(parsed.warnings)
            feedback(ExecutePlanFeedback(stage=Stage.RESOLVE, message=f"resolving {len(parsed.steps)} steps"))
            grounded = self.planner.resolve(parsed)
            if isinstance(grounded, ServiceError):
                return rejected(Stage.RESOLVE, grounded, parsed)
            warnings.extend(grounded.warnings)
            feedback(ExecutePlanFeedback(stage=Stage.SAFETY, message="checking the whole plan with safety"))
            verdict = self.planner.check(grounded)
            if isinstance(verdict, ServiceError):
                return rejected(Stage.SAFETY, verdict, parsed)
        except CallError as exc:
            stage = exc.error.stage or Stage.PARSE
            return ExecutePlanResult(status=PlanStatus.REJECTED, stage=stage, reason=exc.error.message)
        return grounded

    def _execute(self, plan: GroundedPlan, cancel: threading.Event, feedback: FeedbackSink) -> ExecutePlanResult:
        labels = step_labels(plan)
        results: list[StepResult] = []
        reported: set[int] = set()  # steps of the plan itself (not alternatives) with a result
        recovered: list[str] = []
        i = 0
        while i < len(plan.steps):
            result, failure = self._run_one(i, plan.steps[i], labels[i], cancel, feedback)
            results.append(result)
            reported.add(i)
            if failure is None:
                i += 1
                continue
            outcome = self._recover(plan, i, failure, results, cancel, feedback)
            if isinstance(outcome, _Failure):
                return self._finish(plan, results, reported, outcome.status, outcome.reason)
            outcome = min(outcome, len(plan.steps))
            recovered.append(f"{failure.reason}; its on_failure ran instead")
            results.extend(
                StepResult(
                    index=j,
                    action=step_kind(plan.steps[j]),
                    status=StepStatus.SKIPPED,
                    message=f"not run: step {labels[i]} failed and an on_failure ran instead",
                    label=labels[j],
                )
                for j in range(i + 1, outcome)
            )
            reported.update(range(i + 1, outcome))
            i = outcome
        return ExecutePlanResult(
            status=PlanStatus.SUCCEEDED, stage=Stage.EXECUTE, reason="; ".join(recovered), steps=results
        )

    def _run_one(
        self, index: int, step: GroundedStep, label: str, cancel: threading.Event, feedback: FeedbackSink
    ) -> tuple[StepResult, _Failure | None]:
        """Run one step and report it; the failure, if any, says whether an on_failure may follow."""
        action = step_kind(step)

        def report(status: StepStatus, message: str) -> None:
            feedback(
                ExecutePlanFeedback(
                    stage=Stage.EXECUTE, step=index, action=action, status=status, message=message, label=label
                )
            )

        report(StepStatus.RUNNING, describe(step))
        try:
            if cancel.is_set():
                raise Canceled("canceled before the step started")
            message = self._run_step(step, cancel)
        except Canceled as exc:
            result = StepResult(index=index, action=action, status=StepStatus.CANCELED, message=str(exc), label=label)
            return result, _Failure(f"step {label} ({action}) canceled", PlanStatus.CANCELED, final="canceled")
        except (ExecutionError, CallError) as exc:
            report(StepStatus.FAILED, str(exc))
            result = StepResult(index=index, action=action, status=StepStatus.FAILED, message=str(exc), label=label)
            return result, _Failure(f"step {label} ({action}) failed: {exc}", PlanStatus.FAILED, self._final(exc))
        report(StepStatus.SUCCEEDED, message)
        return StepResult(index=index, action=action, status=StepStatus.SUCCEEDED, message=message, label=label), None

    def _final(self, exc: Exception) -> str | None:
        """Why no on_failure may run after `exc`, or None when one may."""
        if isinstance(exc, Vetoed):
            return "safety refused the motion"
        if isinstance(exc, Interrupted):
            return "the robot side ended the motion"
        return self.robot.safety_stop()

    def _recover(
        self,
        plan: GroundedPlan,
        failed: int,
        failure: _Failure,
        results: list[StepResult],
        cancel: threading.Event,
        feedback: FeedbackSink,
    ) -> int | _Failure:
        """Run the on_failure alternatives covering step `failed`, innermost first, each one taking
        over when the one inside it fails too. The index to go on from, or the plan's failure."""
        covering = [f for f in plan.fallbacks if f.first <= failed <= f.last]
        if not covering:
            return failure
        if failure.final is not None:
            if failure.status is PlanStatus.CANCELED:
                return failure
            return _Failure(f"{failure.reason}; no on_failure runs: {failure.final}", failure.status, failure.final)
        reasons = [failure.reason]
        labels = step_labels(plan)
        for fallback in sorted(covering, key=lambda f: (f.last - f.first, -f.first)):
            alternative_labels = fallback_labels(fallback, labels)
            for k, step in enumerate(fallback.steps):
                result, alt_failure = self._run_one(k, step, alternative_labels[k], cancel, feedback)
                results.append(result)
                if alt_failure is not None:
                    break
            else:
                return fallback.last + 1
            results.extend(
                StepResult(index=j, action=step_kind(s), status=StepStatus.SKIPPED, label=alternative_labels[j])
                for j, s in enumerate(fallback.steps)
                if j > k
            )
            reasons.append(f"then {alt_failure.reason}")
            if alt_failure.final is not None:
                return _Failure("; ".join(reasons), alt_failure.status, alt_failure.final)
        return _Failure("; ".join(reasons), PlanStatus.FAILED)

    def _finish(
        self, plan: GroundedPlan, results: list[StepResult], reported: set[int], status: PlanStatus, reason: str
    ) -> ExecutePlanResult:
        labels = step_labels(plan)
        skipped = [
            StepResult(index=i, action=step_kind(s), status=StepStatus.SKIPPED, label=labels[i])
            for i, s in enumerate(plan.steps)
            if i not in reported
        ]
        return ExecutePlanResult(status=status, stage=Stage.EXECUTE, reason=reason, steps=results + skipped)

    def _run_step(self, step: GroundedStep, cancel: threading.Event) -> str:
        m = self.manipulator
        if isinstance(step, NavigateStep):
            m.drive_to(step.goal, cancel, step.max_speed)
            return f"reached {step.target}"
        if isinstance(step, GripperStep):
            return m.operate_gripper(step.open, cancel)
        if isinstance(step, PickStep):
            m.pick(step, cancel)
            return f"holding {step.object_name}"
        if isinstance(step, PlaceStep):
            placed = m.place(step, cancel)
            return f"placed {placed} on {step.surface_name}"
        if isinstance(step, DetectStep):
            position = self.robot.object_position(step.object_id)
            if position is None:
                raise ExecutionError(f"{step.object_name} is not in the current perception")
            return f"{step.object_name} seen at ({position.x:.2f}, {position.y:.2f}, {position.z:.2f})"
        if isinstance(step, SayStep):
            # This robot has no speaker; the text is carried in feedback and the recording.
            log.info("say: %s", step.text)
            return f"said: {step.text}"
        if isinstance(step, WaitStep):
            if cancel.wait(step.duration):
                raise Canceled("canceled while waiting")
            return f"waited {step.duration:g} s"
        if isinstance(step, StopStep):
            self.robot.cmd_vel(Twist())
            return "base stopped"
        raise ExecutionError(f"no way to execute {step_kind(step)}")


def rejected(stage: Stage, error: ServiceError, plan: Plan | None = None) -> ExecutePlanResult:
    steps = []
    if plan is not None:
        for i, step in enumerate(plan.steps):
            failed = error.step == i
            steps.append(
                StepResult(
                    index=i,
                    action=str(step.action) if step.action is not None else "group",
                    status=StepStatus.FAILED if failed else StepStatus.SKIPPED,
                    message=error.message if failed else "",
                    label=str(i + 1),
                )
            )
    reason = error.message
    if error.candidates and "candidates" not in reason:
        reason = f"{reason} (candidates: {', '.join(error.candidates)})"
    return ExecutePlanResult(status=PlanStatus.REJECTED, stage=stage, reason=reason, steps=steps)


def dry_run_steps(plan: GroundedPlan) -> list[StepResult]:
    """Every step, each plan step followed by the alternatives that end with it (innermost first)."""
    labels = step_labels(plan)
    steps: list[StepResult] = []
    for i, step in enumerate(plan.steps):
        steps.append(StepResult(index=i, action=step_kind(step), status=StepStatus.SKIPPED, label=labels[i]))
        for fallback in sorted((f for f in plan.fallbacks if f.last == i), key=lambda f: -f.first):
            steps.extend(
                StepResult(index=k, action=step_kind(s), status=StepStatus.SKIPPED, label=label)
                for k, (s, label) in enumerate(zip(fallback.steps, fallback_labels(fallback, labels), strict=True))
            )
    return steps


def describe(step: GroundedStep) -> str:
    if isinstance(step, NavigateStep):
        goal = step.goal
        return f"moving the base: {step.target} -> ({goal.x:.2f}, {goal.y:.2f}, {math.degrees(goal.yaw):.0f}°)"
    if isinstance(step, GripperStep):
        return "opening the gripper" if step.open else "closing the gripper"
    if isinstance(step, PickStep):
        return f"picking {step.object_name}"
    if isinstance(step, PlaceStep):
        return f"placing on {step.surface_name}"
    if isinstance(step, DetectStep):
        return f"looking for {step.object_name}"
    if isinstance(step, SayStep):
        return f"saying: {step.text}"
    if isinstance(step, WaitStep):
        return f"waiting {step.duration:g} s"
    return step_kind(step)
