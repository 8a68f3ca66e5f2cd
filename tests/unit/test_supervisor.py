"""Stopping services: a service that ignores SIGTERM leaves its stacks in its log and is killed."""

from __future__ import annotations

import signal
import subprocess
import sys
import uuid
from pathlib import Path

from services.runtime import NodeSettings
from tether.supervisor import Supervisor

# A "service" stuck where SIGTERM cannot reach it: the runtime's handlers, then SIGTERM ignored.
STUCK = """
import signal, time
from services.runtime import stop_event
stop_event()
signal.signal(signal.SIGTERM, signal.SIG_IGN)
print("ready", flush=True)
def stuck_here():
    time.sleep(60)
stuck_here()
"""


def test_a_service_that_does_not_stop_is_killed_after_writing_its_stacks_to_its_log(tmp_path: Path) -> None:
    supervisor = Supervisor(NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}"), tmp_path / "logs", None)
    log = (tmp_path / "logs" / "executor.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-c", STUCK], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    supervisor.procs["executor"] = proc
    try:
        for _ in range(200):  # up to 10 s for the interpreter to start
            if "ready" in supervisor.log_tail("executor"):
                break
            try:
                proc.wait(timeout=0.05)
            except subprocess.TimeoutExpired:
                continue
        assert "ready" in supervisor.log_tail("executor"), supervisor.log_tail("executor")

        code = supervisor.stop("executor", timeout=0.5)

        assert code == -signal.SIGKILL
        logged = supervisor.log_tail("executor")
        assert "stuck_here" in logged and "Current thread" in logged, logged
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()
