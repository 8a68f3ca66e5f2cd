"""Safety: heartbeat with the e-stop latch, e-stop triggers, operator reset, decision events."""

from __future__ import annotations

import enum
from typing import Annotated

import msgspec
from msgspec import Meta

from schemas.common import Frozen, Name, Text


class EstopState(Frozen):
    latched: bool
    source: Text = ""
    reason: Text = ""
    stamp: float = 0.0


class SafetyStatus(Frozen):
    """The heartbeat. The robot stops when it stops arriving."""

    seq: Annotated[int, Meta(ge=0)]
    stamp: float
    estop: EstopState


class EStop(Frozen):
    """Anyone may publish this; it latches until an operator resets it."""

    source: Name
    reason: Text = ""


class ResetRequest(Frozen):
    operator: Name
    token: Annotated[str, Meta(max_length=256)]


class ResetReply(Frozen):
    ok: bool
    message: Text


class Decision(enum.StrEnum):
    APPROVED = "approved"
    VETOED = "vetoed"
    CLAMPED = "clamped"
    STOPPED = "stopped"
    LATCHED = "latched"
    RESET = "reset"


class SafetyEvent(Frozen):
    """One safety decision: what was asked, what was decided, and why."""

    stamp: float
    key: Text
    decision: Decision
    reason: Text = ""
    command: msgspec.Raw = msgspec.field(default_factory=lambda: msgspec.Raw(b"null"))
