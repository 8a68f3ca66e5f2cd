"""`tether run ros2sim`."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from services.ros2.rmw import RosNode
from services.ros2.types import RosTypes
from services.ros2.wire import Naming
from services.ros2sim.config import Ros2SimConfig, domain_id
from services.ros2sim.node import NODE_NAME, StandIn, ros_session
from services.runtime import Node, NodeSettings, configure_logging, load_config, stop_event
from services.sdnotify import Notifier
from services.sim.config import SimConfig
from services.sim.simulation import Simulation
from services.worldmodel import load_world

log = logging.getLogger(__name__)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    sim_config = load_config(SimConfig, config_file, "sim")
    config = load_config(Ros2SimConfig, config_file, "ros2sim")
    naming = Naming(config.style, domain_id(config, os.environ))
    world = load_world(sim_config.world)
    stop = stop_event()
    # Its camera renders in a process of its own (StandIn.renderer): no visual meshes here.
    sim = Simulation.served(world, sim_config)
    try:
        with (
            Node("ros2sim", settings) as node,
            ros_session(config) as session,
            RosNode(session, RosTypes(), naming, NODE_NAME) as ros,
        ):
            standin = StandIn(ros, node, sim, sim_config, config)
            node.declare_alive()
            log.info(
                "ROS 2 stand-in robot up: world %s at %gx real time, ROS node %s on %s (%s keys, domain %d)",
                world.name,
                sim_config.realtime_factor,
                NODE_NAME,
                config.listen,
                config.style.value,
                naming.domain_id,
            )
            notifier = Notifier()
            notifier.ready(f"ROS 2 stand-in robot for {settings.robot}")
            # This thread owns pybullet from here on; everything else reaches it through the loop,
            # which feeds the watchdog.
            standin.run(stop, notifier.keepalive)
            notifier.stopping()
            standin.close()
    finally:
        sim.close()
