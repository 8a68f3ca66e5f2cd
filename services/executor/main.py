"""`tether run executor`."""

from __future__ import annotations

import logging
from pathlib import Path

from services.executor.armplanning import ArmPlanner, ArmPlannerConfig
from services.executor.config import ExecutorConfig
from services.executor.manipulation import Manipulator
from services.executor.navigation import BasePlanner
from services.executor.node import IncidentReporter, NodePlanServices, NodeRobot, serve_execute_plan
from services.executor.runner import PlanRunner
from services.heap import release_free_memory
from services.runtime import Node, NodeSettings, configure_logging, load_config, stop_event
from services.sdnotify import Notifier
from services.worldmodel import WorldModel, load_world

log = logging.getLogger(__name__)

# How long a stopping executor waits for its aborted plans to end: each cancels its motion on the
# robot from its own thread, over the session that closes after this.
STOP_WAIT = 5.0


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(ExecutorConfig, config_file, "executor")
    world = WorldModel(load_world(config.world))
    # Both planners build their models once, here, before the executor says it is alive.
    arm = ArmPlanner(world, ArmPlannerConfig(planning_time=config.planning_time))
    base = BasePlanner(world, clearance=config.base_clearance, time_limit=config.planning_time)
    release_free_memory()  # what loading the meshes and building the models freed (services/heap.py)
    stop = stop_event()
    with Node("executor", settings) as node:
        robot = NodeRobot(node, config)
        manipulator = Manipulator(robot, arm, base, world, config)
        runner = PlanRunner(NodePlanServices(node, config), robot, manipulator, config, IncidentReporter(node))
        server = serve_execute_plan(node, runner, config)
        node.declare_alive()
        log.info("executor up for robot %s", settings.robot)
        notifier = Notifier()
        notifier.ready(f"executing plans for robot {settings.robot}")
        notifier.wait(stop)
        notifier.stopping("aborting running plans")
        server.abort_all("executor shutting down")
        if running := server.wait_ended(STOP_WAIT):
            log.error("plan goals %s had not ended %g s after the abort: a motion may go on", running, STOP_WAIT)
