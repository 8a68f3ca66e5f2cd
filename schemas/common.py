"""Geometry, bounded scalar types and the error value every service replies with on failure."""

from __future__ import annotations

import enum
import math
from typing import Annotated

import msgspec
from msgspec import Meta

# What decoding untrusted JSON into these types can raise: malformed or mistyped JSON, invalid UTF-8
# inside a string, and nesting too deep (msgspec raises RecursionError).
DECODE_ERRORS = (msgspec.DecodeError, UnicodeDecodeError, RecursionError)

# Bounded scalars. SI units throughout: metres, radians, seconds, kilograms.
# Where anything may be, in the map frame: what parses or reports a place checks it against these.
METRES_MIN, METRES_MAX = -1000.0, 1000.0
Metres = Annotated[float, Meta(ge=METRES_MIN, le=METRES_MAX)]
Radians = Annotated[float, Meta(ge=-100.0, le=100.0)]
Seconds = Annotated[float, Meta(ge=0.0, le=3600.0)]
Kilograms = Annotated[float, Meta(ge=0.0, le=1000.0)]
Name = Annotated[str, Meta(min_length=1, max_length=200)]
# The longest free text a message carries (a reason, a step's message); code that builds one cuts it to this.
TEXT_CHARS = 4000
Text = Annotated[str, Meta(max_length=TEXT_CHARS)]
# (?!\n): Python's `$` also matches before a last newline, which would let "id\n" through; JSON
# Schema's (ECMA) regexes have no \Z, and read this the same.
Id = Annotated[str, Meta(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:-]+(?!\n)$")]


class Frozen(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Base for every message: immutable, keyword-only, unknown fields are an error."""


class Pose2D(Frozen):
    """A base pose on the floor, in the map frame."""

    x: Metres
    y: Metres
    yaw: Radians = 0.0


def fmt_pose(pose: Pose2D) -> str:
    """A pose for people to read: `(x, y, yaw°)`, metres to the centimetre, degrees."""
    return f"({pose.x:.2f}, {pose.y:.2f}, {math.degrees(pose.yaw):.0f}°)"


def fmt_point(x: float, y: float) -> str:
    """A point on the floor for people to read: `(x, y)`, metres to the centimetre."""
    return f"({x:.2f}, {y:.2f})"


def preview(text: str, limit: int) -> str:
    """`text` on one line, cut to `limit` characters with an ellipsis."""
    flat = " ".join(text.split())
    return flat if len(flat) <= limit else flat[: limit - 1] + "…"


class Vec3(Frozen):
    x: Metres
    y: Metres
    z: Metres


class Stage(enum.StrEnum):
    """Where in the pipeline a plan was decided."""

    PARSE = "parse"
    RESOLVE = "resolve"
    SAFETY = "safety"
    EXECUTE = "execute"


class ErrorKind(enum.StrEnum):
    """Failure kinds, after pyrobosim's ExecutionResult: named for what went wrong."""

    INVALID_REQUEST = "invalid_request"
    UNKNOWN_ACTION = "unknown_action"
    UNKNOWN_NAME = "unknown_name"
    AMBIGUOUS_NAME = "ambiguous_name"
    VETOED = "vetoed"
    ESTOP = "estop"
    PRECONDITION = "precondition"
    PLANNING = "planning"
    EXECUTION = "execution"
    POSTCONDITION = "postcondition"
    CANCELED = "canceled"
    TIMEOUT = "timeout"
    UNAVAILABLE = "unavailable"
    UNAUTHORIZED = "unauthorized"
    INTERNAL = "internal"


class ServiceError(Frozen, tag="error"):
    """A failure as a value: what kind, a message a person can act on, and where it applies."""

    kind: ErrorKind
    message: Text
    stage: Stage | None = None
    step: int | None = None
    candidates: list[str] = []
    # Where in the text, for refusals of plan text (1-based).
    line: int | None = None
    column: int | None = None
