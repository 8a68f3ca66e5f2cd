"""What the runtime publishes on `_trace/**` for every query a service answers."""

from __future__ import annotations

import msgspec

from schemas.common import Frozen


class TraceRecord(Frozen):
    stamp: float
    service: str
    key: str
    duration: float
    # Raw JSON, `null` when absent (msgspec cannot decode `Raw | None`).
    query: msgspec.Raw = msgspec.field(default_factory=lambda: msgspec.Raw(b"null"))
    reply: msgspec.Raw = msgspec.field(default_factory=lambda: msgspec.Raw(b"null"))
    error: str = ""


class Ros2RecorderStatus(Frozen):
    """The ROS 2 side of a recording (`[recorder.ros2]`): its own file beside each of tether's."""

    path: str  # the file being written; "" when it could not be opened
    messages: int = 0
    skipped: int = 0  # samples without a place in the file: unknown keys or types, not CDR
    files: list[str] = []
    # Why nothing is being recorded now (the session to the robot not open, the file not writable); "" when fine.
    error: str = ""


class RecorderStatus(Frozen):
    """The file being written, and totals over every file of this run (one per rotation)."""

    path: str
    messages: int
    started: float
    dropped: int = 0
    files: list[str] = []
    ros2: Ros2RecorderStatus | None = None
    # Why tether's own file is not being written ("" while it is): the disk full, a rotation that failed.
    error: str = ""
