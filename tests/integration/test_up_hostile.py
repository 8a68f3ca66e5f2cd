"""`tether up` and its services as real processes, when things around them go wrong: `up` killed with
SIGKILL, a notify socket nobody reads, a service port someone else holds."""

from __future__ import annotations

import contextlib
import itertools
import os
import queue
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from schemas import keys
from schemas.safety import SafetyStatus
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.integration.conftest import STARTUP_TIMEOUT, dump_logs, write_config
from tests.sessions import free_ports
from tether.supervisor import Supervisor

# Longer than a service takes to stop on SIGTERM, shorter than its supervisor waits before SIGKILL.
STOP_WAIT = 8.0


def settings() -> NodeSettings:
    return NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))


def children(pid: int) -> set[int]:
    """The processes `pid` started (any of its threads), from /proc."""
    found: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            found |= {int(child) for child in (task / "children").read_text().split()}
    return found


def test_the_services_stop_when_tether_up_is_killed(tmp_path: Path) -> None:
    stack = settings()
    env = dict(os.environ, TETHER_ROBOT=stack.robot, TETHER_BASE_PORT=str(stack.base_port))
    command = [sys.executable, "-m", "tether", "up", "--only", "parser,resolver", "--log-dir", str(tmp_path / "logs")]
    up = subprocess.Popen(
        command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    lines: queue.Queue[str] = queue.Queue()
    output = up.stdout
    assert output is not None

    def read() -> None:
        for line in output:
            lines.put(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    services: dict[int, int] = {}  # pid: a pidfd, to wait on and signal what is surely that process
    said: list[str] = []
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while not any("all services up" in line for line in said):
            left = deadline - time.monotonic()
            assert left > 0 and up.poll() is None, "".join(said)
            with contextlib.suppress(queue.Empty):
                said.append(lines.get(timeout=left))
        services = {pid: os.pidfd_open(pid) for pid in children(up.pid)}
        assert len(services) == 2, services

        os.kill(up.pid, signal.SIGKILL)  # no handler runs: as the OOM killer or `kill -9` ends it
        up.wait(timeout=10)

        deadline = time.monotonic() + 2 * STOP_WAIT
        for pid, pidfd in services.items():
            ended, _, _ = select.select([pidfd], [], [], max(0.0, deadline - time.monotonic()))
            assert ended, f"service pid {pid} still runs without its `tether up`"
        for service in ("parser", "resolver"):
            log = (tmp_path / "logs" / f"{service}.log").read_text()
            assert "supervisor that started this service is gone" in log, log
            assert "received SIGTERM" in log, log
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
        reader.join(timeout=10)  # at the pipe's end, now that `up` is gone
        output.close()
        for pidfd in services.values():
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(pidfd, signal.SIGKILL)
            os.close(pidfd)


def fill(path: str) -> socket.socket:
    """Datagrams to the socket at `path` until its queue takes no more; the sender, to close later."""
    sender = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sender.setblocking(False)
    with contextlib.suppress(BlockingIOError):
        for _ in range(100_000):
            sender.sendto(b"STATUS=filler", path)
    return sender


def logged(supervisor: Supervisor, service: str, text: str) -> None:
    """Wait, while `service` runs, until its log holds `text`."""
    deadline = time.monotonic() + STARTUP_TIMEOUT
    while text not in supervisor.log_tail(service):
        assert time.monotonic() < deadline and supervisor.procs[service].poll() is None, supervisor.log_tail(service)
        with contextlib.suppress(subprocess.TimeoutExpired):
            supervisor.procs[service].wait(timeout=0.05)


def test_a_notify_socket_nobody_reads_does_not_keep_a_service_from_stopping(tmp_path: Path) -> None:
    # A service manager that hangs (or a socket left bound by something finished) reads nothing.
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as deaf:
        deaf.bind(path)
        sender = fill(path)
        stack = settings()
        env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"}
        supervisor = Supervisor(stack, tmp_path / "logs", extra_env=env)
        try:
            supervisor.start("parser")
            with Node("cli", stack) as node:
                assert not node.wait_alive(["parser"], STARTUP_TIMEOUT), supervisor.log_tail("parser")
            logged(supervisor, "parser", "cannot notify the service manager")

            code = supervisor.stop("parser", timeout=STOP_WAIT)

            assert code == 0, f"parser exited with {code}, not on its own SIGTERM:\n{supervisor.log_tail('parser')}"
        except BaseException:
            dump_logs(supervisor, ("parser",))
            raise
        finally:
            supervisor.stop_all()
            sender.close()


BEATS = 50  # safety beats at 50 Hz


@pytest.mark.realtime
def test_safety_beats_on_while_its_notify_socket_takes_no_more(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as deaf:
        deaf.bind(path)
        sender = fill(path)
        stack = settings()
        config = write_config(tmp_path / "tether.toml", realtime_factor=1.0, strict_timing=True)
        env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "400000"}  # fed from the heartbeat's loop every 0.2 s
        supervisor = Supervisor(stack, tmp_path / "logs", config, extra_env=env)
        beats: list[float] = []
        enough = threading.Event()

        def on_beat(_status: SafetyStatus) -> None:
            beats.append(time.monotonic())
            if len(beats) >= BEATS:
                enough.set()

        try:
            supervisor.start("safety")
            with Node("cli", stack) as node:
                assert not node.wait_alive(["safety"], STARTUP_TIMEOUT), supervisor.log_tail("safety")
                logged(supervisor, "safety", "cannot notify the service manager")
                subscription = node.subscribe(keys.HEARTBEAT, on_beat)
                try:
                    assert enough.wait(20.0), f"{len(beats)} heartbeats in 20 s"
                finally:
                    subscription.undeclare()
            gaps = [later - earlier for earlier, later in itertools.pairwise(beats)]
            assert max(gaps) < 0.5, f"the heartbeat stalled for {max(gaps):.2f} s"
        except BaseException:
            dump_logs(supervisor, ("safety",))
            raise
        finally:
            supervisor.stop_all()
            sender.close()


def test_a_service_whose_port_is_taken_names_the_port_and_who_holds_it(tmp_path: Path) -> None:
    stack = settings()
    port = stack.base_port + ALL_SERVICES.index("parser")
    with socket.socket() as held:
        held.bind(("127.0.0.1", port))
        held.listen()
        supervisor = Supervisor(stack, tmp_path / "logs")
        try:
            code = supervisor.start("parser").wait(timeout=STARTUP_TIMEOUT)
        finally:
            supervisor.stop_all()
    said = supervisor.log_tail("parser")
    assert code == 1, said
    assert f"error: parser cannot listen on tcp/127.0.0.1:{port}: the port is in use by pid {os.getpid()} (" in said
    assert "Traceback" not in said, said
