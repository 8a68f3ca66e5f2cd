"""Starts services as child processes and stops them cleanly: used by `tether up`, the demo and tests."""

from __future__ import annotations

import contextlib
import logging
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from services.robotlink import KEY_ENV, ensure_key, key_path
from services.runtime import ALL_SERVICES, DUMP_STACKS, SERVICES, NodeSettings
from services.safety.operator import TOKEN_ENV
from tether.runservice import SUPERVISOR_FD_ENV

log = logging.getLogger(__name__)

# The services that sign or check robot commands and heartbeats with the robot key.
KEY_HOLDERS = ("safety", "sim", "ros2")

# Stopped stage by stage, each stage's services together: nothing new is planned; safety goes before
# the robot so its watchdog never sees a robot vanish mid-motion (the robot stops on the missing
# heartbeat); a ROS 2 backend before the robot it drives (the stand-in); the recorder hears it all.
STOP_STAGES = (
    ("planner",),
    ("executor", "parser", "resolver"),
    ("safety",),
    ("sim", "ros2"),
    ("ros2sim",),
    ("recorder",),
)
# How long a service that did not stop gets to write its stacks before it is killed.
STACK_DUMP_WAIT = 0.5
# Stacks for tests and benchmarks listen on ports from here up to the kernel's range for outgoing
# connections. Not inside that range: there one of the sessions' own outgoing sockets could take a
# port between the check and the listen, and a service would fail to start.
LOWEST_PORT = 20000
# A service's log larger than this when the service starts (its restarts after crashes, one run of the
# stack after another, all append to it) becomes `<service>.log.1`, replacing the one before.
LOG_ROTATE_BYTES = 16 * 1024 * 1024


def _outgoing_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_base_port(count: int = len(ALL_SERVICES), band: tuple[int, int] = (0, 1)) -> int:
    """The first of `count` consecutive loopback ports that are free now: a base port for a stack of
    its own (tests, benchmarks), below the range the kernel hands out to outgoing connections.

    `band` (index, of how many) picks from one slice of that range only, so that processes choosing
    at the same moment (parallel test workers) never pick the same ports between check and use."""
    index, bands = band
    if not 0 <= index < bands:
        raise ValueError(f"port band {index} of {bands}: the index must be in 0..{bands - 1}")
    width = (max(LOWEST_PORT + 1, _outgoing_low() - count) - LOWEST_PORT) // bands
    lowest = LOWEST_PORT + index * width
    highest = max(lowest + 1, lowest + width - count)
    for _ in range(200):
        base = random.randrange(lowest, highest)
        try:
            with contextlib.ExitStack() as stack:
                for port in range(base, base + count):
                    stack.enter_context(socket.socket()).bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
    raise RuntimeError(f"no {count} free consecutive loopback ports between {lowest} and {highest}")


# A service that exits again within this long of its start was not well: its next restart waits, twice
# as long each time (from RESTART_DELAY to MAX_RESTART_DELAY), so a service that cannot run (its port
# taken by another stack, a config it refuses) is not restarted twice a second for as long as up runs.
STABLE_AFTER = 60.0
RESTART_DELAY = 1.0
MAX_RESTART_DELAY = 30.0


class Restarts:
    """When `tether up` restarts a service that exited: at once the first time, or after it ran
    STABLE_AFTER; after an exit soon after its start, RESTART_DELAY, doubling up to MAX_RESTART_DELAY.
    Pure: callers pass monotonic `now`."""

    def __init__(self) -> None:
        self._started: dict[str, float] = {}
        self._delay: dict[str, float] = {}

    def started(self, service: str, now: float) -> None:
        self._started[service] = now

    def delay(self, service: str, now: float) -> float:
        """How long to wait before restarting `service`, which exited at `now`."""
        started = self._started.get(service)
        if started is None or now - started >= STABLE_AFTER:
            self._delay.pop(service, None)
            return 0.0
        delay = min(MAX_RESTART_DELAY, 2 * self._delay[service]) if service in self._delay else RESTART_DELAY
        self._delay[service] = delay
        return delay


@contextlib.contextmanager
def _ctrl_c_held() -> Iterator[None]:
    """SIGINT's handler (KeyboardInterrupt) run when the block ends, not inside it: a Ctrl-C while
    services were started or stopped left some running after their supervisor ended (raised in Popen
    after its fork, a service nobody knew of; raised while stopping, the stages after it unsignalled).
    Only the main thread runs handlers, and only it can set them."""
    handler = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or not callable(handler):
        yield
        return
    held: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, _frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)
        if held:
            signal.raise_signal(signal.SIGINT)


class Supervisor:
    """Each service in its own process group, its output in `log_dir/<service>.log`; each stops by
    itself when the process that started it is gone, also when killed before it could stop them.

    Safety and the robot backend share a key (services/robotlink.py): unless the environment names
    one ($TETHER_ROBOT_KEY_FILE), the stack's own, `robot-<robot>.key` (0600) beside the operator
    token when one is named ($TETHER_OPERATOR_TOKEN_FILE, as safety would put it), else in a 0700
    `keys/` directory beside `log_dir`: never in the log directory, which goes into incident reports.
    It is made when the first of safety and the robot backends starts, and only they are told where
    it is (a config's `robot_key_file` wins). Under one Unix user the mode does not keep the other
    services from reading it: only separate users (systemd's DynamicUser) or containers do."""

    def __init__(
        self,
        settings: NodeSettings,
        log_dir: Path,
        config_file: Path | None = None,
        extra_env: dict[str, str] | None = None,
        zenoh_configs: dict[str, Path] | None = None,
    ) -> None:
        self.settings = settings
        # A deployment's services each log in with their own Zenoh config (`tether up --deploy`).
        self.zenoh_configs = zenoh_configs or {}
        self.log_dir = log_dir
        self.config_file = config_file
        self.extra_env = extra_env or {}
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._logs: dict[str, IO[bytes]] = {}
        log_dir.mkdir(parents=True, exist_ok=True)
        self._robot_key_file: Path | None = None
        # A pipe whose write end only this process holds (os.pipe's ends are not inherited): each service
        # gets the read end and stops at its end of file, when this process is gone however it went.
        self._lifeline: tuple[int, int] | None = None

    @property
    def robot_key_file(self) -> Path:
        """Where the robot key is (see the class): fixed at its first use, or set by the caller."""
        if self._robot_key_file is None:
            token = self.extra_env.get(TOKEN_ENV) or os.environ.get(TOKEN_ENV)
            default = Path(token).expanduser().parent if token else self.log_dir.parent / "keys"
            self._robot_key_file = key_path(self.extra_env.get(KEY_ENV), default, self.settings.robot)
        return self._robot_key_file

    @robot_key_file.setter
    def robot_key_file(self, path: Path) -> None:
        self._robot_key_file = path

    def robot_key(self) -> bytes:
        """The key the stack's safety and robot backend share (made if there is none yet): what a test
        that plays safety, or bypasses it as only safety could, signs with."""
        path = self.robot_key_file
        if not path.parent.exists():
            path.parent.mkdir(mode=0o700, parents=True)  # a directory of keys: its owner's only
        return ensure_key(path)

    def env(self, service: str | None = None) -> dict[str, str]:
        env = dict(os.environ)
        env["TETHER_ROBOT"] = self.settings.robot
        env["TETHER_BASE_PORT"] = str(self.settings.base_port)
        if self.settings.zenoh_config is not None:
            env["TETHER_ZENOH_CONFIG"] = str(self.settings.zenoh_config)
        if service in self.zenoh_configs:
            env["TETHER_ZENOH_CONFIG"] = str(self.zenoh_configs[service])
        env.update(self.extra_env)
        # Only safety and the robot backends hold the robot key; nothing else is even told where it
        # is, not by the caller's environment nor by `extra_env`.
        env.pop(KEY_ENV, None)
        if service in KEY_HOLDERS:
            env[KEY_ENV] = str(self.robot_key_file)
        return env

    def start(self, service: str) -> subprocess.Popen[bytes]:
        if service not in ALL_SERVICES:
            raise ValueError(f"unknown service {service!r}; services are {', '.join(ALL_SERVICES)}")
        if service in KEY_HOLDERS:
            self.robot_key()  # made here, before the other holder could race for it
        cmd = [sys.executable, "-m", "tether", "run", service]
        if self.config_file is not None:
            cmd += ["--config", str(self.config_file)]
        out = self._log_file(service)
        if self._lifeline is None:
            self._lifeline = os.pipe()
        env = self.env(service)
        env[SUPERVISOR_FD_ENV] = str(self._lifeline[0])
        with _ctrl_c_held():
            proc = subprocess.Popen(
                cmd,
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                start_new_session=True,
                pass_fds=(self._lifeline[0],),
            )
            self.procs[service] = proc
        log.info("started %s (pid %d)", service, proc.pid)
        return proc

    def _log_file(self, service: str) -> IO[bytes]:
        """The file the service's output goes to, appended to; moved to `.log.1` first when it has grown
        past LOG_ROTATE_BYTES, so a service that crashes and is restarted over and over does not fill
        the disk with its tracebacks."""
        path = self.log_dir / f"{service}.log"
        out = self._logs.get(service)
        if out is not None and not out.closed and os.fstat(out.fileno()).st_size > LOG_ROTATE_BYTES:
            out.close()
        if out is None or out.closed:
            with contextlib.suppress(FileNotFoundError):
                if path.stat().st_size > LOG_ROTATE_BYTES:
                    path.replace(path.with_name(f"{path.name}.1"))
            out = self._logs[service] = open(path, "ab")  # noqa: SIM115
        return out

    def start_all(self, services: tuple[str, ...] = SERVICES) -> None:
        """Each of `services`; interrupted (Ctrl-C), every service started is stopped before it goes on:
        `tether up` ended while its services went on starting, each until it found its supervisor gone."""
        try:
            for service in services:
                self.start(service)
        except BaseException:
            self.stop_all()
            raise

    def exited(self) -> dict[str, int]:
        """Services whose process has ended, with their exit codes."""
        return {name: code for name, proc in self.procs.items() if (code := proc.poll()) is not None}

    def kill(self, service: str) -> None:
        """SIGKILL, as a crash would: no clean-up runs in the service."""
        proc = self.procs[service]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)

    def stop(self, service: str, timeout: float = 10.0) -> int | None:
        with _ctrl_c_held():
            return self._stop_together((service,), timeout).get(service)

    def _stop_together(self, services: tuple[str, ...], timeout: float) -> dict[str, int | None]:
        """SIGTERM to each, then wait for each (killing one that outlives `timeout`)."""
        procs = {s: self.procs[s] for s in services if s in self.procs}
        for proc in procs.values():
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for service, proc in procs.items():
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s; its stacks to its log, then SIGKILL", service, timeout)
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, DUMP_STACKS)
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        proc.wait(timeout=STACK_DUMP_WAIT)
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)
        return {service: proc.returncode for service, proc in procs.items()}

    def stop_all(self, timeout: float = 10.0) -> dict[str, int | None]:
        """Stage by stage (STOP_STAGES); a Ctrl-C meanwhile (the demo's second) is raised once all stopped."""
        staged = {s for stage in STOP_STAGES for s in stage}
        stages = [*STOP_STAGES, tuple(s for s in self.procs if s not in staged)]
        codes: dict[str, int | None] = {}
        with _ctrl_c_held():
            for stage in stages:
                codes.update(self._stop_together(stage, timeout))
            for out in self._logs.values():
                out.close()
            if self._lifeline is not None:
                for fd in self._lifeline:
                    os.close(fd)
                self._lifeline = None
        return codes

    def log_tail(self, service: str, lines: int = 40) -> str:
        path = self.log_dir / f"{service}.log"
        if not path.exists():
            return ""
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()
