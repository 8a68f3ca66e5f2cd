"""`tether deploy init`: write a secured deployment (its own module: it needs cryptography, no other command does)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from tether import deployment
from tether.output import conclude, literal

# An error names paths: one line, never wrapped (and a path broken) at the terminal's width.
console = Console(stderr=True, soft_wrap=True)
out = Console()


def deploy_init(
    directory: Annotated[Path, typer.Argument(help="Where the deployment goes (made if missing).")],
    robot: Annotated[list[str], typer.Option("--robot", help="A robot of the fleet (repeatable).")],
    tls: Annotated[bool, typer.Option("--tls", help="Mutual TLS: a CA and a certificate per identity.")] = False,
    router: Annotated[
        str | None,
        typer.Option(
            "--router",
            help=f"HOST[:PORT] where clients reach the router (default {deployment.DEFAULT_ROUTER_HOST}:"
            f"{deployment.DEFAULT_ROUTER_PORT}).",
        ),
    ] = None,
    backend: Annotated[
        str | None,
        typer.Option(
            "--backend",
            help="The backend of the robots named here: sim, ros2 (a real robot) or any (both); only its "
            "identity may report the robot's state. Default: a new robot any, a robot already there its own.",
        ),
    ] = None,
    as_json: Annotated[
        bool,
        typer.Option(
            "--json", help="Print one JSON object: directory, robots, backends, tls and the files, or the error."
        ),
    ] = False,
) -> None:
    """Write a deployment for these robots, or add them to one: existing secrets, keys and certificates stay.

    Exit 0 written, 2 refused (a bad robot name or router address, a directory that cannot be written).
    """
    try:
        address = deployment.RouterAddress.parse(router) if router is not None else None
        written = deployment.init(directory, robot, tls=tls, router=address, backend=backend)
        made = deployment.Deployment.load(directory)
    except (deployment.DeploymentError, OSError) as exc:
        conclude(console, as_json, {"error": str(exc)}, f"[red]error:[/] {literal(exc)}", 2)
    if warning := deployment.cleartext_warning(made):
        console.print(f"[yellow]warning:[/] {literal(warning)}", soft_wrap=True)
    if as_json:
        files = [{"path": str(w.path), "created": w.created, "secret": w.secret} for w in written]
        backends = {name: made.backend(name) for name in robot}
        summary = {"directory": str(directory.resolve()), "robots": robot, "backends": backends, "tls": tls}
        print(json.dumps(summary | {"files": files}))
        return
    table = Table("file", "", "mode")
    for w in written:
        table.add_row(literal(w.path), "written" if w.created else "kept", "600 (secret)" if w.secret else "")
    out.print(table)
    created = sum(w.created for w in written)
    out.print(f"{created} files written, {len(written) - created} kept, in {directory.resolve()}", markup=False)
