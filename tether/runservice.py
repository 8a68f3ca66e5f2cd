"""`tether run SERVICE`, and the flags every command shares: a service process loads this and its service only.

`python -m tether run ...` (how the Supervisor starts each service) and the `tether` script's
`tether run ...` (how systemd units and containers do) come here through tether/__main__.py without
importing tether.cli, whose other commands pull in pinocchio, shapely, cryptography, mcap and rich.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import typer

from services.runtime import ALL_SERVICES, SWITCH_INTERVAL, ConfigError, NodeSettings
from tether.completion import complete_service

RobotOpt = Annotated[str | None, typer.Option("--robot", envvar="TETHER_ROBOT", help="Robot name in the keys.")]
PortOpt = Annotated[
    int | None, typer.Option("--base-port", envvar="TETHER_BASE_PORT", help="First of the services' loopback ports.")
]
ZenohOpt = Annotated[
    Path | None, typer.Option("--zenoh-config", envvar="TETHER_ZENOH_CONFIG", help="A Zenoh config file.")
]
# The shared flags, each followed by its value: all that may stand before `run` for it to come here.
VALUE_FLAGS = ("--robot", "--base-port", "--zenoh-config")
HELP = "tether: LLM plans to safe robot actions over Zenoh."


def error(message: str) -> None:
    """`error: ...` on stderr, the word in red on a terminal (as tether.cli's rich console shows it)."""
    typer.secho("error:", fg="red", err=True, nl=False)
    typer.echo(f" {message}", err=True)


def common(
    ctx: typer.Context, robot: RobotOpt = None, base_port: PortOpt = None, zenoh_config: ZenohOpt = None
) -> None:
    """Flags every command shares, written once."""
    try:
        ctx.obj = NodeSettings.from_env(robot=robot, base_port=base_port, zenoh_config=zenoh_config)
    except ValueError as exc:
        error(str(exc))
        raise typer.Exit(2) from None


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
    if service not in ALL_SERVICES:
        error(f"unknown service {service!r}; services are {', '.join(ALL_SERVICES)}")
        raise typer.Exit(2)
    sys.setswitchinterval(SWITCH_INTERVAL)
    module = importlib.import_module(f"services.{service}.main")
    settings: NodeSettings = ctx.obj
    try:
        module.main(settings, config)
    except ConfigError as exc:
        error(str(exc))
        raise typer.Exit(2) from None
    except Exception as exc:
        # Only a service that loads a world raises this, and has imported its module (and shapely) by then.
        from services.worldmodel import WorldFileError

        if not isinstance(exc, WorldFileError):
            raise
        error(str(exc))
        raise typer.Exit(2) from None


def runs_a_service(argv: Sequence[str]) -> bool:
    """Whether `argv` (without the program) is `[--robot R] [--base-port N] [--zenoh-config F] run ...`."""
    i = 0
    while i < len(argv):
        flag, joined, _ = argv[i].partition("=")
        if flag not in VALUE_FLAGS:
            return argv[i] == "run"
        i += 1 if joined else 2
    return False


app = typer.Typer(help=HELP, no_args_is_help=True)
app.callback()(common)
app.command()(run)
