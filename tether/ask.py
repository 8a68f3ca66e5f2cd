"""`tether ask "bring me the red cup"`: words to a plan an LLM writes, dry-run checked, then sent.

Where the model is called: with an endpoint configured here (TETHER_LLM_URL, or `[planner] url` in
--config), in this process, so the key stays in this shell's environment; else by the planner
service (`plan/ask`) when it is running; else it says how to configure an endpoint. Either way each
attempt is published on planner/attempts, so the recorder keeps it.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import msgspec
import typer
from rich.console import Console

from schemas import keys
from schemas.planner import MAX_ATTEMPTS, MAX_REQUEST_CHARS, AskReply, AskRequest, AskStatus
from services.errors import CallError
from services.planner.config import HOW_TO_CONFIGURE, PlannerConfig, resolve_endpoint
from services.planner.errors import NotConfigured
from services.planner.node import Planner
from services.runtime import ConfigError, Node, NodeSettings, load_config
from tether.output import literal

console = Console(stderr=True)

EXIT_CODES = {
    AskStatus.APPROVED: 0,
    AskStatus.ACCEPTED: 0,
    AskStatus.LLM_ERROR: 1,
    AskStatus.REJECTED: 2,
    AskStatus.UNCONFIGURED: 2,
    AskStatus.UNREACHABLE: 3,
}


def show(reply: AskReply, as_json: bool) -> None:
    if as_json:
        print(json.dumps(msgspec.to_builtins(reply)))
        return
    if reply.status is AskStatus.UNCONFIGURED:
        console.print("[red]error:[/] ", end="")
        console.print(reply.reason, markup=False, highlight=False)
        return
    if reply.plan:
        console.print(f"plan after {reply.attempts} attempt(s):", highlight=False)
        console.print(reply.plan, markup=False, highlight=False)
    colour = "green" if reply.status in (AskStatus.APPROVED, AskStatus.ACCEPTED) else "red"
    where = f" at stage {reply.stage}" if reply.stage is not None and colour == "red" else ""
    console.print(f"[{colour}]{reply.status}[/]{where}: ", end="")
    console.print(reply.reason, markup=False, highlight=False)
    if reply.goal_id:
        console.print(f"goal {reply.goal_id}; `tether goal {reply.goal_id}` follows it.", markup=False, highlight=False)


def ask(
    ctx: typer.Context,
    request: Annotated[str, typer.Argument(help="What you want the robot to do, in words; - for stdin.")],
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Stop at an approved plan; nothing moves.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object with the outcome.")] = False,
    max_attempts: Annotated[
        int | None,
        typer.Option(
            "--max-attempts", min=1, max=MAX_ATTEMPTS, help=literal("Model calls at most (default: [planner]).")
        ),
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help=literal("TOML file with a [planner] table."))] = None,
    preempt: Annotated[bool, typer.Option("--preempt", help="Cancel a plan already running for this one.")] = False,
    timeout: Annotated[float, typer.Option(help="Seconds to wait for the planner service.")] = 900.0,
) -> None:
    """Ask an LLM for a plan, dry-run it (parse, resolve, safety), feed refusals back, then send it.

    The endpoint: TETHER_LLM_URL, TETHER_LLM_MODEL, TETHER_LLM_API_KEY, or the config's planner table
    (url, model, api_key_env). Exit 0 approved or sent, 1 the LLM endpoint failed, 2 rejected or no
    endpoint configured, 3 no services reachable.
    """
    settings: NodeSettings = ctx.obj
    text = sys.stdin.read() if request == "-" else request
    if not text.strip() or len(text) > MAX_REQUEST_CHARS:
        console.print(f"[red]error:[/] the request must be 1 to {MAX_REQUEST_CHARS} characters, not {len(text)}")
        raise typer.Exit(2)
    try:
        planner_config = load_config(PlannerConfig, config, "planner")
        endpoint = resolve_endpoint(planner_config)
    except (ConfigError, NotConfigured) as exc:
        console.print(f"[red]error:[/] {literal(exc)}", highlight=False)
        raise typer.Exit(2) from None
    ask_request = AskRequest(text=text, dry_run=dry_run, max_attempts=max_attempts or 0, preempt=preempt)
    with Node("cli", settings) as node:
        if endpoint is not None:
            planner = Planner(node, planner_config, endpoint)
            try:
                reply = planner.ask(ask_request)
            finally:
                planner.close()
        elif "planner" in node.alive_services(timeout=2.0):
            try:
                reply = node.call(keys.PLAN_ASK, ask_request, timeout=timeout)
            except CallError as exc:
                console.print(f"[red]planner failed[/]: {literal(exc.error.message)}", highlight=False)
                raise typer.Exit(3 if exc.error.kind == "unavailable" else 1) from None
        else:
            reply = AskReply(status=AskStatus.UNCONFIGURED, request_id="none", reason=HOW_TO_CONFIGURE)
    show(reply, as_json)
    raise typer.Exit(EXIT_CODES[reply.status])
