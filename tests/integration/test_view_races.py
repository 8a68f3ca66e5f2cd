"""`tether view --teleop` and a client whose channels it refuses in a loop, seen by another Foxglove client.

No stack: the view needs only its Zenoh session to serve. Foxglove's own client (tests/integration/
foxglove_client) plays both the flooding client and the other viewer."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.runtime import ALL_SERVICES
from tests.integration.test_view import Client, client_script
from tests.sessions import free_ports

FLOOD = 300  # channels advertised at once, each refused


@pytest.fixture
def view_url(tmp_path: Path) -> Iterator[str]:
    base = ["--robot", f"t{uuid.uuid4().hex[:8]}", "--base-port", str(free_ports(len(ALL_SERVICES)))]
    command = [sys.executable, "-m", "tether", *base, "view", "--json", "--teleop", "--port", "0", "--no-arm"]
    log = tmp_path / "view.log"
    with log.open("w") as log_file:
        view = subprocess.Popen(
            [*command, "--camera-rate", "0"], stdout=subprocess.PIPE, stderr=log_file, text=True, start_new_session=True
        )
    try:
        assert view.stdout is not None
        started = json.loads(view.stdout.readline() or "{}")
        assert started.get("ok"), f"tether view did not start: {started}\n{log.read_text()}"
        yield started["url"]
        os.killpg(view.pid, signal.SIGINT)
        assert view.wait(timeout=20) == 0, log.read_text()
    finally:
        if view.poll() is None:
            os.killpg(view.pid, signal.SIGKILL)
            view.wait(timeout=10)
        assert view.stdout is not None
        view.stdout.close()


def test_a_client_refused_in_a_loop_costs_another_viewer_a_few_status_messages(view_url: str) -> None:
    """Each refusal was broadcast as its own status, up to 16 every 20 ms, into every viewer's control
    queue (the SDK disconnects a viewer whose queue of 64 is full)."""
    script = client_script()
    viewer = Client.start(script, "watch", view_url, "60")
    flooder = Client.start(script, "teleop", view_url, "60", stdin=True)
    try:
        for client in (viewer, flooder):
            assert client.wait_for(lambda lines: any("serverInfo" in line for line in lines), 20.0), client.lines
        assert flooder.proc.stdin is not None
        step = {"op": "advertise", "topic": "/other", "encoding": "json", "schemaName": "geometry_msgs/Twist"}
        flooder.proc.stdin.write((json.dumps(step) + "\n") * FLOOD)
        flooder.proc.stdin.flush()
        assert flooder.wait_for(lambda lines: sum("advertised" in line for line in lines) == FLOOD, 20.0)
        last = max(line["advertised"] for line in flooder.lines if "advertised" in line)

        def told(lines: list[dict[str, object]]) -> list[str]:
            return [str(line["status"]) for line in lines if "not taken" in str(line.get("status"))]

        # The latest refusal reaches the other viewer, and with it only a few status messages.
        assert viewer.wait_for(lambda lines: any(f"channel {last} not taken" in s for s in told(lines)), 20.0), told(
            viewer.lines
        )[-3:]
        assert 1 <= len(told(viewer.lines)) <= 8, len(told(viewer.lines))
        assert viewer.proc.poll() is None, "the other viewer was disconnected"
    finally:
        viewer.close()
        flooder.close()
