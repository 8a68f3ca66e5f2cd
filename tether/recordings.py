"""`tether record`, `replay`, `recheck` and `recover`: making recordings and going back over them."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from concurrent import futures
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
import zenoh
from rich.console import Console
from rich.table import Table

from schemas import keys
from schemas.actions import CancelGoal
from schemas.robot import Twist
from schemas.safety import SafetyStatus
from services.recorder.config import RecorderConfig
from services.recorder.main import provenance
from services.recorder.mcapfile import MAX_CHANNELS, WORLD_ATTACHMENT, SourceFile
from services.recorder.node import bind
from services.recorder.reader import RecordingError, RecordingFile, join_recordings, read_recording, recover
from services.recorder.recorded import no_file, recorded_policy, recorded_world
from services.recorder.recorder import Recorder
from services.recorder.replay import (
    REPLAY_SUFFIX,
    Item,
    ReplayKind,
    ReplayPlan,
    default_target,
    is_replay_name,
    plan_replay,
)
from services.robotlink import KeyFileError, read_key
from services.runtime import SIGNAL_POLL, ConfigError, Node, NodeSettings, encode, load_config, stop_event
from services.safety.recheck import Message, RecheckReport, recheck
from services.worldmodel import WorldFileError, load_world
from tether.output import literal, printable, shown
from tether.progress import Bar, ProgressOpt, progress_bar

console = Console(stderr=True, soft_wrap=True)  # notes name files: paths stay whole
QUERY_TIMEOUT = 5.0
# A replay keeps a publisher for this many keys, as many channels as a recorder writes: past them (a
# crafted file) each message is put without one, for Zenoh takes ever longer to declare each further
# publisher (tens of thousands hold a replay for minutes).
MAX_PUBLISHERS = MAX_CHANNELS
# What drives the base: a replay stopped after sending either stops it (the robot drops a twist only
# after its own timeout).
BASE_COMMANDS = (f"/{keys.CMD_VEL.path}", f"/{keys.TELEOP_CMD_VEL.path}")

FileArg = Annotated[Path, typer.Argument(help="An MCAP recording.", show_default=False)]
FilesArg = Annotated[
    list[Path],
    typer.Argument(
        help="An MCAP recording, or the parts of a rotated one (in any order).", show_default=False, metavar="FILE"
    ),
]
KeysOpt = Annotated[
    str | None,
    typer.Option(
        "--keys",
        help="A Zenoh key expression; relative ones (safety/**) are under the robot's prefix. Default: every key.",
    ),
]
RobotKeyOpt = Annotated[
    Path | None,
    typer.Option(
        "--robot-key",
        help="The robot key file (mode 0600) the recording was made under: every robot-link MAC is checked, "
        "so safety's heartbeats are told from a forger's. Without it, heartbeats of several senders at once "
        "leave the e-stop latch unknown.",
    ),
]


def fail(message: str, code: int = 2, as_json: bool = False) -> NoReturn:
    """End the command with `message` as an error: with --json (`as_json`) one JSON object on stdout,
    {"error": message}, so a script reading it gets one; else words on stderr."""
    if as_json:
        print(json.dumps({"error": message}))
    else:
        console.print(f"[red]error:[/] {shown(message)}", highlight=False)
    raise typer.Exit(code)


def robot_key_of(path: Path | None, as_json: bool = False) -> bytes | None:
    """The key in `--robot-key`'s file, or None without one; exit 2 naming what is wrong with the file."""
    if path is None:
        return None
    try:
        return read_key(path.expanduser())
    except KeyFileError as exc:
        fail(f"--robot-key: {exc}", as_json=as_json)


def key_filter(robot: str, expr: str | None, as_json: bool = False) -> zenoh.KeyExpr:
    """`expr` as a key expression: absolute (tether/...) as it is, relative under the robot's prefix."""
    try:
        return zenoh.KeyExpr(_absolute(robot, expr or "**"))
    except zenoh.ZError as exc:
        fail(f"--keys {expr!r} is not a valid key expression: {str(exc).split(' at ')[0]}", as_json=as_json)


def _absolute(robot: str, key: str) -> str:
    return key if key.startswith(f"{keys.ROOT}/") else f"{keys.prefix(robot)}/{key}"


def key_matcher(robot: str, expr: str, as_json: bool = False) -> Callable[[str], bool]:
    """Whether a key (absolute, or relative to the robot's prefix) is one `expr` selects; each key is
    looked at once. A recorded key no Zenoh session could have published is never selected."""
    selected = key_filter(robot, expr, as_json)
    matches: dict[str, bool] = {}

    def match(key: str) -> bool:
        if key not in matches:
            try:
                matches[key] = selected.intersects(zenoh.KeyExpr(_absolute(robot, key)))
            except zenoh.ZError:
                matches[key] = False
        return matches[key]

    return match


def open_recording(
    files: list[Path],
    expr: str | None = None,
    robot: str | None = None,
    bar: Bar | None = None,
    as_json: bool = False,
) -> RecordingFile:
    """The recording (the parts of a rotated one, joined), with the messages `expr` selects; errors
    exit 2 (said as JSON with `as_json`); a cut file is noted. The bytes read are counted on `bar`."""
    try:
        with (bar or Bar()).reading(files) as watched:
            parts = [read_recording(file) for file in watched]
        recording = join_recordings(parts)
    except RecordingError as exc:
        fail(str(exc), as_json=as_json)
    if expr is not None:
        match = key_matcher(robot or recording.robot, expr, as_json)
        recording.messages = [m for m in recording.messages if match(m.key)]
    for part in parts:
        if part.skipped:
            console.print(
                f"[yellow]{shown(part.path)} is damaged: {shown(part.problem)}; everything else in it is read[/]",
                highlight=False,
            )
        elif not part.complete:
            console.print(
                f"[yellow]{shown(part.path)} was cut short: {shown(part.problem)}; read as far as it is whole "
                "(`tether recover` writes a complete copy)[/]",
                highlight=False,
            )
    return recording


def settings(ctx: typer.Context) -> NodeSettings:
    value: NodeSettings = ctx.obj
    return value


# Record


def record(
    ctx: typer.Context,
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="The file to write. Default: recordings/<robot>_<time>.mcap.")
    ] = None,
    key_expr: KeysOpt = None,
    duration: Annotated[float | None, typer.Option(help="Stop after this many seconds (default: Ctrl-C).")] = None,
    config: Annotated[
        Path | None,
        typer.Option(
            "--config", help=literal("TOML config: [recorder] for files, [safety] for the world and policy kept.")
        ),
    ] = None,
) -> None:
    """Record the robot's traffic to MCAP until Ctrl-C, as the recorder service does (flushed every second)."""
    node_settings = settings(ctx)
    if output is not None and output.exists():
        fail(f"{output} exists; choose another name or remove it")
    if output is not None and not output.parent.is_dir():  # made on the way, as root: /nonexistent
        fail(f"{output}: no directory {output.parent}; make it first or choose another -o")
    if duration is not None and not duration > 0:  # nan too: it would never be reached
        fail(f"--duration must be positive, not {duration:g}")
    selected = key_filter(node_settings.robot, key_expr)
    try:
        recorder_config = load_config(RecorderConfig, config, "recorder")
        recorder = Recorder(recorder_config, provenance(node_settings.robot, config), first_path=output)
    except (ConfigError, OSError) as exc:
        fail(str(exc))
    stop = stop_event()  # Ctrl-C or SIGTERM: finish the file
    started = time.monotonic()
    try:
        with Node("record", node_settings) as node:
            bind(node, recorder, str(selected), serve_status=False)
            if not node.alive_services(timeout=1.0):
                console.print(f"[yellow]no services of robot {node_settings.robot} are up yet; recording anyway[/]")
            with console.status("") as status:
                while not stop.wait(min(recorder_config.flush_interval, _left(duration, started))):
                    recorder.tick()
                    status.update(
                        literal(
                            f"recording {selected} to {recorder.status().path}: {recorder.messages} messages, "
                            f"{time.monotonic() - started:.0f} s (Ctrl-C stops)"
                        )
                    )
                    if duration is not None and time.monotonic() - started >= duration:
                        break
    finally:
        recorder.finish()
    console.print(
        f"recorded {recorder.messages} messages ({recorder.dropped} dropped) to {recorder.files_said()}", markup=False
    )


def _left(duration: float | None, started: float) -> float:
    return 1.0 if duration is None else max(0.0, duration - (time.monotonic() - started))


# Replay


def replay(
    ctx: typer.Context,
    files: FilesArg,
    speed: Annotated[float, typer.Option(help="Playback speed: 2 is twice as fast.")] = 1.0,
    key_expr: KeysOpt = None,
    to: Annotated[
        str | None, typer.Option("--to", help="The robot name to replay under. Default: <recorded robot>_replay.")
    ] = None,
    live_commands: Annotated[
        bool,
        typer.Option(
            "--live-commands",
            help="Replay onto a robot whose services are up: only its commands, through its safety, which checks them.",
        ),
    ] = False,
    progress: ProgressOpt = None,
) -> None:
    """Publish a recording again with its original timing, under a separate robot name by default."""
    if not 0.01 <= speed <= 1000:
        fail(f"--speed must be between 0.01 and 1000, not {speed:g}")
    with progress_bar(progress) as bar:
        _replay(ctx, files, speed, key_expr, to, live_commands, bar)


def _replay(
    ctx: typer.Context,
    files: list[Path],
    speed: float,
    key_expr: str | None,
    to: str | None,
    live_commands: bool,
    bar: Bar,
) -> None:
    recording = open_recording(files, key_expr, bar=bar)
    robot = recording.robot
    target = default_target(robot) if to is None else to  # --to "" is refused below, not the default
    try:
        NodeSettings(robot=target)
    except ValueError as exc:
        fail(f"--to: {exc}")
    plan = plan_replay(recording.messages, robot, target, live=live_commands, key_error=key_error)
    node_settings = NodeSettings(
        robot=target,
        base_port=settings(ctx).base_port,
        host=settings(ctx).host,
        zenoh_config=settings(ctx).zenoh_config,
    )
    if not live_commands and not is_replay_name(target):
        fail(
            f"a replay of every key goes under a robot name ending in {REPLAY_SUFFIX} (default "
            f"{default_target(robot)}), where nothing acts on it; to send the recorded commands to robot "
            f"{target}, through its safety, pass --live-commands"
        )
    with Node("replay", node_settings) as node:
        # A recorder there is someone watching the replay; anything else acts on what it hears.
        alive = node.alive_services(timeout=1.0) - {"recorder"}
        if alive and not live_commands:
            fail(
                f"robot {target} has live services ({', '.join(sorted(alive))}): a replay there would command it. "
                "Replay under another name (--to), or pass --live-commands to send only its commands, through safety"
            )
        if live_commands and "safety" not in alive:
            fail(f"--live-commands needs robot {target}'s safety up to check the commands; it is not reachable")
        for why, count in plan.skipped.items():
            console.print(f"[dim]not replayed: {count} messages {shown(why)}[/]")
        for why, count in plan.retimed.items():
            console.print(f"[yellow]not on their recorded time: {count} messages {shown(why)}[/]")
        console.print(
            printable(
                f"replaying {len(plan.items)} messages of {robot} from {recording.name} as {target} at {speed:g}x "
                f"({plan.duration / speed:.1f} s)"
            ),
            markup=False,
        )
        # Ctrl-C and SIGTERM stop the replay between two of its steps, never inside one.
        player = Player(node, stop_event(), watch_estop=live_commands)
        if not live_commands:
            player.stop_when_a_service_comes_up()
        sent = player.play(plan, speed, bar)
    if player.came_up is not None:
        fail(
            f"robot {target}'s {player.came_up} came up during the replay, and would act on it: stopped "
            f"after {sent} of {len(plan.items)} messages. Replay under another name (--to)"
        )
    refused = f"; {player.sent_latched} of them while the e-stop was latched (safety refused them)"
    console.print(f"replayed {sent} messages" + (refused if player.sent_latched else ""), markup=False)


def key_error(key: str) -> str | None:
    """What Zenoh finds wrong with `key` as a key to publish on, or None when it takes it."""
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        return str(exc).split(" at ")[0]
    return None


class Player:
    """Puts and asks a replay's items on time. Goal queries go one after the other, in order, on a
    worker (so a goal's cancel never overtakes it, and the clock does not wait for replies); a
    replay stopped (`stop` set: Ctrl-C or SIGTERM) cancels the goals it asked, also while it waits
    for the last answers, asks none still queued, and stops the base. With `watch_estop` it says when
    the robot's e-stop latches or clears, and counts what it sends while latched (safety refuses it)."""

    def __init__(self, node: Node, stop: threading.Event | None = None, watch_estop: bool = False) -> None:
        self.node = node
        self.stop = stop or threading.Event()
        self.publishers: dict[str, zenoh.Publisher] = {}
        self.asker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="replay-query")
        self.started: list[Item] = []  # the goals asked, to cancel if the replay is stopped
        self.base: str | None = None  # the robot whose base this replay sent velocities, to stop if stopped
        self.latched: str | None = None  # why the robot's e-stop is latched, as its heartbeat says; None if not
        self.sent_latched = 0  # messages sent while it was
        self.came_up: str | None = None  # the service whose coming up stopped the replay
        if watch_estop:
            node.subscribe(keys.HEARTBEAT, self._heartbeat)

    def stop_when_a_service_comes_up(self) -> None:
        """Stop the replay when a tether service other than a recorder comes up under its robot name:
        checked once before it starts, a driver started later would act on the replayed robot/cmd_vel
        with no safety between."""

        def on_token(sample: zenoh.Sample) -> None:
            service = str(sample.key_expr).rsplit("/", 1)[-1]
            if sample.kind == zenoh.SampleKind.PUT and service != "recorder" and self.came_up is None:
                self.came_up = service
                self.stop.set()

        alive = keys.alive_key(self.node.robot, "*")
        self._watch = self.node.session.liveliness().declare_subscriber(alive, on_token, history=True)

    def play(self, plan: ReplayPlan, speed: float, bar: Bar | None = None) -> int:
        """Send the items on the recorded clock, `speed` times as fast, counting the recorded seconds on `bar`."""
        sent = 0
        played = 0.0  # recorded seconds
        task = (bar or Bar()).task(f"replaying at {speed:g}x (recorded seconds)", plan.duration)
        asked: Future[None] | None = None  # the last goal query queued: the worker asks them in order
        start = time.monotonic()
        try:
            for item in plan.items:
                # The recorded clock: this is the replay's pacing.
                if self.stop.wait(max(0.0, start + item.at / speed - time.monotonic())):
                    break
                asked = self._send(item) or asked
                sent += 1
                task.advance(item.at - played)
                played = item.at
            # The queries still queued are the replay's too: a stop while they are asked cancels them.
            while asked is not None and not asked.done() and not self.stop.is_set():
                futures.wait([asked], SIGNAL_POLL)  # woken to see a signal's stop
            if self.stop.is_set():
                console.print("replay stopped: canceling the goals it sent")
                self.asker.shutdown(wait=True, cancel_futures=True)
                self._stop_what_was_started()
        finally:
            self.asker.shutdown(wait=True)
            for publisher in self.publishers.values():
                publisher.undeclare()
        return sent

    def _heartbeat(self, status: SafetyStatus) -> None:
        latched = f"{status.estop.source}: {status.estop.reason}" if status.estop.latched else None
        if (latched is None) != (self.latched is None):
            said = f"e-stop latched by {latched}; safety refuses what the replay sends" if latched else "e-stop reset"
            console.print(f"[yellow]robot {shown(self.node.robot)}: {shown(said)}[/]", highlight=False)
        self.latched = latched

    def _send(self, item: Item) -> Future[None] | None:
        """Put `item`, or queue its query; the query's future."""
        if self.latched is not None:
            self.sent_latched += 1
        if item.kind is ReplayKind.PUT:
            if item.key.endswith(BASE_COMMANDS):
                self.base = item.key.split("/")[1]
            publisher = self.publishers.get(item.key)
            if publisher is None and len(self.publishers) < MAX_PUBLISHERS:
                publisher = self.publishers[item.key] = self.node.session.declare_publisher(item.key)
            if publisher is None:
                self.node.session.put(item.key, item.payload)
            else:
                publisher.put(item.payload)
            return None
        return self.asker.submit(self._ask_item, item)

    def _ask_item(self, item: Item) -> None:
        if item.goal_id is not None:
            self.started.append(item)  # before it is asked: its answer may come after a stop
        self._ask(item.key, item.payload)

    def _stop_what_was_started(self) -> None:
        for item in self.started:
            cancel = item.key.removesuffix("send_goal") + "cancel_goal"
            self._ask(cancel, encode(CancelGoal(goal_id=str(item.goal_id))))
        if self.base is not None:
            self.node.session.put(keys.CMD_VEL.key(self.base), encode(Twist()))

    def _ask(self, key: str, payload: bytes) -> None:
        """A replayed goal query, asked of the live robot's safety; its answer is shown."""
        for reply in self.node.session.get(key, payload=payload, timeout=QUERY_TIMEOUT):
            answer = reply.ok if reply.ok is not None else reply.err
            data = answer.payload.to_bytes() if answer is not None else b""
            console.print(printable(f"{key.rsplit('/', 3)[0]}: {data[:300].decode(errors='replace')}"), markup=False)
            return
        console.print(f"[yellow]{shown(key)}: no reply within {QUERY_TIMEOUT:g} s[/]")


# Recheck


def recheck_command(
    files: FilesArg,
    policy: Annotated[
        Path | None, typer.Option("--policy", help="The policy to check with. Default: the one kept in the recording.")
    ] = None,
    world_name: Annotated[
        str | None,
        typer.Option("--world", help="The world to check in when the recording has none (a file or a bundled name)."),
    ] = None,
    show_all: Annotated[bool, typer.Option("--all", help="List every rechecked command, not only changes.")] = False,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object: the report, or the error (exit 2).")
    ] = False,
    robot_key_file: RobotKeyOpt = None,
    progress: ProgressOpt = None,
) -> None:
    """Check the recorded commands again, offline, and list every decision that differs from the recorded one.

    Robot commands and heartbeats that are not safety's (no robot-link MAC, another sender, replayed, no
    decision allowing them) are listed as warnings.

    Exit 0 when none differs, 1 when some do (a policy change to look at before it reaches a robot), when
    something not safety's reached the robot's keys, or when the file is damaged (what its skipped records
    held was not rechecked), 2 on bad input or when nothing could be rechecked.
    """
    robot_key = robot_key_of(robot_key_file, as_json)
    if policy is not None and not policy.is_file():
        fail(f"policy file {policy} does not exist", as_json=as_json)
    with progress_bar(progress) as bar:
        recording = open_recording(files, bar=bar, as_json=as_json)
        name = recording.name
        try:
            if recording.world is None:
                if world_name is None:
                    fail(f"{name} {no_file(recording, WORLD_ATTACHMENT)}; give one with --world", as_json=as_json)
                console.print(printable(f"{name} carries no world file: checking in {world_name}"), markup=False)
                world, label = load_world(world_name), f"the world {world_name}"
            else:
                if world_name is not None:
                    unused = f"--world {world_name} not used: {name} carries its own world file"
                    console.print(f"[yellow]{shown(unused)}[/]")
                world, label = recorded_world(recording), "the recorded world"
            safety = recorded_policy(recording, world, policy, label)
        except RecordingError as exc:
            fail(str(exc), as_json=as_json)
        except WorldFileError as exc:
            fail(f"--world {world_name}: {exc}", as_json=as_json)
        robot = recording.robot
        root = keys.prefix(robot) + "/"
        messages = (
            Message(m.log_time / 1e9, m.key[len(root) :], m.data, m.attachment)
            for m in bar.track(recording.messages, len(recording.messages), "rechecking")
            if m.key.startswith(root)
        )
        kept = recording.policy
        # The digest of the file kept, not the one the metadata claims for it: an attachment swapped
        # under intact metadata is still told from what safety's events say it ran with.
        kept_hash = SourceFile(Path(kept.name), kept.data).hash if kept is not None else ""
        report = recheck(messages, safety, kept_hash, robot, robot_key)
    start = recording.messages[0].log_time / 1e9 if recording.messages else 0.0
    if as_json:
        print(json.dumps(_report_json(report, recording, start, show_all)))
    else:
        _print_report(report, name, start, show_all, policy)
    if not report.checked:
        # Not a pass: a file without safety's decisions (recorded with --keys, say) proves nothing. The
        # report is the JSON object already printed (its checked is 0): the error goes to stderr only.
        fail(f"nothing in {name} could be rechecked: it holds no safety decision with the robot's state before it")
    if recording.skipped:
        # Not a pass either: the decisions in the damaged records went unchecked (open_recording named them).
        console.print(
            f"[yellow]{shown(name)}: {recording.skipped} damaged record(s) skipped; the commands they held "
            "were not rechecked[/]",
            highlight=False,
        )
    # Commands or heartbeats that are not safety's are a finding too (listed as warnings).
    raise typer.Exit(1 if report.differences or report.suspects or recording.skipped else 0)


def _report_json(report: RecheckReport, recording: RecordingFile, start: float, show_all: bool) -> dict[str, Any]:
    rows = report.checked if show_all else report.differences
    return {
        "file": str(recording.path),
        "parts": [str(part) for part in recording.files],
        "complete": recording.complete,
        "problem": recording.problem,
        "damaged_records": recording.skipped,
        "policy_hash": report.policy_hash,
        "checked": len(report.checked),
        "differ": len(report.differences),
        "skipped": dict(report.skipped),
        "warnings": report.warnings,
        "decisions": [
            {
                "t": round(c.stamp - start, 3),
                "key": c.key,
                "command": c.command,
                "recorded": str(c.recorded),
                "recorded_reason": c.recorded_reason,
                "now": str(c.now),
                "now_reason": c.now_reason,
                "now_rule": str(c.now_rule) if c.now_rule else None,
            }
            for c in rows
        ],
    }


def _print_report(report: RecheckReport, name: str, start: float, show_all: bool, policy: Path | None) -> None:
    for warning in report.warnings:
        console.print(f"[yellow]warning:[/] {shown(warning)}")
    rows = report.checked if show_all else report.differences
    if rows:
        table = Table("t (s)", "command", "recorded", "now", "why")
        for c in rows:
            colour = "red" if c.differs else "dim"
            texts = (c.command, c.recorded, c.now, c.now_reason if c.now_reason else c.recorded_reason)
            command, recorded, now, why = (shown(text, newlines=False) for text in texts)
            table.add_row(f"{c.stamp - start:.2f}", command, recorded, f"[{colour}]{now}[/]", why)
        Console().print(table)
    skipped = ", ".join(f"{n} {why}" for why, n in report.skipped.items())
    against = f"policy {policy}" if policy else "the recorded policy"
    console.print(
        printable(
            f"{name}: {len(report.checked)} commands rechecked against {against} ({report.policy_hash}); "
            f"{len(report.differences)} decided differently" + (f"; not rechecked: {skipped}" if skipped else "")
        ),
        markup=False,
    )


# Recover


def recover_command(
    file: FileArg,
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="Where the complete copy goes. Default: FILE.recovered.mcap.")
    ] = None,
) -> None:
    """Write a complete copy of a recording cut short (the recorder was killed): every chunk flushed before the cut."""
    if not file.is_file():  # "" is ".", a directory: with_suffix below would raise
        fail(f"{file}: no such file" if not file.exists() else f"{file} is not a file")
    output = output or file.with_suffix(".recovered.mcap")
    if output.exists():
        fail(f"{output} exists; choose another name with -o or remove it")
    try:
        done = recover(file, output)
    except RecordingError as exc:
        fail(str(exc))
    except OSError as exc:
        fail(f"cannot write {output}: {exc.strerror}")
    state = "was complete; copied" if done.complete else f"recovered, without what could not be read ({done.problem})"
    console.print(
        printable(f"{file} {state}: {done.messages} messages on {done.channels} channels written to {output}"),
        markup=False,
    )
