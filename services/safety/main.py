"""`tether run safety`."""

from __future__ import annotations

import logging
from pathlib import Path

from services.heap import release_free_memory
from services.robotlink import KeyFileError, Signer, robot_key
from services.runtime import ConfigError, Node, NodeSettings, configure_logging, load_config, stop_event
from services.safety.config import SafetyConfig
from services.safety.incidents import IncidentStore
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.node import SafetyNode
from services.safety.operator import ensure_token, token_path
from services.safety.policy import load_safety_policy
from services.safety.policyfile import PolicyError
from services.sdnotify import Notifier
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
    release_free_memory()  # what loading the arm's model freed (services/heap.py)
    token_file = token_path(config.operator_token_file)
    state_file = Path(config.estop_state_file) if config.estop_state_file else None
    state_file = state_file or token_file.parent / f"estop-{settings.robot}.json"
    # A fresh install's first start makes the token and an unlatched latch file; after that a missing
    # latch file starts latched (fail closed; services/safety/README.md, The e-stop latch).
    latch = EstopLatch(ensure_token(token_file, state_file), state_file)
    mode_file = Path(config.mode_state_file) if config.mode_state_file else None
    modes = ModeFile(mode_file or token_file.parent / f"mode-{settings.robot}.json")
    store_file = Path(config.incident_store) if config.incident_store else None
    # Never fatal: a store with a fault is reported (log, `safety/incidents`) and safety checks as ever.
    # Beside the e-stop's state file: in a deployment the token is a read-only credential, the state
    # file is in safety's state directory.
    incidents = IncidentStore(store_file or state_file.parent / f"incidents-{settings.robot}.sqlite")
    try:
        key, key_file = robot_key(config.robot_key_file, token_file.parent, settings.robot)
    except (KeyFileError, OSError) as exc:
        raise ConfigError(f"[safety] robot_key_file: {exc}") from None
    stop = stop_event()
    notifier = Notifier()
    with Node("safety", settings) as node:
        # Everything safety sends to the robot (commands, heartbeats) carries a MAC under this key.
        node.signer = Signer(key)
        # The watchdog is fed from the heartbeat loop, not from here: a hung check loop is restarted.
        safety = SafetyNode(node, policy, latch, config, keepalive=notifier.keepalive, modes=modes, incidents=incidents)
        node.declare_alive()
        log.info(
            "safety up for robot %s in mode %s; policy %s (%s); operator token in %s; robot key in %s; "
            "incidents in %s%s",
            settings.robot,
            modes.mode,
            limits.path,
            limits.hash,
            token_file,
            key_file,
            incidents.path,
            f" (FAULT: {incidents.fault})" if incidents.fault else "",
        )
        notifier.ready(f"checking robot {settings.robot}" + (": e-stop latched" if latch.state.latched else ""))
        stop.wait()
        notifier.stopping()
        safety.close()
        incidents.close()
