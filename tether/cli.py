"""The `tether` command line: start services, send plans, watch, stop and reset the robot.

A command imports what only it needs when it runs (the recordings' mcap and matplotlib, the
deployment's cryptography, the world model's shapely, pinocchio), so `tether status` or `tether send`
starts without them; `run` is tether.runcommand's, whose work `tether run` (tether/__main__.py) does in
tether.runservice alone.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import logging
import math
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator, MutableMapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import msgspec
import typer
import typer.main
import zenoh
from rich.console import Console
from rich.table import Table
from typer.core import TyperGroup

from schemas import keys
from schemas.actions import CancelGoal, GetResult
from schemas.common import ErrorKind, ServiceError
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, PlanStatus, StepStatus
from schemas.plan import MAX_PLAN_BYTES
from schemas.process import ProcessStatus
from schemas.robot import Odometry, RobotDiagnostics
from schemas.safety import EstopSource, SafetyStatus
from schemas.trace import RecorderStatus
from schemas.world import Empty, MoveEntity, PerceivedObjects
from services.actionlib import CANCEL_ALL, RESULT_RETENTION
from services.errors import CallError, GoalRejected
from services.runtime import (
    ALL_SERVICES,
    ROBOT_BACKENDS,
    SERVICES,
    ConfigError,
    Node,
    NodeSettings,
    configure_logging,
    encode,
    stack_services,
    stop_event,
    zenoh_config_file,
)
from tether.client import (
    EXIT_CODES,
    EXIT_UNREACHABLE,
    STEP_ENDS,
    PlanRun,
    PlanSender,
    cancel_interrupted,
    ended_without_result,
    next_heartbeat,
    next_message,
    operator_name,
    reset_estop,
    trigger_estop,
)
from tether.completion import complete_backend, complete_plan_format, complete_service, complete_services, one_of
from tether.output import command_node, conclude, literal, printable, shown, wait_seconds
from tether.runcommand import HELP, common, run
from tether.supervisor import Restarts, Supervisor, free_base_port

if TYPE_CHECKING:
    from tether import deployment


# A click Command as typer makes it: this typer brings its own copy of click, with classes of its own.
Command = Any


def load_command(name: str, target: str) -> Command:
    """The command `name` made from the function `target` ("module:function"), importing its module now."""
    module, _, function = target.partition(":")
    callback = getattr(importlib.import_module(module), function)
    if isinstance(callback, typer.Typer):  # a group of its own (`tether incidents show|forget|clear`)
        group = typer.main.get_command(callback)
        group.name = name
        return group
    one = typer.Typer(add_completion=False)
    one.command(name)(callback)
    return typer.main.get_command(one)


class LazyCommands(MutableMapping[str, Command]):
    """A group's commands by name, in their order, those named in `lazy` made only when first looked up."""

    def __init__(self, commands: MutableMapping[str, Command], lazy: dict[str, str]) -> None:
        self._commands = commands
        self._pending = {name: target for name, target in lazy.items() if name in commands}

    def __getitem__(self, name: str) -> Command:
        if (target := self._pending.pop(name, None)) is not None:
            self._commands[name] = load_command(name, target)
        return self._commands[name]

    def __setitem__(self, name: str, command: Command) -> None:
        self._pending.pop(name, None)
        self._commands[name] = command

    def __delitem__(self, name: str) -> None:
        self._pending.pop(name, None)
        del self._commands[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._commands)

    def __len__(self) -> int:
        return len(self._commands)


class LazyGroup(TyperGroup):
    """A group whose commands in `lazy` (name -> "module:function") stand in its help and command list
    under their names, in their places, but import their modules only when one runs (or a help lists it)."""

    lazy: dict[str, str] = {}

    def __init__(self, **attrs: Any) -> None:
        super().__init__(**attrs)
        self.commands = LazyCommands(self.commands, self.lazy)


def lazy_command(group: typer.Typer, name: str, target: str) -> None:
    """Register `name` in `group` (made with a LazyGroup class) as `target` ("module:function"), not imported yet."""
    group_class = group.info.cls
    assert isinstance(group_class, type) and issubclass(group_class, LazyGroup), group_class
    group_class.lazy[name] = target

    def not_loaded() -> None:  # pragma: no cover - replaced by `target` before click can call it
        raise AssertionError(f"{name} ran before {target} was loaded")

    group.command(name)(not_loaded)


# click's UsageError as typer raises it: typer 0.28 brings a click of its own (typer._click), older ones click's.
UsageError: Any = sys.modules[typer.BadParameter.__module__].UsageError
# Where MainGroup keeps the command line after the shared flags: the command's name and its own arguments.
COMMAND_LINE = "tether.command_line"


class MainGroup(LazyGroup):
    """The `tether` group: a usage error click finds (a bad option value, an unknown option, a missing
    argument) of a command given --json is one JSON object on stdout (exit 2), as a script reads it."""

    lazy: dict[str, str] = {}

    def resolve_command(self, ctx: Any, args: list[str]) -> tuple[str | None, Command | None, list[str]]:
        ctx.meta[COMMAND_LINE] = list(args)
        return super().resolve_command(ctx, args)

    def invoke(self, ctx: Any) -> Any:
        try:
            return super().invoke(ctx)
        except UsageError as exc:
            document = usage_error_json(self, ctx, exc)
            if document is None:
                raise
            print(json.dumps(document))
            raise typer.Exit(exc.exit_code) from None


class DeployGroup(LazyGroup):
    lazy: dict[str, str] = {}


def usage_error_json(root: MainGroup, ctx: Any, error: Any) -> dict[str, Any] | None:
    """The JSON object that says `error` (a click UsageError) when the command it is of was given --json,
    in that command's own shape of an error; None when it was not (typer then shows it as ever)."""
    line = ctx.meta.get(COMMAND_LINE)
    if line is None:  # no command named yet: the shared flags have no --json
        return None
    levels = list(invoked(root, ctx, line))
    if error.ctx is not None:
        levels = [level for level in levels if level[1] is error.ctx.command]
    # Without a context (an option's value missing at the end of the line), the error is the last command's.
    if not levels:
        return None
    path, command, args = levels[-1]
    if not given_json(command, args):
        return None
    return usage_error_document(path, error.format_message())


def invoked(group: Command, ctx: Any, line: list[str]) -> Iterator[tuple[str, Command, list[str]]]:
    """Each command `line` (a command's name and what follows it) runs below `group`: its path ("world
    move"), itself and its own arguments, split as click splits them (a group's options stand before
    its command's name)."""
    path, args = "", line
    while args and (command := group.get_command(ctx, args[0])) is not None:
        path, args = f"{path} {args[0]}".lstrip(), args[1:]
        yield path, command, args
        if not isinstance(command, TyperGroup):
            return
        group, ctx = command, typer.Context(command, resilient_parsing=True)
        _, args, _ = command.make_parser(ctx).parse_args(list(args))


def given_json(command: Command, args: list[str]) -> bool:
    """Do `args` give `command` its --json option? Read as click reads them, as far as they can be
    read: `--` ends the options (`send -- --json` sends the text "--json"), and the value of another
    option is that option's (`--format --json`)."""
    ctx = typer.Context(command, resilient_parsing=True)  # a line it cannot read to the end: what it read
    parser = command.make_parser(ctx)
    parser.ignore_unknown_options = True  # an unknown option does not hide a --json after it
    options, _, _ = parser.parse_args(list(args))
    return any("--json" in param.opts and options.get(param.name) for param in command.params)


def usage_error_document(path: str, message: str) -> dict[str, Any]:
    """A usage error of the command `path` ("send", "world move") as that command's --json says an
    error of its own; else {"error": message}."""
    match path.split():
        case ["send"]:
            return {"status": "rejected", "stage": None, "reason": message, "steps": []}
        case ["cancel" | "goal" | "estop" | "ask"]:
            return {"status": "error", "reason": message}  # as output.command_node says a bad config (exit 2)
        case ["reset"]:
            return {"status": "error", "message": message}
        case ["status"]:
            return {"ok": False, "alive": [], "heartbeat": False, "problems": [message]}
        case ["world", _]:
            error = ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
            return {"status": "refused", "error": msgspec.to_builtins(error)}
        case ["teleop"]:
            return {"ended": "error", "error": message}
        case ["policy" | "view" | "mode" | "approve" | "deny" | "pause" | "resume" | "pending"] | ["incidents", *_]:
            return {"ok": False, "error": message}
    return {"error": message}


app = typer.Typer(help=HELP, no_args_is_help=True, cls=MainGroup)
console = Console(stderr=True)
out = Console()

MB = 1024 * 1024
DEMO_PLAN = json.dumps(
    {
        "plan": [
            {"action": "navigate_to", "target": "kitchen counter", "description": "go to where the cup is"},
            {"action": "pick", "target": "red cup"},
            {"action": "navigate_to", "target": "coffee table"},
            {"action": "place", "target": "coffee table"},
        ],
        "description": "bring the red cup from the kitchen counter to the coffee table",
    },
    indent=2,
)

app.callback()(common)


def utf8(value: str) -> str:
    """An argument refused unless UTF-8 text: bytes that are not (Python keeps them as surrogates)
    failed to encode into the message sent, with a traceback."""
    try:
        value.encode()
    except UnicodeEncodeError as exc:
        raise typer.BadParameter(f"not UTF-8 text (a byte at character {exc.start + 1})") from None
    return value


def sim_speed_in_range(value: float) -> float:
    """--sim-speed, refused here as the sim would refuse it (services/sim/config.py), before the
    demo starts any service, NaN too."""
    if not 0.1 <= value <= 20.0:
        raise typer.BadParameter(f"must be from 0.1 to 20, not {value}")
    return value


def settings_of(ctx: typer.Context) -> NodeSettings:
    settings: NodeSettings = ctx.obj
    return settings


def client(ctx: typer.Context) -> Node:
    """This command's session, or exit 3 saying why there is none (output.command_node)."""
    return command_node(ctx, console)


# Services

app.command()(run)


def start_services(
    ctx: typer.Context,
    config: Path | None,
    log_dir: Path,
    timeout: float,
    backend: str = "sim",
    services: tuple[str, ...] | None = None,
    deployed: deployment.Deployment | None = None,
) -> tuple[Supervisor, Node]:
    settings = settings_of(ctx)
    services = services or stack_services(backend)
    if deployed is None:
        supervisor = Supervisor(settings, log_dir, config)
        node_settings = settings
    else:
        # Each service logs in as itself; this process watches their liveliness as the first of them.
        configs = {s: deployed.client_config(settings.robot, s) for s in services}
        supervisor = Supervisor(settings, log_dir, deployed.robot_config(settings.robot), zenoh_configs=configs)
        supervisor.robot_key_file = deployed.directory / settings.robot / "robot.key"
        first = {**dataclasses.asdict(settings), "zenoh_config": configs[services[0]]}
        node_settings = ConnectWithin(**first, seconds=timeout)
    deadline = time.monotonic() + timeout
    supervisor.start_all(services)
    try:
        node = Node("cli", node_settings)
    except BaseException as exc:  # Ctrl-C while it waited too: the services started go with this process
        supervisor.stop_all()
        if isinstance(exc, ConfigError):
            console.print(f"[red]error:[/] {literal(exc)}", soft_wrap=True)
            raise typer.Exit(2) from None
        if not isinstance(exc, zenoh.ZError):
            raise
        console.print(
            f"[red]error:[/] no Zenoh session within {timeout:g} s: {literal(exc)}; the services were stopped",
            soft_wrap=True,
        )
        raise typer.Exit(1) from None
    try:
        with console.status(f"starting {len(services)} services for robot {settings.robot}..."):
            while True:
                missing = node.wait_alive(services, min(UP_POLL, max(0.0, deadline - time.monotonic())))
                # One that exited (a config it refuses, a port taken) will not come up: said now, not at the timeout.
                exited = {name: code for name in missing if (code := supervisor.procs[name].poll()) is not None}
                if not missing or exited or time.monotonic() >= deadline:
                    break
    except BaseException:  # Ctrl-C while waiting for them: they stop with this process, in order, now
        node.close()
        supervisor.stop_all()
        raise
    table = Table("service", "pid", "state")
    for name in services:
        table.add_row(name, str(supervisor.procs[name].pid), "[red]not up[/]" if name in missing else "[green]up[/]")
    console.print(table)
    if missing:
        for name in sorted(missing):
            why = f"it exited with code {exited[name]}" if name in exited else f"not within {timeout:.0f} s"
            console.print(f"[red]{name} did not come up: {why}; its log:[/]")
            console.print(printable(supervisor.log_tail(name), newlines=True), markup=False, highlight=False)
        node.close()
        supervisor.stop_all()
        raise typer.Exit(1)
    return supervisor, node


@dataclasses.dataclass(frozen=True)
class ConnectWithin(NodeSettings):
    """Settings whose session gives up on its router after `seconds`. A deployment's service configs
    wait for the router for ever; `tether up`, watching as one of them, must not: it could then be
    neither timed out nor stopped with Ctrl-C, and was killed with its services left running."""

    seconds: float = 60.0

    def zenoh(self, service: str | None) -> zenoh.Config:
        conf = super().zenoh(service)
        conf.insert_json5("connect/timeout_ms", str(round(self.seconds * 1000)))
        return conf


# How often `tether up` looks, while it waits, whether a service it started has exited.
UP_POLL = 0.2

ConfigOpt = Annotated[
    Path | None, typer.Option("--config", help=literal("TOML file with one table per service ([sim], [safety], ...)."))
]
LogDirOpt = Annotated[Path, typer.Option("--log-dir", help="Where each service's log goes.")]
BackendOpt = Annotated[
    str,
    typer.Option(
        help=literal(
            "The robot backend: sim (pybullet), ros2 (a ROS 2 robot at [ros2] endpoint), or ros2-standin "
            "(the ros2 backend driving the pybullet sim behind a ROS 2 face; docs/ros2.md)."
        ),
        autocompletion=complete_backend,
    ),
]


def only_services(only: str | None, backend: str, deployed: deployment.Deployment | None) -> tuple[str, ...]:
    """The services `--only` names (comma-separated), checked; all of the backend's stack without it."""
    if only is None:
        return stack_services(backend)
    names = tuple(dict.fromkeys(n.strip() for n in only.split(",") if n.strip()))
    from tether.deployment import SERVICE_IDENTITIES

    known = SERVICE_IDENTITIES if deployed is not None else ALL_SERVICES
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        where = f"the deployment {deployed.directory}" if deployed is not None else "tether"
        console.print(
            "[red]error:[/] "
            + literal(
                f"--only {only!r}: {', '.join(unknown) or 'no service named'} not a service of {where}; "
                f"its services are {', '.join(known)}"
            ),
            soft_wrap=True,
        )
        raise typer.Exit(2)
    return names


@app.command()
def up(
    ctx: typer.Context,
    config: ConfigOpt = None,
    log_dir: LogDirOpt = Path("logs"),
    timeout: Annotated[
        float, typer.Option(help="Seconds to wait for every service to come up.", callback=wait_seconds)
    ] = 60.0,
    backend: BackendOpt = "sim",
    deploy: Annotated[
        Path | None,
        typer.Option(
            "--deploy",
            help="A directory from `tether deploy init`: each service logs in to its router as itself, "
            "with DIR/ROBOT/<service>.json5 and DIR/ROBOT/tether.toml.",
        ),
    ] = None,
    robot: Annotated[str | None, typer.Option("--robot", help="The robot whose services to start.")] = None,
    only: Annotated[
        str | None,
        typer.Option(
            "--only",
            help="Comma-separated services to start here (e.g. sim,safety,recorder).",
            autocompletion=complete_services,
        ),
    ] = None,
) -> None:
    """Start every service (or --only some), wait until all are alive, and stop them all cleanly on Ctrl-C."""
    if backend not in ROBOT_BACKENDS:
        known = ", ".join(ROBOT_BACKENDS)
        console.print(f"[red]error:[/] unknown backend {literal(repr(backend))}; backends are {known}")
        raise typer.Exit(2)
    from tether import deployment

    if robot is not None:
        try:
            ctx.obj = dataclasses.replace(settings_of(ctx), robot=robot)
        except ValueError as exc:
            console.print(f"[red]error:[/] {literal(exc)}")
            raise typer.Exit(2) from None
    deployed: deployment.Deployment | None = None
    if deploy is not None:
        if config is not None:
            console.print(
                "[red]error:[/] --config and --deploy: a deployment's config is DIR/ROBOT/tether.toml", soft_wrap=True
            )
            raise typer.Exit(2)
        try:
            deployed = deployment.Deployment.load(deploy)
            services = only_services(only, backend, deployed)
            for service in services:
                deployed.client_config(settings_of(ctx).robot, service)
        except deployment.DeploymentError as exc:
            console.print(f"[red]error:[/] {literal(exc)}", soft_wrap=True)
            raise typer.Exit(2) from None
    else:
        services = only_services(only, backend, None)
    supervisor, node = start_services(ctx, config, log_dir, timeout, backend, services, deployed)
    console.print(f"all services up; logs in {literal(log_dir)}/. Ctrl-C (or SIGTERM) stops them.")
    stop = stop_event()
    restarts, due = Restarts(), dict[str, float]()  # when each service that exited is started again
    for service in services:
        restarts.started(service, time.monotonic())
    try:
        while not stop.wait(0.5):
            now = time.monotonic()
            for name, code in supervisor.exited().items():
                if name not in due:
                    delay = restarts.delay(name, now)
                    due[name] = now + delay
                    later = f" in {delay:g} s (it exited soon after its start)" if delay else ""
                    console.print(f"[yellow]{name} exited with {code}; restarting it{later}[/]")
            for name, at in list(due.items()):
                if now >= at:
                    del due[name]
                    supervisor.start(name)
                    restarts.started(name, now)
        console.print("stopping services...")
    finally:
        node.close()
        codes = supervisor.stop_all()
        console.print("stopped: " + ", ".join(f"{k} ({v})" for k, v in codes.items()))


# Deployments

deploy_app = typer.Typer(
    help="A secured deployment: a router, one identity per service, TLS.", no_args_is_help=True, cls=DeployGroup
)
app.add_typer(deploy_app, name="deploy")


lazy_command(deploy_app, "init", "tether.deploycli:deploy_init")


@app.command()
def router(directory: Annotated[Path, typer.Argument(help="A directory from `tether deploy init`.")]) -> None:
    """Run a deployment's Zenoh router (DIR/router.json5) until SIGINT or SIGTERM."""
    from tether.deployment import ROUTER_CONFIG

    path = directory / ROUTER_CONFIG
    if not path.is_file():
        console.print(
            "[red]error:[/] "
            + literal(f"{path} does not exist; make a deployment with `tether deploy init {directory} --robot NAME`"),
            soft_wrap=True,
        )
        raise typer.Exit(2)
    configure_logging()
    zenoh.init_log_from_env_or("error")
    log = logging.getLogger("tether.router")
    try:
        conf = zenoh_config_file(path)
        endpoints = json.loads(conf.get_json("listen/endpoints"))
    except (zenoh.ZError, ValueError) as exc:
        console.print(f"[red]error:[/] {literal(path)} is not a valid Zenoh config: {literal(exc)}", soft_wrap=True)
        raise typer.Exit(2) from None
    stop = stop_event()
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        console.print(f"[red]error:[/] the router from {literal(path)} did not start: {literal(exc)}", soft_wrap=True)
        raise typer.Exit(1) from None
    with session:
        log.info("router %s listening on %s (config %s)", session.info.zid(), ", ".join(endpoints), path.resolve())
        stop.wait()
        log.info("router stopping")


# Plans


def read_plan(plan: str) -> str:
    if plan == "-":  # bytes that are not UTF-8 replaced, as in a plan file
        return sys.stdin.buffer.read().decode(errors="replace")
    path = Path(plan)
    if len(plan) < 4096 and "\n" not in plan and path.is_file():
        return path.read_text(errors="replace")
    return plan


# The most of a step's action and of the places it searched a step's line shows.
SHOWN_ACTION_CHARS = 100
SHOWN_PLACES = 10


def print_feedback(fb: ExecutePlanFeedback) -> None:
    if fb.step is None:
        console.print(f"[dim]{fb.stage}[/]: {shown(fb.message)}")
        return
    print_step(fb.step, fb.label, fb.action, fb.message, fb.status, fb.failure, fb.searched, fb.attempt)


def print_step(
    index: int,
    label: str | None,
    action: str,
    message: str,
    status: StepStatus,
    failure: str | None,
    searched: list[str],
    attempt: int = 1,
) -> None:
    failed = f"[red]failed ({shown(failure)})[/]" if failure else "[red]failed[/]"
    mark = {StepStatus.SUCCEEDED: "[green]done[/]", StepStatus.FAILED: failed}.get(status, "...")
    if status is StepStatus.RUNNING and attempt > 1:
        mark = "[yellow]retrying[/]"
    # Feedback is anyone's publication, its action and places unbounded in the schema: shown bounded.
    action = action[:SHOWN_ACTION_CHARS]
    places = ", ".join(searched[:SHOWN_PLACES]) + (
        f" and {len(searched) - SHOWN_PLACES} more" if len(searched) > SHOWN_PLACES else ""
    )
    # Where a detect or pick searched, once the step has ended (the notes said it as it went).
    where = f" [dim](searched: {shown(places)})[/]" if searched and status in STEP_ENDS else ""
    said = shown(f"step {label or index + 1} {action}: {message}")
    console.print(f"{said} {mark}{where}")


def print_unseen_ends(run: PlanRun) -> None:
    """The ends of steps the result holds and no feedback showed. Feedback is a publication and the
    result a reply: the last step's end can reach the client after the result (it is then dropped,
    the run being done), or never, and the result is the record of how each step ended."""
    if run.result is None:
        return
    for step in run.result.steps:
        if step.status in STEP_ENDS and (step.index, step.label) not in run.told_ends:
            print_step(step.index, step.label, step.action, step.message, step.status, step.failure, step.searched)


def print_result(run: PlanRun, as_json: bool) -> None:
    if as_json:
        out.print_json(data=run.as_json()) if sys.stdout.isatty() else print(json.dumps(run.as_json()))
        return
    result = run.result
    if result is None and (waiting := run.awaiting_approval) is not None:
        console.print(f"[yellow]awaiting_approval[/] (goal {shown(run.goal_id)}): {shown(waiting.message)}")
        return
    if result is None:
        goal = shown(run.goal_id)
        console.print(f"plan accepted (goal {goal}); executing. `tether goal {goal}` follows it.")
        return
    print_unseen_ends(run)
    for warning in result.warnings:
        console.print(f"[yellow]warning[/]: {shown(warning)}")
    colour = "green" if result.status is PlanStatus.SUCCEEDED else "red"
    reason = f": {shown(result.reason)}" if result.reason else ""
    console.print(f"[{colour}]{result.status}[/] at stage {result.stage}{reason}")


def unreachable(as_json: bool, reason: str) -> NoReturn:
    if as_json:
        print(json.dumps({"status": "unreachable", "stage": None, "reason": reason, "steps": []}))
    else:
        console.print(f"[red]{shown(reason)}[/]")
    raise typer.Exit(EXIT_UNREACHABLE)


def interrupted(sender: PlanSender, goal_id: str, as_json: bool) -> PlanRun:
    """Ctrl-C while sending or waiting: the plan is canceled (one the executor has not answered for
    yet too) and its end waited for, CANCEL_WAIT at most. Exit 3 when no end came (the plan may
    still be moving), or on a second Ctrl-C."""
    console.print("canceling...")
    ended = cancel_interrupted(sender, goal_id)
    if isinstance(ended, str):
        unreachable(as_json, ended)
    return ended


@app.command()
def send(
    ctx: typer.Context,
    plan: Annotated[str, typer.Argument(help="Plan text, a file holding it, or - for stdin.", callback=utf8)],
    fmt: Annotated[
        str, typer.Option("--format", help="auto, json, yaml or text.", autocompletion=complete_plan_format)
    ] = "auto",
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Parse, resolve and check only; nothing moves.")] = False,
    wait: Annotated[bool, typer.Option("--wait", help="Wait until the plan has finished.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object with the outcome.")] = False,
    timeout: Annotated[float, typer.Option(help="Seconds to wait for the outcome.", callback=wait_seconds)] = 600.0,
    preempt: Annotated[
        bool, typer.Option("--preempt", help="Cancel a plan already running (the robot stops first) and run this one.")
    ] = False,
    recover: Annotated[
        bool,
        typer.Option(
            "--recover",
            help="Through the planner: when a step fails, an LLM writes a recovery plan, checked like any "
            "(needs the planner service, or an endpoint here: TETHER_LLM_URL or --config). Same exit codes and "
            "--json object, plus request_id, final_goal_id and recoveries.",
        ),
    ] = False,
    config: Annotated[
        Path | None,
        typer.Option(
            "--config", help=literal("With --recover: TOML file with a [planner] table (url, max_recoveries).")
        ),
    ] = None,
) -> None:
    """Send a plan to the executor. Exit 0 succeeded, 1 failed or canceled, 2 rejected, 3 unreachable.

    Without --wait, returns once the plan is parsed, resolved, approved and moving (status 'accepted'),
    or, in supervised mode, waits for an operator (status 'awaiting_approval' with the goal id and
    safety's dry run; exit 0; `tether approve GOAL_ID` lets it move).
    While another plan runs this one is rejected, unless --preempt. Never replanned, unless --recover:
    then the planner dry-runs and sends it, and asks an LLM for a recovery plan when a step fails
    (up to the planner's max_recoveries). The exit codes stay send's: 1 is the plan failed after any
    recoveries (`tether ask` exits 4 for that, its 1 being an LLM endpoint failure); goal_id is the
    goal first sent, final_goal_id the last recovery's.
    """
    if fmt not in ("auto", "json", "yaml", "text"):
        why = f"--format must be auto, json, yaml or text, not {fmt!r}"
        refused: dict[str, Any] = {"status": "rejected", "stage": None, "reason": why, "steps": []}
        conclude(console, as_json, refused, f"[red]error:[/] {literal(why)}", 2)
    try:
        text = read_plan(plan)
    except OSError as exc:
        why = f"cannot read the plan file {plan}: {exc.strerror or exc}"
        refused = {"status": "rejected", "stage": None, "reason": why, "steps": []}
        conclude(console, as_json, refused, f"[red]error:[/] {literal(why)}", 2)
    if len(text.encode()) > MAX_PLAN_BYTES:
        reason = f"plan is {len(text.encode())} bytes; the limit is {MAX_PLAN_BYTES}"
        if as_json:
            print(json.dumps({"status": "rejected", "stage": "parse", "reason": reason, "steps": []}))
        else:
            console.print(f"[red]rejected[/] at stage parse: {reason}")
        raise typer.Exit(2)
    if recover:
        from tether.sendrecover import send_recover

        send_recover(settings_of(ctx), text, fmt, dry_run, wait, preempt, timeout, as_json, config)
    if config is not None:
        why = "--config is read only with --recover (the planner's [planner] table)"
        refused = {"status": "rejected", "stage": None, "reason": why, "steps": []}
        conclude(console, as_json, refused, f"[red]error:[/] {literal(why)}", 2)
    with client(ctx) as node:
        if not node.is_alive("executor", 2.0):
            unreachable(as_json, "no executor reachable: start the services with `tether up`")
        sender = PlanSender(node, None if as_json else print_feedback)
        goal_id = uuid.uuid4().hex  # known before the send: a Ctrl-C before its answer cancels it by id
        try:
            goal = ExecutePlanGoal(text=text, format=fmt, dry_run=dry_run, preempt=preempt)  # type: ignore[arg-type]
            handle = sender.send(goal, goal_id)
        except GoalRejected as exc:
            if as_json:
                print(json.dumps({"status": "rejected", "stage": "execute", "reason": exc.reason, "steps": []}))
            else:
                console.print(f"[red]rejected[/]: {shown(exc.reason)}")
            raise typer.Exit(2) from None
        except CallError as exc:
            unreachable(as_json, f"executor unreachable: {exc}")
        except KeyboardInterrupt:
            run_ = interrupted(sender, goal_id, as_json)
        else:
            try:
                run_ = sender.wait(handle, timeout, until_started=not (wait or dry_run))
            except KeyboardInterrupt:
                run_ = interrupted(sender, goal_id, as_json)
            except CallError as exc:
                unreachable(as_json, f"no outcome: {exc}")
        print_result(run_, as_json)
        raise typer.Exit(EXIT_CODES[run_.result.status] if run_.result else 0)


@app.command()
def cancel(
    ctx: typer.Context,
    goal_id: Annotated[str, typer.Argument(help="A goal id, or all.", callback=utf8)] = CANCEL_ALL,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object: status, goal_id, reason.")] = False,
) -> None:
    """Cancel the running plan (or the goal given).

    Exit 0 when the cancel was requested (status 'requested') or there was nothing to cancel (status
    'nothing_to_cancel', with the executor's reason: no plan running, an unknown or finished goal),
    3 when the executor is unreachable (status 'unreachable').
    """
    with client(ctx) as node:
        try:
            reply = node.call(keys.EXECUTE_PLAN.cancel_goal, CancelGoal(goal_id=goal_id), timeout=3.0)
        except CallError as exc:
            document = {"status": "unreachable", "goal_id": goal_id, "reason": f"executor unreachable: {exc}"}
            conclude(console, as_json, document, f"[red]executor unreachable[/]: {shown(exc)}", EXIT_UNREACHABLE)
    if reply.accepted:
        conclude(console, as_json, {"status": "requested", "goal_id": goal_id, "reason": ""}, "cancel requested")
    document = {"status": "nothing_to_cancel", "goal_id": goal_id, "reason": reply.reason}
    conclude(console, as_json, document, f"nothing to cancel ({shown(reply.reason)})")


@app.command()
def goal(
    ctx: typer.Context,
    goal_id: Annotated[str, typer.Argument(help="The goal id `tether send` printed.", callback=utf8)],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Where a plan is now, without waiting: its state, the step running, the result once it ended.

    Exit 0 running or succeeded, 1 failed or canceled, 2 unknown goal or rejected, 3 unreachable.
    """
    with client(ctx) as node:
        try:
            progress = node.call(keys.EXECUTE_PLAN.get_status, GetResult(goal_id=goal_id), timeout=3.0)
        except CallError as exc:
            if exc.error.kind is ErrorKind.INVALID_REQUEST:
                if as_json:
                    print(json.dumps({"goal_id": goal_id, "state": "unknown", "reason": exc.error.message}))
                else:
                    kept = RESULT_RETENTION / 60
                    console.print(f"[red]{shown(exc.error.message)}[/] (results are kept for {kept:g} minutes)")
                raise typer.Exit(2) from None
            unreachable(as_json, f"executor unreachable: {exc}")
    result = progress.result
    if result is None and progress.state.terminal:  # ended with none (its run raised): not still running
        result = ended_without_result(progress.state, progress.message)
        progress = msgspec.structs.replace(progress, result=result)  # --json says so too, not "result": null
    code = EXIT_CODES[result.status] if result is not None else 0
    if as_json:
        print(json.dumps(msgspec.to_builtins(progress)))
        raise typer.Exit(code)
    said = f"goal {goal_id}: {progress.state}" + (f" ({progress.message})" if progress.message else "")
    console.print(printable(said, newlines=True), markup=False, highlight=False)
    if result is None and progress.feedback is not None:
        print_feedback(progress.feedback)
    if result is not None:
        print_result(PlanRun(goal_id=goal_id, result=result), as_json=False)
    raise typer.Exit(code)


# Safety


@app.command()
def estop(
    ctx: typer.Context,
    reason: Annotated[
        str, typer.Option(help="Why; kept in the latch and the recording.", callback=utf8)
    ] = "operator e-stop",
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object: status, source, reason.")] = False,
) -> None:
    """Trigger the e-stop. It latches until `tether reset`.

    Exit 0 once safety's heartbeat shows the latch (status 'latched', with the latch's source and
    reason), 3 when no heartbeat confirmed it within 2 s (status 'unconfirmed': the e-stop was sent, but
    safety may be unreachable).
    """
    # The reason is bounded in the message; an over-long one is cut rather than lost.
    sent = f"{reason[:3800]} ({operator_name()[:100]})"
    with client(ctx) as node:
        status = trigger_estop(node, EstopSource.OPERATOR, sent)
    if status is None:
        document = {"status": "unconfirmed", "source": EstopSource.OPERATOR, "reason": sent}
        said = "[red]e-stop sent, but no heartbeat from safety confirmed it[/]"
        conclude(console, as_json, document, said, EXIT_UNREACHABLE)
    latch = status.estop
    document = {"status": "latched", "source": latch.source, "reason": latch.reason}
    conclude(console, as_json, document, f"[red]E-STOP latched[/] by {shown(latch.source)}: {shown(latch.reason)}")


@app.command()
def reset(
    ctx: typer.Context,
    token_file: Annotated[str | None, typer.Option(help="The operator token file safety created.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object: status, message.")] = False,
) -> None:
    """Clear a latched e-stop (operator only: needs the operator token file).

    Exit 0 when safety reset it (status 'reset'), 2 when safety refused (status 'refused': a wrong
    token, a cause still present) or the token file cannot be read or holds no token (status
    'no_token'), 3 when safety is unreachable (status 'unreachable').
    """
    with client(ctx) as node:
        try:
            reply = reset_estop(node, token_file)
        except OSError as exc:
            document = {"status": "no_token", "message": f"cannot read the operator token: {exc}"}
            conclude(console, as_json, document, f"[red]cannot read the operator token[/]: {literal(exc)}", 2)
        except msgspec.ValidationError as exc:  # a file that holds no token: safety would refuse it unread
            document = {"status": "no_token", "message": f"the operator token file holds no token: {exc}"}
            conclude(console, as_json, document, f"[red]no operator token[/]: {literal(exc)}", 2)
        except CallError as exc:
            document = {"status": "unreachable", "message": f"safety unreachable: {exc}"}
            conclude(console, as_json, document, f"[red]safety unreachable[/]: {shown(exc)}", EXIT_UNREACHABLE)
    if not reply.ok:
        document = {"status": "refused", "message": reply.message}
        conclude(console, as_json, document, f"[red]refused[/]: {shown(reply.message)}", 2)
    conclude(console, as_json, {"status": "reset", "message": reply.message}, shown(reply.message))


@app.command()
def policy(
    file: Annotated[
        Path | None, typer.Argument(help="A policy file (TOML or YAML); default: the one safety ships with.")
    ] = None,
    world: Annotated[str, typer.Option(help="The world file (or name) whose robot the policy must fit.")] = "household",
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Check a safety policy as safety does at start; show its effective limits and hash.

    Exit 0 when safety would start with it, 2 (naming the bad entry) when it would not.
    """
    from services.robotmodel import ArmModel
    from services.safety.policyfile import PolicyError, load_policy
    from services.worldmodel import WorldFileError, load_world

    try:
        model = load_world(world)
        try:
            arm = ArmModel(model.robot.arm_urdf)
        except (OSError, ValueError, RuntimeError) as exc:
            raise WorldFileError(f"robot.arm_urdf {model.robot.arm_urdf!r} cannot be loaded: {exc}") from None
        limits = load_policy(file, model.robot, arm, model.keep_out, model.rooms)
    except (PolicyError, WorldFileError) as exc:
        if as_json:
            print(json.dumps({"ok": False, "error": str(exc)}))
        else:
            console.print(f"[red]error:[/] {literal(exc)}")
        raise typer.Exit(2) from None
    summary = limits.summary()
    if as_json:
        print(json.dumps({"ok": True, **summary}))
        return
    console.print(f"policy {summary.pop('path')}\n{summary.pop('hash')}", markup=False)
    table = Table("rule", "limits")
    for section, values in summary.items():
        table.add_row(literal(section), literal(json.dumps(values)))
    console.print(table)


# State


def status_dict(node: Node, timeout: float = 1.5) -> dict[str, Any]:
    found: dict[str, Any] = {}

    def grab(name: str, topic: Any) -> None:
        found[name] = next_message(node, topic, timeout)

    def diagnose() -> None:
        try:
            found["diagnostics"] = node.call(keys.ROBOT_DIAGNOSTICS, Empty(), timeout=timeout)
        except CallError:  # a backend that serves none (the sim), or none running
            found["diagnostics"] = None

    def heartbeat() -> None:
        found["heartbeat"] = next_heartbeat(node, timeout)

    def ask_processes() -> None:
        found["processes"] = node.process_statuses(timeout)

    def ask_recorder() -> None:
        try:
            found["recording"] = node.call(keys.RECORDER_STATUS, Empty(), timeout=timeout)
        except CallError:  # no recorder running
            found["recording"] = None

    threads = [threading.Thread(target=grab, args=a) for a in (("odom", keys.ODOM), ("objects", keys.OBJECTS))]
    threads += [threading.Thread(target=t) for t in (diagnose, heartbeat, ask_processes, ask_recorder)]
    for t in threads:
        t.start()
    alive = node.alive_services(timeout=timeout)
    for t in threads:
        t.join()
    # The latch only from a fresh heartbeat with a robot-link MAC (an unsigned one is not safety's).
    waited = found.get("heartbeat")
    beat: SafetyStatus | None = waited.status if waited is not None else None
    odom: Odometry | None = found.get("odom")
    objects: PerceivedObjects | None = found.get("objects")
    problems = robot_problems(found.get("diagnostics"))
    processes: dict[str, ProcessStatus] = found.get("processes", {})
    recording: RecorderStatus | None = found.get("recording")
    return {
        # The robot's other backends only when one runs.
        "services": {name: name in alive for name in ALL_SERVICES if name in SERVICES or name in alive},
        # Each service that answered (as it counts itself, on its own host), in the order of `services`.
        "processes": {
            name: msgspec.structs.asdict(processes[name])
            for name in [*(n for n in ALL_SERVICES if n in processes), *sorted(set(processes) - set(ALL_SERVICES))]
        },
        "mode": str(beat.mode) if beat else None,
        # The recorder's file, and why it is not being written ("" while it is); null without a recorder.
        "recording": (
            {
                "path": recording.path,
                "messages": recording.messages,
                "dropped": recording.dropped,
                "error": recording.error,
            }
            if recording is not None
            else None
        ),
        "estop": (
            {"latched": beat.estop.latched, "source": beat.estop.source, "reason": beat.estop.reason}
            if beat
            else {
                "latched": None,
                "source": "",
                "reason": waited.why_not(timeout) if waited is not None else "no heartbeat from safety",
            }
        ),
        "robot": (
            {
                "pose": {"x": odom.pose.x, "y": odom.pose.y, "yaw": odom.pose.yaw} if odom else None,
                "linear_x": odom.linear_x if odom else None,
                "angular_z": odom.angular_z if odom else None,
                "problems": problems,
            }
            if odom or problems
            else None
        ),
        "objects": [
            {
                "name": o.name,
                "id": o.id,
                "room": o.room,
                "on": o.on,
                "pose": {"x": o.position.x, "y": o.position.y, "z": o.position.z},
            }
            for o in (objects.objects if objects else [])
        ],
    }


def robot_problems(diagnostics: RobotDiagnostics | None) -> list[dict[str, Any]]:
    """What the robot's backend finds wrong with it (robot/diagnostics), the latest first; `age`:
    how long before the backend answered each was last seen (seconds)."""
    if diagnostics is None:
        return []
    return [
        {"text": p.text, "last_seen": p.last_seen, "age": max(0.0, diagnostics.stamp - p.last_seen)}
        for p in diagnostics.problems
    ]


def health(node: Node, services: list[str], timeout: float = 1.5) -> dict[str, Any]:
    """Are `services` (all of a robot's, the robot backend being sim or ros2, when empty) alive, and is
    safety's heartbeat fresh (one arrives within `timeout`, stamped within `timeout` of now, with a
    robot-link MAC: tether.client.HeartbeatWait)? `problems`: what is not, one phrase each."""
    found: dict[str, Any] = {}
    beat = threading.Thread(target=lambda: found.update(heartbeat=next_heartbeat(node, timeout)))
    beat.start()
    alive = node.alive_services(timeout=timeout)
    beat.join()
    problems = []
    if services:
        problems += [f"{s} not alive" for s in services if s not in alive]
    else:
        problems += [f"{s} not alive" for s in SERVICES if s != "sim" and s not in alive]
        if not alive & {"sim", "ros2"}:
            problems.insert(0, "no robot backend (sim or ros2) alive")
    waited = found.get("heartbeat")  # missing when listening failed
    fresh = waited is not None and waited.status is not None
    if not fresh:
        problems.append(waited.why_not(timeout) if waited is not None else "could not listen for safety's heartbeat")
    return {
        "ok": not problems,
        "alive": sorted(alive),
        "heartbeat": fresh,
        "problems": problems,
    }


def memory_line(processes: dict[str, dict[str, Any]]) -> str:
    """The services' resident memory in MB, their total first (status_dict's `processes`)."""
    # A service's own and its children's (the sim's camera renderer).
    held = {name: p["rss_bytes"] + p.get("children_rss_bytes", 0) for name, p in processes.items()}
    total = sum(held.values())
    each = ", ".join(f"{shown(name, newlines=False)} {rss / MB:.0f}" for name, rss in held.items())
    return f"memory: {total / MB:.0f} MB resident ({each})"


@app.command()
def status(
    ctx: typer.Context,
    as_json: Annotated[
        bool,
        typer.Option(
            "--json",
            help="Print one JSON object: services, processes, mode, recording, estop, robot and objects "
            "(with --check: ok, alive, heartbeat, problems).",
        ),
    ] = False,
    check: Annotated[
        bool,
        typer.Option(
            "--check",
            help="A health probe: exit 0 only if the services are alive and safety's heartbeat is fresh, "
            "else 1 with one line saying what is missing (3: no Zenoh session).",
        ),
    ] = False,
    service: Annotated[
        list[str] | None,
        typer.Option(
            "--service", help="With --check: only this service (repeatable).", autocompletion=complete_service
        ),
    ] = None,
) -> None:
    """Which services are alive, the e-stop latch, the robot's pose and problems, and where objects are."""
    why = ""
    if service and not check:
        why = "--service goes with --check"
    elif unknown := [s for s in service or [] if s not in ALL_SERVICES]:
        why = f"unknown service {', '.join(unknown)}; services are {', '.join(ALL_SERVICES)}"
    if why:
        conclude(console, as_json, usage_error_document("status", why), f"[red]error:[/] {shown(why)}", 2)
    if check:
        try:
            node = Node("cli", settings_of(ctx))
        except Exception as exc:  # zenoh.ZError: no router, refused login; anything else, as unhealthy
            why = f"cannot open a Zenoh session: {exc}"
            if as_json:
                print(json.dumps({"ok": False, "alive": [], "heartbeat": False, "problems": [why]}))
            else:
                console.print(f"unhealthy: {why}", markup=False, soft_wrap=True)
            raise typer.Exit(EXIT_UNREACHABLE) from None
        with node:
            report = health(node, service or [])
        if as_json:
            print(json.dumps(report))
        elif report["ok"]:
            alive = shown(", ".join(service or report["alive"]))
            out.print(f"healthy: {alive} alive; safety's heartbeat fresh", soft_wrap=True)
        else:
            console.print("unhealthy: " + "; ".join(report["problems"]), markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(0 if report["ok"] else 1)
    with client(ctx) as node:
        state = status_dict(node)
    if as_json:
        print(json.dumps(state))
        return
    services = "  ".join(
        f"{k} [{'green' if v else 'red'}]{'up' if v else 'down'}[/]" for k, v in state["services"].items()
    )
    console.print(services)
    if state["processes"]:
        console.print(memory_line(state["processes"]), highlight=False)
    console.print(f"mode: {state['mode'] or 'unknown (no heartbeat)'}")
    if (rec := state["recording"]) is not None:
        counts = f"{rec['messages']} messages, {rec['dropped']} dropped"
        console.print(f"recording: {shown(rec['path'])} ({counts})", highlight=False)
        if rec["error"]:
            console.print(f"[red]recording FAILING:[/] {shown(rec['error'])}", highlight=False)
    console.print(f"e-stop: {estop_line(state['estop'])}", highlight=False)
    robot = state["robot"] or {"pose": None, "problems": []}
    if p := robot["pose"]:
        console.print(f"robot at x={p['x']:.2f} y={p['y']:.2f} yaw={math.degrees(p['yaw']):.0f} deg")
    if robot["problems"]:
        console.print("[red]robot problems[/] (the latest first):")
        for problem in robot["problems"]:
            console.print(f"  {problem['age']:.0f} s ago: {shown(problem['text'])}")
    if not state["objects"]:
        console.print("objects: none reported")
        return
    table = Table("object", "room", "on", "x", "y", "z")
    for o in state["objects"]:
        names = (shown(o[k] or "-") for k in ("name", "room", "on"))
        table.add_row(*names, *(f"{o['pose'][k]:.2f}" for k in "xyz"))
    console.print(table)


def estop_line(estop: dict[str, Any]) -> str:
    """The e-stop latch as `tether status` says it (markup): latched by whom and why, clear, or unknown
    and why (no heartbeat from safety, or one that was not safety's)."""
    if estop["latched"]:
        return f"[red]LATCHED[/] by {shown(estop['source'] + ': ' + estop['reason'])}"
    if estop["latched"] is None:
        return f"unknown ({shown(estop['reason'])})"
    return "clear"


# The simulated world


class WorldGroup(LazyGroup):
    lazy: dict[str, str] = {}


world_app = typer.Typer(
    help="The SIMULATED world: change it under the robot's feet, for demos and tests.",
    no_args_is_help=True,
    cls=WorldGroup,
)
app.add_typer(world_app, name="world")

# How a refusal from the simulator maps to an exit code; anything else is 1.
WORLD_EXIT_CODES = {ErrorKind.INVALID_REQUEST: 2, ErrorKind.PRECONDITION: 2, ErrorKind.UNAVAILABLE: EXIT_UNREACHABLE}


def world_failed(error: ServiceError, as_json: bool = False) -> NoReturn:
    code = WORLD_EXIT_CODES.get(error.kind, 1)
    status = {2: "refused", EXIT_UNREACHABLE: "unreachable"}.get(code, "failed")
    document = {"status": status, "error": msgspec.to_builtins(error)}
    known = "\nknown: " + shown(", ".join(error.candidates)) if error.candidates else ""
    conclude(console, as_json, document, f"[red]{shown(error.kind)}[/]: {shown(error.message)}{known}", code)


@world_app.command("move")
def world_move(
    ctx: typer.Context,
    entity: Annotated[
        str, typer.Argument(metavar="ID", help="An object or person id: red_cup, operator, ...", callback=utf8)
    ],
    x: Annotated[float, typer.Argument(help="Map x in metres.")],
    y: Annotated[float, typer.Argument(help="Map y in metres.")],
    z: Annotated[
        float | None,
        typer.Option(help="Height of an object's bottom in metres. Default: the top of the furniture there, or 0."),
    ] = None,
    yaw: Annotated[float | None, typer.Option(help="Heading in radians. Default: as it is.")] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object: status, and the id and position or the error.")
    ] = False,
) -> None:
    """Move an object or a person in the SIMULATED world, for demos and tests (not a robot action).

    An object is set down upright at (x, y) and let settle; a person stands there. Prints where it ended up.

    Exit 0 moved (status 'moved'), 2 refused (status 'refused': an unknown id, a point outside every room,
    the object in the gripper), 3 no simulator (status 'unreachable'), 1 when the simulator failed otherwise.
    """
    with client(ctx) as node:
        if not node.is_alive("sim", 2.0):
            why = "no simulator reachable: start it with `tether up` or `tether run sim`"
            world_failed(ServiceError(kind=ErrorKind.UNAVAILABLE, message=why), as_json)
        try:
            reply = node.call(keys.SIM_MOVE, MoveEntity(id=entity, x=x, y=y, z=z, yaw=yaw), timeout=10.0)
        except CallError as exc:
            world_failed(exc.error, as_json)
    if isinstance(reply, ServiceError):
        world_failed(reply, as_json)
    p = reply.position
    document = {"status": "moved", "id": reply.id, "position": {"x": p.x, "y": p.y, "z": p.z}}
    conclude(out, as_json, document, f"{shown(reply.id)} now at ({p.x:.3f}, {p.y:.3f}, {p.z:.3f})")


lazy_command(world_app, "fault", "tether.worldfault:world_fault")


def scene_failed(error: ServiceError, as_json: bool) -> NoReturn:
    document = {"status": "unreachable", "error": msgspec.to_builtins(error)}
    conclude(console, as_json, document, f"[red]{shown(error.kind)}[/]: {shown(error.message)}", EXIT_UNREACHABLE)


@world_app.command("scene")
def world_scene(
    ctx: typer.Context,
    as_json: Annotated[bool, typer.Option("--json", help="Print the SceneDescription as one JSON object.")] = False,
) -> None:
    """What the resolver knows about the world, and the description an LLM prompt can use.

    Where each object was last seen, and the relations between things (on, in, near, left of, right of).

    Exit 0, 3 when no resolver is reachable (with --json: status 'unreachable' and the error).
    """
    with client(ctx) as node:
        if not node.is_alive("resolver", 2.0):
            why = "no resolver reachable: start the services with `tether up`"
            scene_failed(ServiceError(kind=ErrorKind.UNAVAILABLE, message=why), as_json)
        try:
            scene = node.call(keys.SCENE, Empty(), timeout=5.0)
        except CallError as exc:
            scene_failed(exc.error, as_json)
    if as_json:
        print(encode(scene).decode())
        return
    console.print(printable(scene.text, newlines=True), markup=False, highlight=False)
    table = Table("object", "on", "room", "x", "y", "z", "seen")
    for o in scene.objects:
        seen = "stale" if o.stale else ("yes" if o.stamp else "world file")
        p = o.position
        names = (shown(name or "-") for name in (o.name, o.on, o.room))
        table.add_row(*names, f"{p.x:.2f}", f"{p.y:.2f}", f"{p.z:.2f}", seen)
    console.print(table)
    relations = [
        f"{r.subject} {r.relation.replace('_', ' ')} {r.object}" for r in scene.relations if r.relation != "in"
    ]
    console.print(printable("relations: " + "; ".join(relations)), markup=False, highlight=False)


# The demo


def demo_config(sim_speed: float, recordings: Path, ros2_endpoint: str | None) -> str:
    """The demo's TOML: the sim's speed, where the recorder writes, the ROS 2 endpoint when on ros2.
    Strings as JSON writes them, which TOML reads the same: a directory named with a quote or a
    backslash is still that directory."""
    text = f"[sim]\nrealtime_factor = {sim_speed}\n\n[recorder]\noutput_dir = {json.dumps(str(recordings))}\n"
    if ros2_endpoint is not None:
        endpoint = json.dumps(ros2_endpoint)
        text += f"\n[ros2]\nendpoint = {endpoint}\n\n[ros2sim]\nlisten = {endpoint}\n"
        text += f"\n[recorder.ros2]\nendpoint = {endpoint}\n"
    return text


@app.command()
def demo(
    ctx: typer.Context,
    sim_speed: Annotated[
        float, typer.Option(help="Simulated seconds per wall-clock second.", callback=sim_speed_in_range)
    ] = 2.0,
    log_dir: LogDirOpt = Path("logs"),
    recordings: Annotated[Path, typer.Option(help="Where the MCAP recording goes.")] = Path("recordings"),
    timeout: Annotated[float, typer.Option(help="Seconds allowed for the plan.", callback=wait_seconds)] = 600.0,
    backend: Annotated[
        str,
        typer.Option(
            help="sim: the pybullet sim on tether's keys; ros2: the ros2 backend driving the sim behind a ROS 2 "
            "face (rmw_zenoh keys), as it would a ROS 2 robot.",
            autocompletion=one_of("sim", "ros2"),
        ),
    ] = "sim",
) -> None:
    """Start everything, bring the red cup to the coffee table, check it in the simulator, keep the recording."""
    configure_logging("WARNING")  # what others wrote, quoted in a warning, escaped (services/runtime.py)
    if backend not in ("sim", "ros2"):
        console.print(f"[red]error:[/] unknown backend {literal(repr(backend))}; the demo runs on sim or ros2")
        raise typer.Exit(2)
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "demo.toml"
        # The stand-in robot's ROS 2 side on a port of its own, not 7447: a real robot's router may be there.
        endpoint = f"tcp/127.0.0.1:{free_base_port(1)}" if backend == "ros2" else None
        config.write_text(demo_config(sim_speed, recordings.resolve(), endpoint))
        stack = "ros2-standin" if backend == "ros2" else "sim"
        supervisor, node = start_services(ctx, config, log_dir, timeout=90.0, backend=stack)
        ok = False
        recording = "(unknown)"
        try:
            try:
                recording = node.call(keys.RECORDER_STATUS, Empty(), timeout=3.0).path
            except CallError as exc:
                console.print(f"[yellow]recorder did not answer: {shown(exc)}[/]")
            console.print("sending the plan:")
            console.print(DEMO_PLAN, markup=False, highlight=False)
            started = time.monotonic()
            run_ = PlanSender(node, print_feedback).run(ExecutePlanGoal(text=DEMO_PLAN), timeout)
            print_result(run_, as_json=False)
            ok = run_.result is not None and run_.result.status is PlanStatus.SUCCEEDED
            ok = verify_demo(node) and ok
            console.print(f"plan took {time.monotonic() - started:.1f} s")
        except CallError as exc:
            console.print(f"[red]demo failed[/]: {shown(exc)}")
        finally:
            node.close()
            supervisor.stop_all()
        console.print(printable(f"recording: {recording}"), markup=False, highlight=False)
        console.print("[green]demo succeeded[/]" if ok else "[red]demo failed[/]")
        raise typer.Exit(0 if ok else 1)


def verify_demo(node: Node) -> bool:
    """Ask the simulator, not the executor: is the red cup resting on the coffee table?"""
    truth = node.call(keys.GROUND_TRUTH, Empty(), timeout=3.0)
    cup = next((o for o in truth.objects if o.id == "red_cup"), None)
    if cup is None:
        console.print("[red]ground truth has no red cup[/]")
        return False
    where = f"({cup.position.x:.2f}, {cup.position.y:.2f}, {cup.position.z:.2f})"
    said = f"simulator: red cup at {where} on {cup.on} in {cup.room}; gripper holds {truth.holding or 'nothing'}"
    console.print(said, markup=False)
    return cup.on == "coffee_table" and truth.holding is None


# The operator's say: the control mode and approving plans (tether/modecli.py)
lazy_command(app, "mode", "tether.modecli:mode")
lazy_command(app, "approve", "tether.modecli:approve")
lazy_command(app, "deny", "tether.modecli:deny")
lazy_command(app, "pause", "tether.modecli:pause")
lazy_command(app, "resume", "tether.modecli:resume")
lazy_command(app, "pending", "tether.modecli:pending")
# Safety's memory of incidents (tether/incidentscli.py)
lazy_command(app, "incidents", "tether.incidentscli:app")

# Recordings
lazy_command(app, "inspect", "tether.inspect:inspect")
lazy_command(app, "record", "tether.recordings:record")
lazy_command(app, "replay", "tether.recordings:replay")
lazy_command(app, "recheck", "tether.recordings:recheck_command")
lazy_command(app, "recover", "tether.recordings:recover_command")

# Agents
lazy_command(app, "schema", "tether.schema:schema")
lazy_command(app, "ask", "tether.ask:ask")

# Operators
lazy_command(app, "teleop", "tether.teleop:teleop")
lazy_command(app, "view", "tether.view:view")


# Only loopback: the MCP server has no authentication, and whoever reaches it can move the robot.
LOOPBACK = ("127.0.0.1", "localhost", "::1")


@app.command("mcp")
def mcp_command(
    ctx: typer.Context,
    http: Annotated[bool, typer.Option("--http", help="Serve streamable HTTP instead of stdio.")] = False,
    host: Annotated[str, typer.Option(help="With --http: the loopback address to bind.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="With --http: the port (tether view takes 8765).", min=1, max=65535)] = 8766,
) -> None:
    """Serve the robot's tools over MCP: stdio for an MCP client that starts this command, or --http.

    Action tools return a goal id at once (get_goal_status, cancel_goal follow it); read tools give
    the robot's state, the scene, objects and a camera image; emergency_stop stops everything. No
    tool resets the e-stop, lifts a limit or changes the safety policy.
    """
    if http and host not in LOOPBACK:
        # No authentication here: a remote agent goes through a proxy that authenticates it.
        print(
            f"error: --host {host}: the MCP server binds to loopback only (it has no authentication and "
            "whoever reaches it can move the robot); put an authenticating reverse proxy in front of it",
            file=sys.stderr,
        )
        raise typer.Exit(2)
    configure_logging("WARNING")  # on stderr, escaped: stdout is the protocol's
    # The MCP SDK and its web server take half a second to import: only for this command.
    from tether.mcpserver import serve

    serve(ctx.obj, http, host, port)
