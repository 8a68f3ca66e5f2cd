"""Real service processes for a bench: started by the Supervisor on their own robot and ports, baselines included.

Services are started with TETHER_BENCH_ECHO=1 (services.runtime.BENCH_ECHO_ENV), so the same process
and session also answer the bare Zenoh echo of `bench.transport`: the baseline each query is compared
with, interleaved with it. Safety is also started with TETHER_BENCH_RELAY=sim (the robot's backend):
a bare relay of raw queries (to its echo) and of a raw topic, the baseline for commands passing
through safety.

Also here, shared by the benches of the robot path (gate, estop, watchdog, stream): the robot and
safety started with a config file and an operator token of their own (`running_robot`; the robot is
the sim, or with `--backend ros2` the ros2 backend driving the stand-in ROS 2 robot on a Zenoh
network of their own, `standin_tables`), the robot's state as its backend reports it with the moment
it comes to a halt (`RobotMotion`), safety's heartbeat (`Heartbeats`), a slow cmd_vel stream that
keeps the base moving (`drive`), the operator's reset, and the command line every bench shares.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

from bench.transport import bare_echo, interleaved, machine, percentile
from schemas import keys
from schemas.keys import Topic
from schemas.robot import ARM_JOINTS, JointState, Odometry, Twist
from schemas.safety import SafetyStatus
from services import runtime
from services.runtime import ALL_SERVICES, ROBOT_BACKENDS, Node, NodeSettings
from tether.supervisor import Supervisor, free_base_port

T = TypeVar("T")
N = TypeVar("N", int, float)

READY_TIMEOUT = 30.0
STOP_TIMEOUT = 5.0

Progress = Callable[[str], None]
# Round trips of each kind a bench may be asked for.
MAX_N = 20_000
# The robot counts as still below these (m/s, rad/s), as moving above MOVING.
STILL = 0.01
MOVING = 0.1
TOKEN_ENV = "TETHER_OPERATOR_TOKEN_FILE"
# `--backend` of the robot path's benches -> the robot's services (runtime.ROBOT_BACKENDS): the sim, or
# the ros2 backend with the stand-in robot (the sim behind a ROS 2 face) in the sim's place.
BACKENDS = {"sim": "sim", "ros2": "ros2-standin"}


class BenchError(Exception):
    """A part of the bench could not run; the message says which and why."""


def reporter(prog: str) -> Progress:
    """Progress lines on stderr, prefixed with the bench's name."""

    def progress(message: str) -> None:
        print(f"{prog}: {message}", file=sys.stderr, flush=True)

    return progress


def ms_summary(ms: list[float]) -> tuple[float, float]:
    """Median and p99, in ms, rounded for the JSON."""
    return round(statistics.median(ms), 4), round(percentile(ms, 99), 4)


def bench_settings(bench: str) -> NodeSettings:
    """A robot name and ports of this bench's own, so it never talks to a running stack."""
    # The service gets our settings only: an inherited Zenoh config file would point it at other peers.
    os.environ.pop("TETHER_ZENOH_CONFIG", None)
    base_port = int(os.environ.get("TETHER_BASE_PORT") or free_base_port())
    return NodeSettings(robot=f"bench-{bench}-{os.getpid()}", base_port=base_port)


# Service processes


@dataclass
class Stack:
    """Services started for a bench, and the bench's own Node on their robot and ports."""

    node: Node
    supervisor: Supervisor
    progress: Progress
    # Environment for every service, then for each one.
    env: dict[str, str]
    service_env: dict[str, dict[str, str]]
    config_file: Path | None = None
    token_file: Path | None = None

    def start(self, service: str) -> None:
        self.supervisor.extra_env = {**self.env, **self.service_env.get(service, {})}
        self.supervisor.start(service)

    def restart(self, service: str) -> None:
        """Start `service` again (after a kill) and wait until it holds its liveliness token."""
        self.start(service)
        wait_ready(self.node, self.supervisor, service, self.progress)


def toml(sections: dict[str, dict[str, Any]]) -> str:
    """A TOML file of flat tables of strings, numbers and booleans (JSON spells those the TOML way)."""
    lines: list[str] = []
    for name, table in sections.items():
        lines += [f"[{name}]", *(f"{key} = {json.dumps(value)}" for key, value in table.items()), ""]
    return "\n".join(lines)


@contextlib.contextmanager
def running_stack(
    services: tuple[str, ...],
    settings: NodeSettings,
    log_dir: Path,
    progress: Progress,
    *,
    config: dict[str, dict[str, Any]] | None = None,
    env: dict[str, str] | None = None,
    service_env: dict[str, dict[str, str]] | None = None,
) -> Iterator[Stack]:
    """`services` as child processes (config file and logs in `log_dir`), with a client Node once
    all are alive; always stopped."""
    config_file = None
    if config:
        config_file = log_dir / "tether.toml"
        config_file.write_text(toml(config))
    supervisor = Supervisor(settings, log_dir, config_file)
    common = {runtime.BENCH_ECHO_ENV: "1", **(env or {})}
    node: Node | None = None
    try:
        stack = Stack(Node("cli", settings), supervisor, progress, common, service_env or {}, config_file)
        node = stack.node
        for service in services:
            stack.start(service)
        for service in services:
            wait_ready(node, supervisor, service, progress)
        yield stack
    finally:
        # A second Ctrl-C must not leave a child running: stopping takes at most STOP_TIMEOUT + 10 s each.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            if node is not None:
                node.close()
            supervisor.stop_all(timeout=STOP_TIMEOUT)
        finally:
            signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def running_service(service: str, settings: NodeSettings, log_dir: Path, progress: Progress) -> Iterator[Node]:
    """`service` as a child process, with a client Node once it is alive; always stopped."""
    with running_stack((service,), settings, log_dir, progress) as stack:
        yield stack.node


def robot_endpoint(settings: NodeSettings) -> str:
    """A free loopback Zenoh endpoint for a ROS 2 robot's own network, none of the stack's ports."""
    stack_ports = range(settings.base_port, settings.base_port + len(ALL_SERVICES))
    while (port := free_base_port(1)) in stack_ports:
        pass
    return f"tcp/{settings.host}:{port}"


def standin_tables(endpoint: str, ros2: dict[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """`[ros2]` (with the entries of `ros2`) and `[ros2sim]` of the ros2 backend and the stand-in robot
    meeting on the robot's network at `endpoint`; the stand-in's world, pace and report rates are `[sim]`'s."""
    return {"ros2": {"endpoint": endpoint, **(ros2 or {})}, "ros2sim": {"listen": endpoint}}


@contextlib.contextmanager
def running_robot(
    bench: str,
    progress: Progress,
    sim: dict[str, Any],
    *,
    backend: str = "sim",
    ros2: dict[str, Any] | None = None,
    safety: dict[str, Any] | None = None,
) -> Iterator[Stack]:
    """The robot of `backend` (a BACKENDS key) and safety, with the bench echo in each and safety's
    bare relay to the robot's backend: the sim (`[sim]` table `sim`), or the ros2 backend (`[ros2]`
    with `ros2`) and the stand-in robot (the same `[sim]`). The operator token, e-stop state file,
    config and logs in a temporary directory; `safety`: more of safety's table."""
    settings = bench_settings(bench)
    robot = ROBOT_BACKENDS[BACKENDS[backend]]
    with tempfile.TemporaryDirectory(prefix=f"bench-{bench}-") as tmp:
        token = Path(tmp) / "operator-token"
        config = {
            "sim": sim,
            "safety": {
                "operator_token_file": str(token),
                "estop_state_file": str(Path(tmp) / "estop-state.json"),
                **(safety or {}),
            },
        }
        if "ros2" in robot:
            config |= standin_tables(robot_endpoint(settings), ros2)
        progress(f"starting {', '.join(robot)} and safety (robot {settings.robot}, base port {settings.base_port})")
        with running_stack(
            (*robot, "safety"),
            settings,
            Path(tmp),
            progress,
            config=config,
            env={TOKEN_ENV: str(token)},
            service_env={"safety": {runtime.BENCH_RELAY_ENV: robot[0]}},
        ) as stack:
            stack.token_file = token
            yield stack


def wait_ready(node: Node, supervisor: Supervisor, service: str, progress: Progress) -> None:
    """Until the service holds its liveliness token; a service that exits is reported at once."""
    deadline = time.monotonic() + READY_TIMEOUT
    while node.wait_alive({service}, timeout=0.5):
        code = supervisor.exited().get(service)
        if code is None and time.monotonic() < deadline:
            continue
        why = f"not alive within {READY_TIMEOUT:g} s" if code is None else f"exited with code {code}"
        tail = supervisor.log_tail(service)
        progress(f"{service} service log:\n{tail}")
        raise BenchError(f"{service} service {why}: {last_line(tail)}")


def last_line(log: str) -> str:
    """The last line of a log with text on it: the exception of a traceback, without rich's box drawing."""
    lines = [line.strip(" \u2502\u2570\u2500\u256f\u256d\u256e") for line in log.splitlines()]
    return next((line for line in reversed(lines) if line), "no output")


def against_echo(
    node: Node, service: str, payload: bytes, query: Callable[[], None], n: int, warmup: int, max_seconds: float
) -> tuple[list[float], list[float]]:
    """Interleaved round trips in ms: (`service`'s bare echo carrying `payload`, `query`)."""
    try:
        return interleaved(bare_echo(node, payload, service), query, n, warmup, max_seconds)
    except RuntimeError as exc:  # the bare echo failed or did not answer
        raise BenchError(str(exc)) from None


# What the robot and safety report


def wait_until(condition: Callable[[], bool], timeout: float, what: str, poll: float = 0.002) -> None:
    """Poll `condition` until it holds; BenchError naming `what` after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise BenchError(f"{what} not seen within {timeout:g} s")
        time.sleep(poll)


class Latest(Generic[T]):
    """The latest message on a topic and when it arrived (wall time)."""

    def __init__(self, node: Node, topic: Topic[T], on_message: Callable[[T], None] | None = None) -> None:
        self.message: T | None = None
        self.arrived = 0.0
        self._on_message = on_message
        node.subscribe(topic, self._on)

    def _on(self, message: T) -> None:
        # The message first: a poll in between sees it with the previous arrival, and waits on.
        arrived = time.time()
        self.message = message
        self.arrived = arrived
        if self._on_message is not None:
            self._on_message(message)

    def wait(self, condition: Callable[[T], bool], timeout: float, what: str, after: float = 0.0) -> T:
        """The first latest message that arrived after `after` (wall time) and passes `condition`."""

        def seen() -> bool:
            return self.message is not None and self.arrived > after and condition(self.message)

        wait_until(seen, timeout, what)
        assert self.message is not None
        return self.message


class Heartbeats(Latest[SafetyStatus]):
    """Safety's heartbeat as it arrives, and when the latch was first heard set or clear."""

    def __init__(self, node: Node) -> None:
        self.arrivals: list[float] = []
        self.latch_changes: list[tuple[float, bool]] = []  # (arrival, latched)
        super().__init__(node, keys.HEARTBEAT, self._on_beat)

    def _on_beat(self, beat: SafetyStatus) -> None:
        self.arrivals.append(self.arrived)
        if not self.latch_changes or self.latch_changes[-1][1] != beat.estop.latched:
            self.latch_changes.append((self.arrived, beat.estop.latched))

    def latched_after(self, t0: float) -> float | None:
        """ms from `t0` to the first beat heard here with the latch set."""
        return next(((at - t0) * 1000 for at, latched in self.latch_changes if latched and at >= t0), None)

    def period_ms(self) -> float | None:
        """The median time between beats: safety's beat period as this process hears it."""
        gaps = [(b - a) * 1000 for a, b in zip(self.arrivals, self.arrivals[1:], strict=False)]
        return round(statistics.median(gaps), 3) if gaps else None

    def wait_clear(self, timeout: float, after: float = 0.0) -> SafetyStatus:
        return self.wait(lambda beat: not beat.estop.latched, timeout, "a heartbeat with the e-stop clear", after)


def base_speed(odom: Odometry) -> float:
    return max(abs(odom.linear_x), abs(odom.angular_z))


def arm_speed(joints: JointState) -> float:
    """The fastest arm joint (fingers left out), rad/s."""
    speeds = [abs(v) for name, v in zip(joints.name, joints.velocity, strict=False) if name in ARM_JOINTS]
    return max(speeds, default=0.0)


@dataclass
class _Halt:
    """The first samples after t0 at which the base (and the arm, when watched) were still."""

    t0: float
    since: dict[str, float | None] = field(default_factory=dict)
    stamp: float | None = None
    done: threading.Event = field(default_factory=threading.Event)


class RobotMotion:
    """Odometry (and joint states with `arm`) as the robot's backend publishes them, and halts measured on them.

    A halt is the first sample, by its `stamp` (the robot's wall clock), after which the base's
    |linear_x| and |angular_z| (and, with `arm`, every arm joint's |velocity|) are below STILL in the
    latest sample of each topic.
    """

    def __init__(self, node: Node, *, arm: bool) -> None:
        self._lock = threading.Lock()
        self._halt: _Halt | None = None
        self.t0 = 0.0  # of the last halt measured
        self._watched = ("odom", "joints") if arm else ("odom",)
        self.odom = Latest(node, keys.ODOM, lambda m: self._sample("odom", m.stamp, base_speed(m) < STILL))
        self.joints = Latest(node, keys.JOINT_STATES, lambda m: self._sample("joints", m.stamp, arm_speed(m) < STILL))

    def _sample(self, topic: str, stamp: float, still: bool) -> None:
        with self._lock:
            halt = self._halt
            if halt is None or stamp < halt.t0 or halt.done.is_set() or topic not in self._watched:
                return
            if not still:
                halt.since[topic] = None
            elif halt.since.get(topic) is None:
                halt.since[topic] = stamp
            since = [halt.since.get(t) for t in self._watched]
            if all(s is not None for s in since):
                # The latest of them: a topic's sample that completes the halt may be older than
                # another topic's first still one (the topics arrive apart, as a backend passes them on).
                halt.stamp = max(s for s in since if s is not None)
                halt.done.set()

    def moving(self) -> bool:
        """The base, and the arm if watched, faster than MOVING in their latest samples."""
        odom, joints = self.odom.message, self.joints.message
        if odom is None or abs(odom.linear_x) <= MOVING:
            return False
        return "joints" not in self._watched or (joints is not None and arm_speed(joints) > MOVING)

    def wait_ready(self, timeout: float) -> None:
        wait_until(lambda: self.odom.message is not None, timeout, "odometry from the robot")
        wait_until(lambda: self.joints.message is not None, timeout, "joint states from the robot")

    def halt_ms(self, trigger: Callable[[], None], timeout: float) -> float:
        """ms from t0, taken just before `trigger()` (which must stop the robot), to the halt."""
        t0 = self.t0 = time.time()
        halt = _Halt(t0)
        with self._lock:
            self._halt = halt
        trigger()
        if not halt.done.wait(timeout):
            odom = self.odom.message
            speed = f"{base_speed(odom):.3f}" if odom else "unknown"
            raise BenchError(f"the robot did not halt within {timeout:g} s (base speed {speed})")
        assert halt.stamp is not None
        return (halt.stamp - t0) * 1000


@contextlib.contextmanager
def drive(node: Node, linear_x: float, hz: float = 20.0) -> Iterator[None]:
    """Keep the base moving with cmd_vel at `hz` on `cmd/cmd_vel` (through safety) until the block ends."""
    stop = threading.Event()

    def stream() -> None:
        while not stop.is_set():
            node.publish(keys.CMD_VEL, Twist(linear_x=linear_x, stamp=time.time()))
            stop.wait(1.0 / hz)

    thread = threading.Thread(target=stream, name="cmd_vel", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


@contextlib.contextmanager
def robot_ready(
    bench: str,
    progress: Progress,
    sim: dict[str, Any],
    *,
    arm: bool,
    backend: str = "sim",
    ros2: dict[str, Any] | None = None,
    safety: dict[str, Any] | None = None,
) -> Iterator[tuple[Stack, RobotMotion, Heartbeats]]:
    """`running_robot`, once the robot reports its state and safety beats with the e-stop clear."""
    with running_robot(bench, progress, sim, backend=backend, ros2=ros2, safety=safety) as stack:
        state = RobotMotion(stack.node, arm=arm)
        beats = Heartbeats(stack.node)
        state.wait_ready(10.0)
        beats.wait_clear(10.0)
        yield stack, state, beats


def halt_trials(trials: int, trial: Callable[[int], float], progress: Progress, cause: str) -> list[float]:
    """`trial(i)` for each trial, the ms to each halt, each reported as it comes."""
    halts: list[float] = []
    for i in range(trials):
        halts.append(round(trial(i), 2))
        progress(f"trial {i + 1}/{trials}: halted {halts[-1]:.1f} ms after {cause}")
    return halts


def reset_latch(stack: Stack, beats: Heartbeats, timeout: float = 5.0) -> None:
    """Clear the e-stop as `tether reset` does, with the operator token, and wait for clear heartbeats.

    Two beats more than the first clear one: the sim hears beats and goals on threads of their
    own, and a goal sent the moment this process hears the clear beat can reach the sim first.
    """
    from tether.client import reset_estop

    asked = time.time()
    reply = reset_estop(stack.node, str(stack.token_file) if stack.token_file else None)
    if not reply.ok:
        raise BenchError(f"safety/reset refused the operator token: {reply.message}")
    clear = beats.wait_clear(timeout, after=asked)
    beats.wait(lambda beat: beat.seq >= clear.seq + 2, timeout, "two heartbeats after the reset")


# Results and the command line


def measured(defaults: dict[str, Any], measure: Callable[[], dict[str, Any]], progress: Progress) -> dict[str, Any]:
    """`defaults` updated by `measure()`, with `errors`: its own (a list it returns) and a BenchError it raises."""
    result = dict(defaults)
    errors: list[str] = []
    try:
        result |= measure()
    except BenchError as exc:
        errors.append(str(exc))
        progress(f"error: {exc}")
    result["errors"] = [*result.get("errors", []), *errors]
    return result


def notes(**extra: Any) -> dict[str, Any]:
    return {**machine(), **extra}


def show(value: Any, unit: str = "") -> str:
    return "-" if value is None else f"{value:,.3f}{unit}" if isinstance(value, float) else f"{value}{unit}"


def print_rows(title: str, rows: list[tuple[str, str, str]], errors: list[str]) -> None:
    """A table of (what, measured, goal), then the errors."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    table.add_column("")
    table.add_column("measured", justify="right")
    table.add_column("goal", justify="right")
    for row in rows:
        table.add_row(*row)
    console = Console()
    console.print(table)
    for error in errors:
        console.print(f"[red]error:[/] {error}", markup=True, highlight=False)


def bounded(kind: Callable[[str], N], low: N, high: N, *, open_low: bool = False) -> Callable[[str], N]:
    """An argparse type: `kind` between `low` and `high` (`low` itself excluded with `open_low`)."""

    def parse(text: str) -> N:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not (low < value if open_low else low <= value) or not value <= high or not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be in {'(' if open_low else '['}{low}, {high}]")
        return value

    return parse


def add_backend_argument(parser: argparse.ArgumentParser) -> None:
    """`--backend`, for the benches of the robot path."""
    parser.add_argument(
        "--backend",
        choices=tuple(BACKENDS),
        default="sim",
        help="the robot: the sim, or the ros2 backend driving the stand-in ROS 2 robot (the sim behind a ROS 2 face)",
    )


def bench_main(
    prog: str,
    doc: str,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    run: Callable[[argparse.Namespace], dict[str, Any]],
    print_table: Callable[[dict[str, Any]], None],
    argv: list[str] | None,
) -> None:
    """The command line every bench shares: `run(args)` gives the result, printed as one JSON object
    with --json, else as a table; SIGTERM unwinds like Ctrl-C (exit 130); exit 1 on errors."""
    parser = argparse.ArgumentParser(prog=f"python -m {prog}", description=doc.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    add_arguments(parser)
    args = parser.parse_args(argv)
    runtime.configure_logging("WARNING")
    # SIGTERM unwinds like Ctrl-C, so the service processes are stopped either way.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        result = run(args)
    except KeyboardInterrupt:
        reporter(prog)("interrupted")
        sys.exit(130)
    if args.json:
        print(json.dumps(result), flush=True)  # before finalization, which a thread left in Zenoh may abort
    else:
        print_table(result)
    if result["errors"]:
        sys.exit(1)


def command_line(
    prog: str,
    doc: str,
    run: Callable[[float, int, int, float], dict[str, Any]],
    print_table: Callable[[dict[str, Any]], None],
    argv: list[str] | None,
    *,
    seconds: float,
    seconds_help: str,
) -> None:
    """The command line of the service benches: `run(seconds, n, warmup, max_query_seconds)`."""

    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument(
            "--seconds", type=bounded(float, 0.0, 600.0, open_low=True), default=seconds, help=seconds_help
        )
        parser.add_argument("--n", type=bounded(int, 10, MAX_N), default=1000, help="round trips of each kind")
        parser.add_argument(
            "--warmup", type=bounded(int, 0, MAX_N), default=50, help="in-process runs and round trips not counted"
        )
        parser.add_argument(
            "--max-query-seconds",
            type=bounded(float, 0.0, 600.0, open_low=True),
            default=15.0,
            help="stop each kind of round trip after this",
        )

    bench_main(
        prog,
        doc,
        add_arguments,
        lambda args: run(args.seconds, args.n, args.warmup, args.max_query_seconds),
        print_table,
        argv,
    )
