"""A service process ends without Python's finalization (tether.runservice.leave): a daemon thread still
inside a Zenoh call then cannot abort it.

Python makes a thread that takes the GIL back during finalization exit on the spot; inside a Zenoh call
that exit unwinds through zenoh's Rust frames, which catch it, and glibc aborts ("FATAL: exception not
rethrown", SIGABRT). A recorder stopped just after answering a status query (its query pool's workers
are daemon threads) died so in a CI run. Here a real process runs `run_service` with a service whose
main leaves a daemon thread publishing on a real Zenoh session, and whose main returns, ends with a
config error, fails or exits with a message: on the code before, such a process aborted about seven times in eight."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

# The service's main as the child imports it: a thread in Zenoh calls all along, then the ending given.
CHILD = """
import sys, threading, types
import logging
import zenoh
from services import runtime
from services.runtime import ConfigError, NodeSettings
from tether import runservice

ending = sys.argv[1]

def main(settings, config):
    runtime.configure_logging()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    publisher = session.declare_publisher("tether/exit-test/spin")
    started = threading.Event()

    def spin():
        while True:
            started.set()
            try:
                publisher.put(b"x")
            except zenoh.ZError:
                pass  # the session closed under it: it goes on calling in

    threading.Thread(target=spin, daemon=True).start()
    started.wait()
    session.close()
    # Neither flushed here: leave() must (stdout to a pipe is block-buffered).
    logging.getLogger("exit-test").info("the service logged this")
    print("main returned")
    if ending == "config":
        raise ConfigError("config file x.toml [recorder]: a value out of bounds")
    if ending == "fails":
        raise RuntimeError("the service failed")
    if ending == "exits":
        raise SystemExit("the service gave up")

service = types.ModuleType("services.recorder.main")
service.main = main
sys.modules["services.recorder.main"] = service
runservice.run_service(NodeSettings(robot="exit-test", base_port=20000), "recorder", None)
"""
RUNS = 3
TIMEOUT = 60.0


@pytest.mark.parametrize(
    ("ending", "code", "said"),
    [
        ("returns", 0, "main returned"),
        ("config", 2, "error: config file x.toml"),
        ("fails", 1, "RuntimeError: the service failed"),
        ("exits", 1, "the service gave up"),
    ],
)
def test_a_service_with_a_thread_in_a_zenoh_call_exits_with_its_own_code(ending: str, code: int, said: str) -> None:
    # Output buffered, as a service's is under systemd or the supervisor: what leave() flushes must show.
    env = {name: value for name, value in os.environ.items() if name != "PYTHONUNBUFFERED"}
    for run in range(RUNS):
        done = subprocess.run(
            [sys.executable, "-c", CHILD, ending], capture_output=True, text=True, timeout=TIMEOUT, check=False, env=env
        )
        output = done.stdout + done.stderr
        assert done.returncode != -signal.SIGABRT, f"run {run + 1} aborted:\n{output}"
        assert done.returncode == code, f"run {run + 1} exited with {done.returncode}:\n{output}"
        assert said in output
        assert "main returned" in done.stdout and "the service logged this" in output, output
        assert "FATAL" not in output
