"""The action envelope: the messages on an action's five keys, as ROS 2 lays them out."""

from __future__ import annotations

import enum
from typing import Annotated, Generic, TypeVar

import msgspec
from msgspec import Meta

from schemas.common import DECODE_ERRORS, ErrorKind, Frozen, Text

G = TypeVar("G")
F = TypeVar("F")
R = TypeVar("R")

GoalId = Annotated[str, Meta(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+(?!\n)$")]


class GoalState(enum.StrEnum):
    ACCEPTED = "accepted"
    EXECUTING = "executing"
    CANCELING = "canceling"
    SUCCEEDED = "succeeded"
    CANCELED = "canceled"
    ABORTED = "aborted"
    REJECTED = "rejected"

    @property
    def terminal(self) -> bool:
        return self in (GoalState.SUCCEEDED, GoalState.CANCELED, GoalState.ABORTED, GoalState.REJECTED)


class SendGoal(Frozen, Generic[G]):
    """Request on `X/_action/send_goal`."""

    goal_id: GoalId
    goal: G


class GoalResponse(Frozen):
    """Reply on `X/_action/send_goal`: accepted, or rejected with the reason. `kind` says what kind
    of refusal (safety sets `vetoed` or `estop`); None for a robot that is busy or unreachable."""

    goal_id: GoalId
    accepted: bool
    reason: Text = ""
    kind: ErrorKind | None = None


# A CancelGoal with this goal id cancels every goal of the action.
CANCEL_ALL = "all"


def goal_id_in(raw: bytes | msgspec.Raw) -> str | None:
    """The `goal_id` of a recorded goal request (SendGoal, CancelGoal, GetResult: raw JSON, untrusted);
    None when there is none."""
    try:
        value = msgspec.json.decode(raw)
    except DECODE_ERRORS:
        return None
    goal_id = value.get("goal_id") if isinstance(value, dict) else None
    return goal_id if isinstance(goal_id, str) else None


class CancelGoal(Frozen):
    goal_id: GoalId


class CancelResponse(Frozen):
    goal_id: GoalId
    accepted: bool
    reason: Text = ""


class GetResult(Frozen):
    goal_id: GoalId


class ResultResponse(Frozen, Generic[R]):
    """Reply on `X/_action/get_result`, sent once the goal is terminal."""

    goal_id: GoalId
    state: GoalState
    result: R | None = None
    message: Text = ""


class GoalProgress(Frozen, Generic[F, R]):
    """Reply on `X/_action/get_status` (a tether addition to the five ROS 2 keys): where a goal is
    now, without waiting for it to end. `feedback` is the latest published, `result` set once the
    goal is terminal."""

    goal_id: GoalId
    state: GoalState
    message: Text = ""
    feedback: F | None = None
    result: R | None = None


class Feedback(Frozen, Generic[F]):
    goal_id: GoalId
    feedback: F


class GoalStatus(Frozen):
    """Published on `X/_action/status` at every transition."""

    goal_id: GoalId
    state: GoalState
    message: Text = ""
    stamp: float = 0.0
