"""Safety's decisions, pure: commands, state reports and ticks in; what to forward, publish and latch out."""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Generic, Protocol, TypeVar

import msgspec
from shapely.geometry import Point

from schemas import keys
from schemas.actions import GoalResponse, GoalStatus, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError, Stage, Vec3
from schemas.incidents import CautionZone, Incident
from schemas.keys import ActionKeys
from schemas.plan import GroundedPlan, PlanApproved, PlanCheckReply
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    JointState,
    NavigateToPoseGoal,
    Odometry,
    Twist,
)
from schemas.safety import (
    ALREADY_LATCHED,
    ApprovalAction,
    ApprovalDecision,
    ApprovalReply,
    ApprovalRequest,
    ApprovalState,
    ControlMode,
    Decision,
    EStop,
    EstopSource,
    ModeReply,
    ModeRequest,
    PendingPlans,
    PlanApproval,
    ResetReply,
    ResetRequest,
    Rule,
    SafetyStatus,
)
from schemas.world import PerceivedHumans
from services.robotmodel import base_to_map
from services.safety.errors import Unauthorized, Vetoed
from services.safety.hazards import (
    MAX_WARNINGS,
    NEAR_LIMIT,
    NO_ZONES,
    ZoneMap,
    plan_places,
    plan_warnings,
    zone_reason,
)
from services.safety.latch import EstopLatch
from services.safety.modes import PLANS_REFUSED, ApprovalBook, ModeFile, plan_lines, replace_approval
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
from services.safety.policy import JOINTS_STAMP, PLAN_RULES, STILL, SafetyPolicy, Verdict, base_moving
from services.safety.shared import SharedFilter, SharedLimits, Surroundings, combine
from services.worldmodel import drive_route

log = logging.getLogger(__name__)

T = TypeVar("T")

# Faster than this (m/s, rad/s) counts as moving, for the watchdog.
MOVING = 0.05
# A teleop stream silent this long has stopped the base (the robot holds a cmd_vel for 0.5 s); the
# first message after it may speed up by at most TELEOP_MAX_STEP seconds of acceleration.
TELEOP_TIMEOUT = 0.5
TELEOP_MAX_STEP = 0.1
# Repeated vetoes of a stream for one rule are one event per this many seconds.
REPEAT_WINDOW = 1.0
# Reset attempts are counted over this many seconds; all identities together may make this many
# times one identity's share (names are whatever a caller says, so one caller can use many).
RESET_WINDOW = 60.0
RESET_SHARES = 3
GoalRuling = SendGoal[Any] | GoalResponse
# Where repeated events are counted: the key, the rule and who asked (the e-stop's source; "" for a veto).
Repeats = tuple[str, Rule, str]
# A plan in these states waits for an operator: pending before its first motion, paused while it ran.
WAITING = (ApprovalState.PENDING, ApprovalState.PAUSED)
# The state a plan must be in for each of an operator's decisions, and the word for it in messages.
DECIDES = {
    ApprovalAction.APPROVE: ((ApprovalState.PENDING,), "approval", "wait for approval"),
    ApprovalAction.DENY: (WAITING, "denial", "wait for an operator"),
    ApprovalAction.PAUSE: ((ApprovalState.APPROVED,), "pause", "run with an approval"),
    ApprovalAction.RESUME: ((ApprovalState.PAUSED,), "resume", "wait paused"),
}
# Why the plans of an executor that went away end.
EXECUTOR_GONE = "the executor went away (its liveliness ended): an approval holds only while its executor runs"


class IncidentMemory(Protocol):
    """What the gate reads of safety's incident store (services/safety/incidents.py), none of which
    waits for its file or computes anything: `fault`: why the store cannot be used ("" when it can);
    `version`: grows with every change; `near`: from its memory; `caution_zones`: the zones its
    writer last computed."""

    @property
    def fault(self) -> str: ...

    @property
    def version(self) -> int: ...

    def near(self, points: Sequence[tuple[float, float]], radius: float, limit: int = NEAR_LIMIT) -> list[Incident]: ...

    def caution_zones(self) -> ZoneMap: ...


@dataclass(frozen=True)
class GateEvent:
    """An event for `safety/events` as the gate decided it; the node stamps and encodes it."""

    key: str
    decision: Decision
    reason: str
    command: object = None
    rule: Rule | None = None
    checks: tuple[Rule, ...] = ()
    values: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Ruling(Generic[T]):
    """What the node does after one input.

    `forward`: what goes on: the twist for robot/cmd_vel (None: nothing), the goal for the robot or
    the refusal for the caller, the reply to a query. `events`: to publish, in order. `latched`: the
    e-stop latched just now: tell the robot at once (a heartbeat, a stop on robot/cmd_vel), write the
    latch down, publish the events `latch_told` gives, then cancel every goal forwarded to the robot.
    `reset`: it was cleared: a heartbeat, write it down, publish the events `latch_told` gives.
    `fresh_joints_may_pass`: a trajectory refused because its first point seems to jump from the
    arm's last known position; decided again on a joint state measured since, it may pass.
    `mode_changed`: a heartbeat, and write the mode down. `cancel_goals`: the mode no longer lets
    the goals under way move the robot: cancel every goal forwarded. `approvals_changed`: wake whoever
    waits for an approval.
    """

    forward: T
    events: tuple[GateEvent, ...] = ()
    latched: bool = False
    reset: bool = False
    fresh_joints_may_pass: bool = False
    mode_changed: bool = False
    cancel_goals: bool = False
    approvals_changed: bool = False


def _veto_event(key: str, exc: Vetoed, command: object) -> GateEvent:
    return GateEvent(key, Decision.VETOED, str(exc), command, exc.rule, (exc.rule,), exc.values)


def _approval(key: str, verdict: Verdict[Any], command: object) -> GateEvent:
    decision = Decision.APPROVED if verdict.clamped_by is None else Decision.CLAMPED
    return GateEvent(key, decision, verdict.note, command, verdict.clamped_by, verdict.checks, verdict.values)


def _positions(joints: JointState | None) -> dict[str, float] | None:
    """Each joint's position by name (None without a joint state)."""
    return None if joints is None else dict(zip(joints.name, joints.position, strict=False))


def _moves(twist: Twist) -> bool:
    return abs(twist.linear_x) > STILL or abs(twist.angular_z) > STILL


def _refusal_kind(exc: Vetoed) -> ErrorKind:
    return ErrorKind.ESTOP if exc.rule is Rule.ESTOP else ErrorKind.VETOED


class AttemptLimit:
    """At most `per_window` failed attempts per identity in any `window` seconds, and `total` for all
    together; `attempt` says how long to wait when a limit is reached (0.0: allowed) and counts the
    attempt if it is a wrong one. A `right` attempt (the right token) is never counted and never held:
    an operator may reset as often as the robot needs, and neither made-up names filling the shared
    limit nor wrong tokens sent under the operator's own name (it is in every event) lock the real
    operator out of a reset or a pause. Not thread-safe: the gate calls it under its lock."""

    def __init__(self, per_window: int, total: int, window: float = RESET_WINDOW) -> None:
        self.per_window = per_window
        self.total = total
        self.window = window
        self._by: dict[str, deque[float]] = {}
        self._all: deque[float] = deque()

    def attempt(self, identity: str, t: float, right: bool = False) -> float:
        for times in (self._all, *self._by.values()):
            while times and t - times[0] >= self.window:
                times.popleft()
        self._by = {k: v for k, v in self._by.items() if v}
        if right:
            return 0.0
        mine = self._by.setdefault(identity, deque())
        full = [times for times, cap in ((mine, self.per_window), (self._all, self.total)) if len(times) >= cap]
        if full:
            # Allowed again once the oldest attempt counted against the full one leaves the window.
            return max(max(times[0] for times in full) + self.window - t, 0.001)
        mine.append(t)
        self._all.append(t)
        return 0.0


class SafetyGate:
    """Every decision safety takes, on inputs the node hands it, at the time of its `clock` (seconds,
    monotonic; a fake one in tests). The gate reads it under its lock, so readings reach it in the
    order they were taken. Its time never runs back: when the clock steps back, the gate's time
    carries on from where it was at the clock's pace (a watchdog is not blind until the clock catches
    up), so ages and ramps are never negative.

    Thread-safe, as Zenoh calls back from several threads: the gate's state (robot state, speed
    scale, last twist sent, repeated vetoes, monitors) is guarded by one lock held only briefly; the
    policy's checks run outside it on a snapshot, so a long plan check never delays a heartbeat. The
    latch, rate limits and people reports guard themselves."""

    def __init__(
        self,
        policy: SafetyPolicy,
        latch: EstopLatch,
        clock: Callable[[], float],
        wall_clock: Callable[[], float],
        max_resets_per_minute: int = 5,
        modes: ModeFile | None = None,
    ) -> None:
        self.policy = policy
        self.latch = latch
        # The control mode (changed only with the operator's token) and, in supervised mode, the plans
        # waiting for an operator or running with one's approval (guarded by the gate's lock).
        self.modes = modes if modes is not None else ModeFile(None)
        # Which goal of a robot action may still run (the node's, which knows what it forwarded);
        # by default none: a gate alone forwards nothing.
        self.running: Callable[[ActionKeys[Any, Any, Any]], str | None] = lambda _action: None
        # Which goal of a robot action was forwarded and is not known to have ended, from the node's
        # notes alone (the robot is not asked: a twist may not wait on it); by default none.
        self.noted: Callable[[ActionKeys[Any, Any, Any]], str | None] = lambda _action: None
        self._approvals = ApprovalBook()
        # How often the executor went away, and whether it is away now (under the lock): an ask that
        # came while it was away, or was checked while it went, is its ask. Counted alive until its
        # liveliness is seen to end: a token already held when safety starts is heard a moment later,
        # perhaps after the first ask, and only an executor alive while safety watched can ask.
        self._executor_gone = 0
        self._executor_away = False
        # The latch's changes (latched, reset) in the order decided, by their event's id, with whether
        # the event is out, kept until the thread that decided one has written it down (see latch_told).
        self._changes: dict[int, tuple[GateEvent, bool]] = {}
        self._clock = clock
        # Only stamps the latch's state (when it latched, when it was reset), never a decision.
        self._wall_clock = wall_clock
        rules = policy.policy
        self.hash = policy.limits.hash
        self._lock = threading.Lock()
        self._now = -math.inf
        self._offset = 0.0
        self._odom: tuple[float, Odometry] | None = None
        self._joints: tuple[float, JointState] | None = None
        # The hand's reach from the base's centre, and the joint state it was worked out from (no lock:
        # threads racing only work it out twice).
        self._reach_of: tuple[JointState | None, float] | None = None
        self._people = PeopleReports(rules.humans.unseen_after)
        self._separation = Separation(rules.humans.reduced_speed_scale, "no report of people yet")
        # What was last put on robot/cmd_vel, from any path, and when: teleop speeds up from it.
        # Never sent counts as sent long ago.
        self._sent_twist: tuple[float, Twist] = (-math.inf, Twist())
        self._repeats: dict[Repeats, tuple[float, int, str]] = {}
        self._resets = AttemptLimit(max_resets_per_minute, RESET_SHARES * max_resets_per_minute)
        self._rates: dict[str, RateLimit] = {}
        for topic in (keys.CMD_VEL, keys.TELEOP_CMD_VEL):
            self._rates[topic.path] = RateLimit(rules.rate.max_cmd_vel_per_second, rules.rate.burst_seconds)
        for action in (keys.CMD_NAVIGATE, keys.CMD_TRAJECTORY, keys.CMD_GRIPPER):
            self._rates[action.send_goal.path] = RateLimit(rules.rate.max_goals_per_second, rules.rate.burst_seconds)
        # Shared mode's teleop filter, over the walls, furniture and keep-out zones (people join per twist).
        size = policy.base_size
        self.shared = SharedFilter(
            SharedLimits(
                horizon=rules.base.cmd_vel_horizon,
                braking=rules.base.max_linear_acceleration,
                max_angular=policy.max_angular,
                length=size.x,
                width=size.y,
                radius=policy.radius,
            )
        )
        self._fixed_obstacles = list(policy.obstacles)
        self._zones = [(f"keep-out zone '{z.name}'", policy.zone_shapes[z.id]) for z in policy.limits.keep_out]
        self.monitor = MotionMonitor(
            rules.monitor,
            policy.max_linear,
            policy.max_angular,
            {name: limit.velocity for name, limit in policy.joint_limits.items()},
            decay_per_second=rules.base.max_linear_acceleration / policy.max_linear,
        )
        # Safety's memory of incidents (set_incidents), the caution zones last read from it, the zone
        # the base was last in, the last failure logged.
        self._incidents: IncidentMemory | None = None
        self._zone_map: ZoneMap = NO_ZONES
        self._in_zone: CautionZone | None = None
        self._memory_error = ""

    def _advance(self) -> float:
        """The gate's time now; call with the lock held. The clock is read here, under the lock: a
        reading taken before another thread's cannot reach the gate after it."""
        now = self._clock()
        if now + self._offset < self._now:
            # Only a clock that stepped back reads earlier here: carry on from where the gate was.
            self._offset = self._now - now
        self._now = max(self._now, now + self._offset)
        return self._now

    def _time(self) -> float:
        """The gate's time now. Public methods read it once into `t`; the private ones take `t`."""
        with self._lock:
            return self._advance()

    # What safety knows of the robot

    @property
    def separation(self) -> Separation:
        """The speed allowed near people, as of the last tick."""
        with self._lock:
            return self._separation

    def pose(self) -> Pose2D | None:
        """The base pose, or None when odometry is missing or stale."""
        return self._pose(self._time())

    def joint_positions(self) -> dict[str, float] | None:
        """The arm's joint positions, or None when joint states are missing or stale."""
        return self._joint_positions(self._time())

    def _pose(self, t: float) -> Pose2D | None:
        with self._lock:
            odom = self._odom
        if odom is None or t - odom[0] > self.policy.policy.monitor.state_max_age:
            return None
        return odom[1].pose

    def _joint_positions(self, t: float) -> dict[str, float] | None:
        return _positions(self._joint_state(t))

    def _joint_state(self, t: float) -> JointState | None:
        """The latest joint state, or None when it is missing or stale."""
        with self._lock:
            joints = self._joints
        if joints is None or t - joints[0] > self.policy.policy.monitor.state_max_age:
            return None
        return joints[1]

    def hand_on_map(self, pose: Pose2D, joints: dict[str, float] | None) -> Vec3 | None:
        """The grasp point on the map, with its height (None when a joint position is unknown)."""
        policy = self.policy
        names = policy.arm.joint_names
        if joints is None or not all(n in joints for n in names):
            return None
        point = policy.arm.grasp_point([joints[n] for n in names])
        x, y = base_to_map(pose, float(point[0]) + policy.mount.x, float(point[1]) + policy.mount.y)
        return Vec3(x=x, y=y, z=float(point[2]) + policy.mount.z)

    def _reach(self, t: float) -> float:
        """How far the hand sticks out from the base's centre (unknown: as far as the arm reaches).
        Worked out once per joint state: a teleop stream asks far more often than states come."""
        joints = self._joint_state(t)
        known = self._reach_of
        if known is not None and known[0] is joints:
            return known[1]
        reach = self.policy.reach(_positions(joints))
        self._reach_of = (joints, reach)
        return reach

    def _base_moving(self) -> bool:
        with self._lock:
            odom = self._odom
        return odom is not None and base_moving(odom[1])

    # State reports, and the monitors on them

    def odometry(self, msg: Odometry) -> Ruling[None]:
        with self._lock:
            t = self._advance()
            self._odom = (t, msg)
            if self.latch.state.latched:
                return Ruling(None)
            trip = self.monitor.base(t, msg.linear_x, msg.angular_z, self._separation.scale)
        if trip is None and (zone := self.policy.zone_at(msg.pose.x, msg.pose.y)) is not None:
            trip = Trip(
                Rule.MONITOR_KEEP_OUT,
                f"the base was measured inside keep-out zone '{zone.name}'",
                {"x": msg.pose.x, "y": msg.pose.y},
            )
        return Ruling(None) if trip is None else self._trip(EstopSource.MONITOR, trip, t)

    def joint_state(self, msg: JointState) -> Ruling[None]:
        with self._lock:
            t = self._advance()
            self._joints = (t, msg)
            if self.latch.state.latched or not msg.velocity:
                return Ruling(None)
            velocities = dict(zip(msg.name, msg.velocity, strict=False))
            trip = self.monitor.joints(t, velocities, self._separation.scale)
        return Ruling(None) if trip is None else self._trip(EstopSource.MONITOR, trip, t)

    def humans(self, msg: PerceivedHumans) -> None:
        self._people.add(self._time(), [Person(h.name, h.pose.x, h.pose.y) for h in msg.humans])

    # The clock's tick: separation, the watchdog, repeated vetoes

    def tick(self) -> Ruling[None]:
        """Once a heartbeat: the speed allowed near people, the watchdog, the counts of repeated vetoes."""
        t = self._time()
        events: list[GateEvent] = []
        try:
            found = self._find_separation(t)
        except Exception as exc:  # the heartbeat goes on, and what cannot be computed stops the robot
            log.exception("speed and separation failed")
            found = Separation(0.0, f"speed and separation could not be computed: {exc}")
        found, zone = self._with_caution(found, t)
        events.extend(self._set_separation(found, zone))
        latched = False
        try:
            for trip in self._watchdog(t):
                ruling = self._trip(EstopSource.WATCHDOG, trip, t)
                latched = latched or ruling.latched
                events.extend(ruling.events)
        except Exception:
            log.exception("the watchdog failed")
        events.extend(self._flush_repeats(t))
        return Ruling(None, tuple(events), latched=latched)

    def status(self, seq: int, stamp: float) -> SafetyStatus:
        """The heartbeat's content: the latch, and the speed allowed now."""
        sep = self.separation
        return SafetyStatus(
            seq=seq,
            stamp=stamp,
            estop=self.latch.state,
            speed_scale=sep.scale,
            speed_reason=sep.reason,
            max_linear_speed=self.policy.max_linear * sep.scale,
            max_angular_speed=self.policy.max_angular * sep.scale,
            policy_hash=self.hash,
            mode=self.modes.mode,
        )

    def _find_separation(self, t: float) -> Separation:
        humans = self.policy.policy.humans
        if self._people.flooded(t):
            # A report not kept may have had someone beside the robot.
            why = (
                f"more than {self._people.limit} people and reports came within {humans.unseen_after:g} s; "
                "the ones beyond were not counted: paused"
            )
            return Separation(0.0, why)
        people = self._people.people(t)
        if people is None:
            return separation(None, False, humans)
        if not people:
            return separation(None, True, humans)
        if (pose := self._pose(t)) is None:
            # People reported and no distance to them to be had: as near as can be.
            return Separation(0.0, "people are reported and the robot's pose is unknown: paused")
        size = self.policy.world.world.robot.base_size
        joints = self._joint_positions(t)
        hand = self.hand_on_map(pose, joints)
        # Joints unknown: the arm may be held out anywhere within its full reach, as navigation assumes.
        reach = 0.0 if hand is not None else self.policy.reach(joints)
        at = None if hand is None else (hand.x, hand.y)
        nearest = nearest_person(pose, (size.x, size.y), at, people, humans.person_radius, reach)
        found = separation(nearest, True, humans, self.separation.scale)
        if hand is not None or not found.reason:
            return found
        why = f"{found.reason} (the arm's joints are unknown: counted as reaching out {reach:.2f} m)"
        return replace(found, reason=why)

    def _set_separation(self, found: Separation, zone: CautionZone | None = None) -> list[GateEvent]:
        """The scale in force from now; `zone`: the caution zone that decided it, if one did."""
        with self._lock:
            previous, self._separation = self._separation, found
        if found.scale == previous.scale:
            return []
        values = {"scale": found.scale}
        if found.distance is not None:
            values["distance_m"] = found.distance
        rule = Rule.HUMAN_SEPARATION
        if zone is not None:
            rule = Rule.CAUTION_ZONE
            values.update(zone_x=zone.x, zone_y=zone.y, zone_radius_m=zone.radius, zone_count=float(zone.count))
        reason = found.reason or "no one near: full speed"
        log.info("speed limit: %s", reason)
        return [GateEvent(keys.HEARTBEAT.path, Decision.LIMITED, reason, None, rule, (), values)]

    # Safety's memory of incidents: only ever more careful

    def set_incidents(self, store: IncidentMemory | None) -> None:
        """The incident store the caution zones and the plan check's warnings come from (None: none).
        Without one, or with one that has a fault, the gate decides exactly as it would without."""
        with self._lock:
            self._incidents = store
            self._zone_map = NO_ZONES
            self._in_zone = None
        self.refresh_zones()

    def refresh_zones(self) -> ZoneMap:
        """The caution zones in force: the ones the store's writer last computed, read without waiting
        (goals, plan checks and the heartbeat's tick alike; nothing here computes them). A store that
        fails keeps the zones read last (none, if it never answered): forgetting them would loosen."""
        with self._lock:
            store, last = self._incidents, self._zone_map
        if store is None:
            return NO_ZONES
        try:
            zones = store.caution_zones()
        except Exception as exc:
            if str(exc) != self._memory_error:  # once, not at every tick
                self._memory_error = str(exc)
                log.exception("the caution zones could not be read; those read last stay in force")
            return last
        if zones is not last:
            with self._lock:
                if self._incidents is store:
                    self._zone_map = zones
            if last is not NO_ZONES or zones.zones:
                log.info("caution zones in force: %d (incident store version %d)", len(zones), store.version)
        return zones

    def _zone_scale(self) -> float:
        """However the store says it, a zone never slows less than the policy asks."""
        return self.policy.policy.incidents.caution_speed_scale

    def _with_caution(self, found: Separation, t: float) -> tuple[Separation, CautionZone | None]:
        """`found`, or the caution zone's lower scale while the base (its centre within the zone's
        radius grown by the half-diagonal) is in one; the zone, when it decided. Leaving a zone takes
        the separation's `release_margin` more, so its edge does not flip the speed back and forth.
        With the pose unknown, the zone the base was last in (while it still stands) holds."""
        try:
            zones = self.refresh_zones()
            with self._lock:
                previous = self._in_zone

            def same(z: CautionZone) -> bool:
                assert previous is not None
                return (z.x, z.y) == (previous.x, previous.y) or z.incidents[:1] == previous.incidents[:1]

            pose = self._pose(t) if zones.zones else None
            if pose is None:
                # Stale odometry says nothing of the base having left: dropping the zone would loosen.
                kept = previous if previous is not None and any(map(same, zones.zones)) else None
                with self._lock:
                    self._in_zone = kept
                return self._caution_limited(found, kept)
            half = self.policy.world.base_radius
            zone = zones.at(pose.x, pose.y, half, self._zone_scale())
            if zone is None and previous is not None:
                margin = half + self.policy.policy.humans.release_margin
                zone = zones.at(pose.x, pose.y, margin, self._zone_scale(), same)
            with self._lock:
                self._in_zone = zone
        except Exception:
            log.exception("the caution zone check failed; the limits apply as without one")
            return found, None
        return self._caution_limited(found, zone)

    @staticmethod
    def _caution_limited(found: Separation, zone: CautionZone | None) -> tuple[Separation, CautionZone | None]:
        if zone is None or zone.speed_scale >= found.scale:
            return found, None
        return Separation(zone.speed_scale, zone_reason(zone), found.distance, found.person), zone

    def _slower_through_zones(self, verdict: Verdict[NavigateToPoseGoal]) -> Verdict[NavigateToPoseGoal]:
        """A route that passes through a caution zone is driven at its scale of the limits all the way
        (the goal's max_speed and max_turn_rate only ever lowered): slower before the base is in it."""
        goal = verdict.command
        try:
            zones = self.refresh_zones()
            if not zones.zones or goal.start is None:
                return verdict
            points = [(goal.start.x, goal.start.y), *drive_route(goal.start, goal.path, goal.pose)]
            zone = zones.on_route(points, self.policy.world.base_radius, self._zone_scale())
        except Exception:
            log.exception("the caution zone check of a route failed; the limits apply as without one")
            return verdict
        if zone is None:
            return verdict
        speed = min(goal.max_speed or self.policy.max_linear, self.policy.max_linear * zone.speed_scale)
        turn = min(goal.max_turn_rate or self.policy.max_angular, self.policy.max_angular * zone.speed_scale)
        if speed >= (goal.max_speed or math.inf) and turn >= (goal.max_turn_rate or math.inf):
            return verdict
        goal = msgspec.structs.replace(goal, max_speed=speed, max_turn_rate=turn)
        values = {
            **verdict.values,
            "speed_mps": speed,
            "turn_rps": turn,
            "caution_scale": zone.speed_scale,
            "zone_x": zone.x,
            "zone_y": zone.y,
        }
        note = f"the route passes a {zone_reason(zone)}: driven at {speed:.2f} m/s, {turn:.2f} rad/s at most"
        return Verdict(goal, (*verdict.checks, Rule.CAUTION_ZONE), values, Rule.CAUTION_ZONE, note)

    def _plan_warnings(self, plan: GroundedPlan) -> list[str]:
        """Earlier incidents near the places the plan sends the base and the hand, and the caution
        zones they are in: never a refusal. A store with a fault says so first (what it still holds
        in memory follows)."""
        with self._lock:
            store = self._incidents
        if store is None:
            return []
        unread = "safety's incident memory has a fault ({}): earlier incidents may be missing here"
        try:
            faults = [unread.format(store.fault)] if store.fault else []
            places = plan_places(plan)
            if not places:
                return faults
            rules = self.policy.policy.incidents
            points = [(p.x, p.y) for p in places]
            incidents = store.near(points, rules.warn_radius, limit=NEAR_LIMIT)
            zones = self.refresh_zones()
            half = self.policy.world.base_radius
            now = self._wall_clock()
            cap = MAX_WARNINGS - len(faults)
            return [
                *faults,
                *plan_warnings(places, incidents, zones, rules.warn_radius, half, now, cap, self._zone_scale()),
            ]
        except Exception as exc:
            log.exception("the plan's places could not be looked up in the incident memory")
            return [unread.format(exc)]

    def _watchdog(self, t: float) -> list[Trip]:
        """The robot's state stopped arriving while it moved: nothing can be monitored, so stop.
        A state exactly `state_max_age` old still counts; a stale one is forgotten once reported."""
        max_age = self.policy.policy.monitor.state_max_age
        with self._lock:
            odom, joints = self._odom, self._joints
            if odom is not None and t - odom[0] > max_age:
                self._odom = None
            else:
                odom = None
            if joints is not None and t - joints[0] > max_age:
                self._joints = None
            else:
                joints = None
        trips = []
        if odom is not None and (abs(odom[1].linear_x) > MOVING or abs(odom[1].angular_z) > MOVING):
            age = t - odom[0]
            why = f"no odometry for {age:.2f} s while the base was moving"
            values = {"age_s": age, "speed_mps": odom[1].linear_x, "turn_rps": odom[1].angular_z}
            trips.append(Trip(Rule.WATCHDOG, why, values))
        if joints is not None:
            fastest = max((abs(v) for v in joints[1].velocity[: len(ARM_JOINTS)]), default=0.0)
            if fastest > MOVING:
                age = t - joints[0]
                why = f"no joint states for {age:.2f} s while the arm was moving"
                trips.append(Trip(Rule.WATCHDOG, why, {"age_s": age, "speed_rps": fastest}))
        return trips

    def _veto_repeated(self, key: str, exc: Vetoed, command: object, t: float) -> list[GateEvent]:
        """A stream vetoed for the same rule over and over (e-stop latched, over the rate): the first
        veto is an event, the rest within REPEAT_WINDOW are counted into one event (see _flush_repeats)."""
        counted = self._repeated((key, exc.rule, ""), str(exc), t)
        return [] if counted is None else [*counted, _veto_event(key, exc, command)]

    def _repeated(self, slot: Repeats, reason: str, t: float) -> list[GateEvent] | None:
        """None: counted into the window `slot` has open. Else this one opens a window: the count of
        the last window's rest first, when a tick did not publish it (counted at t, not lost)."""
        with self._lock:
            seen = self._repeats.get(slot)
            if seen is not None and t - seen[0] < REPEAT_WINDOW:
                self._repeats[slot] = (seen[0], seen[1] + 1, reason)
                return None
            self._repeats[slot] = (t, 0, reason)
        return [] if seen is None else self._count_event(slot, seen, t)

    def _flush_repeats(self, t: float) -> list[GateEvent]:
        with self._lock:
            due = [(k, v) for k, v in self._repeats.items() if t - v[0] >= REPEAT_WINDOW]
            for k, _ in due:
                del self._repeats[k]
        return [event for slot, seen in due for event in self._count_event(slot, seen, t)]

    @staticmethod
    def _count_event(slot: Repeats, seen: tuple[float, int, str], t: float) -> list[GateEvent]:
        key, rule, source = slot
        at, count, reason = seen
        if not count:
            return []
        values = {"count": float(count)}
        if key == keys.ESTOP.path:
            why = f"{count} more asked for by {source} while latched in the last {t - at:.1f} s, the last {reason}"
            return [GateEvent(key, Decision.LATCHED, why, None, rule, (), {**values, ALREADY_LATCHED: 1.0})]
        why = f"{count} more vetoed like this in the last {t - at:.1f} s: {reason}"
        return [GateEvent(key, Decision.VETOED, why, None, rule, (rule,), values)]

    # The e-stop

    def estop(self, msg: EStop) -> Ruling[None]:
        return self._latch(msg.source, msg.reason, msg, Rule.ESTOP, {}, self._time())

    def unreadable_estop(self, size: int, error: str) -> Ruling[None]:
        """Fail closed: someone meant to stop the robot."""
        reason = f"an e-stop message that could not be read ({size} bytes): {error}"[:1000]
        return self._latch("unknown", reason, None, Rule.ESTOP, {}, self._time())

    def _trip(self, source: EstopSource, trip: Trip, t: float) -> Ruling[None]:
        return self._latch(source, trip.reason, None, trip.rule, trip.values, t)

    def _latch(
        self, source: str, reason: str, command: object, rule: Rule, values: dict[str, float], t: float
    ) -> Ruling[None]:
        event = GateEvent(keys.ESTOP.path, Decision.LATCHED, f"by {source}: {reason}", command, rule, (), values)
        with self._lock:
            # Under the gate's lock, as a reset is: each is decided before the other.
            latched, held = self.latch.request(source, reason, self._wall_clock())
            if latched:
                self._sent_twist = (t, Twist())
                self._changes[id(event)] = (event, False)
        if not latched:
            # The latch stays as the first one set it; who else asked, and why, is recorded (the first
            # reason may be stale by now). A flood from one source is one event and a count.
            why = f"by {source}: {reason}; already latched by {held.source}: {held.reason}"
            if (counted := self._repeated((keys.ESTOP.path, rule, source), why, t)) is None:
                return Ruling(None)
            values = {**values, ALREADY_LATCHED: 1.0}
            again = GateEvent(keys.ESTOP.path, Decision.LATCHED, why, command, rule, (), values)
            return Ruling(None, (*counted, again))
        log.warning("E-STOP latched by %s: %s", source, reason)
        return Ruling(None, (event,), latched=True)

    def latch_told(self, events: tuple[GateEvent, ...]) -> tuple[GateEvent, ...]:
        """A latching or resetting ruling's `events` to publish now that the latch is written down:
        the latch's changes decided before its own and not out yet, then its own unless one decided
        later has published it, then the rest. Each thread writes its change down before publishing
        it; published by each thread alone, a reset decided while a latch was written down came out
        before it (or a latch after a reset it followed), and the timeline showed the wrong state."""
        with self._lock:
            own = {id(e) for e in events if id(e) in self._changes}
            left = set(own)
            told: list[GateEvent] = []
            for key, (event, out) in list(self._changes.items()):
                if not left:
                    break
                if not out:
                    told.append(event)
                    self._changes[key] = (event, True)
                if key in left:
                    left.discard(key)
                    del self._changes[key]
        return (*told, *(e for e in events if id(e) not in own))

    def reset(self, req: ResetRequest) -> Ruling[ResetReply]:
        """Clear the latch with the operator's token; the token never leaves in an event."""
        redacted = msgspec.structs.replace(req, token="***")
        with self._lock:
            t = self._advance()
            # Wrong tokens are counted; the right one only waits out its name's lockout.
            wait = self._resets.attempt(req.operator, t, right=self.latch.accepts(req.token))
        if wait > 0.0:
            # A name with too many wrong guesses is locked out for a while, even with the right token.
            limit = self._resets.per_window
            why = (
                f"reset refused for '{req.operator}': too many attempts (at most {limit} a minute per operator, "
                f"{self._resets.total} for all); try again in {math.ceil(wait)} s"
            )
            values = {"retry_after_s": wait, "limit_per_minute": float(limit)}
            event = GateEvent(keys.RESET.path, Decision.VETOED, why, redacted, Rule.OPERATOR, (Rule.OPERATOR,), values)
            return Ruling(ResetReply(ok=False, message=why), (event,))
        event = GateEvent(
            keys.RESET.path, Decision.RESET, f"by operator {req.operator}", redacted, None, (Rule.OPERATOR,)
        )
        try:
            with self._lock:
                # Under the gate's lock, as a latch is set: each is decided before the other.
                self.latch.reset(req.operator, req.token, self._wall_clock())
                self._changes[id(event)] = (event, False)
        except Unauthorized as exc:
            refused = GateEvent(keys.RESET.path, Decision.VETOED, str(exc), redacted, Rule.OPERATOR, (Rule.OPERATOR,))
            return Ruling(ResetReply(ok=False, message=str(exc)), (refused,))
        log.warning("e-stop reset by operator %s", req.operator)
        return Ruling(ResetReply(ok=True, message=f"e-stop reset by {req.operator}"), (event,), reset=True)

    def _estop_veto(self) -> Vetoed | None:
        """Why nothing may move while the e-stop is latched; None when it is not."""
        estop = self.latch.state
        if not estop.latched:
            return None
        return Vetoed(f"e-stop latched by {estop.source}: {estop.reason}; an operator must reset it", Rule.ESTOP)

    def _rate_veto(self, key: str, t: float) -> Vetoed | None:
        """The command on `key` over its rate limit; None while within it."""
        limit = self._rates[key]
        if limit.allow(t):
            return None
        return Vetoed(f"more than {limit.rate:g} commands a second on {key}", Rule.COMMAND_RATE, limit_hz=limit.rate)

    # Commands: velocities

    def cmd_vel(self, twist: Twist) -> Ruling[Twist | None]:
        """A velocity from a program: over a limit it is refused and the base stopped."""

        def check(t: float) -> Verdict[Twist]:
            return self.policy.check_cmd_vel(twist, self._pose(t), self.separation.scale, self._reach(t))

        # A stop is never refused by the mode: only motion is.
        moves = twist.linear_x != 0.0 or twist.angular_z != 0.0
        mode_veto = self._mode_veto() if moves else None
        return self._twist(keys.CMD_VEL.path, twist, check, self._time(), mode_veto, self._arm_goal_veto)

    def teleop(self, twist: Twist) -> Ruling[Twist | None]:
        """A velocity from a person: clamped to the limits, and speeding up from what was last sent."""

        def check(t: float) -> Verdict[Twist]:
            # Speed up from what the robot was last told by anyone (a program, a stop, a veto).
            with self._lock:
                at, previous = self._sent_twist
            # After a pause the base has stopped (the robot drops cmd_vel after half a second).
            if t - at > TELEOP_TIMEOUT:
                previous = Twist()
            step = min(t - at, TELEOP_MAX_STEP)
            if self.modes.mode is ControlMode.SHARED:
                return self._shared_teleop(twist, previous, step, t)
            return self.policy.check_teleop(twist, self._pose(t), previous, step, self.separation.scale, self._reach(t))

        return self._twist(keys.TELEOP_CMD_VEL.path, twist, check, self._time())

    def _shared_teleop(self, twist: Twist, previous: Twist, step: float, t: float) -> Verdict[Twist]:
        """Shared mode: the person's twist slowed and steered off obstacles and people (shared.py), then
        clamped and ramped as in direct mode, then guarded once more as it will be sent (a ramped turn
        bends the path); a twist the guard changed is held to the horizon's check again, or refused
        (the base stopped). The event says what the filter did (`shared` in its values)."""
        pose, scale, reach = self._pose(t), self.separation.scale, self._reach(t)
        if pose is None:
            # check_teleop refuses driving without a pose; a turn in place cannot be checked either.
            return self.policy.check_teleop(Twist(linear_x=twist.linear_x), None, previous, step, scale, reach)
        radius = self.policy.policy.humans.person_radius
        people = [(f"person {p.name}", Point(p.x, p.y).buffer(radius)) for p in self._people.people(t) or []]
        around = Surroundings(obstacles=[*self._fixed_obstacles, *people], zones=self._zones)
        shaped = self.shared.shape(twist, pose, around, scale)
        verdict = self.policy.check_teleop(shaped.twist, pose, previous, step, scale, reach)
        guarded = self.shared.guard(verdict.command, pose, around)
        if guarded.changed:
            # The guard keeps only the base off things; a slower or straighter path than the one
            # checked can still take the hand held out into a keep-out zone.
            try:
                self.policy.check_horizon(guarded.twist, pose, reach)
            except Vetoed as exc:
                raise Vetoed(
                    f"shared: kept off {guarded.nearest or 'an obstacle'}, {exc}", exc.rule, **exc.values
                ) from exc
        done = combine(shaped, guarded)
        values = {**verdict.values, **done.values, "requested_mps": twist.linear_x, "requested_rps": twist.angular_z}
        checks = (*verdict.checks, Rule.OBSTACLE, Rule.KEEP_OUT)
        if not done.changed:
            return Verdict(done.twist, checks, values, verdict.clamped_by, verdict.note)
        zone = done.nearest is not None and done.nearest.startswith("keep-out zone")
        # Slower only by the separation scale, or also by an obstacle: the rule says which.
        cut = abs(shaped.twist.linear_x) < abs(twist.linear_x) * scale - 1e-9
        obstacle = guarded.changed or shaped.deflected or cut
        rule = verdict.clamped_by or ((Rule.KEEP_OUT if zone else Rule.OBSTACLE) if obstacle else Rule.HUMAN_SEPARATION)
        note = "; ".join(n for n in (verdict.note, done.note) if n)
        return Verdict(done.twist, checks, values, rule, note)

    def _twist(
        self,
        key: str,
        twist: Twist,
        check: Callable[[float], Verdict[Twist]],
        t: float,
        mode_veto: Vetoed | None = None,
        unless: Callable[[], Vetoed | None] | None = None,
    ) -> Ruling[Twist | None]:
        """The twist to put on robot/cmd_vel, if any. The node puts it before the next twist is
        decided: the teleop ramp starts from what was sent last. `mode_veto`: the control mode refuses
        this motion (the base is stopped). `unless`: what refuses a twist that moves, asked as it is
        noted as sent (see _sent)."""
        if refused := self._estop_veto():
            return Ruling(None, tuple(self._veto_repeated(key, refused, twist, t)))
        if mode_veto is not None:
            return Ruling(self._sent(Twist(), t), tuple(self._veto_repeated(key, mode_veto, twist, t)))
        if refused := self._rate_veto(key, t):
            events = self._veto_repeated(key, refused, twist, t)
            return Ruling(self._sent(Twist(), t), tuple(events))
        try:
            verdict = check(t)
            sent = self._sent(verdict.command, t, unless)
        except Vetoed as exc:
            # Dropping it is not enough: the last approved twist would carry on until it expires.
            event = GateEvent(key, Decision.VETOED, f"{exc}; base stopped", twist, exc.rule, (exc.rule,), exc.values)
            return Ruling(self._sent(Twist(), t), (event,))
        return Ruling(sent, (_approval(key, verdict, verdict.command),))

    def _sent(self, twist: Twist, t: float, unless: Callable[[], Vetoed | None] | None = None) -> Twist:
        """Note `twist` as the last sent, unless it moves and `unless` refuses it (raised). Asked in
        the same hold of the lock as the note: a trajectory, noted by the node before it is decided,
        either is seen here or sees this twist (_twist_may_drive), so of the two at once one is refused."""
        with self._lock:
            if unless is not None and _moves(twist) and (refused := unless()) is not None:
                raise refused
            self._sent_twist = (t, twist)
        return twist

    def _arm_goal_veto(self) -> Vetoed | None:
        """A program's twist while an arm trajectory forwarded may still run: the arm's path was
        checked from where the base stood, and the hand's reach on the way is not the one measured now."""
        if (goal_id := self.noted(keys.ROBOT_TRAJECTORY)) is None:
            return None
        return Vetoed(
            f"an arm trajectory (goal {goal_id}) may still be under way: the arm and the base do not move at "
            "once; send this once it has ended and its result is fetched",
            Rule.ONE_MOTION,
        )

    def _twist_may_drive(self, t: float) -> None:
        """Refused while a twist put on robot/cmd_vel may still drive the base: the robot holds one for
        up to the horizon, and a base just told to move still stands in its odometry (base_still)."""
        with self._lock:
            at, twist = self._sent_twist
        held = self.policy.policy.base.cmd_vel_horizon
        if _moves(twist) and t - at <= held:
            raise Vetoed(
                f"the base was sent a cmd_vel of {twist.linear_x:g} m/s, {twist.angular_z:g} rad/s "
                f"{max(0.0, t - at):.2f} s ago and may still be moving (the robot holds one for up to {held:g} s): "
                "the arm and the base do not move at once; stop the base first",
                Rule.ONE_MOTION,
                speed_mps=twist.linear_x,
                turn_rps=twist.angular_z,
                age_s=max(0.0, t - at),
            )

    def stopped(self) -> None:
        """The node put a stop on robot/cmd_vel (a latch, a pause, a mode that stops programs):
        teleop speeds up from standstill, not from the twist the stop cut off."""
        with self._lock:
            self._sent_twist = (self._advance(), Twist())

    # Commands: goals and plans

    def _one_motion(self, other: ActionKeys[Any, Any, Any], what: str) -> None:
        """The arm and the base never move at once: refused while a goal of `other` may still run
        (`running`, which the node answers from the goals it forwarded and the robot's word on them).
        Odometry alone let a trajectory through while a navigation just accepted stood still."""
        if (goal_id := self.running(other)) is not None:
            raise Vetoed(
                f"{what} (goal {goal_id}) is still under way: the arm and the base do not move at once; "
                "send this once it has ended",
                Rule.ONE_MOTION,
            )

    def navigate(self, req: SendGoal[NavigateToPoseGoal]) -> Ruling[GoalRuling]:
        t = self._time()

        def check(goal: NavigateToPoseGoal) -> Verdict[NavigateToPoseGoal]:
            self._one_motion(keys.ROBOT_TRAJECTORY, "an arm trajectory")
            return self._slower_through_zones(self.policy.check_navigation(goal, self._pose(t), self._reach(t)))

        return self._goal(keys.CMD_NAVIGATE.send_goal.path, req, check, t)

    def trajectory(self, req: SendGoal[FollowJointTrajectoryGoal], again: bool = False) -> Ruling[GoalRuling]:
        """A trajectory from where the arm is. A goal sent the moment the previous motion ended may
        start where the arm has just stopped, while the latest state here is from a moment before: a
        first point that seems to jump is refused with `fresh_joints_may_pass`, and the node asks
        `again` once a joint state measured since came. Asked again, the e-stop is checked once more
        (it may have latched during the wait), the rate is not (the goal was counted the first time)."""
        t = self._time()
        joints = self._joint_state(t)
        positions = _positions(joints)
        # Which joint state the check rested on, in the decision's values: `tether recheck` checks the
        # recorded goal from that very state (services/safety/recheck.py).
        measured = {} if joints is None else {JOINTS_STAMP: joints.stamp}

        def check(goal: FollowJointTrajectoryGoal) -> Verdict[FollowJointTrajectoryGoal]:
            self._one_motion(keys.ROBOT_NAVIGATE, "a navigation")
            self._twist_may_drive(t)
            try:
                verdict = self.policy.check_trajectory(goal, positions, self._pose(t), self._base_moving())
            except Vetoed as exc:
                exc.values.update(measured)
                raise
            return replace(verdict, values={**verdict.values, **measured})

        return self._goal(keys.CMD_TRAJECTORY.send_goal.path, req, check, t, again=again)

    def gripper(self, req: SendGoal[GripperCommandGoal]) -> Ruling[GoalRuling]:
        return self._goal(keys.CMD_GRIPPER.send_goal.path, req, self.policy.check_gripper, self._time())

    def _goal(
        self, key: str, req: SendGoal[Any], check: Callable[[Any], Verdict[Any]], t: float, again: bool = False
    ) -> Ruling[GoalRuling]:
        """The goal to send to the robot, or the refusal to reply with. `again`: the same goal decided
        once more (see trajectory): not counted against the rate twice, and not offered a third try."""
        try:
            refused = self._estop_veto() or self._mode_veto()
            if refused is None and not again:
                refused = self._rate_veto(key, t)
            if refused is not None:
                raise refused
            verdict = check(req.goal)
        except Vetoed as exc:
            refusal = GoalResponse(
                goal_id=req.goal_id, accepted=False, reason=f"vetoed by safety: {exc}", kind=_refusal_kind(exc)
            )
            # A first point that seems to jump (the check's `jump_rad`) may be a joint state that lags the arm.
            jumped = "jump_rad" in exc.values and not again
            return Ruling(refusal, (_veto_event(key, exc, req),), fresh_joints_may_pass=jumped)
        goal = SendGoal(goal_id=req.goal_id, goal=verdict.command)
        return Ruling(goal, (_approval(key, verdict, goal),))

    def check_plan(self, plan: GroundedPlan) -> Ruling[PlanCheckReply]:
        """The whole plan, before anything moves."""
        key = keys.PLAN_CHECK.path
        t = self._time()
        try:
            if refused := self._estop_veto():
                raise refused
            if (why := PLANS_REFUSED.get(self.modes.mode)) is not None:
                raise Vetoed(why, Rule.MODE)
            checks = self.policy.check_plan(plan, self._pose(t))
        except Vetoed as exc:
            error = ServiceError(kind=_refusal_kind(exc), message=str(exc), stage=Stage.SAFETY)
            return Ruling(error, (_veto_event(key, exc, plan),))
        event = GateEvent(key, Decision.APPROVED, "; ".join(checks), plan, None, PLAN_RULES)
        return Ruling(PlanApproved(checks=checks, warnings=self._plan_warnings(plan)), (event,))

    # The control mode and plan approval (operator only, with the token)

    @property
    def mode(self) -> ControlMode:
        return self.modes.mode

    def _mode_veto(self) -> Vetoed | None:
        """Why the mode refuses a program's motion (a plan's goals, cmd/cmd_vel); None when it lets it."""
        mode = self.modes.mode
        if (why := PLANS_REFUSED.get(mode)) is not None:
            return Vetoed(f"{why}; a program's motion is refused", Rule.MODE)
        if mode is ControlMode.SUPERVISED:
            with self._lock:
                running = self._approvals.running()
                paused = self._approvals.paused()
            # A pause holds whatever else is approved: the operator took over.
            if paused:
                held = paused[0]
                why = (
                    f"mode supervised: plan {held.goal_id} {held.reason}; a program's motion is refused until "
                    f"`tether resume {held.goal_id}` (teleop drives meanwhile)"
                )
                return Vetoed(why, Rule.APPROVAL)
            if running is None:
                why = "mode supervised: no plan an operator approved is running; a program's motion is refused"
                return Vetoed(why, Rule.APPROVAL)
        return None

    def operator_refusal(self, key: str, what: str, operator: str, token: str, redacted: object) -> GateEvent | None:
        """The event refusing `what` unless `token` is the operator's, held to the same limits on wrong
        attempts as the e-stop reset (the same token, the same counts); None when it is the operator."""
        right = self.latch.accepts(token)
        with self._lock:
            t = self._advance()
            wait = self._resets.attempt(operator, t, right=right)
        if wait > 0.0:
            limit = self._resets.per_window
            why = (
                f"{what} refused for '{operator}': too many attempts (at most {limit} a minute per operator, "
                f"{self._resets.total} for all); try again in {math.ceil(wait)} s"
            )
            values = {"retry_after_s": wait, "limit_per_minute": float(limit)}
            return GateEvent(key, Decision.VETOED, why, redacted, Rule.OPERATOR, (Rule.OPERATOR,), values)
        if not right:
            why = f"{what} refused for '{operator}': not the operator's token"
            return GateEvent(key, Decision.VETOED, why, redacted, Rule.OPERATOR, (Rule.OPERATOR,))
        return None

    def set_mode(self, req: ModeRequest) -> Ruling[ModeReply]:
        """Change the control mode with the operator's token; the token never leaves in an event."""
        key = keys.SET_MODE.path
        redacted = msgspec.structs.replace(req, token="***")
        if (refusal := self.operator_refusal(key, "mode change", req.operator, req.token, redacted)) is not None:
            return Ruling(ModeReply(ok=False, message=refusal.reason, mode=self.modes.mode), (refusal,))
        previous = self.modes.set(req.mode, f"operator {req.operator}", self._wall_clock()).mode
        if previous is req.mode:
            return Ruling(ModeReply(ok=True, message=f"mode already {req.mode}", mode=req.mode))
        log.warning("control mode %s -> %s by operator %s", previous, req.mode, req.operator)
        why = f"mode {previous} -> {req.mode} by operator {req.operator}"
        events = [GateEvent(key, Decision.MODE, why, redacted, Rule.MODE, (Rule.OPERATOR,))]
        if req.mode is ControlMode.SUPERVISED:
            # A plan autonomous mode let run was never approved by an operator; supervised mode needs one.
            unreviewed = f"{why}: it ran because mode autonomous needs no approval, not an operator's; it moves no more"
            with self._lock:
                denied = self._approvals.deny_unreviewed(unreviewed, self._advance())
            events += [
                GateEvent(
                    keys.APPROVAL_REQUEST.path,
                    Decision.DENIED,
                    f"plan {a.goal_id}: {unreviewed}",
                    a,
                    Rule.APPROVAL,
                    (Rule.MODE,),
                )
                for a in denied
            ]
        # Goals under way that the new mode would refuse are ended (the next ones are refused).
        cancel = self._mode_veto() is not None
        return Ruling(
            ModeReply(ok=True, message=why, mode=req.mode),
            tuple(events),
            mode_changed=True,
            cancel_goals=cancel,
            approvals_changed=True,
        )

    def request_approval(self, req: ApprovalRequest) -> Ruling[PlanApproval]:
        """The executor asks, before a plan's first motion, whether it may move the robot. In supervised
        mode the plan is checked here once more (the dry run the operator sees) and waits; asking again
        is answered from the book."""
        key = keys.APPROVAL_REQUEST.path
        t = self._time()
        mode = self.modes.mode
        with self._lock:
            known = self._approvals.get(req.goal_id, t)
            asked_for = self._approvals.plan(req.goal_id)
            gone = self._executor_gone
            away = self._executor_away
        if known is not None:
            return self._asked_again(req, known, asked_for, mode, t)
        if mode is ControlMode.AUTONOMOUS:
            return Ruling(PlanApproval(goal_id=req.goal_id, state=ApprovalState.NOT_NEEDED, reason=f"mode {mode}"))
        if (why := PLANS_REFUSED.get(mode)) is not None:
            refusal = PlanApproval(goal_id=req.goal_id, state=ApprovalState.DENIED, reason=why)
            return Ruling(refusal, (GateEvent(key, Decision.DENIED, why, refusal, Rule.MODE, (Rule.MODE,)),))
        checked = self.check_plan(req.plan)
        lines = plan_lines(req.plan)
        wall = self._wall_clock()
        if isinstance(checked.forward, ServiceError):
            why = f"safety's check refuses it: {checked.forward.message}"
            approval = PlanApproval(
                goal_id=req.goal_id, state=ApprovalState.DENIED, reason=why, steps=lines, requested=wall
            )
        else:
            why = f"awaiting an operator: `tether approve {req.goal_id}` or `tether deny {req.goal_id} --reason ...`"
            approval = PlanApproval(
                goal_id=req.goal_id,
                state=ApprovalState.PENDING,
                reason=why,
                steps=lines,
                checks=list(checked.forward.checks),
                requested=wall,
            )
        with self._lock:
            known = self._approvals.get(req.goal_id, t)
            asked_for = self._approvals.plan(req.goal_id)
            if known is None:
                if (away or self._executor_gone != gone) and approval.state is ApprovalState.PENDING:
                    # Its executor had gone when it came (it waited for a worker), or went while it was
                    # checked, after its plans were ended: held pending, an operator could approve a
                    # plan no one runs, whose end never comes.
                    approval = replace_approval(approval, ApprovalState.DENIED, EXECUTOR_GONE)
                approval = self._approvals.add(approval, req.plan, t)
        if known is not None:
            # Another ask under this goal id was held while this one was checked. It stays: replacing
            # it gave the operator's look at (or approval of) that plan to this one, or undid it. This
            # ask is answered as a later one is.
            again = self._asked_again(req, known, asked_for, self.modes.mode, t)
            return replace(again, events=(*checked.events, *again.events))
        decision = Decision.AWAITING_APPROVAL if approval.state is ApprovalState.PENDING else Decision.DENIED
        event = GateEvent(key, decision, f"plan {req.goal_id}: {approval.reason}", approval, Rule.APPROVAL)
        return Ruling(approval, (*checked.events, event), approvals_changed=True)

    def _asked_again(
        self, req: ApprovalRequest, known: PlanApproval, asked_for: GroundedPlan | None, mode: ControlMode, t: float
    ) -> Ruling[PlanApproval]:
        """An ask for a goal the book holds (`known`, for plan `asked_for`): answered from the book, or
        decided by a mode that changed while it waited."""
        key = keys.APPROVAL_REQUEST.path
        if asked_for != req.plan:
            # An approval holds for the plan it was asked for: another plan under the same goal id (a
            # harmless one asked first, to have the real one ride on its approval) is refused, the
            # book as it was.
            other = f"goal {req.goal_id} was asked about with another plan; an approval is for one plan only"
            refusal = PlanApproval(goal_id=req.goal_id, state=ApprovalState.DENIED, reason=other)
            event = GateEvent(key, Decision.DENIED, other, refusal, Rule.APPROVAL, (Rule.APPROVAL,))
            return Ruling(refusal, (event,))
        if known.state not in WAITING or mode is ControlMode.SUPERVISED:
            return Ruling(known)
        # The mode changed while it waited (or was paused): autonomous lets it run (until supervised
        # mode is back), direct and shared refuse it.
        why = PLANS_REFUSED.get(mode)
        state = ApprovalState.DENIED if why else ApprovalState.APPROVED
        why = why or f"mode {mode}: no approval needed"
        with self._lock:
            if state is ApprovalState.APPROVED:
                approval = self._approvals.let_run(req.goal_id, why, t, self._wall_clock())
            else:
                approval = self._approvals.change(req.goal_id, state, why, t, decided=self._wall_clock(), by="mode")
        decision = Decision.DENIED if state is ApprovalState.DENIED else Decision.APPROVED
        event = GateEvent(key, decision, f"plan {req.goal_id}: {why}", approval, Rule.APPROVAL, (Rule.MODE,))
        return Ruling(approval, (event,), approvals_changed=True)

    def approval(self, goal_id: str) -> PlanApproval | None:
        """What safety holds of `goal_id`'s approval now (None: nothing)."""
        t = self._time()
        with self._lock:
            return self._approvals.get(goal_id, t)

    def decide(self, req: ApprovalDecision) -> Ruling[ApprovalReply]:
        """An operator approves, denies, pauses or resumes a plan. An approval or a resume checks the
        plan once more from where the robot is now: a plan safety would refuse now is denied instead.
        A pause cancels every goal forwarded (the plan's motion is refused until it is resumed;
        teleop drives meanwhile)."""
        key = keys.APPROVAL_DECIDE.path
        redacted = msgspec.structs.replace(req, token="***")
        action = req.action
        if action is None and req.approve is not None:
            action = ApprovalAction.APPROVE if req.approve else ApprovalAction.DENY
        if action is None or (req.action is not None and req.approve is not None):
            why = "a decision names either `action` (approve, deny, pause, resume) or the older `approve`, exactly one"
            event = GateEvent(key, Decision.VETOED, why, redacted, Rule.APPROVAL, (Rule.APPROVAL,))
            return Ruling(ApprovalReply(ok=False, message=why), (event,))
        states, verb, waits = DECIDES[action]
        if (refusal := self.operator_refusal(key, verb, req.operator, req.token, redacted)) is not None:
            return Ruling(ApprovalReply(ok=False, message=refusal.reason), (refusal,))
        t = self._time()
        with self._lock:
            known = self._approvals.get(req.goal_id, t)
            plan = self._approvals.plan(req.goal_id)

        def refused(why: str, approval: PlanApproval | None = known) -> Ruling[ApprovalReply]:
            event = GateEvent(key, Decision.VETOED, why, redacted, Rule.APPROVAL, (Rule.APPROVAL,))
            return Ruling(ApprovalReply(ok=False, message=why, approval=approval), (event,))

        if known is None or plan is None:
            unknown = f"no plan with goal id {req.goal_id} is known to safety's approvals (unknown goal)"
            if action is ApprovalAction.APPROVE:
                unknown = f"no plan with goal id {req.goal_id} waits for approval (unknown goal)"
            return refused(f"{unknown}; `tether pending` lists the plans that wait")
        if known.state not in states:
            return refused(f"plan {req.goal_id} does not {waits}: it is {known.state} ({known.reason})")
        mode = self.modes.mode
        if action in (ApprovalAction.PAUSE, ApprovalAction.RESUME) and mode is not ControlMode.SUPERVISED:
            why = f"{verb} is for supervised mode; the mode is {mode}"
            if known.state is ApprovalState.PAUSED:
                why += " (the mode decides the paused plan at the executor's next ask)"
            return refused(why)
        events: list[GateEvent] = []
        by = f"operator {req.operator}"
        said = f": {req.reason}" if req.reason else ""
        fields: dict[str, object] = {"decided": self._wall_clock(), "by": req.operator[:200]}
        if action in (ApprovalAction.APPROVE, ApprovalAction.RESUME):
            if (refusing := PLANS_REFUSED.get(mode)) is not None:
                return refused(f"{refusing}: set the mode to supervised or autonomous first")
            checked = self.check_plan(plan)
            events.extend(checked.events)
            if isinstance(checked.forward, ServiceError):
                state, why = ApprovalState.DENIED, f"safety's check refuses it now: {checked.forward.message}"
            elif action is ApprovalAction.APPROVE:
                state, why = ApprovalState.APPROVED, f"approved by {by}"
            else:
                state, why = ApprovalState.APPROVED, f"resumed by {by}"
        elif action is ApprovalAction.PAUSE:
            state, why = ApprovalState.PAUSED, f"paused by {by}{said}"
            fields["pauses"] = known.pauses + 1
        else:
            state = ApprovalState.DENIED
            why = f"denied by {by}: {req.reason or 'no reason given'}"
        with self._lock:
            current = self._approvals.get(req.goal_id, t)
            if current is None or current.state is not known.state:
                # Decided (or ended) by someone else while this one was checked.
                state_now = current.state if current is not None else "forgotten"
                return refused(f"plan {req.goal_id} does not {waits} any more: it is {state_now}", current)
            approval = self._approvals.change(req.goal_id, state, why, t, **fields)
        log.warning("plan %s %s", req.goal_id, why)
        decision = {
            ApprovalState.PAUSED: Decision.PAUSED,
            ApprovalState.DENIED: Decision.DENIED,
        }.get(state, Decision.RESUMED if action is ApprovalAction.RESUME else Decision.APPROVED)
        events.append(GateEvent(key, decision, f"plan {req.goal_id}: {why}", redacted, Rule.APPROVAL, (Rule.OPERATOR,)))
        ok = state is not ApprovalState.DENIED or action is ApprovalAction.DENY
        # A pause ends the goals under way, as a change to a mode that refuses them does; a denial of
        # a paused plan has nothing under way (the pause ended it).
        return Ruling(
            ApprovalReply(ok=ok, message=why, approval=approval),
            tuple(events),
            cancel_goals=state is ApprovalState.PAUSED,
            approvals_changed=True,
        )

    def pending(self) -> PendingPlans:
        t = self._time()
        with self._lock:
            return PendingPlans(mode=self.modes.mode, plans=self._approvals.waiting(t), paused=self._approvals.paused())

    def executor_gone(self) -> Ruling[None]:
        """The executor's liveliness ended (it stopped or crashed, or its link was lost): the plans it
        ran will never be reported ended, so every plan waiting, approved or paused ends now (one event
        each). Left approved, a plan let every program's motion pass in supervised mode for as long as
        safety ran. Goals under way of a plan that was running are canceled, a program's twist stopped."""
        key = keys.APPROVAL_REQUEST.path
        t = self._time()
        why = EXECUTOR_GONE
        with self._lock:
            self._executor_gone += 1
            self._executor_away = True
            running = self._approvals.running()
            ended = self._approvals.end_all(why, t)
        if not ended:
            return Ruling(None)
        events = tuple(
            GateEvent(key, Decision.DENIED, f"plan {a.goal_id}: {why}", a, Rule.APPROVAL, (Rule.APPROVAL,))
            for a in ended
        )
        stop = running is not None and self.modes.mode is ControlMode.SUPERVISED
        return Ruling(None, events, cancel_goals=stop, approvals_changed=True)

    def executor_alive(self) -> None:
        """The executor's liveliness token is held (it started, or came back): its asks are held again."""
        with self._lock:
            self._executor_away = False

    def plan_status(self, status: GoalStatus) -> Ruling[None]:
        """The executor's plan goal changed state: one that ended no longer waits or moves the robot."""
        if not status.state.terminal:
            return Ruling(None)
        t = self._time()
        with self._lock:
            known = self._approvals.get(status.goal_id, t)
            if known is None:
                # An ask for it may still be on its way (being checked); it is not to wait then.
                self._approvals.gone(status.goal_id, f"the plan ended ({status.state}) before safety held it")
                return Ruling(None)
            if known.state not in (*WAITING, ApprovalState.APPROVED):
                return Ruling(None)
            why = f"the plan ended ({status.state}) after it was {known.state}"
            self._approvals.change(status.goal_id, ApprovalState.FINISHED, why, t)
        return Ruling(None, approvals_changed=True)
