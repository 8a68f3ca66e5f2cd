"""Robot commands and heartbeats that are not safety's, in real MCAP files: recorded with their MACs,
flagged by the audit, shown as such by `tether inspect`'s timeline and `recheck`, never taken as safety's."""

from __future__ import annotations

import json
import os
import secrets
import time
from pathlib import Path

import msgspec
import pytest
import typer
from typer.testing import CliRunner

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.robot import NavigateToPoseGoal, Odometry, Twist
from schemas.safety import Decision, EstopState, SafetyEvent, SafetyStatus
from schemas.trace import TraceRecord
from services.recorder.linkaudit import Why, audit
from services.recorder.mcapfile import Recording
from services.recorder.reader import Recorded, read_recording, recover
from services.recorder.timeline import EventKind, build_timeline
from services.robotlink import Signer, unpack
from services.runtime import encode
from services.safety.policy import load_safety_policy
from services.safety.recheck import Message, recheck
from services.worldmodel import load_world
from tether.inspect import inspect
from tether.recordings import recheck_command

ROBOT = "r1"
T0 = 1_800_000_000_000_000_000
KEY = secrets.token_bytes(32)
HERE = Pose2D(x=9.0, y=1.2)


class Incident:
    """Safety beating (signed, latched from 1 s on) and deciding, an attacker forging and replaying."""

    def __init__(self, path: Path) -> None:
        self.recording = Recording(path, ROBOT)
        self.clock = 0.0
        self.safety = Signer(KEY, lambda: 1.8e9 + self.clock)

    def put(self, t: float, topic: keys.Topic[object], message: object, signer: Signer | None = None) -> bytes | None:
        self.clock = t
        key, payload = topic.key(ROBOT), encode(message)
        attachment = signer.sign(key, payload) if signer is not None else None
        assert self.recording.record(key, payload, log_time=T0 + int(t * 1e9), attachment=attachment)
        return attachment

    def raw(self, t: float, topic: keys.Topic[object], payload: bytes, attachment: bytes | None) -> None:
        self.recording.record(topic.key(ROBOT), payload, log_time=T0 + int(t * 1e9), attachment=attachment)

    def trace(self, t: float, service: str, path: str, query: object, reply: object, error: str = "") -> None:
        record = TraceRecord(
            stamp=1.8e9 + t,
            service=service,
            key=path,
            duration=0.01,
            query=msgspec.Raw(encode(query)),
            reply=msgspec.Raw(encode(reply) if reply is not None else b"null"),
            error=error,
        )
        self.raw(t, keys.Topic(f"_trace/{service}/{path}", TraceRecord), encode(record), None)


def beat(latched: bool) -> SafetyStatus:
    return SafetyStatus(seq=1, stamp=0.0, estop=EstopState(latched=latched, source="operator"), speed_scale=1.0)


def approved_twist(twist: Twist) -> SafetyEvent:
    command = msgspec.Raw(encode(twist))
    return SafetyEvent(stamp=0.0, key=keys.CMD_VEL.path, decision=Decision.APPROVED, reason="ok", command=command)


def approved_goal(goal: SendGoal[NavigateToPoseGoal]) -> SafetyEvent:
    key = keys.CMD_NAVIGATE.send_goal.path
    return SafetyEvent(stamp=0.0, key=key, decision=Decision.APPROVED, reason="ok", command=msgspec.Raw(encode(goal)))


@pytest.fixture
def incident(tmp_path: Path) -> Path:
    path = tmp_path / "incident.mcap"
    rec = Incident(path)
    forger, holder = Signer(secrets.token_bytes(32)), Signer(KEY)  # another key; the key but not safety
    captured = None
    for i in range(40):  # safety's heartbeat at 20 Hz for 2 s, latched from 1 s
        t = i * 0.05
        attachment = rec.put(t, keys.HEARTBEAT, beat(latched=t >= 1.0), rec.safety)
        rec.put(t + 0.01, keys.ODOM, Odometry(stamp=0.0, sim_time=t, pose=HERE, linear_x=0.0, angular_z=0.0))
        if i == 5:
            captured = attachment, encode(beat(latched=False))
    go = Twist(linear_x=0.2)
    rec.put(0.30, keys.SAFETY_EVENTS, approved_twist(go))
    rec.put(0.31, keys.ROBOT_CMD_VEL, go, rec.safety)  # safety's, decided: fine
    rec.put(0.40, keys.ROBOT_CMD_VEL, Twist(linear_x=0.5))  # bare: flagged
    rec.put(0.41, keys.ROBOT_CMD_VEL, Twist(linear_x=0.5), holder)  # the key, but not safety's stream
    rec.put(0.42, keys.ROBOT_CMD_VEL, Twist(linear_x=0.4), rec.safety)  # safety's MAC, no decision
    rec.put(1.20, keys.HEARTBEAT, beat(latched=False))  # forged, bare
    rec.put(1.21, keys.HEARTBEAT, beat(latched=False), forger)  # forged, another key
    assert captured is not None and captured[0] is not None
    rec.raw(1.22, keys.HEARTBEAT, captured[1], captured[0])  # safety's own unlatched beat, replayed
    goal = SendGoal(goal_id="g-safety", goal=NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2)))
    rec.put(0.50, keys.SAFETY_EVENTS, approved_goal(goal))
    send_goal = keys.ROBOT_NAVIGATE.send_goal.path
    rec.trace(0.52, "sim", send_goal, goal, GoalResponse(goal_id="g-safety", accepted=True))
    bypass = SendGoal(goal_id="g-bypass", goal=NavigateToPoseGoal(pose=Pose2D(x=11.2, y=8.0)))
    rec.trace(0.60, "sim", send_goal, bypass, GoalResponse(goal_id="g-bypass", accepted=True))
    refused = ServiceError(kind=ErrorKind.UNAUTHORIZED, message="refused: not signed by safety (no MAC)")
    rec.trace(0.70, "sim", send_goal, bypass, None, error=refused.message)
    rec.recording.finish()
    return path


def test_the_recorder_keeps_each_messages_attachment_and_recover_too(incident: Path, tmp_path: Path) -> None:
    recording = read_recording(incident)
    beats = [m for m in recording.messages if m.key == keys.HEARTBEAT.key(ROBOT)]
    assert len(beats) == 43 and sum(m.attachment is None for m in beats) == 1
    assert all(m.attachment is None for m in recording.messages if m.key == keys.ODOM.key(ROBOT))
    assert f"tether/{ROBOT}/_robot_link" in {c.topic for c in recording.channels.values()}
    assert f"tether/{ROBOT}/_robot_link" not in recording.counts(), "the link records are not messages of a key"
    copy = recover(incident, tmp_path / "copy.mcap")
    again = read_recording(copy.output)
    assert [m.attachment for m in again.messages] == [m.attachment for m in recording.messages]


def test_every_command_and_heartbeat_not_safetys_is_flagged_and_nothing_else(incident: Path) -> None:
    found = audit(read_recording(incident).messages, ROBOT)
    flagged = sorted((f.path, f.why) for f in found.flags)
    assert flagged == sorted(
        [
            ("robot/cmd_vel", Why.UNSIGNED),
            ("robot/cmd_vel", Why.OTHER_SENDER),
            ("robot/cmd_vel", Why.NO_DECISION),
            ("safety/heartbeat", Why.UNSIGNED),
            ("safety/heartbeat", Why.CONFLICTING_STREAM),
            ("safety/heartbeat", Why.REPLAYED),
            ("robot/navigate_to_pose/_action/send_goal", Why.NO_DECISION),
            ("robot/navigate_to_pose/_action/send_goal", Why.REFUSED),
        ]
    ), found.flags
    with_key = audit(read_recording(incident).messages, ROBOT, robot_key=KEY)
    bad = {(f.path, f.why) for f in with_key.flags}
    assert ("safety/heartbeat", Why.BAD_MAC) in bad and ("safety/heartbeat", Why.CONFLICTING_STREAM) not in bad


def test_the_timeline_shows_them_as_not_safetys_and_keeps_the_latch_as_safety_said(incident: Path) -> None:
    timeline = build_timeline(read_recording(incident))
    suspects = [r for r in timeline.rows if r.kind is EventKind.SUSPECT]
    assert {r.key for r in suspects} == {
        "robot/cmd_vel",
        "safety/heartbeat",
        "robot/navigate_to_pose/_action/send_goal",
    }
    assert all(r.text.startswith("NOT SAFETY'S: ") for r in suspects)
    # The forged and replayed unlatched beats came while safety said latched: no reset seen, never unlatched
    # (unknown where a beat of another sender came amid safety's, without the key); latched with the key.
    assert not [r for r in timeline.rows if r.kind is EventKind.RESET]
    after = [r for r in timeline.rows if r.t >= 1.0]
    assert after and all(r.state.estop is not False for r in after)
    keyed = [r for r in build_timeline(read_recording(incident), robot_key=KEY).rows if r.t >= 1.0]
    assert keyed and all(r.state.estop for r in keyed)


def test_an_old_recording_without_macs_is_not_audited_message_by_message(tmp_path: Path) -> None:
    rec = Incident(tmp_path / "old.mcap")
    for i in range(10):
        rec.put(i * 0.05, keys.HEARTBEAT, beat(latched=False))
    rec.put(0.6, keys.ROBOT_CMD_VEL, Twist())
    rec.recording.finish()
    found = audit(read_recording(tmp_path / "old.mcap").messages, ROBOT)
    assert not found.flags and "no robot-link MACs" in found.note


def test_recheck_lists_them_and_uses_only_safetys_heartbeats(incident: Path) -> None:
    recording = read_recording(incident)
    root = keys.prefix(ROBOT) + "/"
    messages = [Message(m.log_time / 1e9, m.key[len(root) :], m.data, m.attachment) for m in recording.messages]
    report = recheck(messages, load_safety_policy(load_world(), None, "household"), robot=ROBOT)
    assert len(report.suspects) == 8
    lines = [w for w in report.warnings if w.startswith("not safety's:")]
    assert any("on safety/heartbeat: replayed or reordered" in w for w in lines), lines
    assert any("on robot/cmd_vel: not signed by safety" in w for w in lines), lines
    assert report.checked and report.checked[0].key == keys.CMD_VEL.path and not report.differences


@pytest.fixture
def forged(tmp_path: Path) -> Path:
    """Safety beating latched at 50 Hz for 2 s; from 0.5 s to 1.5 s a forger beats unlatched at 150 Hz
    under its own key (more beats than safety's, so a count would take it for safety's)."""
    path = tmp_path / "forged.mcap"
    rec = Incident(path)
    forger = Signer(secrets.token_bytes(32), lambda: 1.8e9 + rec.clock)
    beats = [(i * 0.02, True, rec.safety) for i in range(100)]
    beats += [(0.5 + i / 150 + 0.001, False, forger) for i in range(150)]
    for t, latched, signer in sorted(beats, key=lambda b: b[0]):  # recorded as they arrive
        rec.put(t, keys.HEARTBEAT, beat(latched), signer)
    rec.put(2.0, keys.ROBOT_CMD_VEL, Twist(linear_x=0.5), forger)  # the forger's, from a conflicting stream
    rec.recording.finish()
    return path


def test_a_forger_beating_faster_than_safety_is_never_taken_for_safety(forged: Path) -> None:
    messages = read_recording(forged).messages
    found = audit(messages, ROBOT)
    beats = {i: m for i, m in enumerate(messages) if m.key == keys.HEARTBEAT.key(ROBOT)}
    conflicting = {f.index for f in found.flags if f.why is Why.CONFLICTING_STREAM}
    # Without the key: every beat of either sender while both beat conflicts; safety's alone do not.
    during = {i for i, m in beats.items() if 0.5e9 < m.log_time - T0 < 1.5e9}  # the forger's first and last beat
    assert conflicting == during and len(during) == 150 + 49
    assert [(f.path, f.why) for f in found.flags if f.index not in conflicting] == [
        ("robot/cmd_vel", Why.CONFLICTED_SENDER)
    ]
    timeline = build_timeline(read_recording(forged))
    span = [r for r in timeline.rows if 0.5 < r.t < 1.5]
    assert any(r.kind is EventKind.SUSPECT and r.key == "safety/heartbeat" for r in span)
    assert span and all(r.state.estop is None for r in span), [(r.t, r.text, r.state.estop) for r in span]
    assert all(r.state.estop is not False for r in timeline.rows), "the forged latch shown as safety's"
    assert not [r for r in timeline.rows if r.kind is EventKind.RESET]
    # With the key: the forger's MACs do not check out, and safety's stream is safety's, latched throughout.
    with_key = audit(messages, ROBOT, robot_key=KEY)
    safetys = unpack(messages[0].attachment)
    assert safetys is not None
    forgers = {i for i, m in beats.items() if (sig := unpack(m.attachment)) and sig.session != safetys.session}
    assert len(forgers) == 150
    assert {f.index for f in with_key.flags if f.path == "safety/heartbeat"} == forgers
    assert {f.why for f in with_key.flags} == {Why.BAD_MAC}
    keyed = build_timeline(read_recording(forged), robot_key=KEY)
    assert keyed.rows and all(r.state.estop is True for r in keyed.rows)


def write_key(path: Path, key: bytes, mode: int = 0o600) -> Path:
    path.write_text(key.hex() + "\n")
    os.chmod(path, mode)
    return path


def test_inspect_and_recheck_check_the_macs_with_robot_key(forged: Path, tmp_path: Path) -> None:
    app = typer.Typer()
    app.command("inspect")(inspect)
    app.command("recheck")(recheck_command)
    key_file = write_key(tmp_path / "robot.key", KEY)
    runner = CliRunner()
    plain = json.loads(runner.invoke(app, ["inspect", str(forged), "--json"]).stdout)
    assert any(r["state"]["estop"] is None for r in plain["rows"])
    assert all(r["state"]["estop"] is not False for r in plain["rows"])
    keyed = runner.invoke(app, ["inspect", str(forged), "--json", "--robot-key", str(key_file)])
    assert keyed.exit_code == 0, keyed.output
    rows = json.loads(keyed.stdout)["rows"]
    assert rows and all(r["state"]["estop"] is True for r in rows)
    assert any("does not match the robot key" in r["summary"] for r in rows)
    # A key file others may read is refused, naming it; so is recheck's.
    loose = write_key(tmp_path / "loose.key", KEY, 0o644)
    refused = runner.invoke(app, ["inspect", str(forged), "--robot-key", str(loose)])
    assert refused.exit_code == 2 and "--robot-key" in refused.output and "loose.key" in refused.output
    refused = runner.invoke(app, ["recheck", str(forged), "--robot-key", str(loose), "--world", "household"])
    assert refused.exit_code == 2 and "--robot-key" in refused.output


def test_recheck_with_the_key_takes_safetys_heartbeats_beside_a_forgers(forged: Path) -> None:
    recording = read_recording(forged)
    root = keys.prefix(ROBOT) + "/"
    messages = [Message(m.log_time / 1e9, m.key[len(root) :], m.data, m.attachment) for m in recording.messages]
    policy = load_safety_policy(load_world(), None, "household")
    plain = recheck(messages, policy, robot=ROBOT)
    assert {f.why for f in plain.suspects} == {Why.CONFLICTING_STREAM, Why.CONFLICTED_SENDER}
    keyed = recheck(messages, policy, robot=ROBOT, robot_key=KEY)
    assert {f.why for f in keyed.suspects} == {Why.BAD_MAC} and len(keyed.suspects) == 151


def test_the_audit_of_200k_messages_is_not_quadratic() -> None:
    """200k messages: heartbeats, decisions and robot/cmd_vel of safety's, each twist decided once."""
    safety = Signer(KEY, lambda: 1.8e9)
    beat_key, vel_key, events_key = (t.key(ROBOT) for t in (keys.HEARTBEAT, keys.ROBOT_CMD_VEL, keys.SAFETY_EVENTS))
    heartbeat = encode(beat(latched=False))
    messages: list[Recorded] = []
    for k in range(50_000):
        t = T0 + k * 20_000_000  # 50 Hz of each, for 1000 s
        twist = Twist(linear_x=round(0.001 * (k % 500), 3))
        payload = encode(twist)
        messages.append(Recorded(t, beat_key, heartbeat, safety.sign(beat_key, heartbeat)))
        messages.append(Recorded(t + 1, events_key, encode(approved_twist(twist))))
        messages.append(Recorded(t + 2, vel_key, payload, safety.sign(vel_key, payload)))
        undecided = encode(Twist(linear_x=0.7, angular_z=0.1 * (k % 7)))
        messages.append(Recorded(t + 3, vel_key, undecided, safety.sign(vel_key, undecided)))
    started = time.perf_counter()
    found = audit(messages, ROBOT)
    took = time.perf_counter() - started
    assert len(found.flags) == 50_000 and {f.why for f in found.flags} == {Why.NO_DECISION}
    assert all(messages[f.index].data != messages[f.index - 1].data for f in found.flags)
    print(f"audited {len(messages)} messages in {took:.2f} s")
