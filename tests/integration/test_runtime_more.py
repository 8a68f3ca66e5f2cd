"""The CLI's client helpers against what others publish on real Zenoh sessions: heartbeats that are not
safety's, or not fresh, never confirm an e-stop."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from schemas import keys
from schemas.safety import EstopSource, EstopState, SafetyStatus
from services import runtime
from services.robotlink import KEY_BYTES, Signer
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.sessions import free_ports
from tether.client import next_message, trigger_estop

WAIT = 10.0
# How often the stand-in for safety beats (safety's own period is of this order).
BEAT_PERIOD = 0.02
CONFIRM_TIMEOUT = 1.0
STALE_BY = 60.0


@pytest.fixture
def settings() -> NodeSettings:
    return NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))


def latched(seq: int, stamp: float) -> SafetyStatus:
    return SafetyStatus(seq=seq, stamp=stamp, estop=EstopState(latched=True, source="operator", reason="forged"))


@contextmanager
def beating(settings: NodeSettings, beat: Callable[[int], SafetyStatus], signer: Signer | None) -> Iterator[None]:
    """A process other than safety publishing `beat(seq)` on the heartbeat, signed when `signer` is given."""
    node = Node("sim", settings)
    node.signer = signer
    publisher = node.publisher(keys.HEARTBEAT)
    stop = threading.Event()

    def run() -> None:
        seq = 0
        while not stop.wait(BEAT_PERIOD):  # the beat's period, not a wait for anything
            seq += 1
            publisher.put(beat(seq))

    thread = threading.Thread(target=run, name="forger", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(WAIT)
        node.close()


@contextmanager
def client(settings: NodeSettings) -> Iterator[Node]:
    with Node("cli", settings) as node:
        # The beats reach this session: what follows is about which of them it takes.
        assert next_message(node, keys.HEARTBEAT, WAIT) is not None, "no heartbeat arrived"
        yield node


def test_an_unsigned_latched_heartbeat_does_not_confirm_an_estop(settings: NodeSettings) -> None:
    with beating(settings, lambda seq: latched(seq, time.time()), None), client(settings) as node:
        assert trigger_estop(node, EstopSource.OPERATOR, "stop", timeout=CONFIRM_TIMEOUT) is None


def test_a_stale_latched_heartbeat_does_not_confirm_an_estop(settings: NodeSettings) -> None:
    signer = Signer(bytes(KEY_BYTES))
    with beating(settings, lambda seq: latched(seq, time.time() - STALE_BY), signer), client(settings) as node:
        assert trigger_estop(node, EstopSource.OPERATOR, "stop", timeout=CONFIRM_TIMEOUT) is None


def test_a_fresh_signed_latched_heartbeat_confirms_an_estop(settings: NodeSettings) -> None:
    signer = Signer(bytes(KEY_BYTES))
    with beating(settings, lambda seq: latched(seq, time.time()), signer), client(settings) as node:
        status = trigger_estop(node, EstopSource.OPERATOR, "stop", timeout=WAIT)
        assert status is not None and status.estop.latched


def test_a_service_waiting_for_a_router_that_is_down_says_so_and_stops_at_once_on_sigterm(tmp_path: Path) -> None:
    """Blocked in zenoh.open (a deployment's client config waits for its router), the service never ran
    its SIGTERM handler: silent, it outlived every stop until systemd or `tether up` killed it."""
    config = tmp_path / "parser.json5"
    endpoint = f"tcp/127.0.0.1:{free_ports(1)}"  # nothing listens there
    # As a deployment's service config has it (tether/deployment.py SERVICE_CONNECT): wait for the router.
    connect = {"endpoints": [endpoint], "timeout_ms": -1, "exit_on_failure": False}
    config.write_text(json.dumps({"mode": "client", "connect": connect}))
    log = tmp_path / "parser.log"
    env = {**os.environ, "TETHER_ZENOH_CONFIG": str(config)}
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tether", "run", "parser"], stdout=out, stderr=subprocess.STDOUT, env=env
        )
    try:
        deadline = time.monotonic() + WAIT + runtime.OPEN_NOTICE
        while "no Zenoh session after" not in log.read_text(errors="replace"):
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text(errors="replace")
            time.sleep(0.05)  # polling its log, within the deadline above
        assert endpoint in log.read_text(errors="replace")
        stopped = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=WAIT) == 0, log.read_text(errors="replace")
        assert time.monotonic() - stopped < 2.0, "the stop waited for something"
        assert "stopped while its Zenoh session was opening" in log.read_text(errors="replace")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT)
