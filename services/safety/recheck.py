"""Recorded commands through the safety checks again, offline: which decisions a policy would change.

A recording holds every command safety decided on, with the decision, and the robot's state at the
time (odometry, joint states, the heartbeat's speed scale). Each command is checked again with a
policy (the recorded one, or a new one) from the state recorded just before it, as safety would have
seen it, and the new decision is compared with the recorded one. A trajectory is checked from the
joint state safety names in its decision (JOINTS_STAMP) when the recording holds it, heard within
state_max_age of the goal: a goal sent as the previous motion ends meets an arm that moves while the
query travels.

Rechecked: plan checks (`safety/check_plan`), navigation, trajectory and gripper goals (their
`send_goal` queries as safety received them, from `_trace/safety/**`) and program velocity
commands (`cmd/cmd_vel`). Not rechecked, and counted: commands refused for the e-stop or the
command rate (the operator's and the clock's doing, not the policy's), teleop (clamped, not
refused, from a state that depends on the stream's timing), and commands without a recorded
decision (a file cut short).

Also flagged, never taken as safety's: every robot/** command and heartbeat that is not safety's (no
robot-link MAC, another sender, replayed, no decision allowing it; services/recorder/linkaudit.py).
"""

from __future__ import annotations

import bisect
import enum
import math
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import msgspec

from schemas import keys
from schemas.actions import GoalResponse, SendGoal, goal_id_in
from schemas.common import DECODE_ERRORS, ErrorKind, Pose2D
from schemas.plan import GroundedPlan
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, JointState, NavigateToPoseGoal, Odometry, Twist
from schemas.safety import Decision, Rule, SafetyEvent, SafetyStatus
from schemas.trace import TraceRecord
from services.recorder.linkaudit import Flag, audit
from services.recorder.reader import Recorded
from services.safety.errors import Vetoed
from services.safety.policy import FRESH_JOINTS_WAIT, JOINTS_STAMP, SafetyPolicy, Verdict, base_moving

T = TypeVar("T")

# Refusals that are not the policy's: kept as recorded.
NOT_POLICY = {
    Rule.ESTOP: "refused for the e-stop",
    Rule.COMMAND_RATE: "refused for the command rate",
    Rule.MODE: "refused for the control mode",
    Rule.APPROVAL: "refused for want of an operator's approval",
    Rule.ONE_MOTION: "refused while the other motion ran",
}
GOALS = {
    keys.CMD_NAVIGATE.send_goal.path: NavigateToPoseGoal,
    keys.CMD_TRAJECTORY.send_goal.path: FollowJointTrajectoryGoal,
    keys.CMD_GRIPPER.send_goal.path: GripperCommandGoal,
}

# How far (seconds) outside a goal query's answering, by safety's stamps, a safety event about its
# goal id may be stamped and still be about it: both stamps are safety's wall clock, read in one
# process, so only a step of that clock moves one from the other. A goal sent again with the same id
# later is another goal, whose decision says nothing of this one.
EVENT_SLACK = 0.01

# Safety decides a goal query with one event, two when a trajectory is checked again on a fresher
# joint state: more stamped while it answered one query come from a crafted file, and only the first
# this many are weighed (each of its queries would otherwise go through every one).
EVENTS_PER_QUERY = 8

# Where safety's runtime traces each goal query it answered.
GOAL_TRACES = frozenset(f"_trace/safety/{path}" for path in GOALS)


class RecheckOutcome(enum.StrEnum):
    APPROVED = "approved"
    VETOED = "vetoed"


@dataclass(frozen=True)
class Message:
    """A recorded message, as recheck needs it: receive time in seconds, key under the robot's prefix, JSON."""

    time: float
    path: str
    data: bytes
    attachment: bytes | None = None  # the Zenoh attachment recorded with it (safety's MAC)


@dataclass(frozen=True)
class Rechecked:
    stamp: float  # when safety decided (wall clock, seconds)
    key: str  # the command's key under the robot's prefix
    command: str  # what was asked, in a few words
    recorded: RecheckOutcome
    recorded_reason: str
    now: RecheckOutcome
    now_reason: str
    now_rule: Rule | None

    @property
    def differs(self) -> bool:
        return self.recorded is not self.now


@dataclass
class RecheckReport:
    policy_hash: str
    checked: list[Rechecked] = field(default_factory=list)
    skipped: Counter[str] = field(default_factory=Counter)
    warnings: list[str] = field(default_factory=list)
    # Robot commands and heartbeats that are not safety's.
    suspects: list[Flag] = field(default_factory=list)

    @property
    def differences(self) -> list[Rechecked]:
        return [c for c in self.checked if c.differs]


class History(Generic[T]):
    """One state topic's messages by receive time: the latest at or before a moment, or the next after it."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.values: list[T] = []
        self._sorted = True

    def add(self, time: float, value: T) -> None:
        # Sorted once, before the first look-up: inserting each where it belongs costs a move of
        # everything after it, and a file written backwards would make that quadratic.
        self._sorted = self._sorted and (not self.times or self.times[-1] <= time)
        self.times.append(time)
        self.values.append(value)

    def _sort(self) -> None:
        if not self._sorted:
            # Stable: of messages received at one time, the last to arrive is the latest.
            order = sorted(range(len(self.times)), key=self.times.__getitem__)
            self.times = [self.times[i] for i in order]
            self.values = [self.values[i] for i in order]
            self._sorted = True

    def at(self, time: float, max_age: float) -> tuple[float, T] | None:
        self._sort()
        i = bisect.bisect_right(self.times, time) - 1
        if i < 0 or time - self.times[i] > max_age:
            return None
        return self.times[i], self.values[i]

    def after(self, time: float, within: float) -> tuple[float, T] | None:
        self._sort()
        i = bisect.bisect_right(self.times, time)
        if i >= len(self.times) or self.times[i] - time > within:
            return None
        return self.times[i], self.values[i]


@dataclass
class RobotHistory:
    """What safety knew of the robot over the recording."""

    odom: History[Odometry] = field(default_factory=History)
    joints: History[JointState] = field(default_factory=History)
    heartbeat: History[SafetyStatus] = field(default_factory=History)
    # Each joint state by its own stamp, which safety names in a trajectory decision (JOINTS_STAMP),
    # with when it was received.
    joints_stamped: dict[float, tuple[float, JointState]] = field(default_factory=dict)

    def add_joints(self, time: float, joints: JointState) -> None:
        self.joints.add(time, joints)
        self.joints_stamped.setdefault(joints.stamp, (time, joints))


def _short(value: float) -> str:
    return f"{value:.2f}"


def describe(path: str, command: Any) -> str:
    """A command in a few words, for a person reading the list."""
    if isinstance(command, GroundedPlan):
        return "plan: " + ", ".join(str(type(step).__struct_config__.tag) for step in command.steps)
    if isinstance(command, NavigateToPoseGoal):
        pose = command.pose
        return f"navigate to ({_short(pose.x)}, {_short(pose.y)}, {_short(pose.yaw)} rad)"
    if isinstance(command, FollowJointTrajectoryGoal):
        end = command.points[-1].time_from_start if command.points else 0.0
        return f"arm trajectory: {len(command.points)} points over {end:.2f} s"
    if isinstance(command, GripperCommandGoal):
        return f"gripper to {command.position:.3f} m at {command.max_effort:g} N"
    if isinstance(command, Twist):
        return f"cmd_vel {command.linear_x:.2f} m/s, {command.angular_z:.2f} rad/s"
    return path


class Rechecker:
    """Replays the decisions of one recording against `policy`."""

    def __init__(self, policy: SafetyPolicy) -> None:
        self.policy = policy
        self.max_age = policy.policy.monitor.state_max_age
        self.state = RobotHistory()

    def has_state_before(self, time: float) -> bool:
        """Whether the recording holds odometry from before `time` (a stale one counts: safety saw that too)."""
        return self.state.odom.at(time, math.inf) is not None

    def pose(self, time: float) -> Pose2D | None:
        found = self.state.odom.at(time, self.max_age)
        return None if found is None else found[1].pose

    def joints(self, time: float) -> tuple[float, dict[str, float]] | None:
        found = self.state.joints.at(time, self.max_age)
        return None if found is None else (found[0], dict(zip(found[1].name, found[1].position, strict=False)))

    def moving(self, time: float) -> bool:
        found = self.state.odom.at(time, self.max_age)
        return found is not None and base_moving(found[1])

    def scale(self, time: float) -> float:
        found = self.state.heartbeat.at(time, math.inf)
        return 1.0 if found is None else found[1].speed_scale

    def check(
        self, path: str, command: Any, time: float, joints_stamp: float | None = None
    ) -> Verdict[Any] | list[str]:
        """The check safety runs for `command` on `path`, from the state at `time`; raises Vetoed. A
        trajectory with `joints_stamp` (the joint state safety named in its decision) is checked from
        that joint state when the recording holds it."""
        policy = self.policy
        if isinstance(command, GroundedPlan):
            return policy.check_plan(command, self.pose(time))
        if isinstance(command, NavigateToPoseGoal):
            return policy.check_navigation(command, self.pose(time), self._reach(time))
        if isinstance(command, FollowJointTrajectoryGoal):
            return self._check_trajectory(command, time, joints_stamp)
        if isinstance(command, GripperCommandGoal):
            return policy.check_gripper(command)
        if isinstance(command, Twist):
            return policy.check_cmd_vel(command, self.pose(time), self.scale(time), self._reach(time))
        raise TypeError(f"no check for {type(command).__name__} on {path}")

    def _reach(self, time: float) -> float:
        """How far the hand stuck out from the base's centre at `time`, as safety works it out."""
        joints = self.joints(time)
        return self.policy.reach(joints[1] if joints else None)

    def _check_trajectory(
        self, goal: FollowJointTrajectoryGoal, time: float, joints_stamp: float | None
    ) -> Verdict[Any]:
        named = self.state.joints_stamped.get(joints_stamp) if joints_stamp is not None else None
        # The very state safety checked from, when the recorder heard it within state_max_age of the
        # query (safety checks from none older; a decision naming one far off is not taken at its
        # word): when the recorder received what is no guess at it. (A goal sent as a motion ends, at
        # 20 times real time, met the recorded state before the query 0.13 rad from the one safety
        # had.) The pose as at `time`.
        if named is not None and abs(named[0] - time) <= self.max_age:
            positions = dict(zip(named[1].name, named[1].position, strict=False))
            return self.policy.check_trajectory(goal, positions, self.pose(time), self.moving(time))
        # As safety does: a first point that seems to jump is checked again with the next joint state.
        joints = self.joints(time)
        try:
            return self.policy.check_trajectory(goal, joints[1] if joints else None, self.pose(time), self.moving(time))
        except Vetoed as exc:
            fresher = self.state.joints.after(time, FRESH_JOINTS_WAIT)
            if "jump_rad" not in exc.values or fresher is None:
                raise
            later = fresher[0]
        joints = self.joints(later)
        return self.policy.check_trajectory(goal, joints[1] if joints else None, self.pose(later), self.moving(later))

    def recheck(
        self,
        path: str,
        command: Any,
        time: float,
        recorded: RecheckOutcome,
        reason: str,
        joints_stamp: float | None = None,
    ) -> Rechecked:
        try:
            self.check(path, command, time, joints_stamp)
        except Vetoed as exc:
            return Rechecked(
                time, path, describe(path, command), recorded, reason, RecheckOutcome.VETOED, str(exc), exc.rule
            )
        return Rechecked(time, path, describe(path, command), recorded, reason, RecheckOutcome.APPROVED, "", None)


def _decode(data: bytes | msgspec.Raw, type_: type[T]) -> T | None:
    try:
        return msgspec.json.decode(data, type=type_)
    except DECODE_ERRORS:
        # RecursionError: JSON nested too deep to be a command (a hostile file).
        return None


def recheck(
    messages: Iterable[Message],
    policy: SafetyPolicy,
    robot_policy_hash: str = "",
    robot: str = "robot",
    robot_key: bytes | None = None,
) -> RecheckReport:
    """Every rechecked command in `messages` (in arrival order) under `policy`, with what differs.

    Times are the recorder's receive times (one clock for the state and the commands, whichever
    machines published them). `robot_policy_hash` is the hash of the policy file kept with the
    recording, checked against the hash safety put in its events, so a recording whose file does not
    match what safety ran with says so. With `robot_key` every robot-link MAC is checked
    (services/recorder/linkaudit.py): a heartbeat whose MAC checks out is safety's, even beside a forger's.
    """
    rechecker = Rechecker(policy)
    report = RecheckReport(policy.limits.hash)
    messages = list(messages)
    root = keys.prefix(robot) + "/"
    recorded = [Recorded(int(m.time * 1e9), root + m.path, m.data, m.attachment) for m in messages]
    found = audit(recorded, robot, robot_key)
    report.suspects = found.flags
    report.warnings.extend(_suspect_lines(found.flags, messages[0].time if messages else 0.0))
    flagged = found.at()
    state_topics: dict[str, tuple[type[Any], Callable[[float, Any], None]]] = {
        keys.ODOM.path: (Odometry, rechecker.state.odom.add),
        keys.JOINT_STATES.path: (JointState, rechecker.state.add_joints),
        keys.HEARTBEAT.path: (SafetyStatus, rechecker.state.heartbeat.add),
    }
    # The state first, all of it: a command is checked from the state just before it, and a
    # trajectory from the one just after too.
    events: list[tuple[float, SafetyEvent]] = []
    traces: list[tuple[float, TraceRecord]] = []
    for i, message in enumerate(messages):
        if i in flagged:
            continue  # a heartbeat not safety's is not what safety saw
        if (topic := state_topics.get(message.path)) is not None:
            if (value := _decode(message.data, topic[0])) is not None:
                topic[1](message.time, value)
        elif message.path == keys.SAFETY_EVENTS.path:
            if (event := _decode(message.data, SafetyEvent)) is not None:
                events.append((message.time, event))
            else:
                report.skipped["a safety event that does not decode"] += 1
        elif message.path in GOAL_TRACES:
            trace = _decode(message.data, TraceRecord)
            if trace is not None and trace.key in GOALS:
                # The trace is published once the query is answered: the check came `duration` before.
                traces.append((message.time - max(0.0, trace.duration), trace))
            else:
                report.skipped["a goal query trace that does not decode"] += 1
    hashes = {e.policy_hash for _, e in events if e.policy_hash}
    if robot_policy_hash and hashes and hashes != {robot_policy_hash}:
        report.warnings.append(
            f"safety's events name policy {', '.join(sorted(hashes))}, but the policy file kept in the "
            f"recording is {robot_policy_hash}: the recorder was not given the policy safety ran with"
        )
    if not rechecker.state.odom.times:
        report.warnings.append("no odometry in the recording: every check that needs the robot's pose is skipped")
    # Safety's event about each goal: its rule, when the goal was refused.
    goal_events = GoalEvents(events)
    checks: list[Rechecked] = []
    for time, event in events:
        if event.key == keys.PLAN_CHECK.path:
            _recheck_event(rechecker, report, time, event, GroundedPlan, checks)
        elif event.key == keys.CMD_VEL.path:
            _recheck_event(rechecker, report, time, event, Twist, checks)
        elif event.key == keys.TELEOP_CMD_VEL.path and event.decision is not Decision.STOPPED:
            report.skipped["teleop (clamped rather than refused)"] += _count(event)
    for time, trace in traces:
        _recheck_goal(rechecker, report, time, trace, goal_events, checks)
    report.checked = sorted(checks, key=lambda c: c.stamp)
    return report


class GoalEvents:
    """Safety's events about goals, by goal (its key and id), in the order safety stamped them."""

    def __init__(self, events: list[tuple[float, SafetyEvent]]) -> None:
        by_goal: dict[tuple[str, str], list[tuple[float, SafetyEvent]]] = {}
        for time, event in events:
            if event.key in GOALS and (goal_id := goal_id_in(event.command)) is not None:
                by_goal.setdefault((event.key, goal_id), []).append((time, event))
        self.by_goal = {goal: sorted(about, key=lambda c: c[1].stamp) for goal, about in by_goal.items()}
        self.stamps = {goal: [c[1].stamp for c in about] for goal, about in self.by_goal.items()}

    def stamped(self, key: str, goal_id: str, earliest: float, latest: float) -> list[tuple[float, SafetyEvent]]:
        """The events about the goal stamped from `earliest` to `latest` (the first EVENTS_PER_QUERY)."""
        goal = (key, goal_id)
        stamps = self.stamps.get(goal, [])
        start = bisect.bisect_left(stamps, earliest)
        end = min(bisect.bisect_right(stamps, latest), start + EVENTS_PER_QUERY)
        return self.by_goal[goal][start:end] if stamps else []


def _suspect_lines(flags: list[Flag], start: float) -> list[str]:
    """One line per kind of suspect message: how many, and when the first came (seconds from `start`)."""
    kinds: dict[tuple[str, str], list[Flag]] = {}
    for flag in flags:
        kinds.setdefault((flag.path, flag.why), []).append(flag)
    return [
        f"not safety's: {len(same)} message(s) on {path}: {why}; the first at {same[0].log_time / 1e9 - start:.2f} s"
        + (f" ({same[0].detail})" if same[0].detail else "")
        for (path, why), same in kinds.items()
    ]


def _count(event: SafetyEvent) -> int:
    """How many commands an event decided on: one, or a count of repeats (safety sums up a stream
    vetoed over and over in one event a second)."""
    if bytes(event.command) == b"null" and "count" in event.values:
        return max(1, int(event.values["count"]))
    return 1


def _recheck_event(
    rechecker: Rechecker,
    report: RecheckReport,
    time: float,
    event: SafetyEvent,
    type_: type[Any],
    out: list[Rechecked],
) -> None:
    if event.decision not in (Decision.APPROVED, Decision.VETOED):
        return
    # Only a refusal can be the e-stop's or the clock's: safety approves with no rule, so an approval
    # naming one (a crafted file) is checked like any other, not counted away as a refusal.
    if event.decision is Decision.VETOED and event.rule in NOT_POLICY:
        report.skipped[NOT_POLICY[event.rule]] += _count(event)
        return
    command = _decode(event.command, type_)
    if command is None:
        report.skipped["a decision without its command"] += 1
        return
    recorded = RecheckOutcome.APPROVED if event.decision is Decision.APPROVED else RecheckOutcome.VETOED
    _add(rechecker, report, out, event.key, command, time, recorded, event.reason)


def _add(
    rechecker: Rechecker,
    report: RecheckReport,
    out: list[Rechecked],
    key: str,
    command: Any,
    time: float,
    recorded: RecheckOutcome,
    reason: str,
    joints_stamp: float | None = None,
) -> None:
    if not isinstance(command, GripperCommandGoal) and not rechecker.has_state_before(time):
        # The file starts after it (a rotation, a recorder started late): safety saw a state it does not hold.
        report.skipped["no robot state recorded before it"] += 1
        return
    out.append(rechecker.recheck(key, command, time, recorded, reason, joints_stamp))


def _recheck_goal(
    rechecker: Rechecker,
    report: RecheckReport,
    time: float,
    trace: TraceRecord,
    events: GoalEvents,
    out: list[Rechecked],
) -> None:
    goal_type: Any = GOALS[trace.key]
    request = _decode(trace.query, SendGoal[goal_type])
    response = _decode(trace.reply, GoalResponse)
    if request is None or response is None:
        # Not decided: the request did not decode, or safety failed to answer (forwarding failed).
        report.skipped["a goal without a recorded decision"] += 1
        return
    refused = not response.accepted and response.kind in (ErrorKind.VETOED, ErrorKind.ESTOP)
    # Safety's events about this goal: those it stamped while it answered the query (the trace's
    # stamp and duration, on the same clock of the same process), not those of an earlier or later
    # goal sent with the same id, however close, nor the recorder's delays. Of them, the nearest the
    # query that decided as the reply says, if one did: a trajectory refused at first may pass on a
    # fresher joint state.
    earliest, latest = trace.stamp - EVENT_SLACK, trace.stamp + max(0.0, trace.duration) + EVENT_SLACK
    candidates = events.stamped(trace.key, request.goal_id, earliest, latest)
    agreeing = [c for c in candidates if (c[1].decision is Decision.VETOED) == refused] or candidates
    event = min(agreeing, key=lambda c: abs(c[0] - time))[1] if agreeing else None
    if refused and response.kind is ErrorKind.ESTOP:
        report.skipped[NOT_POLICY[Rule.ESTOP]] += 1
        return
    if refused and event is not None and event.rule in NOT_POLICY:
        report.skipped[NOT_POLICY[event.rule]] += 1
        return
    recorded = RecheckOutcome.VETOED if refused else RecheckOutcome.APPROVED
    stamp = event.values.get(JOINTS_STAMP) if event is not None else None
    _add(rechecker, report, out, trace.key, request.goal, time, recorded, response.reason if refused else "", stamp)
