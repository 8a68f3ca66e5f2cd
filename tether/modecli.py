"""`tether mode`, `tether approve`, `tether deny`, `tether pause`, `tether resume`, `tether pending`: the
operator's say over what moves the robot.

Setting the mode and deciding on a plan take the operator token (as `tether reset`); safety checks it,
and in a secured deployment only the operator's identity may ask at all.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Annotated, Any, NoReturn

import msgspec
import typer
from rich.console import Console
from rich.markup import escape

from schemas import keys
from schemas.safety import ApprovalAction, ApprovalDecision, ApprovalReply, ControlMode, ModeRequest, PendingPlans
from schemas.world import Empty
from services.errors import CallError
from services.safety.operator import read_token, token_path
from tether.client import EXIT_UNREACHABLE, next_heartbeat, operator_name, within_schema
from tether.output import command_node, printable

# Exit codes of these commands.
EXIT_OK = 0
EXIT_REFUSED = 2  # safety said no: a wrong token, an unknown or finished goal; or bad input

CALL_TIMEOUT = 3.0
HEARTBEAT_WAIT = 2.0

TokenFileOpt = Annotated[str | None, typer.Option("--token-file", help="The operator token file safety created.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object.")]

console = Console(stderr=True, highlight=False)


def _emit(as_json: bool, data: dict[str, Any], text: str, code: int) -> NoReturn:
    # The text quotes safety's replies, which quote what others sent: its control characters are
    # escaped (rich's escape is for its markup only, it passes ESC sequences through).
    if as_json:
        print(json.dumps(data))
    elif code == EXIT_OK:
        print(printable(text))
    else:
        console.print(escape(printable(text)))
    raise typer.Exit(code)


def _token(token_file: str | None, as_json: bool) -> str:
    try:
        return read_token(token_path(token_file))
    except OSError as exc:
        _emit(
            as_json,
            {"ok": False, "error": f"cannot read the operator token: {exc}"},
            f"error: cannot read the operator token: {exc}",
            EXIT_REFUSED,
        )


def _unreachable(as_json: bool, exc: CallError) -> NoReturn:
    why = f"safety unreachable: {exc}"
    _emit(as_json, {"ok": False, "error": why}, why, EXIT_UNREACHABLE)


def mode(
    ctx: typer.Context,
    new: Annotated[
        str | None, typer.Argument(metavar="[MODE]", help="direct, shared, supervised or autonomous; none: show it.")
    ] = None,
    token_file: TokenFileOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Show the control mode, or set it (operator only: needs the operator token file).

    direct: only a person drives (teleop), plans are refused. shared: a person drives, plans are
    refused. supervised: a plan moves the robot only once `tether approve` let it. autonomous: plans
    safety approves run (the default).

    Exit 0 shown or set, 2 refused (wrong token, unknown mode), 3 safety unreachable.
    """
    if new is None:
        with command_node(ctx, console) as node:
            waited = next_heartbeat(node, HEARTBEAT_WAIT)
        beat = waited.status
        if beat is None:
            why = waited.why_not(HEARTBEAT_WAIT)
            _emit(as_json, {"ok": False, "mode": None, "error": why}, f"error: {why}", EXIT_UNREACHABLE)
        _emit(as_json, {"ok": True, "mode": str(beat.mode)}, f"mode: {beat.mode}", EXIT_OK)
    try:
        wanted = ControlMode(new.strip().lower())
    except ValueError:
        known = ", ".join(m.value for m in ControlMode)
        why = f"unknown mode {new!r}; modes are {known}"
        _emit(as_json, {"ok": False, "mode": None, "error": why}, f"error: {why}", EXIT_REFUSED)
    token = _token(token_file, as_json)
    try:
        # Bounds (the token's length) are the schema's: checked here as safety would, so a file that
        # holds no token is refused as such (exit 2), not taken for safety unreachable (its error reply).
        request = within_schema(ModeRequest(operator=operator_name(), token=token, mode=wanted))
    except msgspec.ValidationError as exc:
        why = f"bad request: {exc}"
        _emit(as_json, {"ok": False, "mode": None, "error": why}, f"error: {why}", EXIT_REFUSED)
    with command_node(ctx, console) as node:
        try:
            reply = node.call(keys.SET_MODE, request, timeout=CALL_TIMEOUT)
        except CallError as exc:
            _unreachable(as_json, exc)
    data = {"ok": reply.ok, "mode": str(reply.mode), "message": reply.message}
    _emit(
        as_json, data, reply.message if reply.ok else f"refused: {reply.message}", EXIT_OK if reply.ok else EXIT_REFUSED
    )


def _decide(
    ctx: typer.Context, goal_id: str, action: ApprovalAction, reason: str, token_file: str | None, as_json: bool
) -> NoReturn:
    token = _token(token_file, as_json)
    # Approve and deny as safety has always read them; pause and resume by name.
    decision: dict[str, Any] = {"action": action}
    if action in (ApprovalAction.APPROVE, ApprovalAction.DENY):
        decision = {"approve": action is ApprovalAction.APPROVE}
    try:
        # Bounds (the goal id's shape, the reason's length) are the schema's: checked here as safety would.
        request = within_schema(
            ApprovalDecision(operator=operator_name(), token=token, goal_id=goal_id, reason=reason, **decision)
        )
    except msgspec.ValidationError as exc:
        why = f"bad request: {exc}"
        _emit(as_json, {"ok": False, "goal_id": goal_id, "error": why}, f"error: {why}", EXIT_REFUSED)
    with command_node(ctx, console) as node:
        try:
            reply: ApprovalReply = node.call(keys.APPROVAL_DECIDE, request, timeout=CALL_TIMEOUT)
        except CallError as exc:
            _unreachable(as_json, exc)
    data: dict[str, Any] = {"ok": reply.ok, "goal_id": goal_id, "message": reply.message}
    if reply.approval is not None:
        data["state"] = str(reply.approval.state)
    _emit(
        as_json, data, reply.message if reply.ok else f"refused: {reply.message}", EXIT_OK if reply.ok else EXIT_REFUSED
    )


def approve(
    ctx: typer.Context,
    goal_id: Annotated[str, typer.Argument(help="The goal id `tether send` or `tether pending` printed.")],
    token_file: TokenFileOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Let a plan waiting in supervised mode move the robot (operator only: needs the operator token file).

    Safety checks the plan once more from where the robot is now; one it would refuse now is denied.
    Exit 0 approved, 2 refused (wrong token, unknown or finished goal, the check refuses it now),
    3 safety unreachable.
    """
    _decide(ctx, goal_id, ApprovalAction.APPROVE, "", token_file, as_json)


def deny(
    ctx: typer.Context,
    goal_id: Annotated[str, typer.Argument(help="The goal id `tether send` or `tether pending` printed.")],
    reason: Annotated[str, typer.Option("--reason", help="Why; the plan's result and the recording keep it.")] = "",
    token_file: TokenFileOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Refuse a plan waiting in supervised mode, or end a paused one (operator only: needs the token file).

    A plan denied moves the robot no more.

    Exit 0 denied, 2 refused (wrong token, unknown or finished goal), 3 safety unreachable.
    """
    _decide(ctx, goal_id, ApprovalAction.DENY, reason, token_file, as_json)


def pause(
    ctx: typer.Context,
    goal_id: Annotated[str, typer.Argument(help="The goal id of the approved plan that runs.")],
    reason: Annotated[str, typer.Option("--reason", help="Why; the events and the plan's feedback keep it.")] = "",
    token_file: TokenFileOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Pause an approved plan while it runs (supervised mode; operator only: needs the token file).

    Safety cancels the plan's goals under way and refuses its motion until `tether resume`; the plan
    waits (it does not fail) and teleop drives meanwhile. Exit 0 paused, 2 refused (wrong token, not
    supervised mode, a goal that is unknown, finished, pending or already paused), 3 safety unreachable.
    """
    _decide(ctx, goal_id, ApprovalAction.PAUSE, reason, token_file, as_json)


def resume(
    ctx: typer.Context,
    goal_id: Annotated[str, typer.Argument(help="The goal id of the paused plan.")],
    token_file: TokenFileOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Hand a paused plan back (supervised mode; operator only: needs the token file).

    Safety checks the plan once more from where the robot is now (one it would refuse now is denied);
    the step that was paused runs again from there. Exit 0 resumed, 2 refused (wrong token, not
    supervised mode, a goal that is not paused, the check refuses it now), 3 safety unreachable.
    """
    _decide(ctx, goal_id, ApprovalAction.RESUME, "", token_file, as_json)


def pending(ctx: typer.Context, as_json: JsonOpt = False) -> None:
    """List the plans waiting for an operator's approval and those an operator paused.

    The oldest first, each with its steps, its route and safety's dry run.

    Exit 0 (also when none waits), 3 safety unreachable.
    """
    with command_node(ctx, console) as node:
        try:
            waiting: PendingPlans = node.call(keys.PENDING_PLANS, Empty(), timeout=CALL_TIMEOUT)
        except CallError as exc:
            _unreachable(as_json, exc)
    if as_json:
        print(json.dumps({"ok": True, **msgspec.to_builtins(waiting)}))
        raise typer.Exit(EXIT_OK)
    # Steps, labels, checks and reasons are what a plan's sender wrote (any peer may ask for an
    # approval): each field is printed with its control characters escaped.
    lines = [f"mode: {printable(waiting.mode)}"]
    if not waiting.plans:
        lines.append("no plan waits for approval")
    for plan in waiting.paused:
        goal = printable(plan.goal_id)
        lines.append(f"goal {goal} is paused ({printable(plan.reason)}): `tether resume {goal}` hands back")
    now = time.time()
    for plan in waiting.plans:
        lines.append(f"goal {printable(plan.goal_id)}, waiting {max(0.0, now - plan.requested):.0f} s:")
        lines += [f"  {printable(step)}" for step in plan.steps]
        lines.append(f"  safety's dry run: {'; '.join(printable(check) for check in plan.checks) or 'approved'}")
    sys.stdout.write("\n".join(lines) + "\n")
    raise typer.Exit(EXIT_OK)
