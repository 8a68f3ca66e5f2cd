"""`tether run recorder`: record all of one robot's traffic to an MCAP file until SIGINT or SIGTERM."""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path

from schemas import keys
from services import runtime
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Recording
from services.recorder.node import bind
from services.runtime import Node, NodeSettings

log = logging.getLogger(__name__)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    runtime.configure_logging()
    config = runtime.load_config(RecorderConfig, config_file, "recorder")
    stop = runtime.stop_event()
    path = config.path_for(settings.robot, dt.datetime.now(dt.UTC))
    path.parent.mkdir(parents=True, exist_ok=True)
    recording = Recording(path, settings.robot, compression=config.compression, chunk_size=config.chunk_size)
    try:
        with Node("recorder", settings) as node:
            bind(node, recording)
            node.declare_alive()
            log.info("recording %s to %s", keys.all_keys(settings.robot), path)
            while not stop.wait(config.flush_interval):
                recording.flush()
    finally:
        # The node is closed first, so no callback writes while the summary is being written.
        recording.finish()
        log.info("recording finished: %s (%d messages, %d dropped)", path, recording.messages, recording.dropped)
