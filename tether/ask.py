"""`tether ask "bring me the red cup"`: words to a plan an LLM writes, dry-run checked, then sent.

Where the model is called: with an endpoint configured here (TETHER_LLM_URL, or `[planner] url` in
--config), in this process, so the key stays in this shell's environment; else by the planner
service (`plan/ask`) when it is running; else it says how to configure an endpoint. Either way each
attempt is published on planner/attempts, so the recorder keeps it.

A sent plan that fails at a step is recovered (the model asked for a new plan from the world as it is
now, `--max-recoveries`). The service does that behind its reply; in this process nobody would once
it exits, so with an endpoint here and recoveries allowed `tether ask` waits for the plan's end.
"""

from __future__ import annotations

import contextlib
import json
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent import futures
from pathlib import Path
from types import FrameType
from typing import Annotated, NoReturn

import msgspec
import typer
import zenoh
from rich.console import Console

from schemas import keys
from schemas.common import Stage
from schemas.executor import ExecutePlanResult, PlanStatus
from schemas.planner import (
    MAX_ATTEMPTS,
    MAX_RECOVERIES,
    MAX_REQUEST_CHARS,
    AskCancel,
    AskCancelReply,
    AskReply,
    AskRequest,
    AskStatus,
)
from services.errors import CallError
from services.planner.config import HOW_TO_CONFIGURE, Endpoint, PlannerConfig, resolve_endpoint
from services.planner.errors import NotConfigured
from services.planner.node import Planner
from services.runtime import ConfigError, Node, NodeSettings, load_config
from tether.client import EXIT_CODES as SEND_EXIT_CODES
from tether.client import EXIT_UNREACHABLE, PlanSender, cancel_interrupted
from tether.output import conclude, literal, printable, shown, wait_seconds
from tether.runservice import leave

console = Console(stderr=True)

# `tether ask`'s own: 1 is the LLM endpoint failing, so a plan that failed is 4. (`tether send --recover`
# keeps send's codes instead: tether/sendrecover.py.)
EXIT_CODES = {
    AskStatus.APPROVED: 0,
    AskStatus.ACCEPTED: 0,
    AskStatus.LLM_ERROR: 1,
    AskStatus.REJECTED: 2,
    AskStatus.UNCONFIGURED: 2,
    AskStatus.UNREACHABLE: 3,
    AskStatus.SUCCEEDED: 0,
    AskStatus.FAILED: 4,
}
# The planner service answered with an error of its own (not an AskReply): `tether ask` exits this.
EXIT_PLANNER_ERROR = 1
GREEN = (AskStatus.APPROVED, AskStatus.ACCEPTED, AskStatus.SUCCEEDED)
# How long a Ctrl-C waits for the planner service's answer, when the service cannot cancel by request
# id (an older one): the goal it sent is named only there.
ANSWER_WAIT = 30.0
# How long a Ctrl-C waits for the planner to cancel the request: a send under way holds it up to
# its timeout (the executor preempting a plan), then the cancel of the goal.
CANCEL_ASK_WAIT = 20.0


class PlannerFailed(Exception):
    """The planner service did not answer `plan/ask` with a reply: `unreachable` when it was not there."""

    def __init__(self, reason: str, unreachable: bool) -> None:
        super().__init__(reason)
        self.reason = reason
        self.unreachable = unreachable


class Interrupted(Exception):
    """Ctrl-C (or SIGTERM) during the ask. `goals` are the goals it sent, first to last (the last
    canceled); `result` how the last ended, None when no end came (it may still be moving) or
    nothing was sent and that is not known for sure; `reason` says which."""

    def __init__(self, goals: list[str], result: ExecutePlanResult | None, reason: str = "") -> None:
        super().__init__(reason or (result.reason if result else ""))
        self.goals = goals
        self.result = result
        self.reason = reason or (result.reason if result else "")
        self.request_id = ""  # the request it interrupted, when this command named it (the planner service's)

    @property
    def goal_id(self) -> str:
        return self.goals[-1] if self.goals else ""

    @property
    def status(self) -> str:
        return self.result.status if self.result is not None else "unreachable"

    @property
    def code(self) -> int:
        """`tether send`'s exit code for the end: 1 canceled, 3 no end came."""
        return SEND_EXIT_CODES[self.result.status] if self.result is not None else EXIT_UNREACHABLE


def canceled(node: Node, goals: list[str]) -> Interrupted:
    """Cancel the last goal the ask sent (or was sending) and wait for its end, as `tether send` does
    at a Ctrl-C."""
    if not goals:
        said = "interrupted (Ctrl-C) before any plan was sent"
        return Interrupted([], ExecutePlanResult(status=PlanStatus.CANCELED, stage=Stage.EXECUTE, reason=said))
    goal_id = goals[-1]
    console.print("canceling...")
    ended = cancel_interrupted(PlanSender(node), goal_id)
    if isinstance(ended, str):
        return Interrupted(goals, None, ended)
    return Interrupted(goals, ended.result)


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM stops the ask as a Ctrl-C does: what it sent is canceled, not left moving."""

    def interrupt(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def show_interrupted(stop: Interrupted, as_json: bool) -> NoReturn:
    """`tether ask`'s object for an interrupted ask: status as `tether send` says a canceled plan's
    end (canceled, or how it ended first; unreachable when no end came), send's exit codes."""
    stage = stop.result.stage if stop.result is not None else None
    document = {
        "status": stop.status,
        "request_id": stop.request_id,
        "attempts": 0,
        "stage": stage,
        "reason": stop.reason,
        "plan": "",
        "goal_id": stop.goal_id,
        "recoveries": [],
    }
    goal = f" (goal {stop.goal_id})" if stop.goal_id else ""
    conclude(console, as_json, document, f"[red]{stop.status}[/]{shown(goal)}: {shown(stop.reason)}", stop.code)


def end_interrupted(show: Callable[[Interrupted, bool], NoReturn], stop: Interrupted, as_json: bool) -> NoReturn:
    """`show` says how the interrupted ask ended; then the process ends without Python's finalization
    (tether.runservice.leave): the thread that asked the planner service may still be inside its Zenoh
    call, and such a thread made to exit at finalization aborts the process (SIGABRT, exit -6, the
    output not yet flushed lost: seen in CI after a correct cancel). Here, not by unwinding to the entry
    point (tether/__main__.py, which would end it the same way): one CI run of that saw the command die
    of SIGINT (-2) after printing the right JSON, not reproduced in 27 runs here, loaded or not."""
    try:
        show(stop, as_json)
    except typer.Exit as ended:
        leave(ended.exit_code)


def refuse(reason: str, as_json: bool) -> NoReturn:
    """End `tether ask` before asking anything: exit 2, the reason as an error (with --json, as one
    JSON object on stdout, as the command's other errors are)."""
    conclude(console, as_json, {"status": "error", "reason": reason}, f"[red]error:[/] {literal(reason)}", 2)


def show(reply: AskReply, as_json: bool) -> None:
    if as_json:
        print(json.dumps(msgspec.to_builtins(reply)))
        return
    if reply.status is AskStatus.UNCONFIGURED:
        console.print("[red]error:[/] ", end="")
        console.print(printable(reply.reason, newlines=True), markup=False, highlight=False)
        return
    if reply.plan:
        console.print(f"plan after {reply.attempts} attempt(s):", highlight=False)
        console.print(printable(reply.plan, newlines=True), markup=False, highlight=False)
    for recovery in reply.recoveries:
        step = f" step {recovery.step + 1}" if recovery.step is not None else ""
        failed = f"after{step} failed ({recovery.failure or 'unknown'})"
        said = f"recovery {recovery.number} {failed}: {recovery.outcome}: {recovery.reason}"
        console.print(printable(said, newlines=True), markup=False, highlight=False)
    colour = "green" if reply.status in GREEN else "red"
    where = f" at stage {reply.stage}" if reply.stage is not None and colour == "red" else ""
    console.print(f"[{colour}]{reply.status}[/]{where}: ", end="")
    console.print(printable(reply.reason, newlines=True), markup=False, highlight=False)
    if reply.goal_id:
        goal = printable(reply.goal_id)
        console.print(f"goal {goal}; `tether goal {goal}` follows it.", markup=False, highlight=False)


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
    timeout: Annotated[
        float,
        typer.Option(
            help="Seconds to wait for the outcome; no model call starts and no plan is sent after.",
            callback=wait_seconds,
        ),
    ] = 900.0,
    wait: Annotated[
        bool, typer.Option("--wait", help="Wait until the plan and any recovery have ended (succeeded or failed).")
    ] = False,
    max_recoveries: Annotated[
        int | None,
        typer.Option(
            "--max-recoveries",
            min=0,
            max=MAX_RECOVERIES,
            help=literal("Recovery plans at most when a step fails (default: [planner], 2; 0: none)."),
        ),
    ] = None,
) -> None:
    """Ask an LLM for a plan, dry-run it (parse, resolve, safety), feed refusals back, then send it.

    When the sent plan fails at a step (an object dropped, not where expected, a route blocked), the
    model is asked for a recovery plan, checked the same way, up to --max-recoveries times; never
    after an e-stop, a veto or a cancel. With --wait the outcome is the plan's end; with an endpoint
    in this process (TETHER_LLM_URL) and recoveries allowed it always waits, since nothing would
    recover the plan once this command exits. The endpoint: TETHER_LLM_URL, TETHER_LLM_MODEL,
    TETHER_LLM_API_KEY, or the config's planner table (url, model, api_key_env). --timeout bounds it
    all: nothing is asked of the model or sent after it. Exit 0 approved, sent or succeeded, 1 the LLM
    endpoint (or the planner service) failed, 2 rejected or no endpoint configured, 3 no services
    reachable, 4 the plan failed (after any recoveries; `tether send --recover` exits 1 for that, as
    `tether send` does). A Ctrl-C (or SIGTERM) cancels the plan sent and waits for its end, as
    `tether send` does: exit 1 canceled, 3 when no end came.
    """
    settings: NodeSettings = ctx.obj
    # Bytes that are not UTF-8 (from stdin, or in the argument) are kept as surrogates, then refused
    # here: sent, they failed to encode with a traceback.
    text = sys.stdin.buffer.read().decode(errors="surrogateescape") if request == "-" else request
    try:
        text.encode()
    except UnicodeEncodeError as exc:
        refuse(f"the request is not UTF-8 text (a byte at character {exc.start + 1})", as_json)
    if not text.strip() or len(text) > MAX_REQUEST_CHARS:
        refuse(f"the request must be 1 to {MAX_REQUEST_CHARS} characters, not {len(text)}", as_json)
    try:
        planner_config = load_config(PlannerConfig, config, "planner")
        endpoint = resolve_endpoint(planner_config)
    except (ConfigError, NotConfigured) as exc:
        refuse(str(exc), as_json)
    recoveries = planner_config.max_recoveries if max_recoveries is None else max_recoveries
    in_process = endpoint is not None
    ask_request = AskRequest(
        text=text,
        dry_run=dry_run,
        max_attempts=max_attempts or 0,
        preempt=preempt,
        max_recoveries=recoveries if in_process else max_recoveries,
        wait=wait or (in_process and recoveries > 0 and not dry_run),
        # A caller that stops waiting has no plan, nor recovery, sent behind its back.
        deadline=time.time() + timeout,
    )
    try:
        reply = ask_planner(settings, ask_request, planner_config, endpoint, timeout)
    except Interrupted as stop:
        end_interrupted(show_interrupted, stop, as_json)
    except PlannerFailed as exc:
        code = 3 if exc.unreachable else EXIT_PLANNER_ERROR
        if as_json:
            print(json.dumps({"status": "unreachable" if exc.unreachable else "error", "reason": exc.reason}))
        else:
            console.print(f"[red]planner failed[/]: {shown(exc.reason)}", highlight=False)
        raise typer.Exit(code) from None
    show(reply, as_json)
    raise typer.Exit(EXIT_CODES[reply.status])


def ask_planner(
    settings: NodeSettings, request: AskRequest, config: PlannerConfig, endpoint: Endpoint | None, timeout: float
) -> AskReply:
    """The planner's reply: in this process with an endpoint of its own, else from the planner service,
    else UNCONFIGURED. PlannerFailed when the service answered with an error instead; Interrupted at a
    Ctrl-C or SIGTERM, once what the ask sent was canceled."""
    try:
        node = Node("cli", settings)
    except zenoh.ZError as exc:  # the router down, the login refused: exit 3, saying so
        raise PlannerFailed(f"cannot open a Zenoh session: {exc}", unreachable=True) from None
    with node, sigterm_interrupts():
        if endpoint is not None:
            goals: list[str] = []
            planner = Planner(node, config, endpoint, on_send=goals.append)
            try:
                return planner.ask(request)
            except KeyboardInterrupt:
                raise canceled(node, goals) from None
            finally:
                planner.close()
        try:
            alive = "planner" in node.alive_services(timeout=2.0)
        except KeyboardInterrupt:
            raise canceled(node, []) from None
        if alive:
            # Named here, so that a Ctrl-C can stop the request by it (plan/ask_cancel).
            return ask_service(node, msgspec.structs.replace(request, request_id=uuid.uuid4().hex), timeout)
    return AskReply(status=AskStatus.UNCONFIGURED, request_id="none", reason=HOW_TO_CONFIGURE)


def ask_service(node: Node, request: AskRequest, timeout: float) -> AskReply:
    """The planner service's reply, asked on a thread of its own. At a Ctrl-C the request is canceled
    by its id (plan/ask_cancel: nothing more is sent for it, and the goal it sent is canceled) and
    that goal's end waited for. A service that cannot cancel it (an older one) names the goal only in
    its answer, which comes at acceptance: that answer is waited for, ANSWER_WAIT at most, and its
    goal canceled; with `wait` it comes only at the plan's end, so nothing names the goal."""
    answer: futures.Future[AskReply] = futures.Future()

    def call() -> None:
        try:
            answer.set_result(node.call(keys.PLAN_ASK, request, timeout=timeout))
        except Exception as exc:  # CallError, or the session closed under the call
            answer.set_exception(exc)

    try:
        # Started inside the try: a Ctrl-C can come while start() waits for the thread to run, by which
        # time the request may have gone (the planner may be acting on it), and must cancel it too.
        threading.Thread(target=call, name="plan/ask", daemon=True).start()
        return answer.result()
    except CallError as exc:
        raise PlannerFailed(exc.error.message, exc.error.kind == "unavailable") from None
    except KeyboardInterrupt:
        pass
    try:
        stop_request(node, request, answer)
    except Interrupted as stop:
        stop.request_id = request.request_id  # named by this command: the planner's records know it by it
        raise


def stop_request(node: Node, request: AskRequest, answer: futures.Future[AskReply]) -> NoReturn:
    """After a Ctrl-C: the request canceled by its id, and its goal's end waited for (Interrupted)."""
    unknown = "a plan it sent may be moving; `tether cancel` stops the plan running"
    console.print("asking the planner to cancel the request...")
    try:
        stopped: AskCancelReply = node.call(
            keys.PLAN_ASK_CANCEL, AskCancel(request_id=request.request_id), timeout=CANCEL_ASK_WAIT
        )
    except KeyboardInterrupt:
        raise Interrupted([], None, f"no outcome: interrupted again before the planner canceled: {unknown}") from None
    except CallError as exc:
        console.print(f"the planner did not cancel the request ({shown(str(exc))})", highlight=False)
        answered_then_canceled(node, request, answer, unknown)
    # A request that ended just now (its answer on the way) is found by id as well, with its goal.
    raise canceled(node, [stopped.goal_id] if stopped.goal_id else [])


def answered_then_canceled(node: Node, request: AskRequest, answer: futures.Future[AskReply], unknown: str) -> NoReturn:
    """The goal named in the service's answer canceled, once it comes (ANSWER_WAIT at most)."""
    if request.wait:
        said = f"no outcome: interrupted; the planner service names the goal it sent only at the plan's end: {unknown}"
        raise Interrupted([], None, said)
    console.print("waiting for the planner's answer, to cancel the plan it sent...")
    try:
        reply = answer.result(ANSWER_WAIT)
    except KeyboardInterrupt:
        raise Interrupted([], None, f"no outcome: interrupted again before the planner answered: {unknown}") from None
    except (CallError, futures.TimeoutError) as exc:
        said = f"no outcome: interrupted; the planner service gave no answer ({exc or 'none yet'}): {unknown}"
        raise Interrupted([], None, said) from None
    raise canceled(node, [reply.goal_id] if reply.goal_id else [])
