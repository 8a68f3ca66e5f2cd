"""Runs one execute_plan goal: parse, resolve, check the whole plan, then each step in order."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from schemas.common import ServiceError, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepResult, StepStatus
from schemas.plan import (
    DetectStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    SayStep,
    StopStep,
    WaitStep,
    step_kind,
)
from schemas.robot import Twist
from services.executor.errors import Canceled, ExecutionError
from services.executor.manipulation import Manipulator
from services.executor.ports import Planner, Robot
from services.runtime import CallError

log = logging.getLogger(__name__)

FeedbackSink = Callable[[ExecutePlanFeedback], None]


class PlanRunner:
    def __init__(self, planner: Planner, robot: Robot, manipulator: Manipulator) -> None:
        self.planner = planner
        self.robot = robot
        self.manipulator = manipulator

    def run(self, goal: ExecutePlanGoal, cancel: threading.Event, feedback: FeedbackSink) -> ExecutePlanResult:
        grounded = self._prepare(goal, feedback)
        if isinstance(grounded, ExecutePlanResult):
            return grounded
        if goal.dry_run:
            return ExecutePlanResult(
                status=PlanStatus.SUCCEEDED,
                stage=Stage.SAFETY,
                reason="dry run: parsed, resolved and approved by safety; nothing moved",
                steps=[
                    StepResult(index=i, action=step_kind(s), status=StepStatus.SKIPPED)
                    for i, s in enumerate(grounded.steps)
                ],
            )
        return self._execute(grounded, cancel, feedback)

    def _prepare(self, goal: ExecutePlanGoal, feedback: FeedbackSink) -> GroundedPlan | ExecutePlanResult:
        """Parse, resolve and check the whole plan before anything moves."""
        try:
            feedback(ExecutePlanFeedback(stage=Stage.PARSE, message="parsing"))
            parsed = self.planner.parse(goal.text, goal.format)
            if isinstance(parsed, ServiceError):
                return rejected(Stage.PARSE, parsed)
            feedback(ExecutePlanFeedback(stage=Stage.RESOLVE, message=f"resolving {len(parsed.steps)} steps"))
            grounded = self.planner.resolve(parsed)
            if isinstance(grounded, ServiceError):
                return rejected(Stage.RESOLVE, grounded, parsed)
            feedback(ExecutePlanFeedback(stage=Stage.SAFETY, message="checking the whole plan with safety"))
            verdict = self.planner.check(grounded)
            if isinstance(verdict, ServiceError):
                return rejected(Stage.SAFETY, verdict, parsed)
        except CallError as exc:
            stage = exc.error.stage or Stage.PARSE
            return ExecutePlanResult(status=PlanStatus.REJECTED, stage=stage, reason=exc.error.message)
        return grounded

    def _execute(self, plan: GroundedPlan, cancel: threading.Event, feedback: FeedbackSink) -> ExecutePlanResult:
        results: list[StepResult] = []
        for i, step in enumerate(plan.steps):
            action = step_kind(step)
            feedback(ExecutePlanFeedback(stage=Stage.EXECUTE, step=i, action=action, message=describe(step)))
            try:
                if cancel.is_set():
                    raise Canceled("canceled before the step started")
                message = self._run_step(step, cancel)
            except Canceled as exc:
                results.append(StepResult(index=i, action=action, status=StepStatus.CANCELED, message=str(exc)))
                return self._finish(plan, results, PlanStatus.CANCELED, f"step {i + 1} ({action}) canceled")
            except (ExecutionError, CallError) as exc:
                results.append(StepResult(index=i, action=action, status=StepStatus.FAILED, message=str(exc)))
                feedback(
                    ExecutePlanFeedback(
                        stage=Stage.EXECUTE, step=i, action=action, status=StepStatus.FAILED, message=str(exc)
                    )
                )
                return self._finish(plan, results, PlanStatus.FAILED, f"step {i + 1} ({action}) failed: {exc}")
            results.append(StepResult(index=i, action=action, status=StepStatus.SUCCEEDED, message=message))
            feedback(
                ExecutePlanFeedback(
                    stage=Stage.EXECUTE, step=i, action=action, status=StepStatus.SUCCEEDED, message=message
                )
            )
        return ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.EXECUTE, reason="", steps=results)

    def _finish(
        self, plan: GroundedPlan, results: list[StepResult], status: PlanStatus, reason: str
    ) -> ExecutePlanResult:
        skipped = [
            StepResult(index=i, action=step_kind(s), status=StepStatus.SKIPPED)
            for i, s in enumerate(plan.steps)
            if i >= len(results)
        ]
        return ExecutePlanResult(status=status, stage=Stage.EXECUTE, reason=reason, steps=results + skipped)

    def _run_step(self, step: GroundedStep, cancel: threading.Event) -> str:
        m = self.manipulator
        if isinstance(step, NavigateStep):
            m.drive_to(step.goal, cancel)
            return f"arrived at {step.target}"
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
                    action=str(step.action),
                    status=StepStatus.FAILED if failed else StepStatus.SKIPPED,
                    message=error.message if failed else "",
                )
            )
    reason = error.message
    if error.candidates and "candidates" not in reason:
        reason = f"{reason} (candidates: {', '.join(error.candidates)})"
    return ExecutePlanResult(status=PlanStatus.REJECTED, stage=stage, reason=reason, steps=steps)


def describe(step: GroundedStep) -> str:
    if isinstance(step, NavigateStep):
        return f"navigating to {step.target} ({step.goal.x:.2f}, {step.goal.y:.2f})"
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
