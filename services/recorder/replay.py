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
from collections.abc import Iterable
from dataclasses import dataclass

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

    @property
    def duration(self) -> float:
        return self.items[-1].at if self.items else 0.0


def default_target(robot: str) -> str:
    return f"{robot}{REPLAY_SUFFIX}"


def is_replay_name(robot: str) -> bool:
    return robot.endswith(REPLAY_SUFFIX)


def _relative(robot: str, key: str) -> str | None:
    root = keys.prefix(robot) + "/"
    return key[len(root) :] if key.startswith(root) else None


def plan_replay(messages: Iterable[Recorded], robot: str, target: str, live: bool = False) -> ReplayPlan:
    """The messages of `robot` to send to `target`, in recorded order, at recorded offsets.

    With `live` only commands, as described above; goal ids are replaced by new ones (a goal id
    names one goal, and the recorded ones may still be known to the robot), consistently for a
    goal's send and cancel.
    """
    items: list[Item] = []
    skipped: dict[str, int] = {}
    goal_ids: dict[str, str] = {}
    start: int | None = None

    def skip(why: str) -> None:
        skipped[why] = skipped.get(why, 0) + 1

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
        start = message.log_time if start is None else start
        at = (message.log_time - start) / 1e9
        items.append(Item(at, kind, f"{keys.prefix(target)}/{path}", payload, goal_id))
    return ReplayPlan(items, skipped)


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
