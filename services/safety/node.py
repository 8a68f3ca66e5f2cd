"""Safety's transport: the only writer of robot/**; heartbeat, e-stop, checks and forwarding."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalResponse, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError, Stage
from schemas.keys import Action
from schemas.plan import GroundedPlan, PlanApproved, PlanCheckReply
from schemas.robot import JointState, Odometry, Twist
from schemas.safety import Decision, EStop, ResetReply, ResetRequest, SafetyEvent, SafetyStatus
from services.actionlib import MAX_RESULT_WAIT
from services.runtime import Node, encode
from services.safety.config import SafetyConfig
from services.safety.errors import Unauthorized, Vetoed
from services.safety.latch import EstopLatch
from services.safety.policy import SafetyPolicy

log = logging.getLogger(__name__)


class SafetyNode:
    def __init__(self, node: Node, policy: SafetyPolicy, latch: EstopLatch, config: SafetyConfig) -> None:
        self.node = node
        self.policy = policy
        self.latch = latch
        self.config = config
        self._odom: tuple[float, Pose2D] | None = None
        self._joints: tuple[float, dict[str, float]] | None = None
        self._seq = 0
        self._forwarded: dict[str, Action[Any, Any, Any]] = {}
        self._lock = threading.Lock()
        self._heartbeat = node.publisher(keys.HEARTBEAT)
        self._events = node.publisher(keys.SAFETY_EVENTS)
        self._robot_cmd_vel = node.publisher(keys.ROBOT_CMD_VEL)
        self._stop = threading.Event()

        node.subscribe(keys.ODOM, self._on_odom)
        node.subscribe(keys.JOINT_STATES, self._on_joints)
        node.subscribe(keys.ESTOP, self._on_estop)
        node.subscribe(keys.CMD_VEL, self._on_cmd_vel)
        node.serve(keys.RESET, self._on_reset)
        node.serve(keys.PLAN_CHECK, self._on_check_plan)
        self._proxy(keys.CMD_NAVIGATE, keys.ROBOT_NAVIGATE, lambda g: policy.check_navigation(g, self.pose()))
        self._proxy(keys.CMD_TRAJECTORY, keys.ROBOT_TRAJECTORY, lambda g: policy.check_trajectory(g, self.joints()))
        self._proxy(keys.CMD_GRIPPER, keys.ROBOT_GRIPPER, policy.check_gripper)
        self._beat_thread = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
        self._beat_thread.start()

    def close(self) -> None:
        self._stop.set()
        self._beat_thread.join(timeout=1.0)

    # Heartbeat and e-stop

    def _publish_heartbeat(self) -> None:
        # Under one lock, so a beat read before a latch can never be sent after the latched one.
        with self._lock:
            self._seq += 1
            self._heartbeat.put(SafetyStatus(seq=self._seq, stamp=time.time(), estop=self.latch.state))

    def _beat(self) -> None:
        period = 1.0 / self.config.heartbeat_hz
        next_beat = time.monotonic()
        while not self._stop.is_set():
            self._publish_heartbeat()
            next_beat += period
            self._stop.wait(max(0.0, next_beat - time.monotonic()))

    def _on_estop(self, msg: EStop) -> None:
        if self.latch.trigger(msg.source, msg.reason):
            log.warning("E-STOP latched by %s: %s", msg.source, msg.reason)
            # Out of cycle, so the robot hears it now rather than at the next beat.
            self._publish_heartbeat()
            self._robot_cmd_vel.put(Twist())
            self._event("safety/estop", Decision.LATCHED, f"by {msg.source}: {msg.reason}", msg)
            # Queries take time; not on Zenoh's callback thread. The heartbeat already stops the robot.
            threading.Thread(target=self._cancel_forwarded, name="estop-cancel", daemon=True).start()

    def _cancel_forwarded(self) -> None:
        with self._lock:
            goals = list(self._forwarded.items())
        for goal_id, action in goals:
            try:
                self.node.call(action.cancel_goal, CancelGoal(goal_id=goal_id), timeout=1.0)
            except Exception as exc:  # the heartbeat stops the robot anyway
                log.warning("cancel of %s on e-stop failed: %s", goal_id, exc)

    def _on_reset(self, req: ResetRequest) -> ResetReply:
        try:
            self.latch.reset(req.operator, req.token)
        except Unauthorized as exc:
            self._event(keys.RESET.path, Decision.VETOED, str(exc), msgspec.structs.replace(req, token="***"))
            return ResetReply(ok=False, message=str(exc))
        log.warning("e-stop reset by operator %s", req.operator)
        self._publish_heartbeat()
        self._event(keys.RESET.path, Decision.RESET, f"by operator {req.operator}", None)
        return ResetReply(ok=True, message=f"e-stop reset by {req.operator}")

    # Commands

    def _on_odom(self, msg: Odometry) -> None:
        self._odom = (time.monotonic(), msg.pose)

    def _on_joints(self, msg: JointState) -> None:
        self._joints = (time.monotonic(), dict(zip(msg.name, msg.position, strict=False)))

    def pose(self) -> Pose2D | None:
        """The base pose, or None when odometry is missing or stale."""
        odom = self._odom
        if odom is None or time.monotonic() - odom[0] > self.config.state_max_age:
            return None
        return odom[1]

    def joints(self) -> dict[str, float] | None:
        joints = self._joints
        if joints is None or time.monotonic() - joints[0] > self.config.state_max_age:
            return None
        return joints[1]

    def _on_cmd_vel(self, twist: Twist) -> None:
        estop = self.latch.state
        if estop.latched:
            self._event(keys.CMD_VEL.path, Decision.VETOED, "e-stop latched", twist)
            return
        try:
            sent = self.policy.check_cmd_vel(twist, self.pose())
        except Vetoed as exc:
            # Dropping it is not enough: the last approved twist would carry on until it expires.
            self._robot_cmd_vel.put(Twist())
            self._event(keys.CMD_VEL.path, Decision.VETOED, f"{exc}; base stopped", twist)
            return
        if sent != twist:
            self._event(keys.CMD_VEL.path, Decision.CLAMPED, "clamped to speed limits", sent)
        self._robot_cmd_vel.put(sent)

    def _on_check_plan(self, plan: GroundedPlan) -> PlanCheckReply:
        estop = self.latch.state
        try:
            if estop.latched:
                raise Vetoed(f"e-stop latched by {estop.source}: {estop.reason}; an operator must reset it")
            checks = self.policy.check_plan(plan, self.pose())
        except Vetoed as exc:
            self._event(keys.PLAN_CHECK.path, Decision.VETOED, str(exc), plan)
            kind = ErrorKind.ESTOP if estop.latched else ErrorKind.VETOED
            return ServiceError(kind=kind, message=str(exc), stage=Stage.SAFETY)
        self._event(keys.PLAN_CHECK.path, Decision.APPROVED, "; ".join(checks), plan)
        return PlanApproved(checks=checks)

    def _proxy(self, cmd: Action[Any, Any, Any], robot: Action[Any, Any, Any], check: Callable[[Any], Any]) -> None:
        """Serve `cmd`'s five keys: check goals, forward them to `robot`, relay its feedback."""

        def send_goal(req: SendGoal[Any]) -> GoalResponse:
            estop = self.latch.state
            try:
                if estop.latched:
                    raise Vetoed(f"e-stop latched by {estop.source}: {estop.reason}")
                goal = check(req.goal)
            except Vetoed as exc:
                self._event(cmd.send_goal.path, Decision.VETOED, str(exc), req)
                return GoalResponse(goal_id=req.goal_id, accepted=False, reason=f"vetoed by safety: {exc}")
            decision = Decision.APPROVED if goal == req.goal else Decision.CLAMPED
            self._event(cmd.send_goal.path, decision, "", SendGoal(goal_id=req.goal_id, goal=goal))
            response = self.node.call(
                robot.send_goal, SendGoal(goal_id=req.goal_id, goal=goal), timeout=self.config.forward_timeout
            )
            if response.accepted:
                with self._lock:
                    self._forwarded[req.goal_id] = robot
            return response

        def cancel_goal(req: CancelGoal) -> CancelResponse:
            return self.node.call(robot.cancel_goal, req, timeout=self.config.forward_timeout)

        def get_result(req: GetResult) -> Any:
            try:
                return self.node.call(robot.get_result, req, timeout=MAX_RESULT_WAIT)
            finally:
                with self._lock:
                    self._forwarded.pop(req.goal_id, None)

        self.node.serve(cmd.send_goal, send_goal)
        self.node.serve(cmd.cancel_goal, cancel_goal)
        self.node.serve(cmd.get_result, get_result)
        feedback = self.node.publisher(cmd.feedback)
        status = self.node.publisher(cmd.status)
        self.node.subscribe(robot.feedback, feedback.put)
        self.node.subscribe(robot.status, status.put)

    def _event(self, key: str, decision: Decision, reason: str, command: Any) -> None:
        raw = msgspec.Raw(encode(command) if command is not None else b"null")
        self._events.put(SafetyEvent(stamp=time.time(), key=key, decision=decision, reason=reason, command=raw))
        if decision is Decision.VETOED:
            log.warning("vetoed %s: %s", key, reason)
