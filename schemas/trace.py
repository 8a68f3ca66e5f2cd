"""What the runtime publishes on `_trace/**` for every query a service answers."""

from __future__ import annotations

import msgspec

from schemas.common import Frozen


class TraceRecord(Frozen):
    stamp: float
    service: str
    key: str
    duration: float
    query: msgspec.Raw | None = None
    reply: msgspec.Raw | None = None
    error: str = ""


class RecorderStatus(Frozen):
    path: str
    messages: int
    started: float
