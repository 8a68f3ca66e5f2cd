"""`tether run ros2`."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import zenoh

from services.robotlink import KeyFileError, robot_key
from services.ros2.config import Ros2Config
from services.ros2.node import Ros2Backend, check_class_map, naming, robot_session_config
from services.runtime import ConfigError, Node, NodeSettings, configure_logging, load_config, stop_event
from services.safety.operator import token_path
from services.sdnotify import Notifier
from services.worldmodel import load_world

log = logging.getLogger(__name__)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(Ros2Config, config_file, "ros2")
    world = load_world(config.world)
    check_class_map(config, world)
    ros_naming, session_config = naming(config), robot_session_config(config)
    try:
        key, _ = robot_key(config.robot_key_file, token_path().parent, settings.robot)
    except (KeyFileError, OSError) as exc:
        raise ConfigError(f"[ros2] robot_key_file: {exc}") from None
    stop = stop_event()
    notifier = Notifier()
    watch_ended = threading.Event()  # the heartbeat watch ended before `stop`: fail closed

    def watch_heartbeat(backend: Ros2Backend) -> None:
        try:
            # The watchdog is fed from the heartbeat watch: if it hangs, the robot is not being kept safe.
            backend.run(stop, notifier.keepalive)
        finally:
            if not stop.is_set():
                watch_ended.set()
                stop.set()

    with Node("ros2", settings) as node, zenoh.open(session_config) as session:
        backend = Ros2Backend(node, session, ros_naming, config, world, robot_key=key)
        watch = threading.Thread(target=watch_heartbeat, args=(backend,), name="heartbeat-watch", daemon=True)
        # The robot stays still (emergency_stop, zero cmd_vel) from the start, until safety's heartbeat.
        watch.start()
        try:
            log.info(
                "ros2 backend for robot %s: waiting for the robot at %s (ROS domain %d, %s keys, node /%s)",
                settings.robot,
                config.zenoh_config or config.endpoint,
                ros_naming.domain_id,
                config.style.value,
                config.node_name,
            )
            notifier.status("waiting for the robot's odometry and joint states")
            if backend.wait_for_robot(stop):
                node.declare_alive()
                log.info("ros2 backend up: the robot reports; it stays still until safety's heartbeat")
                notifier.ready(f"driving robot {settings.robot} over ROS 2")
                stop.wait()
            notifier.stopping()
        finally:
            stop.set()
            watch.join()
            backend.close()
    if watch_ended.is_set():
        log.critical("the heartbeat watch ended: the robot was told to stop and the ros2 backend exits")
        raise SystemExit(1)
