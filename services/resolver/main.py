"""`tether run resolver`: serve plan/resolve until SIGINT or SIGTERM."""

from __future__ import annotations

from pathlib import Path

from services.resolver.config import ResolverConfig
from services.resolver.node import build_resolver, declare
from services.runtime import Node, NodeSettings, configure_logging, load_config, stop_event
from services.sdnotify import Notifier


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(ResolverConfig, config_file, "resolver")
    resolver = build_resolver(config)
    stop = stop_event()
    with Node("resolver", settings) as node:
        declare(node, resolver, config)
        node.declare_alive()
        notifier = Notifier()
        notifier.ready(f"serving plan/resolve for robot {settings.robot}")
        notifier.wait(stop)
        notifier.stopping()
