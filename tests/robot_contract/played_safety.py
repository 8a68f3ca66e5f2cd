"""Safety's heartbeat played by a process of its own, for the robot contract suite and the ROS 2 tests.

The heartbeat has to keep its period while the test's own process is busy: a thread there shares
the test's GIL, and a goal sent over Zenoh on two loaded cores held it for over 200 ms, long enough
for the robot to stop as it should when safety goes quiet. So the beating is done here, and the test
drives it over this process's stdin and hears every beat on its stdout, one JSON object a line.

    python -m tests.robot_contract.played_safety ROBOT BASE_PORT KEY_FILE (beating|silent)

KEY_FILE holds the robot key safety signs with (services/robotlink.read_key). From the test:
{"set": {...}} (the heartbeat's fields from the next beat on), {"silence": true}, {"close": true}.
To the test: {"ready": true}, {"acked": N} for the Nth command, {"beat": sent, "stamp": s,
"applied": N or null} for each heartbeat sent, N when it is the first to carry command N, a "set".
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from schemas import keys
from schemas.safety import EstopState, SafetyStatus
from services.robotlink import Signer, read_key
from services.runtime import Node, NodeSettings
from services.safety.config import SafetyConfig

HEARTBEAT_PERIOD = 1.0 / SafetyConfig().heartbeat_hz  # as often as safety beats by default
START_TIMEOUT = 30.0
REPLY_TIMEOUT = 5.0
ROOT = Path(__file__).resolve().parents[2]


class PlayedSafety:
    """The test in safety's place: the only writer of the heartbeat, every HEARTBEAT_PERIOD, carrying
    whatever `set` last said; `silence` stops it as a crashed safety would. Times are wall (Unix)
    seconds, as the robot's stamps are. The beats come from a child process (see the module)."""

    def __init__(self, settings: NodeSettings, key_file: Path, *, beating: bool = True) -> None:
        self._changed = threading.Condition()
        self.sent = 0
        self.last_sent = 0.0  # the stamp of the latest heartbeat
        self._applied: float | None = None  # the stamp of the first heartbeat carrying what `set` last said
        self._latest_set = 0  # the number of the latest "set" command
        self._commands = 0  # sent to the child
        self._acked = 0  # of those, how many it has taken
        self._replies: dict[int, dict[str, Any]] = {}  # by command number, until _command takes it
        self._ready = False
        argv = [sys.executable, "-m", __name__, settings.robot, str(settings.base_port), str(key_file)]
        argv.append("beating" if beating else "silent")
        self._proc = subprocess.Popen(argv, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._stdin: IO[str] = self._proc.stdin
        self._reader = threading.Thread(target=self._read, args=(self._proc.stdout,), name="played-safety", daemon=True)
        self._reader.start()
        try:
            with self._changed:
                if not self._changed.wait_for(lambda: self._ready or self._proc.poll() is not None, START_TIMEOUT):
                    raise RuntimeError(f"the played safety did not start within {START_TIMEOUT:g} s")
                if not self._ready:
                    raise RuntimeError(f"the played safety exited with {self._proc.returncode} before it was ready")
        except BaseException:
            self.close()
            raise

    def _write(self, line: str) -> None:
        self._stdin.write(line + "\n")
        self._stdin.flush()

    def _read(self, out: IO[str]) -> None:
        for line in out:
            message = json.loads(line)
            with self._changed:
                if "beat" in message:
                    self.sent, self.last_sent = message["beat"], message["stamp"]
                    if message["applied"] is not None and message["applied"] == self._latest_set:
                        self._applied = message["stamp"]
                elif "acked" in message:
                    self._acked = message["acked"]
                    self._replies[self._acked] = message
                elif "ready" in message:
                    self._ready = True
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def _command(self, command: dict[str, Any]) -> dict[str, Any]:
        """Send `command` and wait until the child has taken it; its reply."""
        with self._changed:
            self._commands += 1
            number = self._commands
            self._write(json.dumps(command))
            if not self._changed.wait_for(lambda: self._acked >= number, REPLY_TIMEOUT):
                raise RuntimeError(f"the played safety did not take {command} within {REPLY_TIMEOUT:g} s")
            return self._replies.pop(number)

    def set(
        self,
        *,
        beating: bool = True,
        latched: bool = False,
        speed_scale: float = 1.0,
        max_linear_speed: float | None = None,
        max_angular_speed: float | None = None,
    ) -> None:
        """From the next heartbeat on (none at all when not `beating`)."""
        state = {"beating": beating, "latched": latched, "speed_scale": speed_scale}
        state |= {"max_linear_speed": max_linear_speed, "max_angular_speed": max_angular_speed}
        with self._changed:
            self._applied, self._latest_set = None, self._commands + 1
            self._command({"set": state})

    def silence(self) -> float:
        """Stop the heartbeat; the stamp of the last one that went out."""
        return float(self._command({"silence": True})["last"])

    @property
    def applied(self) -> float:
        """The stamp of the first heartbeat carrying what `set` last said (waits briefly for it)."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._applied is not None, REPLY_TIMEOUT):
                raise RuntimeError("no heartbeat carried the played safety's latest state")
            assert self._applied is not None
            return self._applied

    def beats(self, count: int, timeout: float = 5.0) -> bool:
        """Wait until `count` more heartbeats have gone out with the state as now set."""
        with self._changed:
            target = self.sent + count
            return self._changed.wait_for(lambda: self.sent >= target, timeout)

    def close(self) -> None:
        if self._proc.poll() is None:
            try:
                self._write(json.dumps({"close": True}))
                self._proc.wait(REPLY_TIMEOUT)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait(REPLY_TIMEOUT)
        self._stdin.close()
        self._reader.join(REPLY_TIMEOUT)
        if self._proc.stdout is not None:
            self._proc.stdout.close()


class _Beating:
    """The child's side: one heartbeat every period, commands taken between beats."""

    def __init__(self, node: Node, beating: bool) -> None:
        self.node = node
        self.state: dict[str, Any] = {"beating": beating, "latched": False, "speed_scale": 1.0}
        self.state |= {"max_linear_speed": None, "max_angular_speed": None}
        self.sent = 0
        self.last_sent = 0.0
        self.fresh: int | None = None  # the next beat is the first with this "set" command
        self.commands = 0

    def take(self, command: dict[str, Any]) -> bool:
        """Act on one command and acknowledge it; False for close."""
        if command.get("close"):
            return False
        self.commands += 1
        reply: dict[str, Any] = {"acked": self.commands}
        if "set" in command:
            self.state = dict(command["set"])
            self.fresh = self.commands
        elif command.get("silence"):
            self.state["beating"] = False
            reply["last"] = self.last_sent
        _say(reply)
        return True

    def beat(self) -> None:
        if not self.state["beating"]:
            return
        state = self.state
        status = SafetyStatus(
            seq=self.sent,
            stamp=time.time(),
            estop=EstopState(latched=state["latched"], source="operator", reason="contract test"),
            speed_scale=state["speed_scale"],
            speed_reason="contract test",
            max_linear_speed=state["max_linear_speed"],
            max_angular_speed=state["max_angular_speed"],
        )
        self.node.publish(keys.HEARTBEAT, status)
        self.sent += 1
        self.last_sent = status.stamp
        _say({"beat": self.sent, "stamp": status.stamp, "applied": self.fresh})
        self.fresh = None


def _say(message: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(message) + "\n")
    sys.stdout.flush()


def main(argv: list[str]) -> int:
    robot, base_port, key_file, mode = argv
    fd = sys.stdin.fileno()
    pending = b""
    node = Node("cli", NodeSettings(robot=robot, base_port=int(base_port)))
    try:
        node.signer = Signer(read_key(Path(key_file)))
        beating = _Beating(node, mode == "beating")
        _say({"ready": True})
        due = time.monotonic() + HEARTBEAT_PERIOD
        while True:
            wait = due - time.monotonic()
            if wait > 0:
                if select.select([fd], [], [], wait)[0]:
                    chunk = os.read(fd, 65536)
                    if not chunk:
                        return 0  # the test is gone
                    pending += chunk
                    while b"\n" in pending:
                        line, pending = pending.split(b"\n", 1)
                        if not beating.take(json.loads(line)):
                            return 0
                continue
            beating.beat()
            # Late (the machine was busy): the next one a period from now, not a burst to catch up.
            due = max(due + HEARTBEAT_PERIOD, time.monotonic() + HEARTBEAT_PERIOD / 2)
    finally:
        node.close()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
