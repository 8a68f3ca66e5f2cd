"""Safety's transport: the only writer of robot/**; heartbeat, e-stop, checks, monitors, forwarding."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalResponse, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError, Stage
from schemas.keys import Action, Topic
from schemas.plan import GroundedPlan, PlanApproved, PlanCheckReply
from schemas.robot import ARM_JOINTS, JointState, Odometry, Twist
from schemas.safety import (
    Decision,
    EStop,
    EstopSource,
    ResetReply,
    ResetRequest,
    Rule,
    SafetyEvent,
    SafetyStatus,
)
from schemas.world import PerceivedHumans
from services.actionlib import MAX_RESULT_WAIT
from services.runtime import Node, encode
from services.safety.config import SafetyConfig
from services.safety.errors import Unauthorized, Vetoed
from services.safety.latch import EstopLatch
from services.safety.monitor import MotionMonitor, Person, RateLimit, Separation, Trip, nearest_person, separation
from services.safety.policy import SafetyPolicy, Verdict

log = logging.getLogger(__name__)

# Faster than this (m/s, rad/s) counts as moving, for the watchdog.
MOVING = 0.05
# A teleop stream silent this long has stopped the base (the robot holds a cmd_vel for 0.5 s); the
# first message after it may speed up by at most TELEOP_MAX_STEP seconds of acceleration.
TELEOP_TIMEOUT = 0.5
TELEOP_MAX_STEP = 0.1


class SafetyNode:
    def __init__(self, node: Node, policy: SafetyPolicy, latch: EstopLatch, config: SafetyConfig) -> None:
        self.node = node
        self.policy = policy
        self.latch = latch
        self.config = config
        rules = policy.policy
        self.hash = policy.limits.hash
        self._odom: tuple[float, Odometry] | None = None
        self._joints: tuple[float, JointState] | None = None
        self._humans: tuple[float, list[Person]] | None = None
        self._started = time.monotonic()
        self._separation = Separation(rules.humans.reduced_speed_scale, "no report of people yet")
        self._teleop_sent: tuple[float, Twist] = (0.0, Twist())
        self._seq = 0
        self._forwarded: dict[str, Action[Any, Any, Any]] = {}
        self._lock = threading.Lock()
        self._monitor_lock = threading.Lock()
        self._rates: dict[str, RateLimit] = {}
        for topic in (keys.CMD_VEL, keys.TELEOP_CMD_VEL):
            self._rates[topic.path] = RateLimit(rules.rate.max_cmd_vel_per_second, rules.rate.burst_seconds)
        for action in (keys.CMD_NAVIGATE, keys.CMD_TRAJECTORY, keys.CMD_GRIPPER):
            self._rates[action.send_goal.path] = RateLimit(rules.rate.max_goals_per_second, rules.rate.burst_seconds)
        self.monitor = MotionMonitor(
            rules.monitor,
            policy.max_linear,
            policy.max_angular,
            {name: limit.velocity for name, limit in policy.joint_limits.items()},
            decay_per_second=rules.base.max_linear_acceleration / policy.max_linear,
        )
        self._heartbeat = node.publisher(keys.HEARTBEAT)
        self._events = node.publisher(keys.SAFETY_EVENTS)
        self._robot_cmd_vel = node.publisher(keys.ROBOT_CMD_VEL)
        self._stop = threading.Event()

        node.subscribe(keys.ODOM, self._on_odom)
        node.subscribe(keys.JOINT_STATES, self._on_joints)
        node.subscribe(keys.HUMANS, self._on_humans)
        node.subscribe(keys.ESTOP, self._on_estop)
        node.subscribe(keys.CMD_VEL, self._on_cmd_vel)
        node.subscribe(keys.TELEOP_CMD_VEL, self._on_teleop)
        node.serve(keys.RESET, self._on_reset)
        node.serve(keys.PLAN_CHECK, self._on_check_plan)
        self._proxy(keys.CMD_NAVIGATE, keys.ROBOT_NAVIGATE, lambda g: policy.check_navigation(g, self.pose()))
        self._proxy(
            keys.CMD_TRAJECTORY, keys.ROBOT_TRAJECTORY, lambda g: policy.check_trajectory(g, self.joints(), self.pose())
        )
        self._proxy(keys.CMD_GRIPPER, keys.ROBOT_GRIPPER, policy.check_gripper)
        self._beat_thread = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
        self._beat_thread.start()

    def close(self) -> None:
        self._stop.set()
        self._beat_thread.join(timeout=1.0)

    # Events

    def _event(
        self,
        key: str,
        decision: Decision,
        reason: str,
        command: object,
        rule: Rule | None = None,
        checks: tuple[Rule, ...] = (),
        values: dict[str, float] | None = None,
    ) -> None:
        finite = {k: float(v) for k, v in (values or {}).items() if math.isfinite(v)}
        self._events.put(
            SafetyEvent(
                stamp=time.time(),
                key=key,
                decision=decision,
                reason=reason,
                rule=rule,
                checks=list(checks),
                values=finite,
                policy_hash=self.hash,
                command=msgspec.Raw(encode(command) if command is not None else b"null"),
            )
        )
        if decision is Decision.VETOED:
            log.warning("vetoed %s: %s", key, reason)

    def _veto(self, key: str, exc: Vetoed, command: object) -> None:
        self._event(key, Decision.VETOED, str(exc), command, exc.rule, (exc.rule,), exc.values)

    def _approve(self, key: str, verdict: Verdict[Any], command: object) -> None:
        decision = Decision.APPROVED if verdict.clamped_by is None else Decision.CLAMPED
        self._event(key, decision, verdict.note, command, verdict.clamped_by, verdict.checks, verdict.values)

    # Heartbeat, separation and the watchdog

    def _publish_heartbeat(self) -> None:
        # Under one lock, so a beat read before a latch can never be sent after the latched one.
        with self._lock:
            self._seq += 1
            sep = self._separation
            self._heartbeat.put(
                SafetyStatus(
                    seq=self._seq,
                    stamp=time.time(),
                    estop=self.latch.state,
                    speed_scale=sep.scale,
                    speed_reason=sep.reason,
                    policy_hash=self.hash,
                )
            )

    def _beat(self) -> None:
        period = 1.0 / self.config.heartbeat_hz
        next_beat = time.monotonic()
        while not self._stop.is_set():
            try:
                self._update_separation()
                self._watchdog()
            except Exception:  # the heartbeat must go on; a failed update keeps the last limit
                log.exception("separation or watchdog update failed")
            self._publish_heartbeat()
            next_beat += period
            self._stop.wait(max(0.0, next_beat - time.monotonic()))

    def _update_separation(self) -> None:
        humans = self.policy.policy.humans
        seen = self._humans
        if seen is None or time.monotonic() - seen[0] > humans.unseen_after:
            found = separation(None, False, humans)
        elif not seen[1]:
            found = separation(None, True, humans)
        elif (pose := self.pose()) is None:
            found = Separation(humans.reduced_speed_scale, "the robot's pose is unknown: reduced speed")
        else:
            size = self.policy.world.world.robot.base_size
            found = separation(nearest_person(pose, (size.x, size.y), self.hand(pose), seen[1]), True, humans)
        previous = self._separation
        self._separation = found
        if found.scale != previous.scale:
            values = {"scale": found.scale}
            if found.distance is not None:
                values["distance_m"] = found.distance
            reason = found.reason or "no one near: full speed"
            log.info("speed limit: %s", reason)
            self._event(keys.HEARTBEAT.path, Decision.LIMITED, reason, None, Rule.HUMAN_SEPARATION, (), values)

    def hand(self, pose: Pose2D) -> tuple[float, float] | None:
        """The end effector on the floor plan (map frame), from the latest joint states."""
        joints = self.joints()
        if joints is None:
            return None
        point = self.policy.arm.grasp_point([joints[n] for n in self.policy.arm.joint_names])
        mount = self.policy.mount
        x, y = point[0] + mount.x, point[1] + mount.y
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        return pose.x + c * x - s * y, pose.y + s * x + c * y

    def _watchdog(self) -> None:
        """The robot's state stopped arriving while it moved: nothing can be monitored, so stop."""
        max_age = self.policy.policy.monitor.state_max_age
        now = time.monotonic()
        odom, joints = self._odom, self._joints
        if odom is not None and now - odom[0] > max_age:
            moving = abs(odom[1].linear_x) > MOVING or abs(odom[1].angular_z) > MOVING
            self._odom = None
            if moving:
                self._trip(
                    EstopSource.WATCHDOG,
                    Trip(
                        Rule.WATCHDOG,
                        f"no odometry for {now - odom[0]:.2f} s while the base was moving",
                        {"age_s": now - odom[0], "speed_mps": odom[1].linear_x},
                    ),
                )
        if joints is not None and now - joints[0] > max_age:
            moving = any(abs(v) > MOVING for v in joints[1].velocity[: len(ARM_JOINTS)])
            self._joints = None
            if moving:
                self._trip(
                    EstopSource.WATCHDOG,
                    Trip(Rule.WATCHDOG, f"no joint states for {now - joints[0]:.2f} s while the arm was moving", {}),
                )

    def _trip(self, source: EstopSource, trip: Trip) -> None:
        self._latch(source, trip.reason, None, trip.rule, trip.values)

    # E-stop

    def _on_estop(self, msg: EStop) -> None:
        self._latch(msg.source, msg.reason, msg, Rule.ESTOP, {})

    def _latch(self, source: EstopSource, reason: str, command: object, rule: Rule, values: dict[str, float]) -> None:
        if not self.latch.trigger(source, reason):
            return
        # Out of cycle, so the robot hears it now rather than at the next beat; then written down.
        self._publish_heartbeat()
        self._robot_cmd_vel.put(Twist())
        self.latch.save()
        log.warning("E-STOP latched by %s: %s", source, reason)
        self._event(keys.ESTOP.path, Decision.LATCHED, f"by {source}: {reason}", command, rule, (), values)
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
        redacted = msgspec.structs.replace(req, token="***")
        try:
            self.latch.reset(req.operator, req.token)
        except Unauthorized as exc:
            self._event(keys.RESET.path, Decision.VETOED, str(exc), redacted, Rule.OPERATOR, (Rule.OPERATOR,))
            return ResetReply(ok=False, message=str(exc))
        log.warning("e-stop reset by operator %s", req.operator)
        self._publish_heartbeat()
        self._event(keys.RESET.path, Decision.RESET, f"by operator {req.operator}", redacted, None, (Rule.OPERATOR,))
        return ResetReply(ok=True, message=f"e-stop reset by {req.operator}")

    # The robot's state, and the monitors on it

    def _on_odom(self, msg: Odometry) -> None:
        now = time.monotonic()
        self._odom = (now, msg)
        if self.latch.state.latched:
            return
        with self._monitor_lock:
            trip = self.monitor.base(now, msg.linear_x, msg.angular_z, self._separation.scale)
        if trip is None and (zone := self.policy.zone_at(msg.pose.x, msg.pose.y)) is not None:
            trip = Trip(
                Rule.MONITOR_KEEP_OUT,
                f"the base was measured inside keep-out zone '{zone.name}'",
                {"x": msg.pose.x, "y": msg.pose.y},
            )
        if trip is not None:
            self._trip(EstopSource.MONITOR, trip)

    def _on_joints(self, msg: JointState) -> None:
        now = time.monotonic()
        self._joints = (now, msg)
        if self.latch.state.latched or not msg.velocity:
            return
        velocities = dict(zip(msg.name, msg.velocity, strict=False))
        with self._monitor_lock:
            trip = self.monitor.joints(now, velocities, self._separation.scale)
        if trip is not None:
            self._trip(EstopSource.MONITOR, trip)

    def _on_humans(self, msg: PerceivedHumans) -> None:
        people = [Person(h.name, h.pose.x, h.pose.y) for h in msg.humans]
        self._humans = (time.monotonic(), people)

    def pose(self) -> Pose2D | None:
        """The base pose, or None when odometry is missing or stale."""
        odom = self._odom
        if odom is None or time.monotonic() - odom[0] > self.policy.policy.monitor.state_max_age:
            return None
        return odom[1].pose

    def joints(self) -> dict[str, float] | None:
        joints = self._joints
        if joints is None or time.monotonic() - joints[0] > self.policy.policy.monitor.state_max_age:
            return None
        return dict(zip(joints[1].name, joints[1].position, strict=False))

    # Commands

    def _rate_ok(self, key: str, command: object) -> bool:
        if self._rates[key].allow(time.monotonic()):
            return True
        limit = self._rates[key].rate
        exc = Vetoed(f"more than {limit:g} commands a second on {key}", Rule.COMMAND_RATE, limit_hz=limit)
        self._veto(key, exc, command)
        return False

    def _stop_base(self, key: str, exc: Vetoed, twist: Twist) -> None:
        # Dropping it is not enough: the last approved twist would carry on until it expires.
        self._robot_cmd_vel.put(Twist())
        self._event(key, Decision.VETOED, f"{exc}; base stopped", twist, exc.rule, (exc.rule,), exc.values)

    def _on_cmd_vel(self, twist: Twist) -> None:
        self._forward_twist(keys.CMD_VEL, twist, lambda: self.policy.check_cmd_vel(twist, self.pose()))

    def _on_teleop(self, twist: Twist) -> None:
        def check() -> Verdict[Twist]:
            at, previous = self._teleop_sent
            now = time.monotonic()
            # After a pause the base has stopped (the robot drops cmd_vel after half a second).
            if now - at > TELEOP_TIMEOUT:
                previous = Twist()
            step = min(now - at, TELEOP_MAX_STEP)
            verdict = self.policy.check_teleop(twist, self.pose(), previous, step, self._separation.scale)
            self._teleop_sent = (now, verdict.command)
            return verdict

        self._forward_twist(keys.TELEOP_CMD_VEL, twist, check)

    def _forward_twist(self, topic: Topic[Twist], twist: Twist, check: Callable[[], Verdict[Twist]]) -> None:
        key = topic.path
        estop = self.latch.state
        if estop.latched:
            self._veto(key, Vetoed("e-stop latched", Rule.ESTOP), twist)
            return
        if not self._rate_ok(key, twist):
            self._robot_cmd_vel.put(Twist())
            return
        try:
            verdict = check()
        except Vetoed as exc:
            self._stop_base(key, exc, twist)
            return
        self._robot_cmd_vel.put(verdict.command)
        self._approve(key, verdict, verdict.command)

    def _on_check_plan(self, plan: GroundedPlan) -> PlanCheckReply:
        estop = self.latch.state
        try:
            if estop.latched:
                raise Vetoed(f"e-stop latched by {estop.source}: {estop.reason}; an operator must reset it", Rule.ESTOP)
            checks = self.policy.check_plan(plan, self.pose())
        except Vetoed as exc:
            self._veto(keys.PLAN_CHECK.path, exc, plan)
            kind = ErrorKind.ESTOP if estop.latched else ErrorKind.VETOED
            return ServiceError(kind=kind, message=str(exc), stage=Stage.SAFETY)
        self._event(keys.PLAN_CHECK.path, Decision.APPROVED, "; ".join(checks), plan, None, (Rule.PLAN,))
        return PlanApproved(checks=checks)

    def _proxy(
        self, cmd: Action[Any, Any, Any], robot: Action[Any, Any, Any], check: Callable[[Any], Verdict[Any]]
    ) -> None:
        """Serve `cmd`'s five keys: check goals, forward them to `robot`, relay its feedback."""

        def send_goal(req: SendGoal[Any]) -> GoalResponse:
            key = cmd.send_goal.path
            estop = self.latch.state
            try:
                if estop.latched:
                    raise Vetoed(f"e-stop latched by {estop.source}: {estop.reason}", Rule.ESTOP)
                if not self._rates[key].allow(time.monotonic()):
                    limit = self._rates[key].rate
                    raise Vetoed(f"more than {limit:g} goals a second", Rule.COMMAND_RATE, limit_hz=limit)
                verdict = check(req.goal)
            except Vetoed as exc:
                self._veto(key, exc, req)
                return GoalResponse(goal_id=req.goal_id, accepted=False, reason=f"vetoed by safety: {exc}")
            goal = verdict.command
            self._approve(key, verdict, SendGoal(goal_id=req.goal_id, goal=goal))
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
