"""What a command prints: text from outside (errors, reasons, names, help naming config tables) shown
as it is through rich, and one outcome said either in words or as one JSON object."""

from __future__ import annotations

import json
from typing import Any, NoReturn

import typer
from rich.console import Console
from rich.markup import escape


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
