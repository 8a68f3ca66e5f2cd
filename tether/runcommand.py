"""`tether run` and the flags every command shares, as typer commands: the whole CLI's (tether.cli), and
what `tether run` falls back to for a line tether.runservice does not read itself (help, a bad flag)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from services.runtime import ALL_SERVICES, NodeSettings
from tether.completion import complete_service
from tether.runservice import EXIT_USAGE, error, run_service

RobotOpt = Annotated[str | None, typer.Option("--robot", envvar="TETHER_ROBOT", help="Robot name in the keys.")]
PortOpt = Annotated[
    int | None, typer.Option("--base-port", envvar="TETHER_BASE_PORT", help="First of the services' loopback ports.")
]
ZenohOpt = Annotated[
    Path | None, typer.Option("--zenoh-config", envvar="TETHER_ZENOH_CONFIG", help="A Zenoh config file.")
]
HELP = "tether: LLM plans to safe robot actions over Zenoh."


def common(
    ctx: typer.Context, robot: RobotOpt = None, base_port: PortOpt = None, zenoh_config: ZenohOpt = None
) -> None:
    """Flags every command shares, written once."""
    try:
        ctx.obj = NodeSettings.from_env(robot=robot, base_port=base_port, zenoh_config=zenoh_config)
    except ValueError as exc:
        error(str(exc))
        raise typer.Exit(EXIT_USAGE) from None


def run(
    ctx: typer.Context,
    service: Annotated[
        str, typer.Argument(help=f"One of: {', '.join(ALL_SERVICES)}.", autocompletion=complete_service)
    ],
    config: Annotated[Path | None, typer.Option("--config", help="TOML file with a [SERVICE] table.")] = None,
) -> None:
    """Run one service in the foreground until SIGINT or SIGTERM.

    Exit 0 when stopped by SIGINT or SIGTERM, 2 for an unknown service or a config or world file that
    cannot be read or is invalid (the error names the file, the table and the value), 1 when the
    service fails otherwise (its log says why).
    """
    run_service(ctx.obj, service, config)


typer_app = typer.Typer(help=HELP, no_args_is_help=True)
typer_app.callback()(common)
typer_app.command()(run)
