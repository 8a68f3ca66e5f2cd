"""Recordings offline: rotation, reading files cut short, recovery, what a replay sends, and recheck."""

from __future__ import annotations

import json
import random
import re
import threading
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
from mcap.records import Chunk

from schemas import keys
from schemas.actions import CANCEL_ALL, CancelGoal, GoalResponse, SendGoal
from schemas.common import ErrorKind, Pose2D
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryGoal,
    JointState,
    NavigateToPoseGoal,
    Odometry,
    TrajectoryPoint,
    Twist,
)
from schemas.safety import Decision, EstopState, Rule, SafetyEvent, SafetyStatus
from schemas.trace import TraceRecord
from services.recorder import scene3d
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Provenance, Recording, SourceFile
from services.recorder.reader import (
    RECORD_SIZE_LIMIT,
    Recorded,
    RecordingError,
    RecordingFile,
    join_recordings,
    read_recording,
    recover,
)
from services.recorder.recorder import Recorder
from services.recorder.replay import ReplayKind, default_target, plan_replay
from services.runtime import encode
from services.safety.policy import JOINTS_STAMP, SafetyPolicy, load_safety_policy
from services.safety.policyfile import DEFAULT_POLICY
from services.safety.recheck import Message, RecheckOutcome, recheck
from services.worldmodel import load_world, world_path

ROBOT = "r1"
PREFIX = keys.prefix(ROBOT)
SECOND = 1_000_000_000


class Clock:
    def __init__(self) -> None:
        self.now = 1_800_000_000 * SECOND

    def __call__(self) -> int:
        return self.now


def provenance() -> Provenance:
    return Provenance(ROBOT, world=SourceFile.read(world_path("household")), policy=SourceFile.read(DEFAULT_POLICY))


def payload(i: int, size: int = 100) -> bytes:
    # Random padding: it must not compress away.
    return encode({"i": i, "pad": random.Random(i).randbytes(size // 2).hex()})


# Rotation


def test_a_file_is_rotated_by_age_and_each_part_carries_metadata_and_files(tmp_path: Path) -> None:
    clock = Clock()
    config = RecorderConfig(output_dir=str(tmp_path), max_file_seconds=10.0)
    recorder = Recorder(config, provenance(), clock=clock, monotonic=clock)
    recorder.record(f"{PREFIX}/a", payload(0))
    clock.now += 5 * SECOND
    recorder.tick()
    recorder.record(f"{PREFIX}/a", payload(1))
    clock.now += 6 * SECOND
    recorder.tick()  # 11 s old: a new file
    recorder.record(f"{PREFIX}/a", payload(2))
    recorder.finish()

    assert len(recorder.files) == 2 and recorder.messages == 3
    assert recorder.status().files == [str(p) for p in recorder.files]
    parts = [read_recording(p) for p in recorder.files]
    assert [len(p.messages) for p in parts] == [2, 1]
    for n, part in enumerate(parts):
        assert part.complete
        assert part.metadata["tether"]["part"] == str(n)
        assert part.policy is not None and part.policy.data == DEFAULT_POLICY.read_bytes()
        assert part.world is not None and part.world.name == "world/household.yaml"
    assert parts[0].metadata["tether"]["run"] == parts[1].metadata["tether"]["run"] == recorder.run
    assert len(join_recordings(parts[::-1]).messages) == 3


def test_a_file_is_rotated_by_size_and_names_never_collide(tmp_path: Path) -> None:
    clock = Clock()  # the clock stands still: every file starts in the same second
    config = RecorderConfig(output_dir=str(tmp_path), max_file_bytes=64 * 1024, chunk_size=4096)
    recorder = Recorder(config, provenance(), clock=clock, monotonic=clock)
    for i in range(3000):
        recorder.record(f"{PREFIX}/a", payload(i, 200))
        if i % 500 == 499:
            recorder.tick()
    recorder.finish()

    assert len(recorder.files) > 2
    assert len(set(recorder.files)) == len(recorder.files)
    assert recorder.files[1].name == recorder.files[0].stem + "_1.mcap"
    numbers = [json.loads(m.data)["i"] for p in recorder.files for m in read_recording(p).messages]
    assert numbers == list(range(3000))


def test_status_names_the_file_and_counts_messages(tmp_path: Path) -> None:
    recorder = Recorder(RecorderConfig(output_dir=str(tmp_path)), provenance())
    recorder.record(f"{PREFIX}/a", payload(0))
    assert not recorder.record(f"{PREFIX}/a", b"not json")
    status = recorder.status()
    recorder.finish()
    assert status.path == str(recorder.files[0]) and status.files == [status.path]
    assert (status.messages, status.dropped) == (1, 1)
    assert status.started > 0


def test_a_chosen_file_name_is_used_for_the_first_file(tmp_path: Path) -> None:
    recorder = Recorder(RecorderConfig(), provenance(), first_path=tmp_path / "incident.mcap")
    recorder.finish()
    assert recorder.files == [tmp_path / "incident.mcap"]


# Files cut short


def write_flushed(path: Path, count: int) -> list[int]:
    """A recording of `count` messages flushed every 100; the file sizes after each flush."""
    recording = Recording(path, ROBOT, chunk_size=1 << 20, provenance=provenance())
    sizes = []
    for i in range(count):
        recording.record(f"{PREFIX}/k{i % 3}", payload(i))
        if i % 100 == 99:
            recording.flush()
            sizes.append(path.stat().st_size)
    recording.finish()
    return sizes


def test_a_file_cut_anywhere_reads_back_every_message_flushed_before_the_cut(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    sizes = write_flushed(full, 500)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    for end in range(sizes[0] - 1, sizes[-1], 997):
        cut.write_bytes(data[:end])
        recording = read_recording(cut)
        assert not recording.complete and recording.problem
        flushed = 100 * sum(1 for s in sizes if s <= end)
        numbers = [json.loads(m.data)["i"] for m in recording.messages]
        assert numbers == list(range(len(numbers))), f"cut at {end}: not a prefix"
        assert len(numbers) >= flushed, f"cut at {end}: {len(numbers)} read, {flushed} were flushed"


def test_recover_writes_a_complete_file_with_everything_that_was_whole(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    sizes = write_flushed(full, 300)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[: sizes[1] + 50])
    out = tmp_path / "recovered.mcap"

    done = recover(cut, out)

    assert not done.complete and done.messages == 200
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        # The traffic, and the 3D scene the recorder wrote at the start for Foxglove (scene3d).
        assert summary.statistics.message_count == 200 + 1
        assert summary.statistics.channel_count == 3 + 1
        messages = [m for m in reader.iter_messages(log_time_order=False) if not scene3d.is_derived(m[1].topic)]
        assert [json.loads(m.data)["i"] for _, _, m in messages] == list(range(200))
        assert [a.name for a in reader.iter_attachments()] == ["world/household.yaml", "policy/policy.toml"]
        assert {m.name for m in reader.iter_metadata()} == {"tether"}
    with pytest.raises(RecordingError, match="new file"):
        recover(out, out)


def test_only_consecutive_parts_of_one_run_are_joined_as_one(tmp_path: Path) -> None:
    tighter = tmp_path / "tighter.toml"
    tighter.write_text(DEFAULT_POLICY.read_text().replace("max_linear_speed = 0.6", "max_linear_speed = 0.3"))

    def part(
        name: str, number: int, times: list[int], run: str = "run1", robot: str = ROBOT, policy: Path = DEFAULT_POLICY
    ) -> RecordingFile:
        provenance = Provenance(robot, policy=SourceFile.read(policy))
        recording = Recording(tmp_path / name, robot, provenance=provenance, part=number, run=run, clock=lambda: 0)
        for i, at in enumerate(times):
            recording.record(f"{keys.prefix(robot)}/a", payload(i), log_time=at * SECOND)
        recording.finish()
        return read_recording(tmp_path / name)

    zero, one, two = part("p0.mcap", 0, [1, 2]), part("p1.mcap", 1, []), part("p2.mcap", 2, [3, 4])
    joined = join_recordings([two, zero, one])
    assert joined.name == "p0.mcap (+2 parts)" and [m.log_time // SECOND for m in joined.messages] == [1, 2, 3, 4]
    refusals = {
        "is given twice": [zero, zero],
        "different recorder runs": [zero, part("other_run.mcap", 1, [3], run="run2")],
        "parts between them are missing": [zero, two],
        "given twice": [zero, part("copy.mcap", 0, [1, 2])],
        "of robot": [zero, part("r2.mcap", 1, [3], robot="r2")],
        "different policy files": [zero, part("tighter.mcap", 1, [3], policy=tighter)],
        # Part 1 is empty: part 2 is still checked against part 0.
        "overlap in time": [zero, one, part("early.mcap", 2, [1])],
    }
    for why, parts in refusals.items():
        with pytest.raises(RecordingError, match=why):
            join_recordings(parts)


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all", b"\x89MCAP0\r\n" + b"\xff" * 40])
def test_a_file_that_is_not_a_recording_is_refused_naming_it(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "junk.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=r"junk\.mcap"):
        read_recording(path)
    with pytest.raises(RecordingError, match=r"missing\.mcap"):
        read_recording(tmp_path / "missing.mcap")


def test_a_file_that_cannot_be_read_is_refused_naming_it(tmp_path: Path) -> None:
    # Root reads any file whatever its mode: a write-only attribute of the kernel stands in for one
    # the user may not read (tether incidents show crashed on such a recording).
    unreadable = tmp_path / "theirs.mcap"
    unreadable.write_bytes(b"\x89MCAP0\r\n" + b"\0" * 40)
    unreadable.chmod(0)
    if _readable(unreadable):
        unreadable = Path("/sys/bus/pci/rescan")
        if not unreadable.exists() or _readable(unreadable):
            pytest.skip("no file here that this user cannot read")
    with pytest.raises(RecordingError, match=f"cannot read recording {re.escape(str(unreadable))}"):
        read_recording(unreadable)


def _readable(path: Path) -> bool:
    try:
        with path.open("rb"):
            return True
    except PermissionError:
        return False


# Replay


def trace(service: str, path: str, query: object, reply: object) -> Recorded:
    record = TraceRecord(
        stamp=0.0,
        service=service,
        key=path,
        duration=0.001,
        query=msgspec.Raw(encode(query)),
        reply=msgspec.Raw(encode(reply)),
    )
    return Recorded(0, keys.trace_key(ROBOT, service, path), encode(record))


def at(seconds: float, message: Recorded) -> Recorded:
    return Recorded(int(seconds * SECOND), message.key, message.data)


GOAL = SendGoal(goal_id="g1", goal=NavigateToPoseGoal(pose=Pose2D(x=1.0, y=2.0)))
RECORDED = [
    at(10.0, Recorded(0, keys.ODOM.key(ROBOT), b"{}")),
    at(10.5, Recorded(0, keys.CMD_VEL.key(ROBOT), encode(Twist(linear_x=0.1)))),
    at(11.0, trace("safety", keys.CMD_NAVIGATE.send_goal.path, GOAL, GoalResponse(goal_id="g1", accepted=True))),
    at(11.1, trace("sim", keys.ROBOT_NAVIGATE.send_goal.path, GOAL, GoalResponse(goal_id="g1", accepted=True))),
    at(11.2, Recorded(0, keys.ROBOT_CMD_VEL.key(ROBOT), encode(Twist(linear_x=0.1)))),
    at(11.3, Recorded(0, keys.ESTOP.key(ROBOT), b'{"source":"operator"}')),
    at(12.0, trace("safety", keys.CMD_NAVIGATE.cancel_goal.path, CancelGoal(goal_id="g1"), {"accepted": True})),
    at(12.5, Recorded(0, "tether/other/robot/odom", b"{}")),
]


def test_a_replay_moves_every_message_to_the_other_robot_at_its_recorded_offset() -> None:
    target = default_target(ROBOT)
    plan = plan_replay(RECORDED, ROBOT, target)

    assert [i.kind for i in plan.items] == [ReplayKind.PUT] * 7
    assert [i.at for i in plan.items] == pytest.approx([0.0, 0.5, 1.0, 1.1, 1.2, 1.3, 2.0])
    assert [i.key for i in plan.items] == [m.key.replace(f"/{ROBOT}/", f"/{target}/", 1) for m in RECORDED[:7]]
    assert [i.payload for i in plan.items] == [m.data for m in RECORDED[:7]]
    assert plan.skipped == {"not under tether/r1/": 1}


def test_a_live_replay_sends_only_commands_and_only_through_safety() -> None:
    plan = plan_replay(RECORDED, ROBOT, ROBOT, live=True)

    assert [(i.kind, i.key) for i in plan.items] == [
        (ReplayKind.PUT, keys.CMD_VEL.key(ROBOT)),
        (ReplayKind.QUERY, keys.CMD_NAVIGATE.send_goal.key(ROBOT)),
        (ReplayKind.QUERY, keys.CMD_NAVIGATE.cancel_goal.key(ROBOT)),
    ]
    assert [i.at for i in plan.items] == pytest.approx([0.0, 0.5, 1.5])
    sent, canceled = (json.loads(i.payload) for i in plan.items[1:])
    # A new goal id, the same for the goal's send and its cancel; the goal itself as recorded.
    assert sent["goal_id"] != "g1" and sent["goal_id"] == canceled["goal_id"]
    assert msgspec.convert(sent["goal"], NavigateToPoseGoal) == GOAL.goal
    assert not any("/robot/" in i.key or "estop" in i.key for i in plan.items)


# Recheck


@pytest.fixture(scope="module")
def world_policy() -> SafetyPolicy:
    return load_safety_policy(load_world(), None, "household")


def tightened(speed: float) -> SafetyPolicy:
    text = DEFAULT_POLICY.read_text().replace("max_linear_speed = 0.6", f"max_linear_speed = {speed}")
    return load_safety_policy(load_world(), Path("tight.toml"), "household", data=text.encode())


def msg(time: float, path: str, value: object) -> Message:
    return Message(time, path, encode(value))


def event(time: float, path: str, decision: Decision, command: object, rule: Rule | None = None) -> Message:
    return msg(
        time,
        keys.SAFETY_EVENTS.path,
        SafetyEvent(stamp=time, key=path, decision=decision, rule=rule, command=msgspec.Raw(encode(command))),
    )


def goal_trace(time: float, goal: NavigateToPoseGoal, response: GoalResponse) -> Message:
    record = TraceRecord(
        stamp=time,
        service="safety",
        key=keys.CMD_NAVIGATE.send_goal.path,
        duration=0.001,
        query=msgspec.Raw(encode(SendGoal(goal_id=response.goal_id, goal=goal))),
        reply=msgspec.Raw(encode(response)),
    )
    return msg(time + 0.002, f"_trace/safety/{keys.CMD_NAVIGATE.send_goal.path}", record)


def incident() -> list[Message]:
    start = Pose2D(x=6.0, y=1.2)
    out = [
        msg(t / 50, keys.ODOM.path, Odometry(stamp=t / 50, sim_time=t / 50, pose=start, linear_x=0.0, angular_z=0.0))
        for t in range(200)
    ]
    out += [
        msg(t / 50, keys.HEARTBEAT.path, SafetyStatus(seq=t, stamp=t / 50, estop=EstopState(latched=False)))
        for t in range(200)
    ]
    out += [
        event(1.0, keys.CMD_VEL.path, Decision.APPROVED, Twist(linear_x=0.45)),
        event(1.1, keys.CMD_VEL.path, Decision.VETOED, Twist(linear_x=5.0), Rule.BASE_SPEED),
        event(1.2, keys.CMD_VEL.path, Decision.VETOED, Twist(linear_x=0.1), Rule.ESTOP),
        goal_trace(
            2.0, NavigateToPoseGoal(pose=Pose2D(x=6.4, y=1.2), max_speed=0.45), GoalResponse(goal_id="a", accepted=True)
        ),
        goal_trace(
            2.5,
            NavigateToPoseGoal(pose=Pose2D(x=11.2, y=8.0)),
            GoalResponse(goal_id="b", accepted=False, reason="vetoed by safety: stairs", kind=ErrorKind.VETOED),
        ),
        goal_trace(
            3.0,
            NavigateToPoseGoal(pose=Pose2D(x=6.4, y=1.2)),
            GoalResponse(goal_id="c", accepted=False, reason="vetoed by safety: e-stop", kind=ErrorKind.ESTOP),
        ),
    ]
    return sorted(out, key=lambda m: m.time)


def test_recheck_with_the_same_policy_decides_as_recorded(world_policy: SafetyPolicy) -> None:
    report = recheck(incident(), world_policy)

    assert [(c.key, c.recorded, c.now) for c in report.checked] == [
        (keys.CMD_VEL.path, RecheckOutcome.APPROVED, RecheckOutcome.APPROVED),
        (keys.CMD_VEL.path, RecheckOutcome.VETOED, RecheckOutcome.VETOED),
        (keys.CMD_NAVIGATE.send_goal.path, RecheckOutcome.APPROVED, RecheckOutcome.APPROVED),
        (keys.CMD_NAVIGATE.send_goal.path, RecheckOutcome.VETOED, RecheckOutcome.VETOED),
    ]
    assert report.differences == []
    assert report.skipped == {"refused for the e-stop": 2}
    assert report.checked[3].now_rule is Rule.KEEP_OUT


def test_recheck_with_a_tightened_policy_lists_the_commands_it_would_refuse() -> None:
    report = recheck(incident(), tightened(0.3))

    assert [(c.key, c.command, c.now_rule) for c in report.differences] == [
        (keys.CMD_VEL.path, "cmd_vel 0.45 m/s, 0.00 rad/s", Rule.BASE_SPEED),
        (keys.CMD_NAVIGATE.send_goal.path, "navigate to (6.40, 1.20, 0.00 rad)", Rule.BASE_SPEED),
    ]
    assert all(c.recorded is RecheckOutcome.APPROVED and c.now is RecheckOutcome.VETOED for c in report.differences)
    assert report.policy_hash != load_safety_policy(load_world(), None, "household").limits.hash


def test_recheck_checks_a_command_from_the_state_recorded_before_it(world_policy: SafetyPolicy) -> None:
    # Odometry stops a second before the goal: safety would have found the pose unknown, and so does recheck.
    messages = [m for m in incident() if not (m.path == keys.ODOM.path and m.time > 1.0)]
    report = recheck(messages, world_policy)
    goal = next(c for c in report.checked if c.command.startswith("navigate to (6.40"))
    assert goal.now is RecheckOutcome.VETOED and goal.now_rule is Rule.POSE_KNOWN


def test_recheck_takes_a_goals_decision_only_from_what_safety_stamped_as_it_answered(
    world_policy: SafetyPolicy,
) -> None:
    # Goal "b" (to the stairs, refused by the policy at 2.5, its own event not in the file) was also
    # sent before it and after it with the same id, and refused for the command rate each time:
    # those refusals are not this one's, however close (safety answered it from 2.5 to 2.501).
    other = SendGoal(goal_id="b", goal=NavigateToPoseGoal(pose=Pose2D(x=6.4, y=1.2)))
    rate = [event(t, keys.CMD_NAVIGATE.send_goal.path, Decision.VETOED, other, Rule.COMMAND_RATE) for t in (2.45, 2.55)]
    report = recheck(sorted([*incident(), *rate], key=lambda m: m.time), world_policy)
    stairs = next(c for c in report.checked if c.command.startswith("navigate to (11.20"))
    assert (stairs.recorded, stairs.now) == (RecheckOutcome.VETOED, RecheckOutcome.VETOED)
    assert stairs.now_rule is Rule.KEEP_OUT
    assert report.skipped == {"refused for the e-stop": 2}
    # Its own event, stamped as it was answered, is taken however late the recorder heard it (here 2.5 s
    # late): refused for the rate, it is kept as recorded.
    decided = SafetyEvent(
        stamp=2.5005,
        key=keys.CMD_NAVIGATE.send_goal.path,
        decision=Decision.VETOED,
        rule=Rule.COMMAND_RATE,
        command=msgspec.Raw(encode(other)),
    )
    own = msg(5.0, keys.SAFETY_EVENTS.path, decided)
    report = recheck(sorted([*incident(), own], key=lambda m: m.time), world_policy)
    assert not any(c.command.startswith("navigate to (11.20") for c in report.checked)
    assert report.skipped == {"refused for the e-stop": 2, "refused for the command rate": 1}


def test_recheck_keeps_a_refusal_for_the_other_motion_as_recorded(world_policy: SafetyPolicy) -> None:
    # Which goals ran on the robot is not the policy's to decide again: such a refusal is kept, not
    # listed as a decision the policy now makes otherwise.
    other = SendGoal(goal_id="b", goal=NavigateToPoseGoal(pose=Pose2D(x=6.4, y=1.2)))
    decided = SafetyEvent(
        stamp=2.5005,
        key=keys.CMD_NAVIGATE.send_goal.path,
        decision=Decision.VETOED,
        rule=Rule.ONE_MOTION,
        command=msgspec.Raw(encode(other)),
    )
    own = msg(5.0, keys.SAFETY_EVENTS.path, decided)
    report = recheck(sorted([*incident(), own], key=lambda m: m.time), world_policy)
    assert not any(c.command.startswith("navigate to (11.20") for c in report.checked)
    assert report.skipped == {"refused for the e-stop": 2, "refused while the other motion ran": 1}


# A trajectory sent the moment the previous motion ended, from where that motion ended (END), and
# what the recorder heard meanwhile: the arm still moving, and the joint state safety decided from
# (stamped 1.98, at END) only after the goal. The goal's query came at 2.0.
HOME = list(load_world().robot.home_joints)
END = [HOME[0] + 0.5, *HOME[1:]]


def arm(stamp: float, lag: float) -> JointState:
    return JointState(stamp=stamp, name=list(ARM_JOINTS), position=[END[0] - lag, *END[1:]])


def trajectory_sent_as_the_motion_ends(named: float | None) -> list[Message]:
    """`named`: the stamp of the joint state safety's approval names (None: it names none)."""
    goal = FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS),
        points=[
            TrajectoryPoint(positions=END, time_from_start=0.0),
            TrajectoryPoint(positions=HOME, time_from_start=4.0),
        ],
    )
    sent = SendGoal(goal_id="t", goal=goal)
    values = {} if named is None else {JOINTS_STAMP: named}
    approval = SafetyEvent(
        stamp=2.0,
        key=keys.CMD_TRAJECTORY.send_goal.path,
        decision=Decision.APPROVED,
        values=values,
        command=msgspec.Raw(encode(sent)),
    )
    record = TraceRecord(
        stamp=2.0,
        service="safety",
        key=keys.CMD_TRAJECTORY.send_goal.path,
        duration=0.001,
        query=msgspec.Raw(encode(sent)),
        reply=msgspec.Raw(encode(GoalResponse(goal_id="t", accepted=True))),
    )
    still = Pose2D(x=6.0, y=1.2)
    out = [
        msg(t / 50, keys.ODOM.path, Odometry(stamp=t / 50, sim_time=t / 50, pose=still, linear_x=0.0, angular_z=0.0))
        for t in range(200)
    ]
    out += [
        msg(1.2, keys.JOINT_STATES.path, arm(1.2, 0.0)),  # at END too, but 0.8 s before the query
        msg(1.90, keys.JOINT_STATES.path, arm(1.90, 0.3)),
        msg(1.96, keys.JOINT_STATES.path, arm(1.94, 0.13)),
        msg(2.0005, keys.SAFETY_EVENTS.path, approval),
        msg(2.002, f"_trace/safety/{keys.CMD_TRAJECTORY.send_goal.path}", record),
        msg(2.15, keys.JOINT_STATES.path, arm(1.98, 0.0)),  # the recorder heard it late
    ]
    return sorted(out, key=lambda m: m.time)


def test_recheck_checks_a_trajectory_from_the_joint_state_safety_named(world_policy: SafetyPolicy) -> None:
    [named] = recheck(trajectory_sent_as_the_motion_ends(1.98), world_policy).checked
    assert (named.recorded, named.now) == (RecheckOutcome.APPROVED, RecheckOutcome.APPROVED), named.now_reason
    # Named the state 0.13 rad behind, it would have refused as recheck does: the name is what counts.
    [behind] = recheck(trajectory_sent_as_the_motion_ends(1.94), world_policy).checked
    assert behind.now is RecheckOutcome.VETOED and "would jump 0.130 rad" in behind.now_reason
    # Without a name, one not in the file, or one the recorder heard more than state_max_age (0.5 s)
    # from the query: the state before the query, then the next within 0.1 s.
    for stamp in (None, 1.97, 1.2):
        [guessed] = recheck(trajectory_sent_as_the_motion_ends(stamp), world_policy).checked
        assert guessed.now is RecheckOutcome.VETOED and "would jump 0.130 rad" in guessed.now_reason


def test_recheck_warns_when_the_kept_policy_is_not_the_one_safety_ran_with(world_policy: SafetyPolicy) -> None:
    ran_with = msg(
        0.5,
        keys.SAFETY_EVENTS.path,
        SafetyEvent(stamp=0.5, key="x", decision=Decision.APPROVED, policy_hash="sha256:aa"),
    )
    report = recheck([*incident(), ran_with], world_policy, robot_policy_hash="sha256:bb")
    assert len(report.warnings) == 1 and "sha256:aa" in report.warnings[0]


def test_rotation_while_threads_write_loses_and_repeats_nothing(tmp_path: Path) -> None:
    config = RecorderConfig(output_dir=str(tmp_path), max_file_bytes=64 * 1024, chunk_size=4096)
    recorder = Recorder(config, provenance())
    per_thread, writers = 1500, 3

    def write(n: int) -> None:
        for i in range(per_thread):
            assert recorder.record(f"{PREFIX}/w{n}", payload(i, 200))

    threads = [threading.Thread(target=write, args=(n,)) for n in range(writers)]
    for t in threads:
        t.start()
    while any(t.is_alive() for t in threads):
        recorder.tick()
    for t in threads:
        t.join()
    recorder.finish()

    assert len(recorder.files) > 2
    assert recorder.messages == per_thread * writers
    parts = [read_recording(p) for p in recorder.files]
    assert all(p.complete for p in parts)
    for n in range(writers):
        numbers = [json.loads(m.data)["i"] for p in parts for m in p.messages if m.key == f"{PREFIX}/w{n}"]
        assert numbers == list(range(per_thread))


def test_a_last_chunk_damaged_on_disk_is_skipped_and_said(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    sizes = write_flushed(full, 300)
    data = bytearray(full.read_bytes())
    data[sizes[1] + 200] ^= 0xFF  # inside the third chunk
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    recording = read_recording(damaged)

    assert not recording.complete and recording.skipped == 1 and "1 damaged record skipped" in recording.problem
    assert [json.loads(m.data)["i"] for m in recording.messages] == list(range(200))


def zeros_frame(size: int) -> bytes:
    """A zstd frame of `size` zero bytes that does not say its size: tens of kilobytes on disk."""
    compressor = zstandard.ZstdCompressor().compressobj()
    block = bytes(1 << 20)
    return b"".join(compressor.compress(block) for _ in range(size >> 20)) + compressor.flush()


def zeros_frame_saying_its_size(size: int) -> bytes:
    """A zstd frame of `size` zero bytes whose header says so, as the mcap writer makes them."""
    return zstandard.ZstdCompressor().compress(bytes(size))


@pytest.mark.parametrize(
    ("frame", "declared"),
    [
        (zeros_frame, 1 << 20),
        (zeros_frame_saying_its_size, 1 << 20),
        (zeros_frame, RECORD_SIZE_LIMIT + 1),
    ],
    ids=["understated", "understated_sized_frame", "too_large"],
)
def test_a_chunk_that_would_decompress_into_too_much_memory_ends_the_reading(
    tmp_path: Path, frame: Callable[[int], bytes], declared: int
) -> None:
    full = tmp_path / "full.mcap"
    sizes = write_flushed(full, 200)
    bomb = RecordBuilder()
    data = frame(64 << 20)
    Chunk("zstd", data, 0, 0, 0, declared).write(bomb)
    hostile = tmp_path / "hostile.mcap"
    hostile.write_bytes(full.read_bytes()[: sizes[0]] + bomb.end())

    tracemalloc.start()
    try:
        recording = read_recording(hostile)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()

    assert not recording.complete and "declares" in recording.problem
    assert [json.loads(m.data)["i"] for m in recording.messages] == list(range(100))
    assert peak < 16 << 20, f"reading held {peak >> 20} MiB for a {len(data)}-byte chunk"


def test_a_live_replay_passes_a_cancel_of_everything_on() -> None:
    cancel_all = trace("safety", keys.CMD_NAVIGATE.cancel_goal.path, CancelGoal(goal_id=CANCEL_ALL), {})
    plan = plan_replay([at(1.0, cancel_all)], ROBOT, ROBOT, live=True)
    [item] = plan.items
    assert item.kind is ReplayKind.QUERY and json.loads(item.payload)["goal_id"] == CANCEL_ALL


def test_recheck_lists_a_veto_a_loosened_policy_would_approve(world_policy: SafetyPolicy) -> None:
    # Recorded under a policy of 0.3 m/s; the default allows 0.6.
    messages = [*incident(), event(1.5, keys.CMD_VEL.path, Decision.VETOED, Twist(linear_x=0.45), Rule.BASE_SPEED)]
    report = recheck(sorted(messages, key=lambda m: m.time), world_policy)
    [changed] = report.differences
    assert (changed.recorded, changed.now, changed.command) == (
        RecheckOutcome.VETOED,
        RecheckOutcome.APPROVED,
        "cmd_vel 0.45 m/s, 0.00 rad/s",
    )


def test_recheck_skips_a_command_from_before_any_recorded_state(world_policy: SafetyPolicy) -> None:
    # A file that starts (after a rotation) just before a command: safety saw a pose it does not hold.
    messages = [m for m in incident() if m.path not in (keys.ODOM.path,) or m.time > 1.5]
    report = recheck(messages, world_policy)
    assert report.skipped["no robot state recorded before it"] == 2  # the two cmd_vel at 1.0 and 1.1 s
    assert report.differences == []


def test_recheck_of_a_hostile_file_counts_what_it_cannot_read_and_goes_on(world_policy: SafetyPolicy) -> None:
    deep = b"[" * 5000 + b"]" * 5000
    hostile = [
        Message(
            0.5,
            keys.SAFETY_EVENTS.path,
            b'{"stamp": 1, "key": "cmd/cmd_vel", "decision": "approved", "command": ' + deep + b"}",
        ),
        Message(0.6, keys.SAFETY_EVENTS.path, b"\xff\xfe not json"),
        # A goal query trace whose payload names a key that is not a goal.
        msg(
            0.7,
            f"_trace/safety/{keys.CMD_NAVIGATE.send_goal.path}",
            TraceRecord(stamp=0.7, service="safety", key="safety/reset", duration=0.0),
        ),
        Message(0.8, keys.ODOM.path, deep),
    ]
    report = recheck(sorted([*incident(), *hostile], key=lambda m: m.time), world_policy)
    assert report.differences == []
    assert report.skipped["a safety event that does not decode"] == 2
    assert report.skipped["a goal query trace that does not decode"] == 1
