"""`tether run recorder`: record a robot's traffic (and its ROS 2 traffic) to MCAP files until SIGINT or SIGTERM."""

from __future__ import annotations

import logging
from pathlib import Path

from schemas import keys
from services import runtime
from services.bundled import DEFAULT_POLICY, world_path  # the paths only: no shapely, no numpy
from services.recorder.config import RecorderConfig, Ros2RecordConfig
from services.recorder.mcapfile import Provenance, SourceFile
from services.recorder.node import bind
from services.recorder.recorder import Recorder
from services.recorder.ros2file import Ros2Source, RosKeys
from services.recorder.ros2link import Ros2Link
from services.ros2.types import RosTypeError, RosTypes
from services.ros2.wire import Naming
from services.runtime import ConfigError, Node, NodeSettings
from services.safety.config import SafetyConfig
from services.sdnotify import Notifier

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


def ros2_source(config: Ros2RecordConfig, config_file: Path | None) -> Ros2Source:
    """The robot's ROS 2 network as `[recorder.ros2]` describes it, its types checked against the typestore."""
    try:
        types = RosTypes(config.distro)
        ros_keys = RosKeys(types, Naming(config.style, config.domain()), config.topics)
    except (ValueError, RosTypeError) as exc:
        raise ConfigError(f"config file {config_file} [recorder.ros2]: {exc}") from None
    return Ros2Source(ros_keys, config.endpoint, config.mode)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    runtime.configure_logging()
    config = runtime.load_config(RecorderConfig, config_file, "recorder")
    ros2 = ros2_source(config.ros2, config_file) if config.ros2 is not None else None
    stop = runtime.stop_event()
    recorder = Recorder(config, provenance(settings.robot, config_file), ros2=ros2)
    link = Ros2Link(ros2, recorder) if ros2 is not None else None
    try:
        with Node("recorder", settings) as node:
            bind(node, recorder)
            if link is not None:
                link.start()
            node.declare_alive()
            log.info("recording %s", keys.all_keys(settings.robot))
            notifier = Notifier()
            notifier.ready(f"recording robot {settings.robot} to {config.output_dir}")
            # Fed after each flush, so a recorder stuck writing is restarted; flushes at least that often.
            interval = min(config.flush_interval, notifier.period or config.flush_interval)
            while not stop.wait(interval):
                recorder.tick()
                if link is not None:
                    link.poll()
                notifier.keepalive()
            notifier.stopping("finishing the recording")
    finally:
        # The sessions are closed first, so no callback writes while the summaries are being written.
        if link is not None:
            link.close()
        recorder.finish()
        log.info(
            "recording finished: %s (%d messages, %d dropped)",
            recorder.files_said(),
            recorder.messages,
            recorder.dropped,
        )
        if (ros2_status := recorder.status().ros2) is not None:
            log.info(
                "ROS 2 recording finished: %s (%d messages, %d skipped)",
                ", ".join(ros2_status.files) or "no file",
                ros2_status.messages,
                ros2_status.skipped,
            )
