"""Failures that come back across the wire (an error reply, no reply, a refused goal), as exceptions in the caller."""

from __future__ import annotations

from schemas.common import ErrorKind, ServiceError


class CallError(Exception):
    """A query got an error value back, or no reply at all."""

    def __init__(self, error: ServiceError) -> None:
        super().__init__(error.message)
        self.error = error


class GoalRejected(Exception):
    """The server refused the goal: `reason` in words, `kind` when it says what kind of refusal."""

    def __init__(self, reason: str, kind: ErrorKind | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.kind = kind
