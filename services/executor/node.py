"""Executor transport: the execute_plan action, the planner services and the robot through safety."""

from __future__ import annotations

import logging
import threading
import time
from contextvars import ContextVar
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import GoalState, ResultResponse
from schemas.common import TEXT_CHARS, Pose2D, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepStatus
from schemas.incidents import MAX_INVOLVED, IncidentKind, IncidentReport
from schemas.plan import GroundedPlan, ParseReply, Plan, PlanCheckReply, PlanText, ResolveReply
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    JointState,
    NavigateToPoseGoal,
    Odometry,
    Twist,
)
from schemas.safety import ApprovalRequest, ApprovalState, EStop, EstopSource, PlanApproval, SafetyStatus
from schemas.world import Empty, PerceivedHumans, PerceivedObject, PerceivedObjects
from services.actionlib import (
    MAX_RESULT_WAIT,
    ActionClient,
    ActionServer,
    GoalHandle,
    GoalNotStopped,
    GoalUnanswered,
    Outcome,
)
from services.errors import CallError
from services.executor.config import ExecutorConfig
from services.executor.errors import MotionNotStopped
from services.executor.runner import FeedbackSink, Held, PlanRunner, clip
from services.runtime import Node

log = logging.getLogger(__name__)

# How long to wait for the robot to report its state after a motion.
STATE_TIMEOUT = 1.0
# Safety beats at 20 Hz or more; this long without a beat means it is not there.
HEARTBEAT_STALE = 0.5
# How long an e-stop the executor sends may take to show latched in safety's heartbeat.
LATCH_CONFIRM = 1.0
# Perception reports a few times a second: its latest report, received longer ago than this, is from
# a perception that stopped, and what it saw may have moved since (by teleop, by people).
OBJECTS_STALE = 2.0
# The resolver answers world/scene from memory; this is generous.
SCENE_TIMEOUT = 2.0
# Each ask for a plan's approval waits this long in safety for an operator's decision, then asks
# again (and sees a cancel of the plan by then).
APPROVAL_POLL = 1.0


class NodePlanServices:
    """Parser, resolver and safety's plan check, reached by queries."""

    def __init__(self, node: Node, config: ExecutorConfig) -> None:
        self.node = node
        self.config = config

    def _call(self, stage: Stage, service: Any, request: Any, timeout: float) -> Any:
        try:
            return self.node.call(service, request, timeout=timeout)
        except CallError as exc:
            raise CallError(msgspec.structs.replace(exc.error, stage=stage)) from None

    def parse(self, text: str, fmt: str) -> ParseReply:
        request = PlanText(text=text, format=fmt)  # type: ignore[arg-type]
        return self._call(Stage.PARSE, keys.PLAN_PARSE, request, self.config.parse_timeout)  # type: ignore[no-any-return]

    def resolve(self, plan: Plan) -> ResolveReply:
        return self._call(Stage.RESOLVE, keys.PLAN_RESOLVE, plan, self.config.resolve_timeout)  # type: ignore[no-any-return]

    def check(self, plan: GroundedPlan) -> PlanCheckReply:
        return self._call(Stage.SAFETY, keys.PLAN_CHECK, plan, self.config.check_timeout)  # type: ignore[no-any-return]


class NodeRobot:
    """The robot as the executor may reach it: goals on cmd/** (safety), state from robot/** topics.

    After each motion, the pose and joint positions it reports are ones that arrived after the
    motion ended: planning the next move from a state read mid-motion would start it from where
    the robot no longer is. What perception reports must also have been taken after it ended, by
    the robot's clock (`look`): a camera frame arrives well after it was taken. A motion's time is
    bounded by its step's clock (runner.StepClock), which cancels it; the wait for its result here
    is only a backstop.
    """

    def __init__(self, node: Node, config: ExecutorConfig) -> None:
        self.node = node
        self.config = config
        grace = config.cancel_grace
        self._navigate = ActionClient(node, keys.CMD_NAVIGATE, cancel_grace=grace)
        self._trajectory = ActionClient(node, keys.CMD_TRAJECTORY, cancel_grace=grace)
        self._gripper = ActionClient(node, keys.CMD_GRIPPER, cancel_grace=grace)
        self._cmd_vel = node.publisher(keys.CMD_VEL)
        self._estop = node.publisher(keys.ESTOP)
        self._changed = threading.Condition()
        self._odom: tuple[float, Odometry] | None = None
        self._joints: tuple[float, JointState] | None = None
        self._motion_ended = 0.0
        # The robot's clock once the last motion had ended: the stamp of the first joint state that
        # arrived after it (None until one has; 0 before any motion).
        self._ended_stamp: float | None = 0.0
        self._objects: tuple[float, PerceivedObjects] | None = None
        self._heartbeat: tuple[float, SafetyStatus] | None = None
        self._humans: PerceivedHumans | None = None
        node.subscribe(keys.HEARTBEAT, self._set_heartbeat)
        node.subscribe(keys.HUMANS, self._set_humans)
        node.subscribe(keys.ODOM, self._set_odom)
        node.subscribe(keys.JOINT_STATES, self._set_joints)
        node.subscribe(keys.OBJECTS, self._set_objects)

    def _set_heartbeat(self, msg: SafetyStatus) -> None:
        self._heartbeat = (time.monotonic(), msg)

    def _set_humans(self, msg: PerceivedHumans) -> None:
        self._humans = msg

    def people(self) -> list[Pose2D]:
        humans = self._humans
        return [h.pose for h in humans.humans] if humans is not None else []

    def speed_scale(self) -> float:
        heartbeat = self._heartbeat
        if heartbeat is None or self.safety_stop() is not None:
            return 0.0
        return heartbeat[1].speed_scale

    def remembered(self, object_id: str) -> PerceivedObject | None:
        try:
            scene = self.node.call(keys.SCENE, Empty(), timeout=SCENE_TIMEOUT)
        except CallError as exc:
            log.warning("no scene from the resolver: %s", exc)
            return None
        return next((o for o in scene.objects if o.id == object_id), None)

    def _beat(self) -> SafetyStatus | str:
        """Safety's latest heartbeat, if fresh; else why there is none."""
        heartbeat = self._heartbeat
        if heartbeat is None:
            return "no safety heartbeat received"
        age = time.monotonic() - heartbeat[0]
        if age > HEARTBEAT_STALE:
            return f"no safety heartbeat for {age:.1f} s"
        return heartbeat[1]

    def safety_stop(self) -> str | None:
        if isinstance(beat := self._beat(), str):
            return beat
        estop = beat.estop
        if estop.latched:
            return f"e-stop latched by {estop.source or 'unknown'}: {estop.reason or 'no reason given'}"
        return None

    def _set_odom(self, msg: Odometry) -> None:
        with self._changed:
            self._odom = (time.monotonic(), msg)
            self._changed.notify_all()

    def _set_joints(self, msg: JointState) -> None:
        with self._changed:
            self._joints = (time.monotonic(), msg)
            if self._ended_stamp is None:
                self._ended_stamp = msg.stamp
            self._changed.notify_all()

    def _set_objects(self, msg: PerceivedObjects) -> None:
        with self._changed:
            self._objects = (time.monotonic(), msg)
            self._changed.notify_all()

    def _motion_end(self) -> None:
        with self._changed:
            self._motion_ended = time.monotonic()
            self._ended_stamp = None

    def _fresh(self, attribute: str, timeout: float = STATE_TIMEOUT, since: float | None = None) -> Any:
        """The latest message of `attribute` received after `since` (default: the end of the last
        motion), waiting up to `timeout` for one; None if none comes."""
        after = self._motion_ended if since is None else since
        with self._changed:
            self._changed.wait_for(
                lambda: (latest := getattr(self, attribute)) is not None and latest[0] > after, timeout
            )
            latest = getattr(self, attribute)
            return latest[1] if latest is not None and latest[0] > after else None

    def held_object(self) -> str | None:
        latest = self._objects
        if latest is None:
            return None
        return next((o.id for o in latest[1].objects if o.on == "gripper"), None)

    def look(self, timeout: float, *, new: bool = False) -> list[PerceivedObject] | None:
        """What perception reported last, once that report came after the last motion ended and was
        taken after it too: its stamp (the robot's clock) no earlier than the first joint state that
        arrived after the end. A camera frame arrives a good while after it was taken (rendered,
        detected, sent: a tenth of a second or more on a busy machine, seconds of a sim running
        ten times faster); one taken while the base still drove in has what the hand holds where
        the hand no longer is. Asked again without a motion between, the same frame answers at
        once, if received within OBJECTS_STALE. With `new`, the next such report from now on."""
        now = time.monotonic()
        after = now if new else max(self._motion_ended, now - OBJECTS_STALE)

        def taken_after() -> bool:
            latest, ended = self._objects, self._ended_stamp
            return latest is not None and latest[0] > after and ended is not None and latest[1].stamp >= ended

        with self._changed:
            if not self._changed.wait_for(taken_after, timeout):
                return None
            assert self._objects is not None
            return list(self._objects[1].objects)

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        return self._move(self._navigate, goal, cancel)

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        return self._move(self._trajectory, goal, cancel)

    def gripper(self, goal: GripperCommandGoal, cancel: threading.Event) -> ResultResponse[Any]:
        return self._move(self._gripper, goal, cancel)

    def _move(self, client: ActionClient[Any, Any, Any], goal: Any, cancel: threading.Event) -> ResultResponse[Any]:
        """Run one motion to its end. One that goes on past its cancel may still be moving the robot,
        as may one whose end the robot side did not tell and whose cancel it did not answer either:
        nothing of this plan or the next may move beside it, so the e-stop is latched (an operator
        looks and resets it)."""
        try:
            return client.run(goal, timeout=MAX_RESULT_WAIT, cancel=cancel)
        except GoalUnanswered as exc:
            why = f"the robot side did not answer: {exc.error.message}: it may still be moving the robot"
            raise MotionNotStopped(f"{why}; {self._halt(why)}") from None
        except GoalNotStopped as exc:
            why = f"{exc.error.message}: it may still be moving the robot"
            raise MotionNotStopped(f"{why}; {self._halt(why)}") from None
        finally:
            self._motion_end()

    def _halt(self, why: str) -> str:
        """Latch the e-stop for `why`; what was done, in words: that it latched only once a fresh
        heartbeat says so (LATCH_CONFIRM at most), as safety may be what went away."""
        log.error("latching the e-stop: %s", why)
        try:
            self._estop.put(EStop(source=EstopSource.EXECUTOR, reason=why[:TEXT_CHARS]))
        except Exception as exc:  # the plan still fails; the words must not claim the e-stop latched
            log.exception("the e-stop could not be sent")
            return f"latching the e-stop failed: {exc}"
        deadline = time.monotonic() + LATCH_CONFIRM
        while isinstance(beat := self._beat(), str) or not beat.estop.latched:
            if time.monotonic() >= deadline:
                shown = beat if isinstance(beat, str) else "not latched"
                return f"the executor sent safety an e-stop, which no heartbeat showed latched ({shown})"
            time.sleep(0.02)  # polling the latest heartbeat with a deadline
        return "the executor latched the e-stop"

    def cmd_vel(self, twist: Twist) -> None:
        self._cmd_vel.put(twist)

    def base_pose(self) -> Pose2D | None:
        odom: Odometry | None = self._fresh("_odom")
        return odom.pose if odom else None

    def arm_positions(self) -> list[float] | None:
        joints: JointState | None = self._fresh("_joints")
        if joints is None:
            return None
        by_name = dict(zip(joints.name, joints.position, strict=False))
        if not all(n in by_name for n in ARM_JOINTS):
            return None
        return [by_name[n] for n in ARM_JOINTS]


# The plan goal the calling thread runs (set by serve_execute_plan's execute), for incident reports.
RUNNING_GOAL: ContextVar[str] = ContextVar("running_goal", default="")


class IncidentReporter:
    """Publishes what only the executor sees (a grasp that closed on nothing) on
    safety/incidents/report, with the plan goal and step; safety adds where the robot was."""

    def __init__(self, node: Node) -> None:
        self._publisher = node.publisher(keys.INCIDENT_REPORT)

    def __call__(self, kind: IncidentKind, reason: str, objects: list[str], step: int, label: str) -> None:
        report = IncidentReport(
            kind=kind,
            reason=reason[:TEXT_CHARS],
            objects=[o[:200] for o in objects[:MAX_INVOLVED]],
            goal_id=RUNNING_GOAL.get()[:64],
            step=step,
            label=label[:64],
        )
        try:
            self._publisher.put(report)
        except Exception:  # a report lost must not fail the plan
            log.exception("incident report not sent: %s", reason)


OUTCOME_STATE = {
    PlanStatus.SUCCEEDED: GoalState.SUCCEEDED,
    PlanStatus.CANCELED: GoalState.CANCELED,
    PlanStatus.FAILED: GoalState.ABORTED,
    PlanStatus.REJECTED: GoalState.ABORTED,
}


class Supervision:
    """Safety's word on whether plan goal `goal_id` may move the robot (supervised mode).

    `approve`: asked before the first motion: at once outside supervised mode; in it, once an
    operator decided (feedback `awaiting_approval` meanwhile). Safety itself refuses the motion of a
    plan it has not approved, so this wait is the executor's courtesy, not the gate.

    `hold`: asked after a step's attempt failed. An operator who pauses the plan makes safety cancel
    its goals and refuse its motion; that is no failure: the pause is reported (feedback
    `awaiting_approval` on the step) and waited out, and the step runs again once resumed. Told apart
    from a failure of the plan's own by safety's approval: paused now, or paused more often than
    when the attempt began (a pause resumed before it was asked). `attempting`, as each attempt
    begins, notes how often the plan has been paused so far: a pause resumed while no motion ran (a
    wait step, planning) explains no later failure; one still on as the attempt begins may."""

    def __init__(self, node: Node, goal_id: str, config: ExecutorConfig) -> None:
        self.node = node
        self.goal_id = goal_id
        self.config = config
        self._plan: GroundedPlan | None = None  # set once an operator approved it
        self._pauses = 0  # the pauses of it this executor has seen

    def _ask(self, plan: GroundedPlan, wait: float) -> PlanApproval:
        request = ApprovalRequest(goal_id=self.goal_id, plan=plan, wait=wait)
        reply: PlanApproval = self.node.call(
            keys.APPROVAL_REQUEST, request, timeout=APPROVAL_POLL + self.config.check_timeout
        )
        return reply

    def approve(self, plan: GroundedPlan, cancel: threading.Event, feedback: FeedbackSink) -> ExecutePlanResult | None:
        goal_id = self.goal_id
        told = False
        while not cancel.is_set():
            try:
                reply = self._ask(plan, APPROVAL_POLL if told else 0.0)
            except CallError as exc:
                why = f"safety did not say whether the plan may move: {exc.error.message}"
                return ExecutePlanResult(status=PlanStatus.REJECTED, stage=Stage.SAFETY, reason=why)
            if reply.state is ApprovalState.NOT_NEEDED:
                return None
            if reply.state in (ApprovalState.APPROVED, ApprovalState.PAUSED):
                # Paused already (approved, then paused before this ask was answered): the plan was
                # approved, and its pause, not over yet, is waited out as any (`hold`).
                ongoing = 1 if reply.state is ApprovalState.PAUSED else 0
                self._plan, self._pauses = plan, max(0, reply.pauses - ongoing)
                feedback(ExecutePlanFeedback(stage=Stage.SAFETY, message=reply.reason))
                return None
            if reply.state is not ApprovalState.PENDING:
                return ExecutePlanResult(status=PlanStatus.REJECTED, stage=Stage.SAFETY, reason=reply.reason)
            if not told:
                checks = "; ".join(reply.checks) or "approved"
                message = (
                    f"awaiting an operator's approval of goal {goal_id}: `tether approve {goal_id}` or "
                    f"`tether deny {goal_id} --reason ...`; safety's dry run: {checks}; "
                    f"the plan: {' | '.join(reply.steps)}"
                )
                status = StepStatus.AWAITING_APPROVAL
                feedback(ExecutePlanFeedback(stage=Stage.SAFETY, status=status, message=message[:TEXT_CHARS]))
                log.info("plan goal %s awaits an operator's approval", goal_id)
                told = True
        # Canceled before safety was asked (while the plan was parsed, resolved, checked): no operator
        # was waited for, whatever the mode.
        waited = "while awaiting an operator's approval" if told else "before the plan's first motion"
        reason = f"canceled {waited}; nothing moved"
        return ExecutePlanResult(status=PlanStatus.CANCELED, stage=Stage.SAFETY, reason=reason)

    def attempting(self) -> None:
        plan = self._plan
        if plan is None:  # not a plan an operator approved: no one can pause it
            return
        try:
            reply = self._ask(plan, 0.0)
        except CallError as exc:  # the count stays: a pause before now may then be taken for this attempt's
            log.warning("plan goal %s: safety did not say how often it was paused: %s", self.goal_id, exc)
            return
        # A pause still on as the attempt begins explains its failure (its first goal refused) even
        # when it is resumed before `hold` asks: it is not counted as over.
        ongoing = 1 if reply.state is ApprovalState.PAUSED else 0
        self._pauses = max(self._pauses, reply.pauses - ongoing)

    def hold(self, cancel: threading.Event, feedback: FeedbackSink) -> Held | ExecutePlanResult:
        plan, goal_id = self._plan, self.goal_id
        if plan is None:  # not a plan an operator approved: no one can pause it
            return Held.NOT_PAUSED
        told = False
        while not cancel.is_set():
            try:
                reply = self._ask(plan, APPROVAL_POLL if told else 0.0)
            except CallError as exc:
                if not told:
                    log.warning("plan goal %s: safety did not say whether it is paused: %s", goal_id, exc)
                    return Held.NOT_PAUSED
                why = f"safety did not say whether the paused plan may go on: {exc.error.message}"
                return ExecutePlanResult(status=PlanStatus.FAILED, stage=Stage.SAFETY, reason=why)
            paused_since = reply.pauses > self._pauses
            self._pauses = max(self._pauses, reply.pauses)
            if reply.state is ApprovalState.PAUSED:
                if not told:
                    message = (
                        f"{reply.reason}: the plan waits, teleop drives meanwhile; `tether resume {goal_id}` "
                        f"hands back (the step runs again from where the robot is then), `tether deny {goal_id}` "
                        "ends the plan"
                    )
                    waiting = StepStatus.AWAITING_APPROVAL
                    feedback(ExecutePlanFeedback(stage=Stage.EXECUTE, status=waiting, message=message[:TEXT_CHARS]))
                    log.info("plan goal %s paused by an operator", goal_id)
                    told = True
                continue
            if reply.state in (ApprovalState.APPROVED, ApprovalState.NOT_NEEDED):
                return Held.RESUMED if told or paused_since else Held.NOT_PAUSED
            if reply.state is ApprovalState.DENIED:
                return ExecutePlanResult(status=PlanStatus.FAILED, stage=Stage.SAFETY, reason=reply.reason)
            return Held.NOT_PAUSED
        reason = "canceled while paused by an operator"
        return ExecutePlanResult(status=PlanStatus.CANCELED, stage=Stage.SAFETY, reason=reason)


def serve_execute_plan(node: Node, runner: PlanRunner, config: ExecutorConfig) -> ActionServer[Any, Any, Any]:
    """One plan at a time: another is rejected while one runs, or preempts it (its own `preempt`,
    or `when_busy = "preempt"`): the running plan is canceled and stopped before the new one starts.
    A dry run moves nothing, so it runs beside whatever runs."""

    def execute(handle: GoalHandle[ExecutePlanGoal, ExecutePlanFeedback]) -> Outcome[ExecutePlanResult]:
        log.info("executing plan goal %s (%d bytes)", handle.goal_id, len(handle.goal.text))
        RUNNING_GOAL.set(handle.goal_id)
        supervision = Supervision(node, handle.goal_id, config)
        result = runner.run(handle.goal, handle.cancel_requested, handle.feedback, supervision.approve, supervision)
        if result.status is not PlanStatus.SUCCEEDED and handle.abort_reason:
            # Stopped by abort_all (the executor shutting down): the goal ends aborted for that reason,
            # and its result says the same; no client canceled it.
            status = PlanStatus.FAILED if result.status is PlanStatus.CANCELED else result.status
            reason = clip(f"{handle.abort_reason}; {result.reason}")
            result = msgspec.structs.replace(result, status=status, reason=reason)
        elif result.status is PlanStatus.CANCELED and handle.cancel_reason:
            # Clipped again: the runner's reason fits, the cancel's words before it may not.
            result = msgspec.structs.replace(result, reason=clip(f"{handle.cancel_reason}; {result.reason}"))
        log.info("plan goal %s %s at %s: %s", handle.goal_id, result.status, result.stage, result.reason)
        return Outcome(OUTCOME_STATE[result.status], result, result.reason)

    def preempts(goal: ExecutePlanGoal) -> bool:
        return goal.preempt or config.when_busy == "preempt"

    def moves_nothing(goal: ExecutePlanGoal) -> bool:
        return goal.dry_run

    return ActionServer(node, keys.EXECUTE_PLAN, execute, exclusive=True, preempts=preempts, concurrent=moves_nothing)
