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


class RecorderStatus(Frozen):
    """The file being written, and totals over every file of this run (one per rotation)."""

    path: str
    messages: int
    started: float
    dropped: int = 0
    files: list[str] = []
