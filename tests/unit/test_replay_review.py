"""Recheck against safety's own gate: the gate decides commands on a fake clock, what safety would
publish (its state, events and goal traces) is written to a real MCAP file, and recheck of that file
must decide every command as the gate did."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgspec
import pytest

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryGoal,
    JointState,
    NavigateToPoseGoal,
    Odometry,
    TrajectoryPoint,
    Twist,
)
from schemas.safety import Rule
from schemas.trace import TraceRecord
from schemas.world import PerceivedHumans
from services.recorder.mcapfile import Recording
from services.recorder.reader import read_recording
from services.robotmodel import ArmModel
from services.runtime import encode
from services.safety.gate import GateEvent, Ruling, SafetyGate
from services.safety.latch import EstopLatch
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.safety.recheck import Message, RecheckOutcome, recheck
from services.worldmodel import WorldModel, load_world

WORLD = load_world()
ROBOT = "gated"
HERE = Pose2D(x=6.0, y=1.2)
TICK = 0.02
WALL = 1_700_000_000.0  # the wall clock's offset from the gate's: both move together here


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    arm = ArmModel(WORLD.robot.arm_urdf)
    return SafetyPolicy(WorldModel(WORLD), load_policy(None, WORLD.robot, arm, WORLD.keep_out), arm)


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Session:
    """The gate as safety's node drives it, with the traffic safety's recorder would write."""

    def __init__(self, policy: SafetyPolicy, path: Path) -> None:
        self.clock = Clock()
        self.gate = SafetyGate(policy, EstopLatch("token"), self.clock, lambda: WALL + self.clock.now)
        self.path = path
        self.file = Recording(path, ROBOT)
        # Each command: its key, the gate's decision and the rule that refused it.
        self.decided: list[tuple[str, RecheckOutcome, Rule | None]] = []
        self.beats = 0

    def put(self, path: str, value: object) -> None:
        self.file.record(f"{keys.prefix(ROBOT)}/{path}", encode(value), log_time=int(self.clock.now * 1e9))

    def events(self, events: tuple[GateEvent, ...]) -> None:
        for e in events:
            command = msgspec.Raw(encode(e.command) if e.command is not None else b"null")
            event = dict(stamp=WALL + self.clock.now, key=e.key, decision=e.decision, reason=e.reason, rule=e.rule)
            self.put(keys.SAFETY_EVENTS.path, {**event, "values": e.values, "command": command})

    def run(self, seconds: float, linear: float = 0.0, pose: Pose2D = HERE, odometry: bool = True) -> None:
        """`seconds` of state at 50 Hz: odometry (unless not `odometry`), joint states and heartbeats."""
        for _ in range(round(seconds / TICK)):
            self.clock.now += TICK
            if odometry:
                message = Odometry(stamp=self.clock.now, sim_time=0.0, pose=pose, linear_x=linear, angular_z=0.0)
                self.gate.odometry(message)
                self.put(keys.ODOM.path, message)
            home = list(WORLD.robot.home_joints)
            joints = JointState(stamp=self.clock.now, name=list(ARM_JOINTS), position=home, velocity=[0.0] * 6)
            self.gate.joint_state(joints)
            self.put(keys.JOINT_STATES.path, joints)
            self.events(self.gate.tick().events)
            self.put(keys.HEARTBEAT.path, self.gate.status(self.beats, WALL + self.clock.now))
            self.beats += 1

    def cmd_vel(self, speed: float) -> None:
        ruling = self.gate.cmd_vel(Twist(linear_x=speed))
        self.events(ruling.events)
        event = ruling.events[0]
        self.decided.append((keys.CMD_VEL.path, RecheckOutcome(event.decision.value), event.rule))

    def goal(self, path: str, ruling: Ruling[Any], request: SendGoal[Any]) -> None:
        self.events(ruling.events)
        refused = ruling.forward if isinstance(ruling.forward, GoalResponse) else None
        reply = refused or GoalResponse(goal_id=request.goal_id, accepted=True)
        trace = TraceRecord(
            stamp=WALL + self.clock.now,
            service="safety",
            key=path,
            duration=0.0,
            query=msgspec.Raw(encode(request)),
            reply=msgspec.Raw(encode(reply)),
        )
        self.put(f"_trace/safety/{path}", trace)
        rule = ruling.events[0].rule if refused else None
        self.decided.append((path, RecheckOutcome.VETOED if refused else RecheckOutcome.APPROVED, rule))

    def navigate(self, goal_id: str, to: Pose2D) -> None:
        request = SendGoal(goal_id=goal_id, goal=NavigateToPoseGoal(pose=to, max_speed=0.45))
        self.goal(keys.CMD_NAVIGATE.send_goal.path, self.gate.navigate(request), request)

    def trajectory(self, goal_id: str) -> None:
        home = list(WORLD.robot.home_joints)
        goal = FollowJointTrajectoryGoal(
            joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=home, time_from_start=2.0)]
        )
        request = SendGoal(goal_id=goal_id, goal=goal)
        self.goal(keys.CMD_TRAJECTORY.send_goal.path, self.gate.trajectory(request), request)

    def rechecked(self, policy: SafetyPolicy) -> list[tuple[str, RecheckOutcome, Rule | None]]:
        self.file.finish()
        root = keys.prefix(ROBOT) + "/"
        recording = read_recording(self.path)
        messages = [Message(m.log_time / 1e9, m.key[len(root) :], m.data, m.attachment) for m in recording.messages]
        report = recheck(messages, policy, robot=ROBOT)
        assert not report.differences, report.differences
        return [(c.key, c.now, c.now_rule) for c in report.checked]


def test_recheck_decides_a_recording_of_safetys_gate_as_the_gate_did(policy: SafetyPolicy, tmp_path: Path) -> None:
    session = Session(policy, tmp_path / "gated.mcap")
    session.run(0.2)
    session.cmd_vel(0.45)  # no one reported yet: at the reduced speed near people
    session.gate.humans(PerceivedHumans(stamp=0.0, humans=[]))
    session.run(0.2)
    session.cmd_vel(0.45)
    session.cmd_vel(5.0)
    session.navigate("a", Pose2D(x=6.4, y=1.2))
    session.navigate("b", Pose2D(x=11.2, y=8.0))  # the stairs
    session.run(0.2, linear=0.3)
    session.trajectory("c")  # the base moving
    session.run(0.2)
    session.trajectory("d")
    session.run(2.0, odometry=False)
    session.cmd_vel(0.2)  # the pose stale
    session.trajectory("e")
    decided = session.decided
    assert {outcome for _, outcome, _ in decided} == {RecheckOutcome.APPROVED, RecheckOutcome.VETOED}
    # Each in the order safety decided it (recheck lists them by time), refused by the same rule.
    assert session.rechecked(policy) == decided
