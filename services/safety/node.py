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
from schemas.common import DECODE_ERRORS, ErrorKind, Pose2D, ServiceError, Stage
from schemas.keys import Action, Topic
from schemas.plan import GroundedPlan, PlanApproved, PlanCheckReply
from schemas.robot import ARM_JOINTS, FollowJointTrajectoryGoal, JointState, Odometry, Twist
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
from services.robotmodel import base_to_map
from services.runtime import Node, decoder, encode
from services.safety.config import SafetyConfig
from services.safety.errors import Unauthorized, Vetoed
from services.safety.latch import EstopLatch
from services.safety.monitor import (
    MotionMonitor,
    PeopleReports,
    Person,
    RateLimit,
    Separation,
    Trip,
    nearest_person,
    separation,
)
from services.safety.policy import FRESH_JOINTS_WAIT, PLAN_RULES, SafetyPolicy, Verdict, base_moving

log = logging.getLogger(__name__)

# Faster than this (m/s, rad/s) counts as moving, for the watchdog.
MOVING = 0.05
# A teleop stream silent this long has stopped the base (the robot holds a cmd_vel for 0.5 s); the
# first message after it may speed up by at most TELEOP_MAX_STEP seconds of acceleration.
TELEOP_TIMEOUT = 0.5
TELEOP_MAX_STEP = 0.1
# Repeated vetoes of a stream for one rule are one event per this many seconds.
REPEAT_WINDOW = 1.0


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
        self._state_lock = threading.Lock()
        self._joints_arrived = threading.Condition(self._state_lock)
        self._people = PeopleReports(rules.humans.unseen_after)
        self._separation = Separation(rules.humans.reduced_speed_scale, "no report of people yet")
        # What was last put on robot/cmd_vel, from any path, and when: teleop speeds up from it.
        self._sent_twist: tuple[float, Twist] = (0.0, Twist())
        self._twist_lock = threading.Lock()
        self._seq = 0
        self._repeats: dict[tuple[str, Rule], tuple[float, int, str]] = {}
        self._repeat_lock = threading.Lock()
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
        # Raw: an e-stop that does not decode still stops the robot.
        self._estop_decoder = decoder(EStop)
        node.subscribe_raw(keys.ESTOP.key(node.robot), self._on_estop_raw)
        node.subscribe(keys.CMD_VEL, self._on_cmd_vel)
        node.subscribe(keys.TELEOP_CMD_VEL, self._on_teleop)
        node.serve(keys.RESET, self._on_reset)
        node.serve(keys.PLAN_CHECK, self._on_check_plan)
        self._proxy(
            keys.CMD_NAVIGATE, keys.ROBOT_NAVIGATE, lambda g: policy.check_navigation(g, self.pose(), self.reach())
        )
        self._proxy(keys.CMD_TRAJECTORY, keys.ROBOT_TRAJECTORY, self._check_trajectory)
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
                    max_linear_speed=self.policy.max_linear * sep.scale,
                    max_angular_speed=self.policy.max_angular * sep.scale,
                    policy_hash=self.hash,
                )
            )

    def _beat(self) -> None:
        period = 1.0 / self.config.heartbeat_hz
        next_beat = time.monotonic()
        while not self._stop.is_set():
            try:
                self._update_separation()
            except Exception as exc:  # the heartbeat goes on, and what cannot be computed stops the robot
                log.exception("speed and separation failed")
                self._set_separation(Separation(0.0, f"speed and separation could not be computed: {exc}"))
            try:
                self._watchdog()
            except Exception:
                log.exception("the watchdog failed")
            self._flush_repeats()
            self._publish_heartbeat()
            next_beat += period
            self._stop.wait(max(0.0, next_beat - time.monotonic()))

    def _update_separation(self) -> None:
        humans = self.policy.policy.humans
        people = self._people.people(time.monotonic())
        if people is None:
            found = separation(None, False, humans)
        elif not people:
            found = separation(None, True, humans)
        elif (pose := self.pose()) is None:
            found = Separation(humans.reduced_speed_scale, "the robot's pose is unknown: reduced speed")
        else:
            size = self.policy.world.world.robot.base_size
            nearest = nearest_person(pose, (size.x, size.y), self.hand(pose), people, humans.person_radius)
            found = separation(nearest, True, humans, self._separation.scale)
        self._set_separation(found)

    def _set_separation(self, found: Separation) -> None:
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
        """The end effector on the floor plan (map frame)."""
        local = self.policy.hand_in_base(self.joints())
        return None if local is None else base_to_map(pose, *local)

    def reach(self) -> float:
        """How far the hand sticks out from the base's centre (unknown: as far as the arm reaches)."""
        return self.policy.reach(self.joints())

    def base_moving(self) -> bool:
        odom = self._odom
        return odom is not None and base_moving(odom[1])

    def _watchdog(self) -> None:
        """The robot's state stopped arriving while it moved: nothing can be monitored, so stop."""
        max_age = self.policy.policy.monitor.state_max_age
        now = time.monotonic()
        with self._state_lock:
            odom, joints = self._odom, self._joints
            if odom is not None and now - odom[0] > max_age:
                self._odom = None
            else:
                odom = None
            if joints is not None and now - joints[0] > max_age:
                self._joints = None
            else:
                joints = None
        if odom is not None and (abs(odom[1].linear_x) > MOVING or abs(odom[1].angular_z) > MOVING):
            age = now - odom[0]
            why = f"no odometry for {age:.2f} s while the base was moving"
            self._trip(
                EstopSource.WATCHDOG,
                Trip(Rule.WATCHDOG, why, {"age_s": age, "speed_mps": odom[1].linear_x, "turn_rps": odom[1].angular_z}),
            )
        if joints is not None:
            fastest = max((abs(v) for v in joints[1].velocity[: len(ARM_JOINTS)]), default=0.0)
            if fastest > MOVING:
                age = now - joints[0]
                why = f"no joint states for {age:.2f} s while the arm was moving"
                self._trip(EstopSource.WATCHDOG, Trip(Rule.WATCHDOG, why, {"age_s": age, "speed_rps": fastest}))

    def _trip(self, source: EstopSource, trip: Trip) -> None:
        self._latch(source, trip.reason, None, trip.rule, trip.values)

    # E-stop

    def _on_estop_raw(self, _key: str, payload: bytes) -> None:
        try:
            msg: EStop = self._estop_decoder.decode(payload)
        except DECODE_ERRORS as exc:
            # Fail closed: someone meant to stop the robot.
            reason = f"an e-stop message that could not be read ({len(payload)} bytes): {exc}"[:1000]
            self._latch("unknown", reason, None, Rule.ESTOP, {})
            return
        self._latch(msg.source, msg.reason, msg, Rule.ESTOP, {})

    def _latch(self, source: str, reason: str, command: object, rule: Rule, values: dict[str, float]) -> None:
        if not self.latch.trigger(source, reason):
            return
        # Out of cycle, so the robot hears it now rather than at the next beat; then written down.
        self._publish_heartbeat()
        self._put_twist(Twist())
        self._persist()
        log.warning("E-STOP latched by %s: %s", source, reason)
        self._event(keys.ESTOP.path, Decision.LATCHED, f"by {source}: {reason}", command, rule, (), values)
        # Queries take time; not on Zenoh's callback thread. The heartbeat already stops the robot.
        threading.Thread(target=self._cancel_forwarded, name="estop-cancel", daemon=True).start()

    def _persist(self) -> bool:
        try:
            self.latch.save()
        except OSError as exc:
            log.error("the e-stop state could not be written (%s): a restart may not remember it", exc)
            return False
        return True

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
        saved = self._persist()
        self._event(keys.RESET.path, Decision.RESET, f"by operator {req.operator}", redacted, None, (Rule.OPERATOR,))
        note = "" if saved else " (the state file could not be written: a restart of safety may come up latched)"
        return ResetReply(ok=True, message=f"e-stop reset by {req.operator}{note}")

    # The robot's state, and the monitors on it

    def _on_odom(self, msg: Odometry) -> None:
        now = time.monotonic()
        with self._state_lock:
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
        with self._state_lock:
            self._joints = (now, msg)
            self._joints_arrived.notify_all()
        if self.latch.state.latched or not msg.velocity:
            return
        velocities = dict(zip(msg.name, msg.velocity, strict=False))
        with self._monitor_lock:
            trip = self.monitor.joints(now, velocities, self._separation.scale)
        if trip is not None:
            self._trip(EstopSource.MONITOR, trip)

    def _on_humans(self, msg: PerceivedHumans) -> None:
        self._people.add(time.monotonic(), [Person(h.name, h.pose.x, h.pose.y) for h in msg.humans])

    def pose(self) -> Pose2D | None:
        """The base pose, or None when odometry is missing or stale."""
        odom = self._odom
        if odom is None or time.monotonic() - odom[0] > self.policy.policy.monitor.state_max_age:
            return None
        return odom[1].pose

    def _check_trajectory(self, goal: FollowJointTrajectoryGoal) -> Verdict[FollowJointTrajectoryGoal]:
        """A trajectory from where the arm is. A goal sent the moment the previous motion ended may
        start where the arm has just stopped, while the latest state here is from a moment before:
        a first point that seems to jump is checked once more against a state measured since."""
        policy = self.policy
        checked = self._joints
        try:
            return policy.check_trajectory(goal, self.joints(), self.pose(), self.base_moving())
        except Vetoed as exc:
            if "jump_rad" not in exc.values or not self._joints_since(checked, FRESH_JOINTS_WAIT):
                raise
        return policy.check_trajectory(goal, self.joints(), self.pose(), self.base_moving())

    def _joints_since(self, checked: tuple[float, JointState] | None, timeout: float) -> bool:
        """Wait for a joint state newer than `checked`; whether one came."""
        with self._joints_arrived:
            return self._joints_arrived.wait_for(lambda: self._joints is not checked, timeout)

    def joints(self) -> dict[str, float] | None:
        joints = self._joints
        if joints is None or time.monotonic() - joints[0] > self.policy.policy.monitor.state_max_age:
            return None
        return dict(zip(joints[1].name, joints[1].position, strict=False))

    # Commands

    def _veto_repeated(self, key: str, exc: Vetoed, command: object) -> None:
        """A stream vetoed for the same rule over and over (e-stop latched, over the rate): the first
        veto is an event, the rest are counted into one event a second (see _flush_repeats)."""
        now = time.monotonic()
        with self._repeat_lock:
            seen = self._repeats.get((key, exc.rule))
            if seen is not None and now - seen[0] < REPEAT_WINDOW:
                self._repeats[(key, exc.rule)] = (seen[0], seen[1] + 1, str(exc))
                return
            self._repeats[(key, exc.rule)] = (now, 0, str(exc))
        self._veto(key, exc, command)

    def _flush_repeats(self) -> None:
        now = time.monotonic()
        with self._repeat_lock:
            due = [(k, v) for k, v in self._repeats.items() if now - v[0] >= REPEAT_WINDOW]
            for k, _ in due:
                del self._repeats[k]
        for (key, rule), (at, count, reason) in due:
            if count:
                why = f"{count} more vetoed like this in the last {now - at:.1f} s: {reason}"
                self._event(key, Decision.VETOED, why, None, rule, (rule,), {"count": float(count)})

    def _estop_veto(self) -> Vetoed | None:
        """Why nothing may move while the e-stop is latched; None when it is not."""
        estop = self.latch.state
        if not estop.latched:
            return None
        return Vetoed(f"e-stop latched by {estop.source}: {estop.reason}; an operator must reset it", Rule.ESTOP)

    def _rate_veto(self, key: str) -> Vetoed | None:
        """The command on `key` over its rate limit; None while within it."""
        limit = self._rates[key]
        if limit.allow(time.monotonic()):
            return None
        return Vetoed(f"more than {limit.rate:g} commands a second on {key}", Rule.COMMAND_RATE, limit_hz=limit.rate)

    def _put_twist(self, twist: Twist) -> None:
        """The only writer of robot/cmd_vel; remembers what was sent (callers hold _twist_lock or not)."""
        self._robot_cmd_vel.put(twist)
        self._sent_twist = (time.monotonic(), twist)

    def _on_cmd_vel(self, twist: Twist) -> None:
        self._forward_twist(
            keys.CMD_VEL, twist, lambda: self.policy.check_cmd_vel(twist, self.pose(), self._separation.scale)
        )

    def _on_teleop(self, twist: Twist) -> None:
        def check() -> Verdict[Twist]:
            # Speed up from what the robot was last told by anyone (a program, a stop, a veto).
            at, previous = self._sent_twist
            now = time.monotonic()
            # After a pause the base has stopped (the robot drops cmd_vel after half a second).
            if now - at > TELEOP_TIMEOUT:
                previous = Twist()
            step = min(now - at, TELEOP_MAX_STEP)
            return self.policy.check_teleop(twist, self.pose(), previous, step, self._separation.scale)

        self._forward_twist(keys.TELEOP_CMD_VEL, twist, check)

    def _forward_twist(self, topic: Topic[Twist], twist: Twist, check: Callable[[], Verdict[Twist]]) -> None:
        key = topic.path
        if refused := self._estop_veto():
            self._veto_repeated(key, refused, twist)
            return
        if refused := self._rate_veto(key):
            self._veto_repeated(key, refused, twist)
            with self._twist_lock:
                self._put_twist(Twist())
            return
        with self._twist_lock:
            try:
                verdict = check()
            except Vetoed as exc:
                # Dropping it is not enough: the last approved twist would carry on until it expires.
                self._put_twist(Twist())
                self._event(key, Decision.VETOED, f"{exc}; base stopped", twist, exc.rule, (exc.rule,), exc.values)
                return
            self._put_twist(verdict.command)
        self._approve(key, verdict, verdict.command)

    def _on_check_plan(self, plan: GroundedPlan) -> PlanCheckReply:
        try:
            if refused := self._estop_veto():
                raise refused
            checks = self.policy.check_plan(plan, self.pose())
        except Vetoed as exc:
            self._veto(keys.PLAN_CHECK.path, exc, plan)
            kind = ErrorKind.ESTOP if exc.rule is Rule.ESTOP else ErrorKind.VETOED
            return ServiceError(kind=kind, message=str(exc), stage=Stage.SAFETY)
        self._event(keys.PLAN_CHECK.path, Decision.APPROVED, "; ".join(checks), plan, None, PLAN_RULES)
        return PlanApproved(checks=checks)

    def _proxy(
        self, cmd: Action[Any, Any, Any], robot: Action[Any, Any, Any], check: Callable[[Any], Verdict[Any]]
    ) -> None:
        """Serve `cmd`'s keys: check goals, forward them to `robot`, relay its feedback and status."""

        def send_goal(req: SendGoal[Any]) -> GoalResponse:
            key = cmd.send_goal.path
            try:
                if refused := self._estop_veto() or self._rate_veto(key):
                    raise refused
                verdict = check(req.goal)
            except Vetoed as exc:
                self._veto(key, exc, req)
                kind = ErrorKind.ESTOP if exc.rule is Rule.ESTOP else ErrorKind.VETOED
                return GoalResponse(goal_id=req.goal_id, accepted=False, reason=f"vetoed by safety: {exc}", kind=kind)
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

        def get_status(req: GetResult) -> Any:
            return self.node.call(robot.get_status, req, timeout=self.config.forward_timeout)

        self.node.serve(cmd.send_goal, send_goal)
        self.node.serve(cmd.cancel_goal, cancel_goal)
        self.node.serve(cmd.get_result, get_result)
        self.node.serve(cmd.get_status, get_status)
        feedback = self.node.publisher(cmd.feedback)
        status = self.node.publisher(cmd.status)
        self.node.subscribe(robot.feedback, feedback.put)
        self.node.subscribe(robot.status, status.put)
