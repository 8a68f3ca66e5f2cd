"""The operator's tools on real processes (a review): `tether view` driving from Foxglove, closed by
its terminal, tells the robot to stop; `tether mode` with a token file that holds no token says so;
`tether teleop` takes no key typed before it took the terminal for a command."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from schemas import keys
from schemas.robot import Twist
from schemas.safety import SafetyEvent
from tests.fastsim import FAST_SIM
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli
from tests.integration.test_view import Client, client_script
from tether.teleop import CLEAR_LINE, FOCUS_ON
from tether.viewteleop import DEADMAN, TELEOP_TOPIC


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    s = start_stack(tmp_path_factory.mktemp("operator"), 1.0, services=("sim", "safety"), sim_options=FAST_SIM)
    try:
        yield s
    finally:
        stop_stack(s)


class Twists:
    """The twists that reached safety on cmd/teleop/cmd_vel (each is decided and reported on safety/events),
    each with when it was reported (monotonic)."""

    def __init__(self) -> None:
        self.items: list[tuple[float, Twist]] = []
        self._cond = threading.Condition()

    def __call__(self, event: SafetyEvent) -> None:
        if event.key != keys.TELEOP_CMD_VEL.path or "requested_mps" not in event.values:
            return
        twist = Twist(linear_x=event.values["requested_mps"], angular_z=event.values["requested_rps"])
        with self._cond:
            self.items.append((time.monotonic(), twist))
            self._cond.notify_all()

    def wait(self, test: Any, timeout: float) -> tuple[float, Twist] | None:
        """The first (when, twist) that passes `test`, waited for up to `timeout` seconds; None if none came."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while (found := next((item for item in self.items if test(*item)), None)) is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(min(left, 0.2))
        return found


def test_the_view_closed_by_its_terminal_while_driving_tells_the_robot_to_stop(stack: Stack, tmp_path: Path) -> None:
    script = client_script()
    log = (tmp_path / "view.log").open("w")
    heard = Twists()
    subscription = stack.node.subscribe(keys.SAFETY_EVENTS, heard)
    args = ["--json", "--teleop", "--port", "0", "--no-arm", "--camera-rate", "0"]
    view = subprocess.Popen(
        [sys.executable, "-m", "tether", "view", *args],
        env=stack.supervisor.env(),
        stdout=subprocess.PIPE,
        stderr=log,
        text=True,
        start_new_session=True,
    )
    client: Client | None = None
    try:
        assert view.stdout is not None
        started = json.loads(view.stdout.readline() or "{}")
        assert started.get("teleop") == TELEOP_TOPIC, started
        client = Client.start(script, "teleop", started["url"], "120", stdin=True)
        assert client.wait_for(lambda lines: any("serverInfo" in line for line in lines), 20.0), client.lines
        channel = client.step(
            "advertise", "advertised", topic=TELEOP_TOPIC, encoding="json", schemaName="geometry_msgs/Twist"
        )
        forward = {"linear": {"x": 0.2, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}
        # The panel's button held for long: the view is driving when its terminal closes.
        assert client.proc.stdin is not None
        client.proc.stdin.write(
            json.dumps({"op": "publish", "channel": channel["advertised"], "message": forward, "hz": 10, "seconds": 60})
            + "\n"
        )
        client.proc.stdin.flush()
        assert heard.wait(lambda at, t: t.linear_x == 0.2, 20.0) is not None, (
            "the view never drove",
            heard.items[-3:],
            client.lines[-5:],
        )
        os.kill(view.pid, signal.SIGHUP)
        hung_up = time.monotonic()
        code = view.wait(timeout=30)
        stop = heard.wait(lambda at, t: at >= hung_up and t == Twist(), 5.0)
        # At once, as `tether teleop` does on SIGHUP, not once the robot's own timeout lets the twist go;
        # and nothing moving after it.
        assert stop is not None, f"no stop after SIGHUP (exit {code}); last: {heard.items[-3:]}"
        assert stop[0] - hung_up < DEADMAN, stop[0] - hung_up
        assert heard.items[-1][1].linear_x == 0.0, heard.items[-3:]
        assert code == 0, (code, (tmp_path / "view.log").read_text()[-2000:])
    finally:
        subscription.undeclare()
        if client is not None:
            client.close()
        if view.poll() is None:
            os.killpg(view.pid, signal.SIGKILL)
            view.wait(timeout=10)
        if view.stdout is not None:
            view.stdout.close()
        log.close()


def test_mode_with_a_token_file_that_holds_no_token_is_refused_naming_it(stack: Stack, tmp_path: Path) -> None:
    # A wrong file given as the token (a certificate, a key): longer than any token safety takes.
    wrong = tmp_path / "client.pem"
    wrong.write_text("-----BEGIN CERTIFICATE-----\n" + "A" * 600 + "\n-----END CERTIFICATE-----\n")
    for args in (["mode", "direct"], ["approve", "0123456789abcdef"]):
        done = tether_cli(stack, *args, "--token-file", str(wrong), "--json")
        reply = json.loads(done.stdout)
        # Safety reached and answering is not "safety unreachable" (exit 3): the token is what is wrong.
        assert (done.returncode, reply["ok"]) == (2, False), (args, done.returncode, reply)
        assert "token" in reply["error"], reply
    # tether reset the same (its own document: status no_token).
    done = tether_cli(stack, "reset", "--token-file", str(wrong), "--json")
    reply = json.loads(done.stdout)
    assert (done.returncode, reply["status"]) == (2, "no_token"), (done.returncode, reply)
    assert "holds no token" in reply["message"] and "$.token" in reply["message"], reply
    beat = tether_cli(stack, "mode", "--json")
    assert json.loads(beat.stdout)["mode"] == "autonomous", beat.stdout


def test_a_key_typed_before_teleop_took_the_terminal_does_not_drive(stack: Stack) -> None:
    """A key pressed while teleop starts (it waits for safety's heartbeat first) is no command: it
    sat in the terminal's line buffer, and was read as a press once the terminal went raw."""
    master, terminal = os.openpty()
    os.write(master, b"w")  # typed ahead, before teleop even runs
    teleop = subprocess.Popen(
        [sys.executable, "-m", "tether", "teleop"],
        env=stack.supervisor.env(),
        stdin=terminal,
        stdout=terminal,
        stderr=terminal,
        start_new_session=True,
    )
    os.close(terminal)
    shown = bytearray()
    cond = threading.Condition()

    def read() -> None:
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # the terminal's last user closed it
                data = b""
            with cond:
                shown.extend(data)
                cond.notify_all()
            if not data:
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()

    def lines_drawn() -> list[bytes]:
        started = shown.find(FOCUS_ON.encode())
        return [] if started < 0 else shown[started:].split(CLEAR_LINE.encode())[1:]

    try:
        with cond:
            # Two lines drawn after teleop took the terminal: its loop has read what was waiting.
            assert cond.wait_for(lambda: len(lines_drawn()) >= 2, timeout=60.0), bytes(shown[-500:])
            drawn = [line.decode(errors="replace") for line in lines_drawn()]
        assert all(line.startswith("cmd +0.00 m/s +0.00 rad/s") for line in drawn), drawn
        os.write(master, b"q")
        assert teleop.wait(timeout=30) == 0
        with cond:
            assert cond.wait_for(lambda: b"teleop ended" in shown, timeout=10.0), bytes(shown[-500:])
            ended = shown[shown.find(b"teleop ended") :].decode(errors="replace")
        assert ended.startswith("teleop ended (quit): 0 twists sent"), ended
    finally:
        if teleop.poll() is None:
            os.killpg(teleop.pid, signal.SIGKILL)
            teleop.wait(timeout=10)
        os.close(master)
        reader.join(timeout=10)
