"""`tether run parser`: serve plan/parse until SIGINT or SIGTERM."""

from __future__ import annotations

from pathlib import Path

from services.parser.config import ParserConfig
from services.parser.node import build_parser, declare
from services.runtime import Node, NodeSettings, configure_logging, load_config, stop_event
from services.sdnotify import Notifier


def main(settings: NodeSettings, config_file: Path | None) -> None:
    configure_logging()
    config = load_config(ParserConfig, config_file, "parser")
    parser = build_parser(config)
    stop = stop_event()
    with Node("parser", settings) as node:
        declare(node, parser)
        node.declare_alive()
        notifier = Notifier()
        notifier.ready(f"serving plan/parse for robot {settings.robot}")
        notifier.wait(stop)
        notifier.stopping()
