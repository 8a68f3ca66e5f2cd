"""A supervisor (`tether up`) stopped while it is still starting its services: none it started outlives it."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.integration.conftest import STARTUP_TIMEOUT
from tests.procs import children
from tests.sessions import free_ports

# Services quick to start and to stop: the longer starting them takes, the likelier the Ctrl-C lands
# there, between one fork and the next.
SERVICES = "parser,resolver,planner,recorder"
# As `tether up` starts its services: on a Ctrl-C once all are started (waiting for them to come up),
# it stops them.
SUPERVISING = """
import sys, threading
from pathlib import Path
from services.runtime import NodeSettings
from tether.supervisor import Supervisor

supervisor = Supervisor(NodeSettings(robot=sys.argv[1], base_port=int(sys.argv[2])), Path(sys.argv[3]))
supervisor.start_all(tuple(sys.argv[4].split(",")))
try:
    threading.Event().wait(60)
except BaseException:
    supervisor.stop_all()
    raise
"""


def forked(pid: int, service: str) -> int | None:
    """The process `pid` started for `tether run SERVICE`, if it has started it yet."""
    for child in children(pid):
        with contextlib.suppress(OSError):
            argv = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
            if b"run" in argv and service.encode() in argv:
                return child
    return None


def running_for(robot: str) -> set[int]:
    """Live processes (not zombies) whose environment names `robot`: the stack's, wherever they went."""
    marker = f"TETHER_ROBOT={robot}".encode()
    found: set[int] = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdecimal():
            continue
        with contextlib.suppress(OSError):
            if marker in (entry / "environ").read_bytes().split(b"\0"):
                state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
                if state != "Z":
                    found.add(int(entry.name))
    return found


def test_ctrl_c_while_services_start_stops_each_started_before_their_supervisor_ends(tmp_path: Path) -> None:
    """`tether up` ended at once on a Ctrl-C in its first moment, its services running on (one of them
    forked as the Ctrl-C came, so nobody knew of it), each until it found its supervisor gone."""
    robot = f"t{uuid.uuid4().hex[:8]}"
    base_port = free_ports(len(ALL_SERVICES))
    command = [sys.executable, "-c", SUPERVISING, robot, str(base_port), str(tmp_path / "logs"), SERVICES]
    supervising = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path
    )
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while not children(supervising.pid):  # its first service forked: it is forking the others now
            assert time.monotonic() < deadline and supervising.poll() is None, supervising.communicate()[0]
            with contextlib.suppress(subprocess.TimeoutExpired):
                supervising.wait(timeout=0.001)
        os.kill(supervising.pid, signal.SIGINT)  # a terminal's Ctrl-C (a new session has no terminal)
        out, _ = supervising.communicate(timeout=60)

        left = running_for(robot)
        assert not left, f"still running after their supervisor ended: {left}\n{out.decode(errors='replace')}"
        assert supervising.returncode == -signal.SIGINT, out.decode(errors="replace")
    finally:
        if supervising.poll() is None:
            supervising.kill()
            supervising.communicate()
        for pid in running_for(robot):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def test_ctrl_c_while_tether_up_waits_for_its_services_stops_them_before_it_ends(tmp_path: Path) -> None:
    """Once all were started, `tether up` waits for them to come up: a Ctrl-C there ended it at once
    (exit 130), its services left running until each found its supervisor gone."""
    robot = f"t{uuid.uuid4().hex[:8]}"
    base_port = free_ports(len(ALL_SERVICES))
    services = SERVICES.split(",")
    command = [sys.executable, "-m", "tether", "--robot", robot, "--base-port", str(base_port), "up"]
    command += ["--only", SERVICES, "--log-dir", str(tmp_path / "logs")]
    first_alive = threading.Event()
    up = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    held: int | None = None
    try:
        with Node("cli", NodeSettings(robot=robot, base_port=base_port)) as watcher:
            for service in services:
                watcher.watch_alive(service, lambda alive: first_alive.set() if alive else None)
            # The last service held (SIGSTOP) as soon as it is forked, a second or more before it could
            # have imported and come up: `up` is still waiting for it when the Ctrl-C comes, however
            # quickly the others came up (on a loaded machine they all did before the Ctrl-C landed).
            deadline = time.monotonic() + STARTUP_TIMEOUT
            while held is None:
                assert time.monotonic() < deadline and up.poll() is None, up.communicate()[0]
                held = forked(up.pid, services[-1])
            os.kill(held, signal.SIGSTOP)
            # One service up: `up` has started them all and waits for the others.
            while not first_alive.wait(0.01):
                assert time.monotonic() < deadline and up.poll() is None, up.communicate()[0]
            os.kill(up.pid, signal.SIGINT)
            os.kill(held, signal.SIGCONT)  # to stop as it is told
        out, _ = up.communicate(timeout=60)
        left = running_for(robot)
        assert not left, f"still running after tether up ended: {left}\n{out.decode(errors='replace')}"
        assert up.returncode != 0, out.decode(errors="replace")
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
        for pid in running_for(robot):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
