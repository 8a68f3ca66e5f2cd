"""Recorded robot commands and heartbeats that are not safety's: no MAC, another sender, replayed, undecided. Pure."""

from __future__ import annotations

import bisect
import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import goal_id_in
from schemas.common import DECODE_ERRORS
from schemas.robot import Twist
from schemas.safety import Decision, SafetyEvent
from schemas.trace import TraceRecord
from services.recorder.reader import Recorded
from services.robotlink import Signature, mac_matches, unpack

# A command on robot/cmd_vel matches a decision of safety's recorded this close to it (seconds).
MATCH_WINDOW = 1.0
Actions = tuple[keys.ActionKeys[Any, Any, Any], ...]
ROBOT_ACTIONS: Actions = (keys.ROBOT_NAVIGATE, keys.ROBOT_TRAJECTORY, keys.ROBOT_GRIPPER)
CMD_ACTIONS: Actions = (keys.CMD_NAVIGATE, keys.CMD_TRAJECTORY, keys.CMD_GRIPPER)
# The robot's goal path -> safety's key for the same goal.
SAFETY_GOAL = {robot.send_goal.path: cmd.send_goal.path for robot, cmd in zip(ROBOT_ACTIONS, CMD_ACTIONS, strict=True)}
ROBOT_CANCELS = frozenset(a.cancel_goal.path for a in ROBOT_ACTIONS)
TWIST_DECISIONS = (keys.CMD_VEL.path, keys.TELEOP_CMD_VEL.path)
PASSED = (Decision.APPROVED, Decision.CLAMPED)
# Twists closer than this in each value are the same.
SAME = 1e-6
# A twist's own cell first (every decision in it is the same twist), then those around it.
NEIGHBOURS = sorted(((dx, dz) for dx in (-1, 0, 1) for dz in (-1, 0, 1)), key=lambda d: abs(d[0]) + abs(d[1]))


class Why(enum.StrEnum):
    """Why a message is flagged: the same words for one kind, for folding repeats together."""

    UNSIGNED = "not signed by safety (no robot-link MAC)"
    MALFORMED = "robot-link MAC malformed"
    BAD_MAC = "robot-link MAC does not match the robot key"
    REPLAYED = "replayed or reordered (robot-link counter not increasing)"
    OTHER_SENDER = "signed by another sender than safety's heartbeat stream"
    CONFLICTING_STREAM = "one of several heartbeat streams at once: which is safety's cannot be told"
    CONFLICTED_SENDER = "signed by a sender whose heartbeats all conflict with another stream's"
    NO_DECISION = "no matching safety decision"
    REFUSED = "refused by the robot as not safety's"


@dataclass(frozen=True)
class Flag:
    """One message that is not safety's, or does not follow from a decision of safety's."""

    index: int  # in the messages audited
    log_time: int
    path: str  # the key under the robot's prefix (a goal's: the key it went to)
    why: Why
    detail: str = ""

    @property
    def text(self) -> str:
        return f"{self.path}: {self.why}" + (f" ({self.detail})" if self.detail else "")


@dataclass
class Audit:
    flags: list[Flag]
    # Said once when the recording cannot be audited (made without the robot link's MACs).
    note: str = ""

    def at(self) -> dict[int, Flag]:
        return {f.index: f for f in self.flags}


def _twist(data: bytes | msgspec.Raw) -> Twist | None:
    try:
        return msgspec.json.decode(data, type=Twist)
    except (*DECODE_ERRORS, msgspec.ValidationError):
        return None


def _same(a: Twist, b: Twist) -> bool:
    return abs(a.linear_x - b.linear_x) < SAME and abs(a.angular_z - b.angular_z) < SAME


def audit(messages: Sequence[Recorded], robot: str, robot_key: bytes | None = None) -> Audit:
    """Every robot/** command (robot/cmd_vel puts, goals and cancels sent to the robot, from their
    traces) and every heartbeat in `messages` that is not safety's: without its MAC, with a MAC that
    does not check out under `robot_key` (when given), replayed, from a sender that is not the one
    beating safety's heartbeat at the time; and every robot command without a decision of safety's
    that allows it. A recording with no MAC at all (made before the robot link) is not audited."""
    root = keys.prefix(robot) + "/"
    if not any(m.attachment is not None for m in messages):
        return Audit([], "the recording carries no robot-link MACs: safety's messages cannot be told from others")
    flags: list[Flag] = []
    signed: list[tuple[int, Recorded, str, Signature]] = []  # heartbeats and cmd_vel with a MAC
    events: list[tuple[float, SafetyEvent]] = []
    goal_traces: list[tuple[int, Recorded, TraceRecord]] = []
    for i, m in enumerate(messages):
        if not m.key.startswith(root):
            continue
        path = m.key[len(root) :]
        if path in (keys.HEARTBEAT.path, keys.ROBOT_CMD_VEL.path):
            sig = unpack(m.attachment)
            if m.attachment is None:
                flags.append(Flag(i, m.log_time, path, Why.UNSIGNED))
            elif sig is None:
                flags.append(Flag(i, m.log_time, path, Why.MALFORMED, f"{len(m.attachment)} bytes"))
            elif robot_key is not None and not mac_matches(robot_key, m.key, m.data, sig):
                flags.append(Flag(i, m.log_time, path, Why.BAD_MAC))
            else:
                signed.append((i, m, path, sig))
        elif path == keys.SAFETY_EVENTS.path:
            try:
                events.append((m.log_time / 1e9, msgspec.json.decode(m.data, type=SafetyEvent)))
            except (*DECODE_ERRORS, msgspec.ValidationError):
                pass
        elif path.startswith("_trace/") and path.split("/", 2)[-1] in (*SAFETY_GOAL, *ROBOT_CANCELS):
            if path.split("/")[1] == "safety":
                continue  # safety's own trace of a query it answered: none go to robot/**
            try:
                goal_traces.append((i, m, msgspec.json.decode(m.data, type=TraceRecord)))
            except (*DECODE_ERRORS, msgspec.ValidationError):
                pass
    safety_sessions, conflicted = _heartbeat_streams(signed, flags)
    flagged = {f.index for f in flags}
    decided = _Decided(events)
    last: dict[tuple[bytes, str], int] = {}
    for i, m, path, sig in signed:
        if i in flagged:
            continue
        previous = last.get((sig.session, path), 0)
        if sig.counter <= previous:
            flags.append(Flag(i, m.log_time, path, Why.REPLAYED, f"counter {sig.counter} after {previous}"))
            continue
        last[(sig.session, path)] = sig.counter
        if path == keys.ROBOT_CMD_VEL.path:
            if sig.session in conflicted:
                flags.append(Flag(i, m.log_time, path, Why.CONFLICTED_SENDER, f"sender {sig.session.hex()[:8]}"))
            elif sig.session not in safety_sessions:
                flags.append(Flag(i, m.log_time, path, Why.OTHER_SENDER, f"sender {sig.session.hex()[:8]}"))
            elif not decided.twist(m):
                flags.append(Flag(i, m.log_time, path, Why.NO_DECISION))
    flags.extend(_goal_flags(goal_traces, events))
    return Audit(sorted(flags, key=lambda f: f.index))


def _heartbeat_streams(
    signed: list[tuple[int, Recorded, str, Signature]], flags: list[Flag]
) -> tuple[set[bytes], set[bytes]]:
    """The senders whose heartbeats are safety's, and those whose heartbeats all conflict.

    One safety beats at a time (a restart is a new sender after the last), so where the span (first to
    last beat) of one sender's heartbeats overlaps another's, the beats cannot tell which is safety's:
    not by which beats more often, as a forger can beat faster. Every beat inside another sender's span
    is flagged as conflicting and taken from no one (its latch state is unknown). With the robot key a
    forger's beats are already flagged (BAD_MAC) and never get here, so safety's stream stands alone."""
    spans: dict[bytes, tuple[int, int]] = {}  # sender -> first, last log time
    for _, m, path, sig in signed:
        if path == keys.HEARTBEAT.path:
            first, end = spans.get(sig.session, (m.log_time, m.log_time))
            spans[sig.session] = (min(first, m.log_time), max(end, m.log_time))
    firsts = sorted(first for first, _ in spans.values())
    ends = sorted(end for _, end in spans.values())
    clear: set[bytes] = set()
    conflicting: set[bytes] = set()
    for i, m, path, sig in signed:
        if path != keys.HEARTBEAT.path:
            continue
        # How many senders' spans hold this beat: those begun by then, less those already over.
        senders = bisect.bisect_right(firsts, m.log_time) - bisect.bisect_left(ends, m.log_time)
        if senders > 1:
            detail = f"sender {sig.session.hex()[:8]}, {senders} senders beating at once"
            flags.append(Flag(i, m.log_time, path, Why.CONFLICTING_STREAM, detail))
            conflicting.add(sig.session)
        else:
            clear.add(sig.session)
    return clear, conflicting - clear


class _Decided:
    """The twists safety approved or clamped, by value and time, to find the decision of a twist on
    robot/cmd_vel in O(log n)."""

    def __init__(self, events: list[tuple[float, SafetyEvent]]) -> None:
        cells: dict[tuple[int, int], list[tuple[float, Twist]]] = {}
        for at, event in events:
            if event.key in TWIST_DECISIONS and event.decision in PASSED:
                decided = _twist(event.command)
                if decided is not None and (cell := _cell(decided)) is not None:
                    cells.setdefault(cell, []).append((at, decided))
        self._cells = {cell: sorted(twists, key=lambda d: d[0]) for cell, twists in cells.items()}
        self._times = {cell: [at for at, _ in twists] for cell, twists in self._cells.items()}

    def twist(self, m: Recorded) -> bool:
        """A twist safety put on robot/cmd_vel follows a decision: a stop (any refusal, a latch), or the
        twist an approval or clamp carries, recorded within MATCH_WINDOW."""
        twist = _twist(m.data)
        if twist is None:
            return False
        if _same(twist, Twist()):
            return True  # a stop: safety's own (a veto, a latch); never a danger
        t = m.log_time / 1e9
        if (cell := _cell(twist)) is None:
            return False
        x, z = cell
        # Twists the same within _same's tolerance are at most one cell apart; in its own cell, all are.
        for near in ((x + dx, z + dz) for dx, dz in NEIGHBOURS):
            if (times := self._times.get(near)) is None:
                continue
            twists = self._cells[near]
            for k in range(bisect.bisect_left(times, t - MATCH_WINDOW), len(times)):
                if times[k] > t + MATCH_WINDOW:
                    break
                if _same(twists[k][1], twist):
                    return True
        return False


def _cell(twist: Twist) -> tuple[int, int] | None:
    if not (math.isfinite(twist.linear_x) and math.isfinite(twist.angular_z)):
        return None  # no decision carries one, and rounding it fails
    return round(twist.linear_x / SAME), round(twist.angular_z / SAME)


def _goal_flags(traces: list[tuple[int, Recorded, TraceRecord]], events: list[tuple[float, SafetyEvent]]) -> list[Flag]:
    passed = {
        (event.key, goal_id)
        for _, event in events
        if event.decision in PASSED and (goal_id := goal_id_in(event.command)) is not None
    }
    flags = []
    for i, m, trace in traces:
        if "not signed by safety" in trace.error or "robot-link" in trace.error:
            flags.append(Flag(i, m.log_time, trace.key, Why.REFUSED, trace.error))
        elif trace.key in SAFETY_GOAL:
            goal_id = goal_id_in(trace.query)
            if goal_id is None or (SAFETY_GOAL[trace.key], goal_id) not in passed:
                flags.append(Flag(i, m.log_time, trace.key, Why.NO_DECISION, f"goal {goal_id or '?'}"))
    return flags
