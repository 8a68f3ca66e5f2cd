"""`tether run planner`: serve plan/ask until SIGINT or SIGTERM."""

from __future__ import annotations

import logging
from pathlib import Path

from services.planner.config import PlannerConfig, resolve_endpoint
from services.planner.errors import NotConfigured
from services.planner.node import Planner, declare
from services.runtime import ConfigError, Node, NodeSettings, configure_logging, load_config, stop_event
from services.sdnotify import Notifier

log = logging.getLogger(__name__)


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(PlannerConfig, config_file, "planner")
    try:
        endpoint = resolve_endpoint(config)
    except NotConfigured as exc:
        raise ConfigError(f"{config_file or 'environment'}: {exc}") from None
    if endpoint is None:
        # Still serves plan/ask, answering `unconfigured` with how to configure: `tether up` works without an LLM.
        log.warning("no LLM endpoint configured; plan/ask will say how to configure one")
    else:
        log.info("LLM endpoint %s, model %s, key %s", endpoint.shown_url, endpoint.model, endpoint.key_source or "none")
    stop = stop_event()
    with Node("planner", settings) as node:
        planner = Planner(node, config, endpoint)
        try:
            declare(node, planner)
            node.declare_alive()
            notifier = Notifier()
            notifier.ready("serving plan/ask" + ("" if endpoint else " (no LLM endpoint configured)"))
            notifier.wait(stop)
            notifier.stopping()
        finally:
            planner.close()
