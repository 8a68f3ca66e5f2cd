"""Real services tell a (test-bound) systemd notify socket they are ready and feed its watchdog; a stopped
safety stops feeding it, so systemd would restart it."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import struct
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from services.runtime import ALL_SERVICES, NodeSettings
from tests.integration.conftest import STARTUP_TIMEOUT, dump_logs, write_config
from tests.sessions import free_ports
from tether.supervisor import Supervisor

# Bounds in wall-clock time: `make test` runs these one at a time at normal priority (tests/suite.py).
pytestmark = pytest.mark.realtime

WATCHDOG_USEC = 400_000  # fed every 0.2 s
SERVICES = ("parser", "safety")
UCRED = struct.Struct("3i")  # pid, uid, gid: what SO_PASSCRED attaches, as systemd reads the sender


@dataclass
class NotifySocket:
    """The socket systemd listens on for a Type=notify service, with each datagram's sender pid."""

    sock: socket.socket
    heard: dict[int, list[tuple[float, str]]] = field(default_factory=dict)

    def receive(self, timeout: float) -> tuple[int, str] | None:
        self.sock.settimeout(max(timeout, 1e-3))
        try:
            data, ancillary, _flags, _addr = self.sock.recvmsg(4096, socket.CMSG_SPACE(UCRED.size))
        except TimeoutError:
            return None
        pid = next(UCRED.unpack(d[: UCRED.size])[0] for lvl, kind, d in ancillary if kind == socket.SCM_CREDENTIALS)
        for line in data.decode().split("\n"):
            self.heard.setdefault(pid, []).append((time.monotonic(), line))
        return pid, data.decode()

    def wait_for(
        self, pid: int, line: str, count: int = 1, timeout: float = STARTUP_TIMEOUT, since: float = 0.0
    ) -> None:
        """Until `pid` has sent `line` `count` times after `since` (monotonic), or fail at the deadline."""
        deadline = time.monotonic() + timeout
        while self.count(pid, line, since) < count:
            left = deadline - time.monotonic()
            assert left > 0, (
                f"{count} x {line} from pid {pid} not heard within {timeout} s: {self.heard.get(pid, [])[-5:]}"
            )
            self.receive(left)

    def count(self, pid: int, line: str, since: float = 0.0) -> int:
        return sum(1 for t, heard in self.heard.get(pid, []) if heard == line and t >= since)

    def listen(self, duration: float) -> None:
        """Take in whatever arrives for `duration` seconds (a bound on waiting for something not to happen)."""
        deadline = time.monotonic() + duration
        while (left := deadline - time.monotonic()) > 0:
            self.receive(left)


@pytest.fixture
def notify(tmp_path: Path) -> Iterator[tuple[NotifySocket, str]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
    path = tmp_path / "notify"
    sock.bind(str(path))
    try:
        yield NotifySocket(sock), str(path)
    finally:
        sock.close()


def stopped(pid: int) -> bool:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "T"


def test_ready_then_watchdog_and_a_stopped_safety_stops_feeding(
    tmp_path: Path, notify: tuple[NotifySocket, str]
) -> None:
    listener, path = notify
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    config = write_config(tmp_path / "tether.toml", realtime_factor=1.0, strict_timing=True)
    env = {
        "NOTIFY_SOCKET": path,
        "WATCHDOG_USEC": str(WATCHDOG_USEC),
        "TETHER_OPERATOR_TOKEN_FILE": str(tmp_path / "operator-token"),
    }
    supervisor = Supervisor(settings, tmp_path / "logs", config, extra_env=env)
    safety_pid: int | None = None
    try:
        supervisor.start_all(SERVICES)
        pids = {service: supervisor.procs[service].pid for service in SERVICES}
        safety_pid = pids["safety"]
        for service, pid in pids.items():
            listener.wait_for(pid, "READY=1")
            ready_at = next(t for t, line in listener.heard[pid] if line == "READY=1")
            listener.wait_for(pid, "WATCHDOG=1", count=3, timeout=5.0, since=ready_at)
            assert any(line.startswith("STATUS=") for _, line in listener.heard[pid]), service

        # A hung safety (SIGSTOP: alive, scheduled never): no more WATCHDOG=1, while the parser's go on.
        os.kill(safety_pid, signal.SIGSTOP)
        deadline = time.monotonic() + 5.0
        while not stopped(safety_pid):
            assert time.monotonic() < deadline, "safety did not stop"
            listener.receive(0.01)
        listener.listen(0.05)  # what was in flight before it stopped
        since = time.monotonic()
        listener.listen(2.5 * WATCHDOG_USEC / 1e6)  # systemd would have restarted it by now
        assert listener.count(safety_pid, "WATCHDOG=1", since) == 0
        assert listener.count(pids["parser"], "WATCHDOG=1", since) >= 2, "the socket still hears the parser"

        os.kill(safety_pid, signal.SIGCONT)
        resumed = time.monotonic()
        listener.wait_for(safety_pid, "WATCHDOG=1", count=2, timeout=5.0, since=resumed)

        supervisor.stop("parser")
        listener.wait_for(pids["parser"], "STOPPING=1", timeout=5.0)
    except BaseException:
        dump_logs(supervisor, SERVICES)
        raise
    finally:
        if safety_pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(safety_pid, signal.SIGCONT)
        supervisor.stop_all()
