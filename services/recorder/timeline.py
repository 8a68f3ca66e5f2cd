"""An incident's timeline from a recording: plan, steps, commands, safety decisions, e-stops. Pure logic."""

from __future__ import annotations

import bisect
import enum
import functools
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import Feedback, GoalState, GoalStatus, ResultResponse, SendGoal, goal_id_in
from schemas.common import DECODE_ERRORS, ServiceError, fmt_point, fmt_pose, preview
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus, StepStatus
from schemas.incidents import Incident
from schemas.plan import (
    GroundedPlan,
    Plan,
    walk,
)
from schemas.planner import Recovery, RecoveryOutcome
from schemas.robot import (
    FollowJointTrajectoryGoal,
    FollowJointTrajectoryResult,
    GripperCommandGoal,
    GripperCommandResult,
    NavigateToPoseGoal,
    NavigateToPoseResult,
    Odometry,
    Twist,
)
from schemas.safety import ALREADY_LATCHED, Decision, EStop, Rule, SafetyEvent, SafetyStatus
from schemas.trace import TraceRecord
from schemas.world import FaultInjected, GroundTruth, InjectFault, Moved, MoveEntity
from services.recorder.linkaudit import Flag, Why, audit
from services.recorder.reader import Recorded, RecordingFile

# Without a heartbeat for this long the robot has stopped (safety's timeout is 200 ms): worth a row.
HEARTBEAT_GAP = 0.5
# A heartbeat's change of the latch or speed scale is already a row when safety's own event about it
# arrived this close to it (seconds).
SAME_CHANGE = 1.0
# Summaries quote at most this much of free text (plan text, raw messages).
PREVIEW = 70
# Steps listed by name in a parse or resolve row.
LISTED_STEPS = 6
GRIPPER_OPEN = 0.079  # metres: at least this wide counts as open
GRIPPER_CLOSED = 0.001


class EventKind(enum.StrEnum):
    PLAN = "plan"  # a plan submitted, parsed, resolved, ended; a cancel of it
    STEP = "step"  # a step of the plan starting, progressing, ending
    COMMAND = "command"  # a goal towards the robot (approved), its result, its cancel; cmd_vel
    DECISION = "decision"  # safety vetoed or clamped something, or approved a whole plan
    SPEED = "speed"  # safety changed the speed allowed near people
    ESTOP = "estop"  # an e-stop asked for, or latched
    RESET = "reset"  # the e-stop cleared
    HEARTBEAT = "heartbeat"  # safety's heartbeat missing
    WORLD = "world"  # the simulated world changed (a move, a fault injected), or was read for a check
    INCIDENT = "incident"  # safety remembered an incident (services/safety/incidents.py)
    RECOVERY = "recovery"  # the planner asked the model for a recovery plan after a failure, and its outcome
    BAD = "bad"  # a message that does not decode into its key's type
    SUSPECT = "suspect"  # a robot command or heartbeat that is not safety's (services/recorder/linkaudit.py)
    MESSAGE = "message"  # any other message (only with everything=True)


class Level(enum.StrEnum):
    INFO = "info"
    GOOD = "good"
    WARN = "warn"
    BAD = "bad"


@dataclass(frozen=True)
class RobotState:
    """The robot at one moment: the latest odometry and heartbeat received before it (None: none yet)."""

    x: float | None = None
    y: float | None = None
    yaw: float | None = None
    speed: float | None = None  # measured forward speed, m/s
    estop: bool | None = None
    speed_scale: float | None = None

    def as_json(self) -> dict[str, Any]:
        return {
            "x": self.x,
            "y": self.y,
            "yaw": self.yaw,
            "speed": self.speed,
            "estop": self.estop,
            "speed_scale": self.speed_scale,
        }


@dataclass
class Row:
    """One thing that happened. `key` is what it is about (the key a command or query went to, under
    the robot's prefix); `source` the key it was recorded on. `target` is where a command aimed the
    base, for the map; `repeats` counts identical messages folded into this row."""

    t: float
    log_time: int
    kind: EventKind
    key: str
    summary: str
    state: RobotState
    source: str
    level: Level = Level.INFO
    decision: Decision | None = None
    rule: str | None = None
    target: tuple[float, float] | None = None
    repeats: int = 0
    # A change seen only in the heartbeat; dropped when safety's own event about it is in the file.
    implied: bool = field(default=False, repr=False)

    @property
    def text(self) -> str:
        return self.summary + (f" (and {self.repeats} more like it)" if self.repeats else "")

    def as_json(self) -> dict[str, Any]:
        return {
            "t": round(self.t, 6),
            "log_time": self.log_time,
            "kind": str(self.kind),
            "key": self.key,
            "source": self.source,
            "summary": self.text,
            "level": str(self.level),
            "decision": None if self.decision is None else str(self.decision),
            "rule": self.rule,
            "target": None if self.target is None else list(self.target),
            "repeats": self.repeats,
            "state": self.state.as_json(),
        }


@dataclass(frozen=True)
class Timeline:
    """The rows in the order their messages arrived; `t` counts seconds from the first message."""

    robot: str
    rows: list[Row]
    start_ns: int
    duration: float
    messages: int


def build_timeline(recording: RecordingFile, everything: bool = False, robot_key: bytes | None = None) -> Timeline:
    """The incident timeline of `recording`. High-rate streams (odometry, joint states, heartbeats,
    perception, action feedback) only set the robot's state, except where they change something
    (the e-stop latch, the speed scale, a missing heartbeat); `everything` lists every other message too.
    With the robot key (`robot_key`) the MACs are checked, so a forger's heartbeats are told from safety's;
    without it, while heartbeats of several senders overlap, the latch is unknown (None)."""
    builder = _Builder(recording, everything)
    # What is not safety's is a row of its own, and never taken as safety's (a forged heartbeat's latch).
    flags = audit(recording.messages, recording.robot, robot_key).at()
    for i, message in enumerate(recording.messages):
        builder.add(message, flags.get(i))
    rows = builder.finish()
    start = recording.messages[0].log_time if recording.messages else 0
    return Timeline(recording.robot, rows, start, recording.duration, len(recording.messages))


# Formatting


def short_id(goal_id: str) -> str:
    return goal_id[:8]


def error_text(error: ServiceError) -> str:
    where = f" (line {error.line}, column {error.column})" if error.line is not None else ""
    known = f"; known: {', '.join(error.candidates[:5])}" if error.candidates else ""
    return f"{error.kind}: {error.message}{where}{known}"


def _goal_text(goal: Any) -> str:
    """A command's goal in a few words, without the action's name."""
    if isinstance(goal, NavigateToPoseGoal):
        via = f" via {len(goal.path)} waypoint{'s' if len(goal.path) != 1 else ''}" if goal.path else ""
        speed = f" at ≤{goal.max_speed:.2f} m/s" if goal.max_speed is not None else ""
        return f"goal {fmt_pose(goal.pose)}{via}{speed}"
    if isinstance(goal, FollowJointTrajectoryGoal):
        return f"{len(goal.points)} points over {goal.points[-1].time_from_start:.1f} s"
    if isinstance(goal, GripperCommandGoal):
        if goal.position >= GRIPPER_OPEN:
            how = "open"
        elif goal.position <= GRIPPER_CLOSED:
            how = "close"
        else:
            how = f"to {goal.position * 1000:.0f} mm"
        on = f" on {goal.object_id}" if goal.object_id else ""
        return f"{how}{on} ({goal.max_effort:.0f} N)"
    if isinstance(goal, Twist):
        return f"{goal.linear_x:.2f} m/s, {goal.angular_z:.2f} rad/s"
    return ""


def _listed(items: list[str]) -> str:
    shown = items[:LISTED_STEPS]
    more = f", … ({len(items) - len(shown)} more)" if len(items) > len(shown) else ""
    return ", ".join(shown) + more


def _action_name(path: str) -> str:
    """cmd/navigate_to_pose/_action/send_goal -> navigate_to_pose."""
    return path.split("/_action/")[0].rsplit("/", 1)[-1]


def _subject(path: str) -> str:
    """What a decision was about, as people say it: cmd/navigate_to_pose, plan, safety/reset."""
    if path == keys.PLAN_CHECK.path:
        return "plan"
    return path.split("/_action/")[0]


# Decoding


@functools.cache
def _decoder(type_: Any) -> msgspec.json.Decoder[Any]:
    return msgspec.json.Decoder(type_)


SERVICES = {service.path: service for service in keys.SERVICES}
CMD_ACTIONS = {action.path: action for action in (keys.CMD_NAVIGATE, keys.CMD_TRAJECTORY, keys.CMD_GRIPPER)}
CMD_GOALS = {action.send_goal.path: action for action in CMD_ACTIONS.values()}
CMD_STATUS = {action.status.path: action for action in CMD_ACTIONS.values()}
CMD_VEL_KEYS = (keys.CMD_VEL.path, keys.TELEOP_CMD_VEL.path)
# What a safety event's `command` holds, by the event's key.
EVENT_COMMANDS: dict[str, Any] = {
    **{path: action.send_goal.request for path, action in CMD_GOALS.items()},
    keys.CMD_VEL.path: Twist,
    keys.TELEOP_CMD_VEL.path: Twist,
    keys.PLAN_CHECK.path: GroundedPlan,
    keys.ESTOP.path: EStop,
}
RESULT_TYPES: dict[str, Any] = {
    action.get_result.path: action.get_result.reply for action in (keys.EXECUTE_PLAN, *CMD_ACTIONS.values())
}


class Undecodable(Exception):
    """A recorded payload that is not the message its key carries."""


@dataclass(frozen=True)
class _Failed:
    """A query the service answered with an error (the trace keeps only its message)."""

    message: str


def _failure(reply: Any) -> str | None:
    """What went wrong, when a reply is a failure."""
    if isinstance(reply, ServiceError):
        return error_text(reply)
    if isinstance(reply, _Failed):
        return reply.message
    return None


def decode(data: bytes | msgspec.Raw, type_: Any) -> Any:
    """`data` as a `type_`, or Undecodable saying why not."""
    try:
        return _decoder(type_).decode(data)
    except DECODE_ERRORS as exc:
        raise Undecodable(f"not a {getattr(type_, '__name__', type_)}: {exc}") from None


# The builder


@dataclass
class _MutableRobotState:
    x: float | None = None
    y: float | None = None
    yaw: float | None = None
    speed: float | None = None
    estop: bool | None = None
    speed_scale: float | None = None

    def snapshot(self) -> RobotState:
        return RobotState(self.x, self.y, self.yaw, self.speed, self.estop, self.speed_scale)


@dataclass
class _Known:
    """What a first pass over the file finds, so that one row is not made twice from two messages."""

    decided: dict[str, Decision] = field(default_factory=dict)  # goal id -> safety's decision on it
    event_times: dict[str, list[int]] = field(default_factory=dict)  # event key -> log times, sorted
    with_result: set[str] = field(default_factory=set)  # goal ids whose get_result trace is recorded


def _first_pass(messages: Iterable[Recorded], prefix: str) -> _Known:
    known = _Known()
    events = prefix + keys.SAFETY_EVENTS.path
    traces = prefix + "_trace/"
    for message in messages:
        if message.key == events:
            try:
                event: SafetyEvent = decode(message.data, SafetyEvent)
            except Undecodable:
                continue
            known.event_times.setdefault(event.key, []).append(message.log_time)
            if event.key in CMD_GOALS and (goal_id := goal_id_in(event.command)):
                known.decided[goal_id] = event.decision
        elif message.key.startswith(traces) and message.key.endswith("/_action/get_result"):
            try:
                record: TraceRecord = decode(message.data, TraceRecord)
            except Undecodable:
                continue
            held = bytes(record.reply) != b"null" or record.error
            if record.key in RESULT_TYPES and held and (goal_id := goal_id_in(record.query)):
                known.with_result.add(goal_id)
    for times in known.event_times.values():
        times.sort()  # looked up by bisection: a file of many plan checks is not quadratic
    return known


class _Builder:
    def __init__(self, recording: RecordingFile, everything: bool) -> None:
        self.robot = recording.robot
        self.prefix = keys.prefix(self.robot) + "/"
        self.everything = everything
        self.start = recording.messages[0].log_time if recording.messages else 0
        self.end = recording.messages[-1].log_time if recording.messages else 0
        self.known = _first_pass(recording.messages, self.prefix)
        self.state = _MutableRobotState()
        self.rows: list[Row] = []
        self.now = 0
        self.source = ""
        self.goals: dict[str, str] = {}  # goal id -> the command in words
        self.goal_values: dict[str, Any] = {}  # goal id -> the goal as safety decided on it
        self.results_shown: set[str] = set()
        self.feedback: dict[str, tuple[Any, ...]] = {}  # plan goal id -> the last step feedback shown
        self.twists: dict[str, tuple[Row, tuple[float, float]]] = {}  # cmd_vel key -> last row, values
        self.bad: dict[str, Row] = {}  # key -> the row about its first undecodable message
        self.suspects: dict[tuple[str, str], Row] = {}  # (key, why) -> the latest row about such messages
        self.last_heartbeat: int | None = None
        self.since_heartbeat = 0
        # Heartbeats of several senders came at once since safety's last one: the latch is unknown.
        self.conflicted = False
        self.handlers = {
            keys.ODOM.path: self._odom,
            keys.HEARTBEAT.path: self._heartbeat,
            keys.SAFETY_EVENTS.path: self._event,
            keys.ESTOP.path: self._estop,
            keys.EXECUTE_PLAN.feedback.path: self._plan_feedback,
            keys.EXECUTE_PLAN.status.path: self._plan_status,
            keys.NEW_INCIDENT.path: self._incident,
            keys.PLANNER_RECOVERIES.path: self._recovery,
            **{path: self._cmd_status for path in CMD_STATUS},
        }

    # Rows

    def row(
        self,
        kind: EventKind,
        key: str,
        summary: str,
        level: Level = Level.INFO,
        decision: Decision | None = None,
        rule: str | None = None,
        target: tuple[float, float] | None = None,
        implied: bool = False,
    ) -> Row:
        row = Row(
            t=(self.now - self.start) / 1e9,
            log_time=self.now,
            kind=kind,
            key=key,
            summary=summary,
            state=self.state.snapshot(),
            source=self.source,
            level=level,
            decision=decision,
            rule=rule,
            target=target,
            implied=implied,
        )
        self.rows.append(row)
        return row

    def add(self, message: Recorded, flag: Flag | None = None) -> None:
        if not message.key.startswith(self.prefix):
            if self.everything:
                self.now, self.source = message.log_time, message.key
                self._raw(message.key, message)
            return
        key = message.key[len(self.prefix) :]
        self.now, self.source = message.log_time, key
        if flag is not None:
            if flag.why is Why.CONFLICTING_STREAM:
                self._conflicting_heartbeat()
            self._suspect(flag)
            return
        if key != keys.HEARTBEAT.path:
            self.since_heartbeat += 1
        before = len(self.rows)
        handler = self.handlers.get(key)
        try:
            if handler is not None:
                handler(message.data)
            elif key.startswith("_trace/"):
                self._trace(decode(message.data, TraceRecord))
        except Undecodable as exc:
            self._bad(key, str(exc))
        if self.everything and len(self.rows) == before:
            self._raw(key, message)

    def _raw(self, key: str, message: Recorded) -> None:
        self.row(EventKind.MESSAGE, key, preview(message.data.decode(errors="replace"), 2 * PREVIEW))

    def _suspect(self, flag: Flag) -> None:
        """Folded into the row about the last one like it, when that is at most a second old."""
        last = self.suspects.get((flag.path, flag.why))
        if last is not None and self.now - last.log_time <= SAME_CHANGE * 1e9:
            last.repeats += 1
            return
        row = self.row(EventKind.SUSPECT, flag.path, f"NOT SAFETY'S: {flag.text}", Level.BAD)
        self.suspects[(flag.path, flag.why)] = row

    def _conflicting_heartbeat(self) -> None:
        """A heartbeat that may be safety's or a forger's: neither its latch nor the one before holds now."""
        self.state.estop, self.state.speed_scale = None, None
        self.last_heartbeat, self.since_heartbeat = self.now, 0
        self.conflicted = True

    def _bad(self, key: str, why: str) -> None:
        if key in self.bad:
            self.bad[key].repeats += 1
            return
        self.bad[key] = self.row(EventKind.BAD, key, f"a message on {key} does not decode: {why}", Level.BAD)

    def finish(self) -> list[Row]:
        if self.last_heartbeat is not None and (self.end - self.last_heartbeat) / 1e9 > HEARTBEAT_GAP:
            self.now, self.source = self.end, keys.HEARTBEAT.path
            silent = (self.end - self.last_heartbeat) / 1e9
            self.row(
                EventKind.HEARTBEAT,
                keys.HEARTBEAT.path,
                f"no heartbeat from safety in the last {silent:.2f} s of the recording: the robot stops without one",
                Level.BAD,
            )
        told = told_by_safety([r for r in self.rows if not r.implied])
        return [r for r in self.rows if not r.implied or not told(r)]

    # Robot state

    def _odom(self, data: bytes) -> None:
        odom: Odometry = decode(data, Odometry)
        self.state.x, self.state.y, self.state.yaw = odom.pose.x, odom.pose.y, odom.pose.yaw
        self.state.speed = odom.linear_x

    def _heartbeat(self, data: bytes) -> None:
        status: SafetyStatus = decode(data, SafetyStatus)
        key = keys.HEARTBEAT.path
        if self.last_heartbeat is not None and (gap := (self.now - self.last_heartbeat) / 1e9) > HEARTBEAT_GAP:
            if self.since_heartbeat:
                why = f"no heartbeat from safety for {gap:.2f} s before this one: the robot stops without one"
            else:
                why = f"nothing at all was recorded for {gap:.2f} s, heartbeats included (recorder or network stalled?)"
            self.row(EventKind.HEARTBEAT, key, why, Level.BAD)
        self.last_heartbeat, self.since_heartbeat = self.now, 0
        state = self.state
        latched, scale = state.estop, state.speed_scale
        state.estop, state.speed_scale = status.estop.latched, status.speed_scale
        estop = status.estop
        after_conflict, self.conflicted = self.conflicted, False
        if latched is None and after_conflict:
            said = f"latched: by {estop.source}: {estop.reason}" if estop.latched else "clear"
            why = f"e-stop {said} (the first heartbeat of one sender after several senders' at once)"
            kind, level = (EventKind.ESTOP, Level.BAD) if estop.latched else (EventKind.HEARTBEAT, Level.WARN)
            self.row(kind, key, why, level)
            return
        if latched is None:
            if estop.latched:
                why = f"e-stop latched when the recording starts: by {estop.source}: {estop.reason}"
                self.row(EventKind.ESTOP, key, why, Level.BAD, Decision.LATCHED, implied=True)
            return
        if estop.latched and not latched:
            why = f"e-stop latched (seen in the heartbeat): by {estop.source}: {estop.reason}"
            self.row(EventKind.ESTOP, key, why, Level.BAD, Decision.LATCHED, implied=True)
        elif latched and not estop.latched:
            self.row(
                EventKind.RESET, key, "e-stop cleared (seen in the heartbeat)", Level.GOOD, Decision.RESET, implied=True
            )
        if scale is not None and status.speed_scale != scale:
            why = f"speed scale {scale:g} -> {status.speed_scale:g}: {status.speed_reason or 'full speed'}"
            level = Level.WARN if status.speed_scale < 1.0 else Level.INFO
            self.row(EventKind.SPEED, key, why, level, Decision.LIMITED, implied=True)

    # Safety

    def _estop(self, data: bytes) -> None:
        key = keys.ESTOP.path
        try:
            estop: EStop = decode(data, EStop)
        except Undecodable:
            # Safety latches on these too (fail closed): say so rather than call it bad.
            self.row(EventKind.ESTOP, key, f"an e-stop message that does not decode ({len(data)} bytes)", Level.BAD)
            return
        self.row(EventKind.ESTOP, key, f"e-stop requested by {estop.source}: {estop.reason}", Level.BAD)

    def _event(self, data: bytes) -> None:
        event: SafetyEvent = decode(data, SafetyEvent)
        command: Any = None
        if (type_ := EVENT_COMMANDS.get(event.key)) is not None:
            try:
                command = decode(event.command, type_)
            except Undecodable:
                command = None
        goal = command.goal if isinstance(command, SendGoal) else command
        rule = None if event.rule is None else str(event.rule)
        decision = event.decision
        key = event.key
        if decision is Decision.LATCHED and ALREADY_LATCHED in event.values:
            # Asked for again while it held: the latch is the first one's, this is who else asked.
            self.row(
                EventKind.ESTOP,
                key,
                f"e-stop asked for again while latched: {event.reason}",
                Level.WARN,
                decision,
                rule,
            )
        elif decision is Decision.LATCHED:
            self.state.estop = True
            said = _rule(rule) if event.rule is not Rule.ESTOP else ""
            self.row(EventKind.ESTOP, key, f"e-stop latched {event.reason}{said}", Level.BAD, decision, rule)
        elif decision is Decision.RESET:
            self.state.estop = False
            self.row(EventKind.RESET, key, f"e-stop reset {event.reason}", Level.GOOD, decision, rule)
        elif decision is Decision.LIMITED:
            scale = event.values.get("scale")
            if scale is not None:
                self.state.speed_scale = scale
            level = Level.WARN if scale is not None and scale < 1.0 else Level.INFO
            said = f"speed scale {scale:g}: " if scale is not None else ""
            self.row(EventKind.SPEED, key, f"{said}{event.reason}", level, decision, rule)
        elif decision is Decision.VETOED and key in CMD_VEL_KEYS:
            summary = f"vetoed {key}{_rule(rule)}: {_goal_text(goal) + ': ' if goal else ''}{event.reason}"
            self._twist_row(key, goal, EventKind.DECISION, summary, Level.BAD, decision, rule)
        elif decision is Decision.VETOED:
            what = _goal_text(goal)
            target = _target(goal, event.values)
            summary = f"vetoed {_subject(key)}{_rule(rule)}: {what + ': ' if what else ''}{event.reason}"
            self.row(EventKind.DECISION, key, summary, Level.BAD, decision, rule, target)
            if isinstance(command, SendGoal):
                self.goals[command.goal_id] = f"{_action_name(key)} {what}"
        elif decision is Decision.CLAMPED:
            sent = _goal_text(goal)
            note = f": {event.reason}" if event.reason else ""
            summary = f"clamped {_subject(key)}{_rule(rule)}: sent {sent}{note}" if sent else f"clamped {key}{note}"
            self._twist_row(key, goal, EventKind.DECISION, summary, Level.WARN, decision, rule)
        elif decision is Decision.APPROVED and isinstance(command, SendGoal):
            words = f"{_action_name(key)} {_goal_text(goal)}"
            self.goals[command.goal_id] = words
            self.goal_values[command.goal_id] = goal
            self.row(EventKind.COMMAND, key, f"{words}: approved", decision=decision)
        elif decision is Decision.APPROVED and key in CMD_VEL_KEYS:
            note = f": {event.reason}" if event.reason else ""
            self._twist_row(
                key, goal, EventKind.COMMAND, f"{key} {_goal_text(goal)}: approved{note}", Level.INFO, decision
            )
        elif decision is Decision.APPROVED and key == keys.PLAN_CHECK.path:
            self.row(EventKind.DECISION, key, f"plan approved by safety: {event.reason}", Level.GOOD, decision)
        else:
            reason = f": {event.reason}" if event.reason else ""
            self.row(
                EventKind.DECISION, key, f"{decision} {_subject(key)}{_rule(rule)}{reason}", Level.INFO, decision, rule
            )

    def _twist_row(
        self,
        key: str,
        twist: Any,
        kind: EventKind,
        summary: str,
        level: Level,
        decision: Decision,
        rule: str | None = None,
    ) -> None:
        """A cmd_vel stream is one row per change of what is sent, not one per message."""
        values = (round(twist.linear_x, 2), round(twist.angular_z, 2)) if isinstance(twist, Twist) else (math.nan, 0.0)
        last = self.twists.get(key)
        if last is not None and last[1] == values and last[0].decision is decision and last[0].rule == rule:
            last[0].repeats += 1
            return
        self.twists[key] = (self.row(kind, key, summary, level, decision, rule), values)

    # The plan

    def _plan_feedback(self, data: bytes) -> None:
        message: Feedback[ExecutePlanFeedback] = decode(data, Feedback[ExecutePlanFeedback])
        fb = message.feedback
        if fb.step is None:  # parsing, resolving, checking: the traces of those queries say more
            return
        seen = (fb.step, fb.label, fb.status, fb.message, fb.attempt, fb.failure)
        if self.feedback.get(message.goal_id) == seen:
            return
        self.feedback[message.goal_id] = seen
        status = str(fb.status) + (f" ({fb.failure})" if fb.failure else "")
        attempt = f", attempt {fb.attempt}" if fb.attempt > 1 else ""
        said = f": {fb.message}" if fb.message else ""
        level = {StepStatus.SUCCEEDED: Level.GOOD, StepStatus.FAILED: Level.BAD}.get(fb.status, Level.INFO)
        if fb.status is StepStatus.CANCELED:
            level = Level.WARN
        label = fb.label or str(fb.step + 1)
        self.row(EventKind.STEP, keys.EXECUTE_PLAN.path, f"step {label} {fb.action}: {status}{attempt}{said}", level)

    def _plan_status(self, data: bytes) -> None:
        status: GoalStatus = decode(data, GoalStatus)
        if not status.state.terminal or status.goal_id in self.known.with_result:
            return
        said = f": {status.message}" if status.message else ""
        level = Level.GOOD if status.state is GoalState.SUCCEEDED else Level.BAD
        self.row(EventKind.PLAN, keys.EXECUTE_PLAN.path, f"plan {short_id(status.goal_id)} {status.state}{said}", level)

    def _cmd_status(self, data: bytes) -> None:
        status: GoalStatus = decode(data, GoalStatus)
        if not status.state.terminal or status.goal_id in self.known.with_result:
            return
        action = CMD_STATUS[self.source]
        words = self.goals.get(status.goal_id, f"{_action_name(action.path)} goal {short_id(status.goal_id)}")
        said = f": {status.message}" if status.message else ""
        level = Level.INFO if status.state is GoalState.SUCCEEDED else Level.BAD
        self.row(EventKind.COMMAND, action.path, f"{words}: {status.state}{said}", level)

    # Queries, from their traces

    def _trace(self, record: TraceRecord) -> None:
        path = record.key
        service = SERVICES.get(path)
        if service is None:
            return
        if path == keys.EXECUTE_PLAN.send_goal.path:
            self._plan_goal(record)
        elif path == keys.EXECUTE_PLAN.cancel_goal.path or path in (a.cancel_goal.path for a in CMD_ACTIONS.values()):
            self._cancel(record)
        elif path in RESULT_TYPES:
            self._result(record)
        elif path == keys.PLAN_PARSE.path:
            self._parsed(record)
        elif path == keys.PLAN_RESOLVE.path:
            self._resolved(record)
        elif path in CMD_GOALS:
            self._cmd_goal(record)
        elif path in (keys.PLAN_CHECK.path, keys.RESET.path):
            self._told_by_event(record, service.reply)
        elif path == keys.SIM_MOVE.path:
            self._moved(record)
        elif path == keys.SIM_FAULT.path:
            self._fault(record)
        elif path == keys.GROUND_TRUTH.path:
            self._ground_truth(record)

    def _reply(self, record: TraceRecord, type_: Any) -> Any:
        """The reply in the trace: the value (maybe a ServiceError), _Failed for an error reply, or None
        when the trace does not hold it (too large to trace)."""
        if record.error:
            return _Failed(record.error)
        if bytes(record.reply) == b"null":
            return None
        return decode(record.reply, type_)

    def _plan_goal(self, record: TraceRecord) -> None:
        key = keys.EXECUTE_PLAN.path
        if record.error:
            self.row(EventKind.PLAN, key, f"plan refused: {record.error}", Level.BAD)
            return
        request = decode(record.query, keys.EXECUTE_PLAN.send_goal.request)
        goal: ExecutePlanGoal = request.goal
        flags = "".join(f" ({flag})" for flag, on in (("dry run", goal.dry_run), ("preempt", goal.preempt)) if on)
        reply = self._reply(record, keys.EXECUTE_PLAN.send_goal.reply)
        head = f"plan {short_id(request.goal_id)} submitted{flags}: {preview(goal.text, PREVIEW)!r}"
        if reply is None:
            self.row(EventKind.PLAN, key, head)
        elif reply.accepted:
            self.row(EventKind.PLAN, key, f"{head}: accepted")
        else:
            self.row(EventKind.PLAN, key, f"{head}: rejected: {reply.reason}", Level.BAD)

    def _parsed(self, record: TraceRecord) -> None:
        key = keys.PLAN_PARSE.path
        reply = self._reply(record, keys.PLAN_PARSE.reply)
        if (failed := _failure(reply)) is not None:
            self.row(EventKind.PLAN, key, f"parse failed: {failed}", Level.BAD)
        elif reply is None:
            self.row(EventKind.PLAN, key, "parsed (the plan was too large for the trace to keep)")
        elif isinstance(reply, Plan):
            steps = [f"{s.action} {s.target or ''}".strip() for s in walk(reply.steps) if s.action]
            about = f"{preview(reply.description, 50)!r}: " if reply.description else ""
            warned = f"; {len(reply.warnings)} warning(s): {'; '.join(reply.warnings)}" if reply.warnings else ""
            summary = f"parsed {about}{len(steps)} steps ({reply.source_format}): {_listed(steps)}{warned}"
            self.row(EventKind.PLAN, key, summary, Level.WARN if reply.warnings else Level.INFO)

    def _resolved(self, record: TraceRecord) -> None:
        key = keys.PLAN_RESOLVE.path
        reply = self._reply(record, keys.PLAN_RESOLVE.reply)
        if (failed := _failure(reply)) is not None:
            self.row(EventKind.PLAN, key, f"resolve failed: {failed}", Level.BAD)
        elif reply is None:
            self.row(EventKind.PLAN, key, "resolved (the plan was too large for the trace to keep)")
        elif isinstance(reply, GroundedPlan):
            steps = [step.brief() for step in reply.steps]
            fallbacks = f"; {len(reply.fallbacks)} on_failure" if reply.fallbacks else ""
            warned = f"; {len(reply.warnings)} warning(s): {'; '.join(reply.warnings)}" if reply.warnings else ""
            summary = f"resolved {len(steps)} steps: {_listed(steps)}{fallbacks}{warned}"
            self.row(EventKind.PLAN, key, summary, Level.WARN if reply.warnings else Level.INFO)

    def _result(self, record: TraceRecord) -> None:
        path = record.key
        goal_id = goal_id_in(record.query) or "?"
        if goal_id in self.results_shown:
            return
        reply = self._reply(record, RESULT_TYPES[path])
        if reply is None:
            return
        self.results_shown.add(goal_id)
        plan = path == keys.EXECUTE_PLAN.get_result.path
        base = path.split("/_action/")[0]
        if (failed := _failure(reply)) is not None:
            what = f"plan {short_id(goal_id)}" if plan else f"{_action_name(path)} goal {short_id(goal_id)}"
            self.row(EventKind.PLAN if plan else EventKind.COMMAND, base, f"{what}: no result: {failed}", Level.BAD)
        elif plan:
            self._plan_result(goal_id, reply)
        else:
            self._cmd_result(base, goal_id, reply)

    def _plan_result(self, goal_id: str, reply: ResultResponse[ExecutePlanResult]) -> None:
        key = keys.EXECUTE_PLAN.path
        result = reply.result
        if result is None:
            said = f": {reply.message}" if reply.message else ""
            level = Level.GOOD if reply.state is GoalState.SUCCEEDED else Level.BAD
            self.row(EventKind.PLAN, key, f"plan {short_id(goal_id)} {reply.state}{said}", level)
            return
        counts: dict[str, int] = {}
        for step in result.steps:
            counts[str(step.status)] = counts.get(str(step.status), 0) + 1
        tally = ", ".join(f"{n} {status}" for status, n in counts.items())
        failure = f" ({result.failure})" if result.failure else ""
        reason = f": {result.reason}" if result.reason else ""
        steps = f"; steps: {tally}" if tally else ""
        summary = f"plan {short_id(goal_id)} {result.status} at stage {result.stage}{failure}{reason}{steps}"
        self.row(EventKind.PLAN, key, summary, Level.GOOD if result.status is PlanStatus.SUCCEEDED else Level.BAD)

    def _cmd_result(self, base: str, goal_id: str, reply: ResultResponse[Any]) -> None:
        words = self.goals.get(goal_id, f"{_action_name(base)} goal {short_id(goal_id)}")
        result = reply.result
        notes = [reply.message] if reply.message else []
        level = Level.INFO if reply.state is GoalState.SUCCEEDED else Level.BAD
        if isinstance(result, NavigateToPoseResult):
            notes += [m for m in (result.message,) if m and m not in notes] + [f"ended at {fmt_pose(result.pose)}"]
        elif isinstance(result, FollowJointTrajectoryResult):
            notes += [m for m in (result.message,) if m and m not in notes]
        elif isinstance(result, GripperCommandResult):
            meant = self.goal_values.get(goal_id)
            if result.holding and result.holding not in reply.message:
                notes.append(f"holding {result.holding}")
            elif not result.holding and isinstance(meant, GripperCommandGoal) and meant.object_id:
                notes.append(f"holding nothing, though it closed to hold {meant.object_id}")
                level = Level.WARN if level is Level.INFO else level
        said = f": {'; '.join(notes)}" if notes else ""
        self.row(EventKind.COMMAND, base, f"{words}: {reply.state}{said}", level)

    def _cancel(self, record: TraceRecord) -> None:
        path = record.key
        base = path.split("/_action/")[0]
        plan = base == keys.EXECUTE_PLAN.path
        goal_id = goal_id_in(record.query) or "?"
        if plan:
            what = "every plan" if goal_id == "all" else f"plan {short_id(goal_id)}"
        else:
            what = self.goals.get(goal_id, f"{_action_name(path)} goal {short_id(goal_id)}")
        reply = self._reply(record, SERVICES[path].reply)
        if (failed := _failure(reply)) is not None:
            outcome, level = f"failed: {failed}", Level.BAD
        elif reply is None:
            outcome, level = "asked", Level.WARN
        elif reply.accepted:
            outcome, level = "accepted", Level.WARN
        else:
            outcome, level = f"nothing to cancel ({reply.reason})" if reply.reason else "refused", Level.INFO
        self.row(EventKind.PLAN if plan else EventKind.COMMAND, base, f"cancel {what}: {outcome}", level)

    def _cmd_goal(self, record: TraceRecord) -> None:
        """A goal safety answered; a row only when its event did not already say it all."""
        path = record.key
        action = CMD_GOALS[path]
        goal_id = goal_id_in(record.query)
        decided = self.known.decided.get(goal_id or "")
        if record.error:
            self.row(EventKind.COMMAND, path, f"{_action_name(path)} goal refused: {record.error}", Level.BAD)
            return
        reply = self._reply(record, action.send_goal.reply)
        if decided is Decision.VETOED or (decided is not None and (reply is None or reply.accepted)):
            return
        request = decode(record.query, action.send_goal.request)
        words = self.goals.setdefault(request.goal_id, f"{_action_name(path)} {_goal_text(request.goal)}")
        if reply is None:
            self.row(EventKind.COMMAND, path, f"{words}: sent")
        elif reply.accepted:
            self.row(EventKind.COMMAND, path, f"{words}: accepted")
        else:
            by = "approved by safety, refused by the robot" if decided is not None else "refused"
            self.row(EventKind.COMMAND, path, f"{words}: {by}: {reply.reason}", Level.BAD)

    def _told_by_event(self, record: TraceRecord, reply_type: Any) -> None:
        """A plan check or reset: safety's event about it is the row; the trace only when that is missing."""
        path = record.key
        window = SAME_CHANGE * 1e9
        times = self.known.event_times.get(path, [])
        nearest = bisect.bisect_left(times, self.now - window)  # the first event from now - window on
        if nearest < len(times) and times[nearest] <= self.now + window:
            return
        reply = self._reply(record, reply_type)
        if (failed := _failure(reply)) is not None:
            self.row(EventKind.DECISION, path, f"{_subject(path)} refused: {failed}", Level.BAD)
        elif reply is not None:
            ok = getattr(reply, "ok", True)
            said = getattr(reply, "message", "") or "; ".join(getattr(reply, "checks", []))
            kind = EventKind.RESET if path == keys.RESET.path else EventKind.DECISION
            verb = "approved" if ok else "refused"
            self.row(kind, path, f"{_subject(path)} {verb}: {said}", Level.GOOD if ok else Level.BAD)

    def _moved(self, record: TraceRecord) -> None:
        reply = self._reply(record, keys.SIM_MOVE.reply)
        if isinstance(reply, _Failed):  # the request itself was refused, and is not in the trace
            self.row(EventKind.WORLD, record.key, f"a move in the simulation refused: {reply.message}", Level.WARN)
            return
        request: MoveEntity = decode(record.query, MoveEntity)
        asked = f"move {request.id} to {fmt_point(request.x, request.y)} in the simulation"
        if isinstance(reply, Moved):
            self.row(EventKind.WORLD, record.key, f"{asked}: now at {fmt_point(reply.position.x, reply.position.y)}")
        elif (failed := _failure(reply)) is not None:
            self.row(EventKind.WORLD, record.key, f"{asked}: refused: {failed}", Level.WARN)

    def _fault(self, record: TraceRecord) -> None:
        reply = self._reply(record, keys.SIM_FAULT.reply)
        if isinstance(reply, _Failed):
            self.row(EventKind.WORLD, record.key, f"a fault in the simulation refused: {reply.message}", Level.WARN)
            return
        request: InjectFault = decode(record.query, InjectFault)
        asked = f"fault {request.kind}{' ' + request.target if request.target else ''} injected in the simulation"
        if isinstance(reply, FaultInjected):
            self.row(EventKind.WORLD, record.key, f"{asked}: {reply.message}", Level.WARN)
        elif (failed := _failure(reply)) is not None:
            self.row(EventKind.WORLD, record.key, f"{asked}: refused: {failed}", Level.WARN)

    def _incident(self, data: bytes) -> None:
        incident: Incident = decode(data, Incident)
        where = "" if incident.x is None or incident.y is None else f" at {fmt_point(incident.x, incident.y)}"
        by = f" ({incident.source})" if incident.source else ""
        summary = f"incident {incident.id} remembered: {incident.kind}{by}{where}: {incident.reason}"
        self.row(EventKind.INCIDENT, keys.NEW_INCIDENT.path, summary, Level.WARN, target=_point(incident))

    def _recovery(self, data: bytes) -> None:
        recovery: Recovery = decode(data, Recovery)
        failed = f" after {recovery.failure or 'a failure'}" if recovery.failed_goal else ""
        step = f" at step {recovery.step}" if recovery.step is not None else ""
        goal = f" as plan {short_id(recovery.goal_id)}" if recovery.goal_id else ""
        summary = f"recovery {recovery.number}{failed}{step}: {recovery.outcome}{goal}"
        summary += f": {recovery.reason}" if recovery.reason else ""
        good = recovery.outcome in (RecoveryOutcome.SENT, RecoveryOutcome.SUCCEEDED)
        self.row(EventKind.RECOVERY, keys.PLANNER_RECOVERIES.path, summary, Level.GOOD if good else Level.WARN)

    def _ground_truth(self, record: TraceRecord) -> None:
        truth = self._reply(record, GroundTruth)
        if isinstance(truth, GroundTruth):
            holding = truth.holding or "nothing"
            summary = f"simulator ground truth: robot at {fmt_pose(truth.robot)}, gripper holding {holding}"
            self.row(EventKind.WORLD, record.key, summary)


def _point(incident: Incident) -> tuple[float, float] | None:
    return None if incident.x is None or incident.y is None else (incident.x, incident.y)


def _rule(rule: str | None) -> str:
    return f" ({rule})" if rule else ""


def _target(goal: Any, values: dict[str, float]) -> tuple[float, float] | None:
    """Where a vetoed command aimed the base: its goal pose, else the point the veto names."""
    if isinstance(goal, NavigateToPoseGoal):
        return goal.pose.x, goal.pose.y
    if "x" in values and "y" in values:
        return values["x"], values["y"]
    return None


def told_by_safety(rows: list[Row]) -> Callable[[Row], bool]:
    """Whether safety's own event about the change an implied row saw in the heartbeat is among `rows`:
    an event of the same decision within SAME_CHANGE of it. Each decision's times sorted once, so a
    file of many implied rows and many events is read in n log n, not n times n (16,000 took 11 s)."""
    times: dict[Decision | None, list[int]] = {}
    for r in rows:
        if r.source == keys.SAFETY_EVENTS.path:
            times.setdefault(r.decision, []).append(r.log_time)
    for each in times.values():
        each.sort()
    window = SAME_CHANGE * 1e9

    def told(implied: Row) -> bool:
        at = times.get(implied.decision, [])
        k = bisect.bisect_left(at, implied.log_time - window)
        return k < len(at) and at[k] <= implied.log_time + window

    return told
