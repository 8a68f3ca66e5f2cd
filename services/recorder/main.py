"""`tether run recorder`: record all of one robot's traffic to MCAP files until SIGINT or SIGTERM."""

from __future__ import annotations

import logging
from pathlib import Path

from schemas import keys
from services import runtime
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Provenance, SourceFile
from services.recorder.node import bind
from services.recorder.recorder import Recorder
from services.runtime import ConfigError, Node, NodeSettings
from services.safety.config import SafetyConfig
from services.safety.policyfile import DEFAULT_POLICY
from services.worldmodel import world_path

log = logging.getLogger(__name__)


def provenance(robot: str, config_file: Path | None) -> Provenance:
    """The world and policy safety runs with (the `[safety]` table of the same config file), read now."""
    safety = runtime.load_config(SafetyConfig, config_file, "safety")
    files: dict[str, SourceFile] = {}
    for name, path in (("world", world_path(safety.world)), ("policy", Path(safety.policy or DEFAULT_POLICY))):
        try:
            files[name] = SourceFile.read(path)
        except OSError as exc:
            raise ConfigError(f"cannot read the {name} file {path} to keep in the recording: {exc.strerror}") from None
    return Provenance(robot, world=files["world"], policy=files["policy"])


def main(settings: NodeSettings, config_file: Path | None) -> None:
    runtime.configure_logging()
    config = runtime.load_config(RecorderConfig, config_file, "recorder")
    stop = runtime.stop_event()
    recorder = Recorder(config, provenance(settings.robot, config_file))
    try:
        with Node("recorder", settings) as node:
            bind(node, recorder)
            node.declare_alive()
            log.info("recording %s", keys.all_keys(settings.robot))
            while not stop.wait(config.flush_interval):
                recorder.tick()
    finally:
        # The node is closed first, so no callback writes while the summary is being written.
        recorder.finish()
        log.info(
            "recording finished: %s (%d messages, %d dropped)",
            ", ".join(map(str, recorder.files)),
            recorder.messages,
            recorder.dropped,
        )
