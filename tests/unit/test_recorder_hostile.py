"""Recordings damaged after they were written: each file is written with the recorder's own writer, then
damaged here; the tools read what is whole, name what is not, and never raise."""

from __future__ import annotations

import functools
import json
import struct
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

import msgspec
import pytest
import typer
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from typer.testing import CliRunner

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal, Twist
from schemas.safety import Decision, SafetyEvent
from services.recorder import replay
from services.recorder.mcapfile import Recording
from services.recorder.reader import Recorded, read_recording, recover
from services.recorder.replay import Item, ReplayKind, ReplayPlan, default_target, plan_replay
from services.runtime import encode
from services.worldmodel import WorldFileError, parse_world
from tests.unit import test_timeline as timeline
from tether import cli, recordings
from tether.inspect import inspect
from tether.recordings import Player, recover_command

ROBOT = "r1"
PREFIX = keys.prefix(ROBOT)
T0 = 1_800_000_000 * 1_000_000_000
HEAD = struct.Struct("<BQ")
MAGIC = b"\x89MCAP0\r\n"


def write(path: Path, compression: str = "zstd", count: int = 300, flush_every: int = 100) -> Path:
    """`count` messages on three keys, a chunk flushed every `flush_every`."""
    recording = Recording(path, ROBOT, compression=compression, chunk_size=1 << 20, clock=lambda: T0)
    for i in range(count):
        recording.record(f"{PREFIX}/k{i % 3}", encode({"i": i}), log_time=T0 + i)
        if i % flush_every == flush_every - 1:
            recording.flush()
    recording.finish()
    return path


def records(data: bytes) -> Iterator[tuple[int, int, int]]:
    """(offset, opcode, length) of each top-level record, up to the footer."""
    at = len(MAGIC)
    while at + HEAD.size <= len(data):
        opcode, length = HEAD.unpack_from(data, at)
        yield at, opcode, length
        if opcode == Opcode.FOOTER:
            return
        at += HEAD.size + length


def numbers(path: Path) -> list[int]:
    return [json.loads(m.data)["i"] for m in read_recording(path).messages]


# 3. A damaged chunk is skipped, and reading goes on past it


def damage_flip(data: bytearray, at: int, length: int) -> None:
    data[at + HEAD.size + length // 2] ^= 0x55  # inside the chunk's data


def damage_length(data: bytearray, at: int, length: int) -> None:
    struct.pack_into("<Q", data, at + 1, 1 << 63)


def damage_declared_size(data: bytearray, at: int, length: int) -> None:
    (size,) = struct.unpack_from("<Q", data, at + HEAD.size + 16)
    struct.pack_into("<Q", data, at + HEAD.size + 16, size - 1)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("damage", [damage_flip, damage_length, damage_declared_size])
def test_a_damaged_chunk_is_skipped_named_and_the_chunks_after_it_are_read(
    tmp_path: Path, compression: str, damage: Callable[[bytearray, int, int], None]
) -> None:
    data = bytearray(write(tmp_path / "full.mcap", compression).read_bytes())
    chunks = [(at, length) for at, opcode, length in records(bytes(data)) if opcode == Opcode.CHUNK]
    assert len(chunks) == 3
    damage(data, *chunks[1])
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    recording = read_recording(damaged)

    assert numbers(damaged) == [*range(100), *range(200, 300)]
    assert recording.skipped == 1 and not recording.complete
    assert f"at byte {chunks[1][0]}" in recording.problem and "crash" not in recording.problem


def test_recover_and_inspect_say_a_chunk_was_skipped(tmp_path: Path) -> None:
    data = bytearray(write(tmp_path / "full.mcap").read_bytes())
    at, _, length = [r for r in records(bytes(data)) if r[1] == Opcode.CHUNK][1]
    damage_flip(data, at, length)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    app = typer.Typer()
    app.command("inspect")(inspect)
    app.command("recover")(recover_command)
    out = tmp_path / "out.mcap"
    recovered = CliRunner().invoke(app, ["recover", str(damaged), "-o", str(out)])
    assert recovered.exit_code == 0, recovered.output
    said = " ".join(recovered.output.split())
    assert "1 damaged record skipped" in said and "200 messages" in said
    assert numbers(out) == [*range(100), *range(200, 300)]

    inspected = CliRunner().invoke(app, ["inspect", "--json", "--no-progress", str(damaged)])
    assert inspected.exit_code == 0, inspected.output
    document = json.loads(inspected.stdout)
    assert document["complete"] is False and "damaged record skipped" in document["problem"]
    assert "is damaged" in " ".join(inspected.stderr.split())


# 1. A channel id defined again for another topic


def rewrite(source: Path, target: Path, edit: Callable[[list[object]], list[object]]) -> None:
    """`source` with each chunk's records passed through `edit`, written uncompressed (no summary)."""
    out = RecordBuilder()
    with source.open("rb") as stream:
        for record in StreamReader(stream, emit_chunks=True).records:
            if isinstance(record, DataEnd):
                break
            if isinstance(record, Chunk):
                inner = RecordBuilder()
                for item in edit(breakup_chunk(record)):
                    item.write(inner)  # type: ignore[attr-defined]
                body = inner.end()
                crc, size = zlib.crc32(body), len(body)
                record = Chunk("", body, record.message_end_time, record.message_start_time, crc, size)
            record.write(out)
    DataEnd(0).write(out)
    Footer(0, 0, 0).write(out)
    target.write_bytes(MAGIC + out.end() + MAGIC)


def test_recover_keeps_every_topic_of_a_channel_id_defined_again(tmp_path: Path) -> None:
    source = write(tmp_path / "source.mcap", count=3, flush_every=3)
    original = read_recording(source).messages

    def second_channel_reuses_the_first_id(found: list[object]) -> list[object]:
        ids = [r.id for r in found if isinstance(r, Channel)]
        again = {ids[1]: ids[0]}
        changed: list[object] = []
        for r in found:
            if isinstance(r, Channel):
                r = Channel(again.get(r.id, r.id), r.topic, r.message_encoding, r.metadata, r.schema_id)
            elif isinstance(r, Message):
                r = Message(again.get(r.channel_id, r.channel_id), r.log_time, r.data, r.publish_time, r.sequence)
            changed.append(r)
        return changed

    hostile = tmp_path / "again.mcap"
    rewrite(source, hostile, second_channel_reuses_the_first_id)
    assert [(m.key, m.data) for m in read_recording(hostile).messages] == [(m.key, m.data) for m in original]

    done = recover(hostile, tmp_path / "recovered.mcap")

    assert done.messages == 3
    copied = read_recording(tmp_path / "recovered.mcap")
    assert [(m.key, m.data) for m in copied.messages] == [(m.key, m.data) for m in original]
    assert len({c.topic for c in copied.channels.values()}) == len(copied.channels) == 3


# 2. A recorded key Zenoh does not take


def test_a_replay_skips_keys_zenoh_refuses_before_sending_anything(tmp_path: Path) -> None:
    path = tmp_path / "keys.mcap"
    with Recording(path, ROBOT, clock=lambda: T0) as recording:
        for n, key in enumerate([keys.ODOM.key(ROBOT), f"{PREFIX}/bad//key", f"{PREFIX}/a/**b", f"{PREFIX}/a/b"]):
            recording.record(key, b"{}", log_time=T0 + n)
    messages = read_recording(path).messages
    assert len(messages) == 4

    plan = plan_replay(messages, ROBOT, default_target(ROBOT), key_error=recordings.key_error)

    assert [item.key for item in plan.items] == [
        keys.ODOM.key(default_target(ROBOT)),
        f"{keys.prefix(default_target(ROBOT))}/a/b",
    ]
    [(why, count)] = plan.skipped.items()
    assert count == 2 and "not a valid Zenoh key expression" in why and "bad//key" in why


# 5. Log times far apart or going backwards


class Publisher:
    def __init__(self, sent: list[str], key: str) -> None:
        self.sent, self.key = sent, key

    def put(self, payload: bytes) -> None:
        self.sent.append(self.key)

    def undeclare(self) -> None:
        pass


class Session:
    def __init__(self) -> None:
        self.sent: list[str] = []

    def declare_publisher(self, key: str) -> Publisher:
        return Publisher(self.sent, key)


class FakeNode:
    def __init__(self) -> None:
        self.session = Session()


def test_a_replay_of_wild_log_times_keeps_its_order_and_shortens_gaps(tmp_path: Path) -> None:
    path = tmp_path / "wild.mcap"
    times = [T0, T0 - 10**18, 0, (1 << 64) - 1, T0 + 5]
    with Recording(path, ROBOT, clock=lambda: T0) as recording:
        for n, at in enumerate(times):
            recording.record(keys.CMD_VEL.key(ROBOT), encode(Twist(linear_x=n / 10)), log_time=at)

    plan = plan_replay(read_recording(path).messages, ROBOT, default_target(ROBOT))

    offsets = [item.at for item in plan.items]
    assert len(offsets) == 5 and offsets == sorted(offsets)
    assert plan.duration == max(offsets) == replay.MAX_GAP
    assert plan.retimed[replay.BACKWARDS] == 3 and sum(plan.retimed.values()) == 4
    node = FakeNode()
    started = time.monotonic()
    assert Player(node).play(plan, 1000.0) == 5  # type: ignore[arg-type]
    assert time.monotonic() - started < 10 * replay.MAX_GAP / 1000
    assert len(node.session.sent) == 5


def test_a_plans_duration_is_its_latest_item() -> None:
    items = [Item(at, ReplayKind.PUT, f"{PREFIX}/a", b"{}") for at in (0.0, 5.0, 2.0)]
    assert ReplayPlan(items, {}).duration == 5.0


# 4. Terminal control codes in a file's texts


def test_inspect_escapes_control_characters_a_file_carries(tmp_path: Path) -> None:
    path = tmp_path / "escape.mcap"
    reason = "\x1b[2J\x1b]0;owned\x07\x9b31mFAKE OK"
    event = SafetyEvent(
        stamp=0.0,
        key=keys.CMD_VEL.path,
        decision=Decision.VETOED,
        reason=reason,
        command=msgspec.Raw(encode(Twist(linear_x=5.0))),
    )
    with Recording(path, ROBOT, clock=lambda: T0) as recording:
        recording.record(keys.SAFETY_EVENTS.key(ROBOT), encode(event), log_time=T0)
        recording.record(f"{PREFIX}/cmd/\x1b[31mkey", encode(Twist()), log_time=T0 + 1)
    app = typer.Typer()
    app.command()(inspect)

    result = CliRunner().invoke(app, ["--all", "--no-progress", str(path)], env={"COLUMNS": "200"})

    assert result.exit_code == 0, result.output
    assert not any(code in result.output for code in ("\x1b", "\x07", "\x9b")), repr(result.output)
    assert "\\x1b[2J\\x1b]0;owned\\x07\\x9b31mFAKE OK" in result.output.replace("\n", "")


def test_printable_escapes_c0_and_c1_and_keeps_newlines_only_when_asked() -> None:
    assert recordings.printable("a\x1b[0m\tb\x7f\x85\nc") == "a\\x1b[0m\\x09b\\x7f\\x85\\x0ac"
    assert recordings.printable("a\nb\x00", newlines=True) == "a\nb\\x00"
    assert recordings.printable("plain — ünïcode") == "plain — ünïcode"


def test_a_recording_reads_back_whole_after_the_changes(tmp_path: Path) -> None:
    path = write(tmp_path / "whole.mcap", "lz4")
    recording = read_recording(path)
    assert recording.complete and recording.problem == "" and recording.skipped == 0
    assert numbers(path) == list(range(300))
    assert recording.messages[0] == Recorded(T0, f"{PREFIX}/k0", encode({"i": 0}))


def alias_bomb(levels: int) -> bytes:
    """A YAML document of ten nodes per level, each level ten aliases of the one before: 10**levels nodes."""
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, levels)]
    return "\n".join(lines).encode()


@pytest.mark.parametrize("text", [alias_bomb(7), b"rooms: &r [*r]"], ids=["ten million nodes", "holds itself"])
def test_a_recorded_world_of_aliases_that_expand_without_end_is_refused_before_it_is_built(text: bytes) -> None:
    """A recording's world file is hostile: 400 KB of aliases cost 3.9 GB and 28 s before the refusal."""
    started = time.thread_time()
    with pytest.raises(WorldFileError, match=r"YAML of more than 1000000 nodes once its aliases are expanded"):
        parse_world(text, Path("world.yaml"))
    assert time.thread_time() - started < 1.0
    # Aliases that stay small are YAML as any other: the same check passes them on to decoding.
    with pytest.raises(WorldFileError, match=r"world file world\.yaml") as small:
        parse_world(alias_bomb(2), Path("world.yaml"))
    assert "aliases are expanded" not in str(small.value)


def test_recheck_of_a_damaged_file_is_no_pass_even_when_what_it_read_agrees(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A chunk skipped held commands no one rechecked: exit 1 (it was 0), the damage named."""
    monkeypatch.setattr(timeline, "Recording", functools.partial(Recording, chunk_size=2048))  # many chunks
    path = tmp_path / "drive.mcap"
    writer = timeline.Writer(path, timeline.household(), beating=True)
    writer.beat(0.0, seq=1)
    for i in range(400):  # the base stands at the start; a goal to where it stands every 0.1 s
        t = 0.01 + i * 0.02
        writer.odom(t, 6.0, 1.2)
        if i % 5 == 4:
            goal = SendGoal(goal_id=f"g{i}", goal=NavigateToPoseGoal(pose=Pose2D(x=6.0, y=1.2)))
            writer.event(t + 0.001, keys.CMD_NAVIGATE.send_goal.path, Decision.APPROVED, command=goal)
            response = GoalResponse(goal_id=goal.goal_id, accepted=True)
            writer.trace(t + 0.002, "safety", keys.CMD_NAVIGATE.send_goal.path, goal, response)
    writer.finish()
    intact = CliRunner().invoke(cli.app, ["recheck", "--json", "--no-progress", str(path)])
    assert intact.exit_code == 0, intact.output
    assert json.loads(intact.stdout)["damaged_records"] == 0
    data = bytearray(path.read_bytes())
    chunks = [(at, length) for at, opcode, length in records(bytes(data)) if opcode == Opcode.CHUNK]
    assert len(chunks) > 3
    damage_flip(data, *chunks[len(chunks) // 2])
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    result = CliRunner().invoke(cli.app, ["recheck", "--json", "--no-progress", str(damaged)])

    document = json.loads(result.stdout)
    assert 0 < document["checked"] < json.loads(intact.stdout)["checked"] and document["differ"] == 0
    assert document["damaged_records"] == 1
    assert result.exit_code == 1, result.output
    assert "were not rechecked" in " ".join(result.stderr.split())
