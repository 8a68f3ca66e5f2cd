"""`tether run safety`."""

from __future__ import annotations

import logging
from pathlib import Path

from services.runtime import ConfigError, Node, NodeSettings, configure_logging, load_config, stop_event
from services.safety.config import SafetyConfig
from services.safety.latch import EstopLatch
from services.safety.node import SafetyNode
from services.safety.operator import ensure_token, token_path
from services.safety.policy import load_safety_policy
from services.safety.policyfile import PolicyError
from services.worldmodel import load_world

log = logging.getLogger(__name__)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(SafetyConfig, config_file, "safety")
    world = load_world(config.world)
    try:
        policy = load_safety_policy(world, Path(config.policy) if config.policy else None, f"world {config.world}")
    except PolicyError as exc:
        raise ConfigError(str(exc)) from None
    limits = policy.limits
    token_file = token_path(config.operator_token_file)
    state_file = Path(config.estop_state_file) if config.estop_state_file else None
    latch = EstopLatch(ensure_token(token_file), state_file or token_file.parent / f"estop-{settings.robot}.json")
    stop = stop_event()
    with Node("safety", settings) as node:
        safety = SafetyNode(node, policy, latch, config)
        node.declare_alive()
        log.info(
            "safety up for robot %s; policy %s (%s); operator token in %s",
            settings.robot,
            limits.path,
            limits.hash,
            token_file,
        )
        stop.wait()
        safety.close()
