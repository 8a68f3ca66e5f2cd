"""Review 46 of the recording tools: files damaged or crafted after they were written, and bad input."""

from __future__ import annotations

import struct
import time
from pathlib import Path

import msgspec
import pytest
from mcap.opcode import Opcode
from typer.testing import CliRunner

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.plan import PlanApproved
from schemas.robot import NavigateToPoseGoal
from schemas.safety import Decision, SafetyEvent
from schemas.trace import TraceRecord
from services.recorder.mapview import Track, draw_map, vetoed_goals
from services.recorder.mcapfile import Recording
from services.recorder.reader import Recorded, RecordingError, RecordingFile, join_recordings, read_recording
from services.recorder.timeline import EventKind, RobotState, Row, build_timeline
from services.runtime import encode
from services.worldmodel import load_world
from tests.unit import test_timeline as timeline
from tests.unit.test_recorder_hostile import HEAD, records
from tether import cli, recordings


def drive(path: Path) -> Path:
    """A recording with the household world and policy, and goals safety approved."""
    writer = timeline.Writer(path, timeline.household(), beating=True)
    writer.beat(0.0, seq=1)
    for i in range(20):
        t = 0.01 + i * 0.02
        writer.odom(t, 6.0, 1.2)
        if i % 5 == 4:
            goal = SendGoal(goal_id=f"g{i}", goal=NavigateToPoseGoal(pose=Pose2D(x=6.0, y=1.2)))
            writer.event(t + 0.001, keys.CMD_NAVIGATE.send_goal.path, Decision.APPROVED, command=goal)
            response = GoalResponse(goal_id=goal.goal_id, accepted=True)
            writer.trace(t + 0.002, "safety", keys.CMD_NAVIGATE.send_goal.path, goal, response)
    writer.finish()
    return path


def world_attachment(data: bytes) -> tuple[int, int]:
    """The offset and length of the first attachment record (the world file)."""
    at, _, length = next(r for r in records(data) if r[1] == Opcode.ATTACHMENT)
    return at, length


def test_a_world_file_changed_on_disk_is_skipped_as_damaged_not_taken_for_the_robots(tmp_path: Path) -> None:
    """An attachment's CRC was never checked: a digit of the world changed on disk (a wall moved, still
    valid YAML) was rechecked in as the world the robot ran in, with exit 0."""
    path = drive(tmp_path / "drive.mcap")
    intact = CliRunner().invoke(cli.app, ["recheck", "--json", "--no-progress", str(path)])
    assert intact.exit_code == 0, intact.output
    data = bytearray(path.read_bytes())
    at, length = world_attachment(bytes(data))
    digit = next(i for i in range(at + HEAD.size + 40, at + HEAD.size + length) if data[i] in b"123456789")
    data[digit] = data[digit] - 1
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    recording = read_recording(damaged)

    assert recording.world is None and recording.policy is not None
    assert recording.skipped == 1 and not recording.complete
    assert f"attachment record at byte {at}: its CRC does not match" in recording.problem
    result = CliRunner().invoke(cli.app, ["recheck", "--no-progress", str(damaged)])
    said = " ".join(result.stderr.split())
    assert result.exit_code == 2, result.output
    assert "is damaged" in said and "its metadata names is missing or damaged; give one with --world" in said


def test_parts_of_a_run_whose_world_differs_for_a_damaged_record_say_so(tmp_path: Path) -> None:
    paths = [tmp_path / "part0.mcap", tmp_path / "part1.mcap"]
    for part, path in enumerate(paths):
        recording = Recording(path, timeline.ROBOT, provenance=timeline.household(), part=part, run="run")
        recording.record(keys.ODOM.key(timeline.ROBOT), b"{}", log_time=timeline.T0 + part)
        recording.finish()
    data = bytearray(paths[1].read_bytes())
    at, length = world_attachment(bytes(data))
    data[at + HEAD.size + length - 10] ^= 0x01
    paths[1].write_bytes(bytes(data))

    with pytest.raises(RecordingError) as refused:
        join_recordings([read_recording(path) for path in paths])

    said = str(refused.value)
    assert "carry different world files" in said
    assert f"{paths[1]}: 1 damaged record skipped" in said and "its CRC does not match" in said


def test_an_attachment_written_without_a_crc_is_read(tmp_path: Path) -> None:
    """A CRC of 0 means none was computed (MCAP's rule): such a file is not damaged."""
    data = bytearray(drive(tmp_path / "drive.mcap").read_bytes())
    at, length = world_attachment(bytes(data))
    struct.pack_into("<I", data, at + HEAD.size + length - 4, 0)
    plain = tmp_path / "plain.mcap"
    plain.write_bytes(bytes(data))

    recording = read_recording(plain)

    assert recording.world is not None and recording.skipped == 0 and recording.complete


@pytest.mark.parametrize("duration", ["nan", "0", "-1"])
def test_record_refuses_a_duration_that_is_not_a_positive_number(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, duration: str
) -> None:
    """--duration nan passed `<= 0` and recorded without end, flushing in a busy loop."""

    def no_node(*args: object, **kwargs: object) -> None:
        raise AssertionError("a recording was started")

    monkeypatch.setattr(recordings, "Node", no_node)
    output = tmp_path / "out.mcap"

    result = CliRunner().invoke(cli.app, ["record", "-o", str(output), "--duration", duration])

    assert result.exit_code == 2, result.output
    assert f"--duration must be positive, not {duration}" in " ".join(result.stderr.split())
    assert not output.exists()


def test_a_timeline_of_many_plan_checks_is_not_quadratic() -> None:
    """Each plan check's trace looked through every event about plan checks for one within a second
    of it: 8,000 of each took 25 s to inspect, 100,000 (a few MB of file) hours."""
    count = 20_000
    prefix = keys.prefix("r1") + "/"
    event = encode(SafetyEvent(stamp=1.0, key=keys.PLAN_CHECK.path, decision=Decision.APPROVED, reason="ok"))
    reply = msgspec.Raw(encode(PlanApproved(checks=["checked"])))
    trace = encode(
        TraceRecord(
            stamp=1.0, service="safety", key=keys.PLAN_CHECK.path, duration=0.0, query=msgspec.Raw(b"null"), reply=reply
        )
    )
    second = 1_000_000_000
    t0 = 1_800_000_000 * second
    # Events 10 s apart, then the traces: the first half each half a second after an event (told by
    # it), the second half long after them all (rows of their own).
    events = [Recorded(t0 + i * 10 * second, prefix + keys.SAFETY_EVENTS.path, event) for i in range(count)]
    told = [
        Recorded(t0 + i * 10 * second + second // 2, prefix + "_trace/safety/" + keys.PLAN_CHECK.path, trace)
        for i in range(count // 2)
    ]
    alone = [
        Recorded(t0 + (count + i) * 10 * second, prefix + "_trace/safety/" + keys.PLAN_CHECK.path, trace)
        for i in range(count // 2)
    ]
    recording = RecordingFile(Path("many.mcap"), messages=[*events, *told, *alone], complete=True)

    started = time.monotonic()
    timeline = build_timeline(recording)

    assert time.monotonic() - started < 8.0
    from_traces = [row for row in timeline.rows if row.source.startswith("_trace/")]
    assert len(from_traces) == count // 2
    assert all(row.log_time >= t0 + count * 10 * second for row in from_traces)
    assert all(row.kind is EventKind.DECISION for row in from_traces)


def test_a_map_of_thousands_of_vetoes_at_distinct_spots_is_drawn_in_seconds(tmp_path: Path) -> None:
    """Each veto was grouped against every spot before it and drawn with its own label: 4,000 took
    25 s to draw, 100,000 (a crafted file's) hours."""
    count = 20_000
    spots = [(1.0 + (i % 200) * 0.055, 1.0 + (i // 200) * 0.055) for i in range(count)]
    rows = [
        Row(
            float(i),
            i,
            EventKind.DECISION,
            "cmd/x",
            "vetoed",
            RobotState(),
            "safety/events",
            decision=Decision.VETOED,
            target=spot,
        )
        for i, spot in enumerate(spots)
    ]
    again = Row(
        9e3,
        0,
        EventKind.DECISION,
        "cmd/x",
        "vetoed",
        RobotState(),
        "safety/events",
        decision=Decision.VETOED,
        target=(1.01, 1.01),
    )
    world = load_world()

    started = time.monotonic()
    marks = vetoed_goals([*rows, again])
    draw_map(tmp_path / "map.png", "many", world, world.keep_out, Track(), marks)

    assert time.monotonic() - started < 10.0
    assert len(marks) == count and marks[0].label == "vetoed @ 0.0, 9000.0 s"  # one spot, two vetoes
    assert (tmp_path / "map.png").stat().st_size > 0


def test_recover_of_a_directory_or_an_empty_name_is_a_usage_error(tmp_path: Path) -> None:
    # "" is ".", a directory: its name has no suffix to replace, and recover ended in a ValueError traceback.
    for name in ("", str(tmp_path)):
        result = CliRunner().invoke(cli.app, ["recover", name])
        assert result.exit_code == 2, result.output
        assert "is not a file" in " ".join(result.stderr.split()), result.stderr


def test_record_into_a_directory_that_does_not_exist_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # It made the missing directories on the way (as root, /nonexistent) and reported success.
    def no_node(*args: object, **kwargs: object) -> None:
        raise AssertionError("a recording was started")

    monkeypatch.setattr(recordings, "Node", no_node)
    output = tmp_path / "missing" / "x.mcap"
    result = CliRunner().invoke(cli.app, ["record", "-o", str(output), "--duration", "1"])
    assert result.exit_code == 2, result.output
    assert "no directory" in " ".join(result.stderr.split()), result.stderr
    assert not output.parent.exists()


def test_replay_to_an_empty_robot_name_is_refused(tmp_path: Path) -> None:
    # --to "" fell back to the default robot name and replayed, exit 0.
    path = tmp_path / "run.mcap"
    recording = Recording(path, timeline.ROBOT, provenance=timeline.household())
    recording.record(keys.ODOM.key(timeline.ROBOT), b"{}", log_time=timeline.T0)
    recording.finish()
    result = CliRunner().invoke(cli.app, ["replay", str(path), "--to", ""])
    assert result.exit_code == 2, result.output
    assert "--to" in result.stderr, result.stderr
