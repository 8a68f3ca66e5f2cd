"""Stopping services while a Ctrl-C comes in: every service is still stopped, then the Ctrl-C is raised."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import pytest

from services.runtime import NodeSettings
from tether.supervisor import Supervisor

# Safety that takes its time to stop: says it heard SIGTERM, then goes on until it is killed.
SLOW_TO_STOP = """
import signal, sys, time
signal.signal(signal.SIGTERM, lambda *_: print("term", flush=True))
print("ready", flush=True)
while True:
    time.sleep(1)
"""
# The robot: stops on SIGTERM as any process does.
PLAIN = "import time; print('ready', flush=True); time.sleep(60)"


def spawn(code: str) -> subprocess.Popen[bytes]:
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, start_new_session=True)
    assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
    return proc


def test_a_second_ctrl_c_while_the_services_stop_stops_the_later_stages_too(tmp_path: Path) -> None:
    """The demo's finally stops the stack after a Ctrl-C; a second one while safety was stopping ended
    the demo with the robot's process never told to stop."""
    supervisor = Supervisor(NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}"), tmp_path / "logs")
    procs: list[subprocess.Popen[bytes]] = []
    try:
        safety = spawn(SLOW_TO_STOP)
        procs.append(safety)
        sim = spawn(PLAIN)
        procs.append(sim)
        supervisor.procs.update(safety=safety, sim=sim)

        def ctrl_c_once_safety_stops() -> None:
            assert safety.stdout is not None
            if safety.stdout.readline() == b"term\n":
                os.kill(os.getpid(), signal.SIGINT)

        pressing = threading.Thread(target=ctrl_c_once_safety_stops, daemon=True)
        pressing.start()
        with pytest.raises(KeyboardInterrupt):
            supervisor.stop_all(timeout=1.0)
        pressing.join(timeout=10)

        assert safety.poll() is not None, "safety was left running"
        assert sim.poll() == -signal.SIGTERM, "the robot's process was left running"
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
        with contextlib.suppress(KeyboardInterrupt):
            supervisor.stop_all()
