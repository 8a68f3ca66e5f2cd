"""`tether replay --live-commands` as a real process, stopped or latched while it runs.

The live robot's safety is a stand-in here (a node named safety, over real Zenoh): it holds a goal's
reply until the test lets it go, which real safety cannot be made to do, and beats a heartbeat the
test latches. What the replay sends is what the stand-in hears.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import pytest
import zenoh

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal, Twist
from schemas.safety import EstopState, SafetyStatus
from schemas.trace import TraceRecord
from services.recorder.mcapfile import Recording
from services.runtime import ALL_SERVICES, Node, NodeSettings, encode
from tests.sessions import free_ports

RECORDED = "incident"
LIVE = "live"
DEADLINE = 20.0


@dataclass
class StandIn:
    """The live robot's safety: what it was asked and sent, and its replies held until `release`."""

    node: Node
    release: threading.Event = field(default_factory=threading.Event)
    goals: list[str] = field(default_factory=list)  # the goal ids asked for, in order
    cancels: list[str] = field(default_factory=list)
    twists: list[Twist] = field(default_factory=list)
    changed: threading.Condition = field(default_factory=threading.Condition)

    def add(self, what: list, value: object) -> None:
        with self.changed:
            what.append(value)
            self.changed.notify_all()

    def heard(self, what: list, count: int) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: len(what) >= count, timeout=DEADLINE)


def trace(time: float, goal_id: str) -> bytes:
    query = SendGoal(goal_id=goal_id, goal=NavigateToPoseGoal(pose=Pose2D(x=1.0, y=1.0)))
    return encode(
        TraceRecord(
            stamp=time,
            service="safety",
            key=keys.CMD_NAVIGATE.send_goal.path,
            duration=0.001,
            query=msgspec.Raw(encode(query)),
            reply=msgspec.Raw(encode(GoalResponse(goal_id=goal_id, accepted=True))),
        )
    )


def recording(path: Path, messages: list[tuple[float, str, bytes]]) -> Path:
    """A recording of robot RECORDED holding `messages` (seconds, key under its prefix, payload)."""
    file = Recording(path, RECORDED)
    for at, key, payload in messages:
        file.record(f"{keys.prefix(RECORDED)}/{key}", payload, log_time=int((1000.0 + at) * 1e9))
    file.finish()
    return path


@pytest.fixture
def safety() -> Iterator[StandIn]:
    with Node("safety", NodeSettings(robot=LIVE, base_port=free_ports(len(ALL_SERVICES)))) as node:
        stand_in = StandIn(node)
        heard = stand_in.add

        def on_goal(query: zenoh.Query) -> None:
            goal_id = msgspec.json.decode(query.payload.to_bytes() if query.payload else b"{}")["goal_id"]
            heard(stand_in.goals, goal_id)
            stand_in.release.wait(DEADLINE)
            query.reply(query.key_expr, encode(GoalResponse(goal_id=goal_id, accepted=True)))

        def on_cancel(query: zenoh.Query) -> None:
            goal_id = msgspec.json.decode(query.payload.to_bytes() if query.payload else b"{}")["goal_id"]
            heard(stand_in.cancels, goal_id)
            query.reply(query.key_expr, b'{"ok":true}')

        prefix = keys.prefix(LIVE)
        node._declared += [
            node.session.declare_queryable(f"{prefix}/{keys.CMD_NAVIGATE.send_goal.path}", on_goal),
            node.session.declare_queryable(f"{prefix}/{keys.CMD_NAVIGATE.cancel_goal.path}", on_cancel),
        ]
        node.subscribe(keys.CMD_VEL, lambda twist: heard(stand_in.twists, twist))
        node.declare_alive()
        try:
            yield stand_in
        finally:
            stand_in.release.set()


def replay(safety: StandIn, file: Path, *args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "TETHER_BASE_PORT": str(safety.node.settings.base_port)}
    env.pop("TETHER_ZENOH_CONFIG", None)
    env.pop("TETHER_ROBOT", None)
    command = [sys.executable, "-m", "tether", "replay", str(file), "--to", LIVE, "--live-commands", *args]
    return subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True)


def ended(process: subprocess.Popen[str]) -> str:
    try:
        _, stderr = process.communicate(timeout=DEADLINE)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        _, stderr = process.communicate()
        raise AssertionError(f"the replay did not end:\n{stderr}") from None
    return stderr


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_a_replay_stopped_while_its_last_goals_are_asked_cancels_them_and_asks_no_more(
    safety: StandIn, tmp_path: Path, stop: signal.Signals
) -> None:
    path = f"_trace/safety/{keys.CMD_NAVIGATE.send_goal.path}"
    file = recording(tmp_path / "goals.mcap", [(0.0, path, trace(0.0, "a")), (0.0, path, trace(0.0, "b"))])
    process = replay(safety, file)
    try:
        # Both at one recorded time: the replay has sent every item and waits for the first goal's answer,
        # the second queued behind it.
        assert safety.heard(safety.goals, 1), "the replay asked no goal"
        process.send_signal(stop)
        safety.release.set()
        stderr = ended(process)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert safety.heard(safety.cancels, 1), f"the goal sent was not canceled:\n{stderr}"
    assert safety.cancels == safety.goals, stderr  # the one goal asked, and no other
    assert "replay stopped" in stderr


def test_a_live_replay_says_when_the_robots_e_stop_latches_and_what_it_sent_meanwhile(
    safety: StandIn, tmp_path: Path
) -> None:
    push = encode(Twist(linear_x=0.2))
    file = recording(tmp_path / "pushes.mcap", [(i * 0.05, keys.CMD_VEL.path, push) for i in range(30)])
    beating = threading.Event()
    latched = threading.Event()

    def beat() -> None:
        seq = 0
        while not beating.wait(0.02):  # safety's heartbeat at 50 Hz
            estop = EstopState(latched=latched.is_set(), source="operator", reason="test")
            safety.node.publish(keys.HEARTBEAT, SafetyStatus(seq=seq, stamp=seq * 0.02, estop=estop))
            seq += 1

    heart = threading.Thread(target=beat)
    heart.start()
    try:
        process = replay(safety, file)
        assert safety.heard(safety.twists, 1), "the replay put no twist"
        latched.set()
        stderr = ended(process)
    finally:
        beating.set()
        heart.join()
    assert process.returncode == 0, stderr
    assert "e-stop latched" in stderr, stderr
    assert "safety refused" in stderr.split("replayed 30 messages", 1)[-1], stderr


def test_a_replay_of_teleop_stopped_midway_stops_the_base(safety: StandIn, tmp_path: Path) -> None:
    push = encode(Twist(linear_x=0.2))
    file = recording(tmp_path / "teleop.mcap", [(i * 0.05, keys.TELEOP_CMD_VEL.path, push) for i in range(200)])
    teleop: list[Twist] = []
    safety.node.subscribe(keys.TELEOP_CMD_VEL, lambda twist: safety.add(teleop, twist))
    process = replay(safety, file)
    try:
        assert safety.heard(teleop, 1), "the replay put no teleop twist"
        process.send_signal(signal.SIGINT)
        stderr = ended(process)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert safety.heard(safety.twists, 1), f"the base was not stopped:\n{stderr}"
    assert safety.twists == [Twist()], stderr
