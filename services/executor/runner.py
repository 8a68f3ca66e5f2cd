"""Runs one execute_plan goal: parse, resolve, check the whole plan, then each step in order, each
within its time, retried after a failure a retry can mend."""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Protocol

import msgspec

from schemas.common import TEXT_CHARS, ServiceError, Stage
from schemas.executor import (
    ExecutePlanFeedback,
    ExecutePlanGoal,
    ExecutePlanResult,
    FailureKind,
    PlanStatus,
    StepResult,
    StepStatus,
)
from schemas.incidents import IncidentKind
from schemas.plan import (
    GroundedPlan,
    GroundedStep,
    Plan,
    fallback_labels,
    step_kind,
    step_labels,
)
from services.errors import CallError
from services.executor.config import ExecutorConfig
from services.executor.errors import (
    Canceled,
    CommandVetoed,
    ExecutionError,
    GraspFailed,
    Interrupted,
    MotionNotStopped,
)
from services.executor.manipulation import Manipulator, Note
from services.executor.ports import PlanServices, Robot

log = logging.getLogger(__name__)

FeedbackSink = Callable[[ExecutePlanFeedback], None]
# Reports an incident only the executor sees: kind, reason, objects involved, step index and label.
IncidentSink = Callable[[IncidentKind, str, list[str], int, str], None]
# Asks safety whether a checked plan may move the robot now, waiting for an operator in supervised
# mode: None to go on, or the result that ends the plan (denied, canceled while it waited).
Approval = Callable[[GroundedPlan, threading.Event, FeedbackSink], ExecutePlanResult | None]


class Held(enum.Enum):
    """What a step's failure was, asked of safety's approval (supervised mode): not an operator's
    pause (the failure stands), or a pause the operator has since resumed (run the step again)."""

    NOT_PAUSED = "not_paused"
    RESUMED = "resumed"


class PauseWatch(Protocol):
    """Whether an operator paused the plan (supervised mode; the node's Supervision asks safety)."""

    def attempting(self) -> None:
        """A step's attempt starts: a pause resumed before now explains no failure of this attempt."""

    def hold(self, cancel: threading.Event, feedback: FeedbackSink) -> Held | ExecutePlanResult:
        """Asked after an attempt failed: did an operator pause the plan since the attempt began? If so
        the pause is reported (feedback `awaiting_approval`) and waited out: RESUMED; or the result that
        ends the plan when the operator denies it meanwhile or it is canceled. NOT_PAUSED: the failure
        stands."""


# What a retry, after re-detecting and planning anew, can mend.
RETRYABLE = (FailureKind.PLANNING, FailureKind.EXECUTION, FailureKind.POSTCONDITION)
# How often a step's clock looks at the speed scale and the goal's cancel.
CLOCK_PERIOD = 0.05
# A message or reason is schemas.common.Text: its receivers refuse a longer one, so a reason gathered
# over attempts and alternatives (each with the robot's or a planner's words) is cut to fit.
CUT = " [...]"


def clip(text: str) -> str:
    return text if len(text) <= TEXT_CHARS else text[: TEXT_CHARS - len(CUT)] + CUT


@dataclass(frozen=True)
class _Failure:
    """Why the plan stopped or a step failed. `final` says why no on_failure may run, if so."""

    reason: str
    status: PlanStatus
    final: str | None = None
    kind: FailureKind | None = None


class StepTimedOut(ExecutionError):
    """The step used up its time (motion time: pauses for people do not count)."""


class StepCancel(threading.Event):
    """The cancel a step's motions obey. The step's clock sets it on its rounds (every CLOCK_PERIOD);
    a look (`is_set`) also sees the goal's own cancel at once, so a motion about to be sent after the
    goal was canceled is not sent (ActionClient.run looks first), even before the clock's next round.
    A `wait` wakes on that round."""

    def __init__(self, goal_cancel: threading.Event) -> None:
        super().__init__()
        self.goal_cancel = goal_cancel

    def is_set(self) -> bool:
        return super().is_set() or self.goal_cancel.is_set()


class StepClock:
    """A step's time, counted in motion time, and the cancel its motions obey.

    `cancel` is set when the goal is canceled (for a look at once, see StepCancel) or when `timeout`
    seconds of motion have passed: each period adds its wall time times the speed scale safety allows
    (0 while paused for a person).
    """

    def __init__(self, timeout: float, goal_cancel: threading.Event, speed_scale: Callable[[], float]) -> None:
        self.timeout = timeout
        self.goal_cancel = goal_cancel
        self.speed_scale = speed_scale
        self.cancel = StepCancel(goal_cancel)
        self.elapsed = 0.0
        self.expired = False
        self._done = threading.Event()

    def _watch(self) -> None:
        last = time.monotonic()
        while not self._done.wait(CLOCK_PERIOD):
            now = time.monotonic()
            self.elapsed += (now - last) * min(1.0, max(0.0, self.speed_scale()))
            last = now
            if self.goal_cancel.is_set():
                self.cancel.set()
            elif self.elapsed > self.timeout and not self.expired:
                self.expired = True
                self.cancel.set()

    @contextmanager
    def running(self) -> Iterator[threading.Event]:
        if self.goal_cancel.is_set():
            self.cancel.set()
        watcher = threading.Thread(target=self._watch, name="step-clock", daemon=True)
        watcher.start()
        try:
            yield self.cancel
        finally:
            self._done.set()
            watcher.join()


class PlanRunner:
    def __init__(
        self,
        planner: PlanServices,
        robot: Robot,
        manipulator: Manipulator,
        config: ExecutorConfig,
        incidents: IncidentSink | None = None,
    ) -> None:
        self.planner = planner
        self.robot = robot
        self.manipulator = manipulator
        self.config = config
        # Where a grasp that closed on nothing is reported (safety's incident memory), with the step.
        self.incidents = incidents

    def run(
        self,
        goal: ExecutePlanGoal,
        cancel: threading.Event,
        feedback: FeedbackSink,
        approval: Approval | None = None,
        pauses: PauseWatch | None = None,
    ) -> ExecutePlanResult:
        """Run `goal`; `approval`, when given, is asked after the plan check and before the first
        motion; `pauses` whether a step's attempt that failed was paused by an operator (no failure)."""
        warnings: list[str] = []
        result = self._run(goal, cancel, feedback, warnings, approval, pauses)
        result = msgspec.structs.replace(result, reason=clip(result.reason))
        return msgspec.structs.replace(result, warnings=warnings) if warnings else result

    def _run(
        self,
        goal: ExecutePlanGoal,
        cancel: threading.Event,
        feedback: FeedbackSink,
        warnings: list[str],
        approval: Approval | None = None,
        pauses: PauseWatch | None = None,
    ) -> ExecutePlanResult:
        grounded = self._prepare(goal, feedback, warnings)
        if isinstance(grounded, ExecutePlanResult):
            return grounded
        if goal.dry_run:
            if cancel.is_set():  # canceled while it was checked: the check was not seen through
                reason = "dry run canceled while the plan was being checked; nothing moved"
                return ExecutePlanResult(status=PlanStatus.CANCELED, stage=Stage.SAFETY, reason=reason)
            return ExecutePlanResult(
                status=PlanStatus.SUCCEEDED,
                stage=Stage.SAFETY,
                reason="dry run: parsed, resolved and approved by safety; nothing moved",
                steps=dry_run_steps(grounded),
            )
        if approval is not None and (ended := approval(grounded, cancel, feedback)) is not None:
            return ended
        return self._execute(grounded, cancel, feedback, pauses)

    def _prepare(
        self, goal: ExecutePlanGoal, feedback: FeedbackSink, warnings: list[str]
    ) -> GroundedPlan | ExecutePlanResult:
        """Parse, resolve and check the whole plan before anything moves; `warnings` collects what
        the parser, the resolver and safety said back."""
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
            # What safety remembers of the places the plan goes (earlier incidents, caution zones).
            warnings.extend(verdict.warnings)
        except CallError as exc:
            stage = exc.error.stage or Stage.PARSE
            return ExecutePlanResult(status=PlanStatus.REJECTED, stage=stage, reason=exc.error.message)
        return grounded

    def _execute(
        self, plan: GroundedPlan, cancel: threading.Event, feedback: FeedbackSink, pauses: PauseWatch | None = None
    ) -> ExecutePlanResult:
        labels = step_labels(plan)
        results: list[StepResult] = []
        reported: set[int] = set()  # steps of the plan itself (not alternatives) with a result
        recovered: list[str] = []
        i = 0
        while i < len(plan.steps):
            result, failure = self._run_one(i, plan.steps[i], labels[i], cancel, feedback, pauses)
            results.append(result)
            reported.add(i)
            if failure is None:
                i += 1
                continue
            outcome = self._on_failure(plan, i, failure, results, cancel, feedback, pauses)
            if isinstance(outcome, _Failure):
                return self._finish(plan, results, reported, outcome)
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
        self,
        index: int,
        step: GroundedStep,
        label: str,
        cancel: threading.Event,
        feedback: FeedbackSink,
        pauses: PauseWatch | None = None,
    ) -> tuple[StepResult, _Failure | None]:
        """Run one step, retrying as configured, and report it; the failure, if any, says whether
        an on_failure may follow. An attempt that failed because an operator paused the plan
        (`pauses`) is no failure: once resumed the step runs again from where the robot is then,
        not counted as an attempt."""
        action = step_kind(step)
        timeout = self.config.timeouts.of(step)
        tries = 1 + self.config.retries.of(step)

        searched: list[str] = []  # where the attempt under way has looked for its object
        searching_before = self.manipulator.search_time

        def report(status: StepStatus, message: str, attempt: int, kind: FailureKind | None = None) -> None:
            feedback(
                ExecutePlanFeedback(
                    stage=Stage.EXECUTE,
                    step=index,
                    action=action,
                    status=status,
                    message=clip(message),
                    label=label,
                    failure=kind,
                    attempt=attempt,
                    searched=list(searched),
                )
            )

        def result(status: StepStatus, message: str, attempt: int, kind: FailureKind | None = None) -> StepResult:
            return StepResult(
                index=index,
                action=action,
                status=status,
                message=clip(message),
                label=label,
                failure=kind,
                attempts=attempt,
                searched=list(searched),
                search_s=round(self.manipulator.search_time - searching_before, 3),
            )

        report(StepStatus.RUNNING, step.describe(), 1)
        attempt = 1

        def note(message: str) -> None:
            report(StepStatus.RUNNING, message, attempt)

        def paused(fb: ExecutePlanFeedback) -> None:
            report(fb.status, fb.message, attempt)

        def canceled(message: str) -> tuple[StepResult, _Failure]:
            failure = _Failure(
                f"step {label} ({action}) canceled", PlanStatus.CANCELED, "canceled", FailureKind.CANCELED
            )
            return result(StepStatus.CANCELED, message, attempt, FailureKind.CANCELED), failure

        earlier: list[str] = []  # why the tries before the last failed
        resumed = False  # the next try follows an operator's pause: the robot is where teleop left it
        while True:
            if pauses is not None:
                pauses.attempting()
            try:
                message = self._attempt(step, timeout, cancel, attempt, note, searched, recover=resumed)
            except Canceled as exc:
                return canceled(str(exc))
            except (ExecutionError, CallError) as exc:
                # A motion that did not stop is no cancel and no pause: the plan fails with it.
                stuck = isinstance(exc, MotionNotStopped)
                if cancel.is_set() and not stuck:
                    # Canceled while the try failed for a reason of its own (its route could not be
                    # planned): the plan was canceled, so no pause is waited out, no retry or on_failure
                    # runs, and no one plans a recovery for a failure.
                    return canceled(f"canceled (the try had failed: {exc})")
                held = Held.NOT_PAUSED if pauses is None or stuck else pauses.hold(cancel, paused)
                if held is Held.RESUMED:
                    log.info("step %s (%s) resumed after an operator's pause (%s)", label, action, exc)
                    note(f"resumed by the operator: {step.describe()} again from where the robot is now")
                    resumed = True
                    continue
                if isinstance(held, ExecutePlanResult):
                    if held.status is PlanStatus.CANCELED:
                        failure = _Failure(
                            f"step {label} ({action}) canceled while paused",
                            PlanStatus.CANCELED,
                            "canceled",
                            FailureKind.CANCELED,
                        )
                        return result(StepStatus.CANCELED, held.reason, attempt, FailureKind.CANCELED), failure
                    why = f"step {label} ({action}) stopped while paused: {held.reason}"
                    report(StepStatus.FAILED, held.reason, attempt, FailureKind.VETOED)
                    failure = _Failure(why, held.status, held.reason, FailureKind.VETOED)
                    return result(StepStatus.FAILED, held.reason, attempt, FailureKind.VETOED), failure
                kind = exc.kind if isinstance(exc, ExecutionError) else FailureKind.EXECUTION
                if isinstance(exc, GraspFailed) and self.incidents is not None:
                    self.incidents(IncidentKind.GRASP_FAILED, str(exc), [exc.object_name], index, label)
                final = self._final(exc)
                if final is None and kind in RETRYABLE and attempt < tries and not cancel.is_set():
                    attempt += 1
                    report(
                        StepStatus.RUNNING,
                        f"attempt {attempt - 1} failed ({kind}): {exc}; re-detecting and planning again, "
                        f"attempt {attempt} of {tries}",
                        attempt,
                        kind,
                    )
                    log.info("step %s (%s) attempt %d failed (%s): %s", label, action, attempt - 1, kind, exc)
                    earlier.append(f"attempt {attempt - 1} ({kind}): {exc}")
                    continue
                tried = f" after {attempt} attempts" if attempt > 1 else ""
                report(StepStatus.FAILED, str(exc), attempt, kind)
                reason = f"step {label} ({action}) failed{tried} ({kind}): {exc}"
                if any(not e.endswith(f": {exc}") for e in earlier):
                    reason += f" (before: {'; '.join(earlier)})"
                return result(StepStatus.FAILED, str(exc), attempt, kind), _Failure(
                    reason, PlanStatus.FAILED, final, kind
                )
            except Exception as exc:
                # A fault of the executor's own (a planner's check that raised inside OMPL), which no
                # retry or on_failure is known to mend: the plan fails with results saying so, rather
                # than the goal ending without any. The first line names it; the log has the rest.
                log.exception("step %s (%s) failed inside the executor", label, action)
                why = f"the executor failed ({type(exc).__name__}): {(str(exc).splitlines() or [''])[0]}"
                if cancel.is_set():
                    return canceled(f"canceled (the try had failed: {why})")
                report(StepStatus.FAILED, why, attempt, FailureKind.EXECUTION)
                return result(StepStatus.FAILED, why, attempt, FailureKind.EXECUTION), _Failure(
                    f"step {label} ({action}) failed: {why}",
                    PlanStatus.FAILED,
                    "the executor itself failed",
                    FailureKind.EXECUTION,
                )
            report(StepStatus.SUCCEEDED, message, attempt)
            return result(StepStatus.SUCCEEDED, message, attempt), None

    def _attempt(
        self,
        step: GroundedStep,
        timeout: float,
        cancel: threading.Event,
        attempt: int,
        note: Note,
        searched: list[str],
        recover: bool = False,
    ) -> str:
        """One try at a step within its time; a retry (or, with `recover`, a try after a pause) first
        brings the robot back to where a step can start (hand empty and open, or holding, with the
        arm stowed). `searched` starts empty and gets the places the try looks for its object."""
        searched.clear()
        if cancel.is_set():
            raise Canceled("canceled before the step started")
        clock = StepClock(timeout, cancel, self.robot.speed_scale)
        try:
            with clock.running() as step_cancel:
                if attempt > 1 or recover:
                    self.manipulator.recover(step, step_cancel)
                return self.manipulator.run(step, step_cancel, attempt, note, searched)
        except Canceled as exc:
            if clock.expired and not cancel.is_set():
                raise StepTimedOut(
                    f"{step.describe()}: timed out after {timeout:g} s of motion (pauses for people not counted), "
                    f"during {str(exc).removesuffix(' canceled')}"
                ) from None
            raise

    def _final(self, exc: Exception) -> str | None:
        """Why no retry and no on_failure may follow `exc`, or None when they may."""
        if isinstance(exc, CommandVetoed):
            return "safety refused the motion"
        if isinstance(exc, Interrupted):
            return "the robot side ended the motion"
        if isinstance(exc, MotionNotStopped):
            # Past its cancel's grace, or neither its end nor a cancel answered (GoalUnanswered).
            return "the motion may still be running: the executor latched the e-stop"
        if isinstance(exc, CallError):
            # A goal sent but never answered for may still be moving the robot.
            return f"the robot side did not answer ({exc})"
        return self.robot.safety_stop()

    def _on_failure(
        self,
        plan: GroundedPlan,
        failed: int,
        failure: _Failure,
        results: list[StepResult],
        cancel: threading.Event,
        feedback: FeedbackSink,
        pauses: PauseWatch | None = None,
    ) -> int | _Failure:
        """Run the on_failure alternatives covering step `failed`, innermost first, each one taking
        over when the one inside it fails too. The index to go on from, or the plan's failure."""
        covering = [f for f in plan.fallbacks if f.first <= failed <= f.last]
        if not covering:
            return failure
        if failure.final is not None:
            if failure.status is PlanStatus.CANCELED:
                return failure
            reason = f"{failure.reason}; no on_failure runs: {failure.final}"
            return _Failure(reason, failure.status, failure.final, failure.kind)
        reasons = [failure.reason]
        labels = step_labels(plan)
        kind = failure.kind
        for fallback in sorted(covering, key=lambda f: (f.last - f.first, -f.first)):
            alternative_labels = fallback_labels(fallback, labels)
            for k, step in enumerate(fallback.steps):
                result, alt_failure = self._run_one(k, step, alternative_labels[k], cancel, feedback, pauses)
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
            kind = alt_failure.kind
            if alt_failure.final is not None:
                return _Failure("; ".join(reasons), alt_failure.status, alt_failure.final, kind)
        return _Failure("; ".join(reasons), PlanStatus.FAILED, kind=kind)

    def _finish(
        self, plan: GroundedPlan, results: list[StepResult], reported: set[int], failure: _Failure
    ) -> ExecutePlanResult:
        labels = step_labels(plan)
        skipped = [
            StepResult(index=i, action=step_kind(s), status=StepStatus.SKIPPED, label=labels[i])
            for i, s in enumerate(plan.steps)
            if i not in reported
        ]
        return ExecutePlanResult(
            status=failure.status,
            stage=Stage.EXECUTE,
            reason=failure.reason,
            steps=results + skipped,
            failure=failure.kind,
        )


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
