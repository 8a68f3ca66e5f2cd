"""`tether send --recover PLAN`: a plan given as is, sent through the planner, which asks the model for a
recovery plan only when a step fails.

It keeps `tether send`'s contract: its exit codes (tether.client.EXIT_CODES: 0 succeeded, sent, or passed
a dry run; 1 failed, after any recoveries; 2 rejected or no planner; 3 unreachable) and its --json
object (PlanRun.as_json: status, stage, reason, failure, goal_id, steps), with `request_id`,
`final_goal_id` and `recoveries` added. `goal_id` is the goal first sent, as `tether send` names it;
`final_goal_id` the last one (a recovery's, or the same). `steps` is empty: the planner's reply does
not carry them (`tether goal ID` shows a goal's). `tether ask` differs: its 1 is the LLM endpoint
failing, so a failed plan exits 4 there.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, NoReturn

import msgspec
import typer
from rich.console import Console

from schemas.common import Stage
from schemas.executor import ExecutePlanResult, FailureKind, PlanStatus
from schemas.planner import MAX_RECORDED_CHARS, MAX_REQUEST_CHARS, AskReply, AskRequest, AskStatus
from services.planner.config import PlannerConfig, resolve_endpoint
from services.planner.errors import NotConfigured
from services.runtime import ConfigError, NodeSettings, load_config
from tether.ask import Interrupted, PlannerFailed, ask_planner, end_interrupted, show
from tether.client import EXIT_CODES, EXIT_UNREACHABLE, PlanRun
from tether.output import literal, shown

console = Console(stderr=True)

# The planner's outcome as `tether send` reports a plan's: None is 'accepted' (sent, not waited for).
# A dry run that passed is 'succeeded', as `tether send --dry-run` says it.
SEND_STATUS: dict[AskStatus, PlanStatus | None] = {
    AskStatus.APPROVED: PlanStatus.SUCCEEDED,
    AskStatus.ACCEPTED: None,
    AskStatus.SUCCEEDED: PlanStatus.SUCCEEDED,
    AskStatus.FAILED: PlanStatus.FAILED,
    AskStatus.LLM_ERROR: PlanStatus.FAILED,
    AskStatus.REJECTED: PlanStatus.REJECTED,
}
NO_PLANNER = (
    "--recover sends the plan through the planner, which asks an LLM for a recovery plan when a step fails; "
    "no planner service is running and no LLM endpoint is set here: start the planner (`tether up` with a "
    "[planner] url), set TETHER_LLM_URL and TETHER_LLM_MODEL, or give --config with a [planner] url "
    "(see `tether ask --help`)"
)


def purpose(plan: str) -> str:
    """What the plan is for, as the request the model reads: its own description when it has one."""
    try:
        description = json.loads(plan).get("description")
    except (ValueError, AttributeError, RecursionError):
        description = None
    said = description.strip() if isinstance(description, str) and description.strip() else ""
    head = "Carry out the plan given by an operator (shown below as the plan that ran)"
    return (f"{head}: {said}" if said else head)[:MAX_REQUEST_CHARS]


def final_failure(reply: AskReply) -> FailureKind | None:
    """The failure kind that ended the last goal: its record is the last recovery's (the one that was
    not asked for, or found no plan)."""
    if reply.status is not AskStatus.FAILED or not reply.recoveries:
        return None
    try:
        return FailureKind(reply.recoveries[-1].failure)
    except ValueError:
        return None


def unsent(status: str, reason: str) -> dict[str, Any]:
    """`tether send`'s object for a plan that was not sent (refused here, no planner, unreachable), with
    the fields --recover adds."""
    document: dict[str, Any] = {"status": status, "stage": None, "reason": reason, "goal_id": "", "steps": []}
    return {**document, "request_id": "", "final_goal_id": "", "recoveries": []}


def outcome(reply: AskReply) -> tuple[dict[str, Any], int]:
    """The planner's reply as `tether send --json` prints a plan's outcome, and send's exit code for it."""
    if reply.status is AskStatus.UNREACHABLE:
        document, code = unsent("unreachable", reply.reason), EXIT_UNREACHABLE
    elif reply.status is AskStatus.UNCONFIGURED:
        document, code = unsent(PlanStatus.REJECTED, reply.reason), EXIT_CODES[PlanStatus.REJECTED]
    else:
        status = SEND_STATUS[reply.status]
        first = reply.recoveries[0].failed_goal if reply.recoveries else reply.goal_id
        result = None
        if status is not None:
            stage = reply.stage or Stage.EXECUTE
            result = ExecutePlanResult(status=status, stage=stage, reason=reply.reason, failure=final_failure(reply))
        document = PlanRun(goal_id=first, result=result).as_json()
        code = EXIT_CODES[status] if status is not None else 0
    document.update(
        request_id=reply.request_id,
        final_goal_id=reply.goal_id,
        recoveries=msgspec.to_builtins(reply.recoveries),
    )
    return document, code


def send_recover(
    settings: NodeSettings,
    plan: str,
    fmt: str,
    dry_run: bool,
    wait: bool,
    preempt: bool,
    timeout: float,
    as_json: bool,
    config_path: Path | None = None,
) -> NoReturn:
    """Dry-run, send and follow `plan` through the planner; exits with `tether send`'s codes."""
    if fmt != "auto":
        refuse(as_json, f"--recover reads the plan's format itself: leave --format at auto, not {fmt!r}")
    if len(plan) > MAX_RECORDED_CHARS:
        refuse(as_json, f"--recover takes plans of up to {MAX_RECORDED_CHARS} characters, not {len(plan)}")
    try:
        config = load_config(PlannerConfig, config_path, "planner")
        endpoint = resolve_endpoint(config)
    except (ConfigError, NotConfigured) as exc:
        refuse(as_json, str(exc))
    in_process = endpoint is not None
    request = AskRequest(
        text=purpose(plan),
        plan=plan,
        dry_run=dry_run,
        preempt=preempt,
        # The bound of --config's [planner] table (or of the environment's endpoint here); else the service's.
        max_recoveries=config.max_recoveries if in_process or config_path is not None else None,
        # In this process nothing recovers the plan once the command exits: it waits for the end.
        wait=wait or (in_process and not dry_run and config.max_recoveries > 0),
        # --timeout bounds it all: no model call starts and no plan is sent after it.
        deadline=time.time() + timeout,
    )
    try:
        reply = ask_planner(settings, request, config, endpoint, timeout)
    except Interrupted as stop:
        end_interrupted(interrupted, stop, as_json)
    except PlannerFailed as exc:
        reason = f"the planner service failed: {exc.reason}"
        if exc.unreachable:
            reply = AskReply(status=AskStatus.UNREACHABLE, request_id="none", reason=reason)
        else:  # an error of the planner's own, not a reply: the plan may or may not have been sent
            if as_json:
                print(json.dumps(unsent(PlanStatus.FAILED, reason)))
            else:
                console.print(f"[red]failed[/]: {shown(reason)}", highlight=False)
            raise typer.Exit(EXIT_CODES[PlanStatus.FAILED]) from None
    if reply.status is AskStatus.UNCONFIGURED and reply.request_id == "none":  # no service answered
        reply = AskReply(status=AskStatus.UNCONFIGURED, request_id=reply.request_id, reason=NO_PLANNER)
    document, code = outcome(reply)
    if as_json:
        print(json.dumps(document))
    else:
        show(reply, as_json=False)
    sys.stdout.flush()
    raise typer.Exit(code)


def interrupted(stop: Interrupted, as_json: bool) -> NoReturn:
    """A Ctrl-C (or SIGTERM): what was sent is canceled (tether.ask: through the planner service, the
    request by its id) and its end said as `tether send` says a canceled plan's: 1 canceled, 3 when no
    end came. `request_id` names the service's request this command made ("" when it made none)."""
    first = stop.goals[0] if stop.goals else ""
    if stop.result is not None:
        document = {**PlanRun(goal_id=first, result=stop.result).as_json(), "recoveries": []}
    else:
        document = {**unsent("unreachable", stop.reason), "goal_id": first}
    document.update(request_id=stop.request_id, final_goal_id=stop.goal_id)
    if as_json:
        print(json.dumps(document))
    else:
        goal = f" (goal {stop.goal_id})" if stop.goal_id else ""
        console.print(f"[red]{stop.status}[/]{shown(goal)}: {shown(stop.reason)}", highlight=False)
    sys.stdout.flush()
    raise typer.Exit(stop.code)


def refuse(as_json: bool, reason: str) -> NoReturn:
    if as_json:
        print(json.dumps(unsent(PlanStatus.REJECTED, reason)))
    else:
        console.print(f"[red]error:[/] {literal(reason)}", highlight=False)
    sys.stdout.flush()
    raise typer.Exit(EXIT_CODES[PlanStatus.REJECTED])
