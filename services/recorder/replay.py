"""What a replay sends, and when: recorded messages moved to another robot's keys, on the recorded clock.

By default everything is replayed under a robot name ending in `_replay` (`<robot>_replay`), where
no service acts: viewers and recorders see the incident again, no robot does. Onto any other robot
only commands are replayed, and only through safety's doors: velocity commands on `cmd/**`, and
the `send_goal` / `cancel_goal` queries safety answered (from its `_trace/**`), asked again of
safety, which checks them as it checks anything. Nothing is then replayed onto `robot/**` (what
only safety writes), onto sensors, or onto the e-stop.
"""

from __future__ import annotations

import enum
import json
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from schemas import keys
from schemas.actions import CANCEL_ALL
from services.recorder.reader import Recorded

# Replays of everything go under robot names ending so; nothing real is named like that.
REPLAY_SUFFIX = "_replay"

# The commands safety accepts from programs and people: the only topics put onto a live robot.
LIVE_TOPICS = frozenset({keys.CMD_VEL.path, keys.TELEOP_CMD_VEL.path})
# The goal queries asked again of a live robot's safety.
LIVE_QUERIES = frozenset(
    path
    for action in (keys.CMD_NAVIGATE, keys.CMD_TRAJECTORY, keys.CMD_GRIPPER)
    for path in (action.send_goal.path, action.cancel_goal.path)
)
SAFETY_TRACE = "_trace/safety/"
# A longer silence between two replayed messages is shortened to this (seconds, at speed 1): a log
# time months ahead, in a damaged or hostile file, would otherwise hold the replay for months. Ten
# minutes with nothing on any replayed key is no pause of a session worth keeping to the second.
MAX_GAP = 600.0
BACKWARDS = "recorded before the message ahead of them (log time going backwards): sent right after it"


class ReplayKind(enum.StrEnum):
    PUT = "put"  # a publication, put again
    QUERY = "query"  # a recorded query, asked again (live commands only)


@dataclass(frozen=True)
class Item:
    at: float  # seconds after the first replayed message, at speed 1
    kind: ReplayKind
    key: str  # the full key to put or ask on
    payload: bytes
    goal_id: str | None = None  # the new id of a goal a live replay sends


@dataclass(frozen=True)
class ReplayPlan:
    items: list[Item]
    skipped: dict[str, int]  # why -> how many recorded messages were not replayed
    retimed: dict[str, int] = field(default_factory=dict)  # why -> how many are sent off their recorded time

    @property
    def duration(self) -> float:
        return max((item.at for item in self.items), default=0.0)


def default_target(robot: str) -> str:
    return f"{robot}{REPLAY_SUFFIX}"


def is_replay_name(robot: str) -> bool:
    return robot.endswith(REPLAY_SUFFIX)


def _relative(robot: str, key: str) -> str | None:
    root = keys.prefix(robot) + "/"
    return key[len(root) :] if key.startswith(root) else None


def plan_replay(
    messages: Iterable[Recorded],
    robot: str,
    target: str,
    live: bool = False,
    key_error: Callable[[str], str | None] | None = None,
    max_gap: float = MAX_GAP,
) -> ReplayPlan:
    """The messages of `robot` to send to `target`, in recorded order, at recorded offsets.

    With `live` only commands, as described above; goal ids are replaced by new ones (a goal id
    names one goal, and the recorded ones may still be known to the robot), consistently for a
    goal's send and cancel. `key_error` says what is wrong with a key the transport would refuse
    (None for a good one): such messages are skipped. Offsets never go backwards, and a silence
    longer than `max_gap` seconds is shortened to it; `retimed` counts both.
    """
    items: list[Item] = []
    skipped: dict[str, int] = {}
    retimed: dict[str, int] = {}
    goal_ids: dict[str, str] = {}
    bad_keys: dict[str, str | None] = {}
    first_bad: tuple[str, str] | None = None
    refused = 0
    previous: int | None = None  # the log time of the last message planned
    at = 0.0

    def skip(why: str) -> None:
        skipped[why] = skipped.get(why, 0) + 1

    def retime(why: str) -> None:
        retimed[why] = retimed.get(why, 0) + 1

    for message in messages:
        path = _relative(robot, message.key)
        if path is None:
            skip(f"not under {keys.prefix(robot)}/")
            continue
        if live:
            item = _live_item(path, message.data, goal_ids)
            if item is None:
                skip("not a command (a live robot only gets commands, through safety)")
                continue
            kind, path, payload, goal_id = item
        else:
            kind, payload, goal_id = ReplayKind.PUT, message.data, None
        key = f"{keys.prefix(target)}/{path}"
        if key_error is not None:
            if key not in bad_keys:
                bad_keys[key] = key_error(key)
            if (error := bad_keys[key]) is not None:
                refused += 1
                first_bad = first_bad or (key, error)
                continue
        if previous is not None:
            gap = (message.log_time - previous) / 1e9
            if gap < 0:
                retime(BACKWARDS)
            elif gap > max_gap:
                retime(f"after a silence of more than {max_gap:g} s (the gap is shortened to {max_gap:g} s)")
            at += min(max(gap, 0.0), max_gap)
        previous = message.log_time if previous is None else max(previous, message.log_time)
        items.append(Item(at, kind, key, payload, goal_id))
    if first_bad is not None:
        key, error = first_bad
        skipped[f"on a key that is not a valid Zenoh key expression (first {key!r}: {error})"] = refused
    return ReplayPlan(items, skipped, retimed)


def _live_item(path: str, data: bytes, goal_ids: dict[str, str]) -> tuple[ReplayKind, str, bytes, str | None] | None:
    if path in LIVE_TOPICS:
        return ReplayKind.PUT, path, data, None
    if not path.startswith(SAFETY_TRACE):
        return None
    query_path = path[len(SAFETY_TRACE) :]
    if query_path not in LIVE_QUERIES:
        return None
    try:
        trace = json.loads(data)
        query = trace["query"]
        old = query["goal_id"]
    except (ValueError, KeyError, TypeError, RecursionError):
        return None
    if not isinstance(old, str):
        return None
    goal_id = None
    if query_path.endswith("/send_goal"):
        goal_id = goal_ids[old] = f"replay-{uuid.uuid4().hex[:12]}"
    elif old != CANCEL_ALL:  # cancelling everything is the safe direction: passed on as it is
        if old not in goal_ids:
            return None  # a cancel of a goal this replay did not send
        old = goal_ids[old]
    query["goal_id"] = goal_id or old
    return ReplayKind.QUERY, query_path, json.dumps(query, separators=(",", ":")).encode(), goal_id
