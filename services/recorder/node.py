"""Binds a Recording to Zenoh: every key of the robot in, recorder/status out."""

from __future__ import annotations

from schemas import keys
from schemas.trace import RecorderStatus
from schemas.world import Empty
from services.recorder.mcapfile import Recording
from services.runtime import Node


def bind(node: Node, recording: Recording) -> None:
    """Record every publication under the robot's prefix, `_trace/**` included, and serve the status."""

    def on_sample(key: str, payload: bytes) -> None:
        recording.record(key, payload)

    def status(_request: Empty) -> RecorderStatus:
        return recording.status()

    node.subscribe_raw(keys.all_keys(node.robot), on_sample)
    node.serve(keys.RECORDER_STATUS, status)
