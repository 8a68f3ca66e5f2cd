"""`tether run executor`."""

from __future__ import annotations

import logging
from pathlib import Path

import pybullet_data

from services.executor.config import ExecutorConfig
from services.executor.kinematics import ArmKinematics
from services.executor.manipulation import Manipulator
from services.executor.node import NodePlanner, NodeRobot, serve_execute_plan
from services.executor.runner import PlanRunner
from services.runtime import Node, NodeSettings, configure_logging, load_config, stop_event
from services.worldmodel import WorldModel, load_world

log = logging.getLogger(__name__)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(ExecutorConfig, config_file, "executor")
    world = WorldModel(load_world(config.world))
    kinematics = ArmKinematics(Path(pybullet_data.getDataPath()) / world.world.robot.arm_urdf)
    stop = stop_event()
    with Node("executor", settings) as node:
        robot = NodeRobot(node, config)
        runner = PlanRunner(NodePlanner(node, config), robot, Manipulator(robot, kinematics, world, config))
        server = serve_execute_plan(node, runner)
        node.declare_alive()
        log.info("executor up for robot %s", settings.robot)
        stop.wait()
        server.abort_all("executor shutting down")
