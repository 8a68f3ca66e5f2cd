"""Recordings someone hands over, crafted to mislead `tether recheck` or to wear it out."""

from __future__ import annotations

import json
import time
from pathlib import Path

import msgspec
from mcap.writer import Writer
from typer.testing import CliRunner

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal, Odometry, Twist
from schemas.safety import Decision, EstopState, Rule, SafetyEvent, SafetyStatus
from schemas.trace import TraceRecord
from schemas.world import PerceivedHuman, PerceivedHumans
from services.recorder.mcapfile import SourceFile
from services.runtime import encode
from services.safety.policy import load_safety_policy
from services.safety.policyfile import DEFAULT_POLICY
from services.safety.recheck import History, Message, recheck
from services.worldmodel import load_world, world_path
from tether.cli import app

ROBOT = "r1"
SECOND = 1_000_000_000
START = 1_800_000_000 * SECOND


def approved(speed: float, policy_hash: str = "", rule: Rule | None = None) -> SafetyEvent:
    """Safety's approval of a cmd_vel at `speed`, as a file may put it."""
    return SafetyEvent(
        stamp=0.9,
        key=keys.CMD_VEL.path,
        decision=Decision.APPROVED,
        rule=rule,
        policy_hash=policy_hash,
        command=msgspec.Raw(encode(Twist(linear_x=speed))),
    )


def craft(path: Path, policy: bytes, metadata_hash: str, *decisions: SafetyEvent) -> Path:
    """A recording of safety's `decisions`, with the robot standing still before it, keeping `policy` as its
    policy file and its metadata naming `metadata_hash`."""
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="crafted")
        writer.add_metadata("tether", {"robot": ROBOT, "part": "0", "run": "x", "policy_hash": metadata_hash})
        world = world_path("household")
        for name, data in ((f"world/{world.name}", world.read_bytes()), ("policy/policy.toml", policy)):
            writer.add_attachment(create_time=START, log_time=START, name=name, media_type="text/plain", data=data)
        schema = writer.register_schema(name="any", encoding="jsonschema", data=b"{}")
        channels: dict[str, int] = {}

        def put(seconds: float, topic: keys.Topic, value: object) -> None:
            key = topic.key(ROBOT)
            if key not in channels:
                channels[key] = writer.register_channel(topic=key, message_encoding="json", schema_id=schema)
            at = START + int(seconds * SECOND)
            writer.add_message(channel_id=channels[key], log_time=at, publish_time=at, data=encode(value))

        for t in range(50):
            odom = Odometry(stamp=t / 50, sim_time=t / 50, pose=Pose2D(x=6.0, y=1.2), linear_x=0.0, angular_z=0.0)
            put(t / 50, keys.ODOM, odom)
            put(t / 50, keys.HEARTBEAT, SafetyStatus(seq=t, stamp=t / 50, estop=EstopState(latched=False)))
        for decision in decisions:
            put(decision.stamp, keys.SAFETY_EVENTS, decision)
        writer.finish()
    return path


def test_recheck_tells_a_swapped_policy_file_from_the_one_safety_ran_with(tmp_path: Path) -> None:
    ran_with = DEFAULT_POLICY.read_bytes()
    swapped = ran_with + b"\n# not the file safety ran with\n"
    claimed = SourceFile(DEFAULT_POLICY, ran_with).hash
    # The metadata and safety's events agree with each other, and both name the file safety ran with;
    # the file kept is another.
    file = craft(tmp_path / "swapped.mcap", swapped, claimed, approved(0.2, claimed))

    done = CliRunner().invoke(app, ["recheck", str(file), "--json"])

    report = json.loads(done.stdout)
    assert report["checked"] == 1 and report["differ"] == 0
    assert any(
        claimed in warning and "not given the policy safety ran with" in warning for warning in report["warnings"]
    )

    # The file safety ran with, kept as it was: nothing to say.
    honest = craft(tmp_path / "honest.mcap", ran_with, claimed, approved(0.2, claimed))
    done = CliRunner().invoke(app, ["recheck", str(honest), "--json"])
    assert done.exit_code == 0, done.output
    assert json.loads(done.stdout)["warnings"] == []


def test_recheck_checks_an_approval_that_names_the_e_stop_instead_of_counting_it_refused(tmp_path: Path) -> None:
    policy = DEFAULT_POLICY.read_bytes()
    # 5 m/s, approved (so the file says), by a rule only a refusal names: the policy refuses it.
    file = craft(tmp_path / "approved.mcap", policy, "", approved(0.2), approved(5.0, rule=Rule.ESTOP))

    done = CliRunner().invoke(app, ["recheck", str(file), "--json"])

    report = json.loads(done.stdout)
    assert done.exit_code == 1, done.output
    assert report["checked"] == 2 and report["skipped"] == {}
    [decision] = report["decisions"]
    assert decision["recorded"] == "approved" and decision["now"] == "vetoed"


def test_state_recorded_backwards_is_looked_up_in_time_order_without_quadratic_cost() -> None:
    count = 400_000
    history: History[int] = History()
    started = time.monotonic()
    for i in range(count):  # log times running backwards, as a hostile file may have them
        history.add(float(count - i), i)
    found = history.at(10.5, 1.0)
    # Inserting each in place moved everything after it: some 20 s for these on this machine.
    assert time.monotonic() - started < 5.0
    assert found == (10.0, count - 10)
    assert history.after(10.0, 1.0) == (11.0, count - 11)


def test_state_received_at_one_time_keeps_its_arrival_order() -> None:
    history: History[str] = History()
    for stamp, value in ((2.0, "a"), (1.0, "b"), (2.0, "c"), (1.0, "d")):
        history.add(stamp, value)
    assert history.at(1.5, 1.0) == (1.0, "d")
    assert history.at(2.0, 1.0) == (2.0, "c")
    assert history.after(1.0, 2.0) == (2.0, "a")


def test_inspect_draws_a_map_of_names_holding_escapes_without_putting_them_on_the_terminal(tmp_path: Path) -> None:
    robot = "r\x1b]0;owned\x07"
    file = tmp_path / "escapes.mcap"
    with file.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="crafted")
        writer.add_metadata("tether", {"robot": robot})
        schema = writer.register_schema(name="any", encoding="jsonschema", data=b"{}")
        odom, humans = (
            writer.register_channel(topic=topic.key(robot), message_encoding="json", schema_id=schema)
            for topic in (keys.ODOM, keys.HUMANS)
        )
        pose = Pose2D(x=6.0, y=1.2)
        person = PerceivedHuman(id="h1", name="\x1b[2J\x1b]0;owned\x07", pose=pose)
        for channel, value in (
            (odom, Odometry(stamp=0.0, sim_time=0.0, pose=pose, linear_x=0.0, angular_z=0.0)),
            (humans, PerceivedHumans(stamp=0.0, humans=[person])),
        ):
            writer.add_message(channel_id=channel, log_time=START, publish_time=START, data=encode(value))
        writer.finish()
    png = tmp_path / "map.png"

    done = CliRunner().invoke(app, ["inspect", str(file), "--png", str(png), "--world", "household"])

    assert done.exit_code == 0, done.output
    assert png.stat().st_size > 0
    assert "\x1b" not in done.output and "\x07" not in done.output


def test_recheck_of_a_file_repeating_one_goal_id_is_not_quadratic() -> None:
    policy = load_safety_policy(load_world(), None, "household")
    goal = SendGoal(goal_id="g", goal=NavigateToPoseGoal(pose=Pose2D(x=6.4, y=1.2)))
    about_it = encode(
        SafetyEvent(
            stamp=2.0,
            key=keys.CMD_NAVIGATE.send_goal.path,
            decision=Decision.APPROVED,
            command=msgspec.Raw(encode(goal)),
        )
    )
    trace = encode(
        TraceRecord(
            stamp=2.0,
            service="safety",
            key=keys.CMD_NAVIGATE.send_goal.path,
            duration=0.001,
            query=msgspec.Raw(encode(goal)),
            reply=msgspec.Raw(encode(GoalResponse(goal_id="g", accepted=True))),
        )
    )
    odom = Odometry(stamp=0.0, sim_time=0.0, pose=Pose2D(x=6.0, y=1.2), linear_x=0.0, angular_z=0.0)
    # Safety's events all stamped as it answered each of the queries, all with one goal id.
    messages = [
        Message(1.9, keys.ODOM.path, encode(odom)),
        *(Message(2.0, keys.SAFETY_EVENTS.path, about_it) for _ in range(100_000)),
        *(Message(2.002, f"_trace/safety/{keys.CMD_NAVIGATE.send_goal.path}", trace) for _ in range(2_000)),
    ]
    started = time.monotonic()
    report = recheck(messages, policy)
    # Each query went through all 100 000 events: some 20 s on this machine.
    assert time.monotonic() - started < 8.0
    assert len(report.checked) == 2_000 and report.differences == []
