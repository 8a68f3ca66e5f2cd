"""`tether run sim`."""

from __future__ import annotations

import logging
from pathlib import Path

from services.heap import release_free_memory
from services.robotlink import KeyFileError, robot_key
from services.runtime import ConfigError, Node, NodeSettings, configure_logging, load_config, stop_event
from services.safety.operator import token_path
from services.sdnotify import Notifier
from services.sim.config import SimConfig
from services.sim.node import SimNode
from services.sim.simulation import Simulation
from services.worldmodel import load_world

log = logging.getLogger(__name__)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(SimConfig, config_file, "sim")
    world = load_world(config.world)
    try:
        key, _ = robot_key(config.robot_key_file, token_path().parent, settings.robot)
    except (KeyFileError, OSError) as exc:
        raise ConfigError(f"[sim] robot_key_file: {exc}") from None
    stop = stop_event()
    # Its camera renders in a process of its own (SimNode.renderer): no visual meshes here.
    sim = Simulation.served(world, config)
    release_free_memory()  # what loading the world into pybullet freed (services/heap.py)
    try:
        with Node("sim", settings) as node:
            sim_node = SimNode(node, sim, config, robot_key=key)
            node.declare_alive()
            log.info(
                "sim up for robot %s: world %s at %gx real time; the robot stays still until safety's heartbeat",
                settings.robot,
                world.name,
                config.realtime_factor,
            )
            notifier = Notifier()
            notifier.ready(f"simulating {world.name} for robot {settings.robot}")
            # This thread owns pybullet from here on; everything else reaches it through SimNode.submit.
            # The watchdog is fed from the physics loop: a simulator that hangs is restarted.
            sim_node.run(stop, notifier.keepalive)
            notifier.stopping()
            sim_node.close()
    finally:
        sim.close()
