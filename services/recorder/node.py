"""Binds a Recording to Zenoh: every key of the robot in, recorder/status out."""

from __future__ import annotations

from schemas import keys
from schemas.trace import RecorderStatus
from schemas.world import Empty
from services.recorder.recorder import Recorder
from services.runtime import Node


def bind(node: Node, recording: Recorder, key_expr: str | None = None, serve_status: bool = True) -> None:
    """Record every publication under `key_expr` (default: the robot's prefix, `_trace/**` included),
    and serve the status (the recorder service; `tether record` does not, so there is one answer)."""

    def status(_request: Empty) -> RecorderStatus:
        return recording.status()

    # With the attachments: safety's MACs, for `tether inspect` and `recheck` to tell its messages from others.
    def on_sample(key: str, payload: bytes, attachment: bytes | None) -> None:
        recording.record(key, payload, attachment)

    node.subscribe_raw(key_expr or keys.all_keys(node.robot), on_sample, attachments=True)
    if serve_status:
        node.serve(keys.RECORDER_STATUS, status)
