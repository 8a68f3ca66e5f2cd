"""`tether run SERVICE`, and the flags every command shares: a service process loads this and its service only.

`python -m tether run ...` (how the Supervisor starts each service) and the `tether` script's
`tether run ...` (how systemd units and containers do) come here through tether/__main__.py without
importing tether.cli, whose other commands pull in pinocchio, shapely, cryptography, mcap and rich.
A well-formed command line is read here without typer's parsing too: typer checks each value with
pydantic, some 7 MB in every service process for four flags (`read_command_line`).
"""

from __future__ import annotations

import importlib
import os
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
    run_service(ctx.obj, service, config)


def run_service(settings: NodeSettings, service: str, config: Path | None) -> None:
    """`run`'s work, once the command line is read (by typer or by `read_command_line`)."""
    if service not in ALL_SERVICES:
        error(f"unknown service {service!r}; services are {', '.join(ALL_SERVICES)}")
        raise typer.Exit(2)
    sys.setswitchinterval(SWITCH_INTERVAL)
    module = importlib.import_module(f"services.{service}.main")
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


def read_command_line(argv: Sequence[str]) -> tuple[dict[str, str], str, Path | None] | None:
    """`[--robot R] [--base-port N] [--zenoh-config F] run SERVICE [--config FILE]` (a flag's value
    after `=` or as the next word) as (the shared flags given, the service, the config file); None for
    anything else, for typer to answer as ever: help, an unknown flag, a flag twice, a value that is
    empty or starts with `-`, a base port that is no number (also in $TETHER_BASE_PORT)."""
    words = list(argv)

    def take_flag() -> tuple[str, str] | None:
        flag, joined, value = words.pop(0).partition("=")
        if not joined:
            value = words.pop(0) if words else ""
        return (flag, value) if value and not value.startswith("-") else None

    shared: dict[str, str] = {}
    while words and words[0] != "run":
        taken = take_flag()
        if taken is None or taken[0] not in VALUE_FLAGS or taken[0] in shared:
            return None
        shared[taken[0]] = taken[1]
    if not words:
        return None
    words.pop(0)
    service: str | None = None
    config: str | None = None
    while words:
        if not words[0].startswith("-"):
            if service is not None:
                return None
            service = words.pop(0)
            continue
        taken = take_flag()
        if taken is None or taken[0] != "--config" or config is not None:
            return None
        config = taken[1]
    port = shared.get("--base-port", os.environ.get("TETHER_BASE_PORT") or "0")
    if service is None or not port.isdecimal():
        return None
    return shared, service, None if config is None else Path(config)


def app() -> None:
    """`tether run ...` as the `tether` script and `python -m tether` give it: see `read_command_line`."""
    line = read_command_line(sys.argv[1:])
    if line is None:
        typer_app()
        return
    shared, service, config = line
    try:
        settings = NodeSettings.from_env(
            robot=shared.get("--robot"),
            base_port=int(shared["--base-port"]) if "--base-port" in shared else None,
            zenoh_config=Path(shared["--zenoh-config"]) if "--zenoh-config" in shared else None,
        )
    except ValueError as exc:
        error(str(exc))
        sys.exit(2)
    try:
        run_service(settings, service, config)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    sys.exit(0)


typer_app = typer.Typer(help=HELP, no_args_is_help=True)
typer_app.callback()(common)
typer_app.command()(run)
