"""What a command prints: text from outside (errors, reasons, names, help naming config tables) shown
as it is through rich, and one outcome said either in words or as one JSON object."""

from __future__ import annotations

import json
from typing import Any, NoReturn

import typer
import zenoh
from rich.console import Console
from rich.markup import escape

from services.runtime import CONTROLS, ConfigError, Node

# No services reachable (the CLI contract's exit code 3), here: no Zenoh session at all.
EXIT_UNREACHABLE = 3


def literal(value: object) -> str:
    """`value` as markup that prints as written: `[sim]` stays `[sim]`, and a stray `[/]` is text, not
    a closing tag (which rich would refuse with an error). For anything a service, a file, an exception
    or a person wrote, put into a console message that has markup of its own."""
    return escape(str(value))


def conclude(console: Console, as_json: bool, document: dict[str, Any], said: str, code: int = 0) -> NoReturn:
    """End a command: `document` as one JSON object on stdout with --json, else `said` (markup) on
    `console`; exit with `code`."""
    if as_json:
        print(json.dumps(document))
    else:
        console.print(said)
    raise typer.Exit(code)


def command_node(ctx: typer.Context, console: Console) -> Node:
    """A command's session from its settings (`ctx.obj`). A router that is down, a refused login or a
    config Zenoh cannot use ends the command, saying so: exit 3 (2 for the config), with --json one
    object, status 'unreachable' (or 'error') and the reason."""
    as_json = bool(ctx.params.get("as_json"))
    try:
        return Node("cli", ctx.obj)
    except ConfigError as exc:  # --zenoh-config names a file Zenoh cannot use
        conclude(console, as_json, {"status": "error", "reason": str(exc)}, f"[red]error:[/] {shown(exc)}", 2)
    except zenoh.ZError as exc:
        why = f"cannot open a Zenoh session: {exc}"
        said = f"[red]unreachable[/]: {shown(why)}"
        conclude(console, as_json, {"status": "unreachable", "reason": why}, said, EXIT_UNREACHABLE)


# Text someone else wrote (a file, a peer, the robot), before it reaches a terminal: its control
# characters escaped, so no ESC sequence retitles, clears or repaints the operator's terminal.
_CONTROLS_BUT_NEWLINE = {code: escaped for code, escaped in CONTROLS.items() if code != ord("\n")}


def printable(value: object, newlines: bool = False) -> str:
    """`value` as text with its control characters escaped (`\\x1b`), newlines kept if `newlines`:
    for anything a file holds, before it reaches a terminal."""
    return str(value).translate(_CONTROLS_BUT_NEWLINE if newlines else CONTROLS)


def shown(value: object, newlines: bool = True) -> str:
    """`value` as markup that prints as written, control characters escaped (see printable); on one
    line unless `newlines` (a table cell)."""
    return literal(printable(value, newlines))


# The longest --timeout: a week. Longer ones overflowed the clock's waits (a traceback, after the
# plan was sent), and no plan nor start-up is meant to take longer.
MAX_WAIT = 7 * 24 * 3600.0


def wait_seconds(value: float) -> float:
    """A --timeout (a typer callback), refused unless more than 0 and at most MAX_WAIT (NaN too: it
    compares false). A negative or NaN one had `send` give up only after the plan was sent and
    moving, and `up` start services it could not wait for."""
    if not 0 < value <= MAX_WAIT:
        raise typer.BadParameter(f"must be more than 0 and at most {MAX_WAIT:g} seconds, not {value}")
    return value
