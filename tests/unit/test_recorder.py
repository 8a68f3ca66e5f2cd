"""The recorder's MCAP writer and config: write messages, finish, read back with mcap's own reader."""

from __future__ import annotations

import datetime as dt
import io
import json
import shutil
import threading
from pathlib import Path
from typing import Any

import msgspec
import pytest
from mcap.reader import make_reader

from schemas import keys
from schemas.actions import Feedback
from schemas.common import Pose2D, Stage
from schemas.executor import ExecutePlanFeedback
from schemas.plan import PlanText
from schemas.robot import NavigateToPoseFeedback, Twist
from schemas.trace import TraceRecord
from services.recorder import recorder as recorder_module
from services.recorder import scene3d
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import MAX_CHANNELS, Provenance, Recording, link_channel, link_record
from services.recorder.reader import read_recording
from services.recorder.recorder import Recorder
from services.runtime import ConfigError, encode, load_config

ROBOT = "r1"
CMD_VEL = keys.CMD_VEL.key(ROBOT)
FEEDBACK = keys.EXECUTE_PLAN.feedback.key(ROBOT)
TRACE = keys.trace_key(ROBOT, "parser", keys.PLAN_PARSE.path)
UNKNOWN = f"{keys.prefix(ROBOT)}/someone/else"

TRACE_RECORD = TraceRecord(
    stamp=1.5,
    service="parser",
    key=keys.PLAN_PARSE.path,
    duration=0.002,
    query=msgspec.Raw(encode(PlanText(text="go to the kitchen"))),
    error="",
)
MESSAGES: list[tuple[str, Any]] = [
    (CMD_VEL, Twist(linear_x=0.5, angular_z=-0.1)),
    (FEEDBACK, Feedback(goal_id="g1", feedback=ExecutePlanFeedback(stage=Stage.PARSE, step=0, action="navigate"))),
    (TRACE, TRACE_RECORD),
    (CMD_VEL, Twist(linear_x=0.0)),
]


class Clock:
    def __init__(self) -> None:
        self.now = 1_000_000_000

    def __call__(self) -> int:
        self.now += 1000
        return self.now


def read(data: bytes) -> tuple[dict[str, Any], list[tuple[Any, Any, Any]]]:
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    assert summary is not None, "finish() must write a summary"
    # The traffic only: what the recorder adds for Foxglove is tested in test_scene3d.py.
    channels = {c.topic: c for c in summary.channels.values() if not scene3d.is_derived(c.topic)}
    messages = [m for m in reader.iter_messages(log_time_order=True) if not scene3d.is_derived(m[1].topic)]
    return channels, messages


def write(messages: list[tuple[str, Any]]) -> tuple[Recording, bytes]:
    stream = io.BytesIO()
    recording = Recording(stream, ROBOT, clock=Clock())
    for key, message in messages:
        assert recording.record(key, encode(message))
    recording.finish()
    return recording, stream.getvalue()


def test_one_json_channel_per_key_with_the_json_schema_of_its_type() -> None:
    _, data = write(MESSAGES)
    channels, messages = read(data)

    assert set(channels) == {CMD_VEL, FEEDBACK, TRACE}
    assert len(messages) == len(MESSAGES)
    for schema, channel, _ in messages:
        assert channel.message_encoding == "json"
        assert schema.encoding == "jsonschema"
        document = json.loads(schema.data)
        assert document["type"] == "object"
    names = {channel.topic: schema.name for schema, channel, _ in messages}
    assert names[CMD_VEL] == "Twist"
    assert names[TRACE] == "TraceRecord"
    assert names[FEEDBACK] == "Feedback[ExecutePlanFeedback]"


def test_messages_decode_back_into_their_structs() -> None:
    _, data = write(MESSAGES)
    _, messages = read(data)

    decoded = []
    for _, channel, message in messages:
        topic = keys.topic_for_key(ROBOT, channel.topic)
        assert topic is not None
        if topic.type is TraceRecord:
            # See test_a_trace_record_decodes_back: the Struct itself cannot decode its Raw fields yet.
            decoded.append((channel.topic, json.loads(message.data)))
        else:
            decoded.append((channel.topic, msgspec.json.decode(message.data, type=topic.type)))
    expected = [(key, json.loads(encode(m)) if isinstance(m, TraceRecord) else m) for key, m in MESSAGES]
    assert decoded == expected
    assert decoded[2][1]["query"] == {"text": "go to the kitchen", "format": "auto"}


def test_a_trace_record_decodes_back() -> None:
    _, data = write([(TRACE, TRACE_RECORD)])
    _, [(_, _, message)] = read(data)
    record = msgspec.json.decode(message.data, type=TraceRecord)
    assert record.query is not None
    assert msgspec.json.decode(record.query, type=PlanText).text == "go to the kitchen"


def test_times_are_nanoseconds_and_in_order() -> None:
    _, data = write(MESSAGES)
    _, messages = read(data)

    times = [m.log_time for _, _, m in messages]
    assert times == sorted(times)
    assert all(m.publish_time == m.log_time for _, _, m in messages)
    assert [m.sequence for _, _, m in messages] == [0, 1, 2, 3]


def test_a_schema_is_written_once_for_keys_of_the_same_type() -> None:
    cmd_feedback = keys.CMD_NAVIGATE.feedback.key(ROBOT)
    robot_feedback = keys.ROBOT_NAVIGATE.feedback.key(ROBOT)
    feedback = Feedback(
        goal_id="g2", feedback=NavigateToPoseFeedback(pose=Pose2D(x=1.0, y=2.0), distance_remaining=1.0)
    )
    _, data = write([(cmd_feedback, feedback), (robot_feedback, feedback)])

    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    assert len(summary.channels) == 2
    assert len(summary.schemas) == 1


def test_an_unknown_key_under_the_prefix_is_recorded_with_a_permissive_schema() -> None:
    _, data = write([(UNKNOWN, {"anything": [1, 2]})])
    _, messages = read(data)

    [(schema, channel, message)] = messages
    assert channel.topic == UNKNOWN
    assert json.loads(schema.data) == {}
    assert json.loads(message.data) == {"anything": [1, 2]}


@pytest.mark.parametrize(
    "payload",
    [b"\x00\x01 not json", b'{"linear_x": 0.5', b'{"frame": "\xff"}'],
    ids=["binary", "cut short", "invalid utf-8 in a string"],
)
def test_a_payload_that_is_not_json_is_dropped_and_counted(payload: bytes) -> None:
    stream = io.BytesIO()
    recording = Recording(stream, ROBOT)
    assert not recording.record(CMD_VEL, payload)
    assert recording.record(CMD_VEL, encode(Twist()))
    recording.finish()

    assert (recording.messages, recording.dropped) == (1, 1)
    _, messages = read(stream.getvalue())
    assert len(messages) == 1


def test_finish_is_idempotent_and_later_messages_are_dropped() -> None:
    recording, _ = write(MESSAGES[:1])
    recording.finish()
    assert not recording.record(CMD_VEL, encode(Twist()))
    assert recording.dropped == 1
    recording.flush()  # a no-op once finished


def test_flush_writes_a_readable_chunk_before_finish() -> None:
    stream = io.BytesIO()
    recording = Recording(stream, ROBOT)
    recording.record(CMD_VEL, encode(Twist(linear_x=0.2)))
    recording.flush()
    # An unfinished file has no summary, but the flushed chunk is already there.
    assert len(stream.getvalue()) > 100
    recording.finish()


def test_concurrent_writers_lose_nothing() -> None:
    stream = io.BytesIO()
    recording = Recording(stream, ROBOT)
    threads_count, per_thread = 4, 250

    def publish(n: int) -> None:
        for i in range(per_thread):
            recording.record(f"{keys.prefix(ROBOT)}/load/{n}", encode({"i": i}))

    threads = [threading.Thread(target=publish, args=(n,)) for n in range(threads_count)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    recording.finish()

    channels, messages = read(stream.getvalue())
    assert len(channels) == threads_count
    assert len(messages) == recording.messages == threads_count * per_thread


def test_compression_options_all_read_back() -> None:
    for compression in ("zstd", "lz4", "none"):
        stream = io.BytesIO()
        with Recording(stream, ROBOT, compression=compression) as recording:
            recording.record(CMD_VEL, encode(Twist(linear_x=0.1)))
        _, messages = read(stream.getvalue())
        assert len(messages) == 1, compression


def test_config_defaults_and_file_name() -> None:
    config = load_config(RecorderConfig, None, "recorder")
    started = dt.datetime(2025, 1, 31, 13, 0, 5, tzinfo=dt.timezone(dt.timedelta(hours=1)))
    assert config.path_for("robot1", started) == Path("recordings/robot1_20250131T120005Z.mcap")


def test_config_from_a_file(tmp_path: Path) -> None:
    path = tmp_path / "tether.toml"
    path.write_text('[recorder]\noutput_dir = "/var/lib/tether"\nfile_pattern = "{stamp}-{robot}.mcap"\n')
    config = load_config(RecorderConfig, path, "recorder")
    started = dt.datetime(2025, 1, 31, 12, tzinfo=dt.UTC)
    assert config.path_for("r2", started) == Path("/var/lib/tether/20250131T120000Z-r2.mcap")


@pytest.mark.parametrize(
    ("table", "named"),
    [
        ('file_pattern = "{robot}.mcap"', "file_pattern"),
        ('file_pattern = "{robot}_{stamp}_{user}.mcap"', "file_pattern"),
        ('file_pattern = "sub/{robot}_{stamp}.mcap"', "file_pattern"),
        ('compression = "gzip"', "compression"),
        ("flush_interval = 0", "flush_interval"),
        ("colour = 1", "colour"),
    ],
)
def test_a_bad_config_value_is_named_with_the_file(tmp_path: Path, table: str, named: str) -> None:
    path = tmp_path / "tether.toml"
    path.write_text(f"[recorder]\n{table}\n")
    with pytest.raises(ConfigError, match=named) as err:
        load_config(RecorderConfig, path, "recorder")
    assert str(path) in str(err.value)


# What a peer or the disk does to a live recording (a review's findings): never raised, always counted


def test_keys_past_max_channels_are_dropped_and_counted_and_the_file_stays_whole(tmp_path: Path) -> None:
    """Past 65,535 keys, mcap's 16-bit channel id overflowed inside a chunk: the chunk unreadable,
    every later new key an exception, and finish() raising with the file left without its summary."""
    path = tmp_path / "flood.mcap"
    recording = Recording(path, ROBOT)
    assert recording.record(CMD_VEL, encode(Twist(linear_x=0.1)))
    for i in range(MAX_CHANNELS + 50):
        assert recording.record(f"{keys.prefix(ROBOT)}/made_up/k{i}", b"{}") == (i < MAX_CHANNELS - 1)
    assert recording.record(CMD_VEL, encode(Twist(linear_x=0.2))), "a key already known is still recorded"
    recording.finish()
    assert recording.dropped == 51 and recording.messages == MAX_CHANNELS + 1
    recorded = read_recording(path)
    assert recorded.complete and len(recorded.messages) == MAX_CHANNELS + 1
    assert recorded.messages[-1].key == CMD_VEL


def test_a_payload_too_big_for_a_chunk_the_reader_takes_is_dropped_not_the_chunk(tmp_path: Path) -> None:
    """Counted recorded, a 130 MiB message made a chunk the reader refuses, with its neighbours and
    every later message on a channel defined in it."""
    path = tmp_path / "big.mcap"
    recording = Recording(path, ROBOT)
    assert recording.record(CMD_VEL, encode(Twist(linear_x=0.1)))
    assert not recording.record(UNKNOWN, b'"' + b"a" * (recording.max_payload + 1) + b'"')
    assert recording.record(CMD_VEL, encode(Twist(linear_x=0.2)))
    recording.finish()
    assert recording.dropped == 1
    assert [m.key for m in read_recording(path).messages] == [CMD_VEL, CMD_VEL]


def test_a_message_on_the_robot_links_own_key_is_dropped(tmp_path: Path) -> None:
    """Recorded there, a peer's message was read as a link record: it vanished, and its 'MAC' was put
    on another message that had none."""
    path = tmp_path / "link.mcap"
    recording = Recording(path, ROBOT)
    heartbeat = keys.HEARTBEAT.key(ROBOT)
    assert recording.record(heartbeat, b'{"seq": 1}')
    assert not recording.record(link_channel(ROBOT), link_record(0, b"\xab" * 32))
    recording.finish()
    [beat] = read_recording(path).messages
    assert beat.key == heartbeat and beat.attachment is None


def test_a_disk_that_fills_drops_and_counts_and_says_so_once(caplog: pytest.LogCaptureFixture) -> None:
    """/dev/full answers every write with ENOSPC: the error escaped into Zenoh's callback, then the
    flush and finish raised, and the service died with only tracebacks."""
    with open("/dev/full", "wb", buffering=0) as full:
        recording = Recording(full, ROBOT, chunk_size=1024)
        for i in range(2000):
            recording.record(CMD_VEL, encode(Twist(linear_x=i / 2000)))
        recording.flush()
        recording.finish()
    assert "No space left on device" in recording.error
    assert recording.dropped > 0 and recording.messages + recording.dropped == 2000
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == [
        f"{recording.error}; messages are dropped and counted until a new file can be written"
    ]


def test_a_rotation_that_cannot_start_its_file_keeps_the_current_one(tmp_path: Path) -> None:
    """The next file's directory gone: tick() raised and the recorder exited, though the file it
    was writing could go on."""
    out = tmp_path / "out"
    clock = [1_800_000_000 * 10**9]
    recorder = Recorder(
        RecorderConfig(output_dir=str(out), max_file_seconds=60),
        Provenance(ROBOT),
        clock=lambda: clock[0],
        monotonic=lambda: clock[0],
    )
    assert recorder.record(CMD_VEL, encode(Twist(linear_x=0.1)))
    first = recorder.status().path
    moved = tmp_path / "moved"
    out.rename(moved)
    out.write_text("not a directory")  # where new files go, no file can be made
    clock[0] += 61 * 10**9
    recorder.tick()
    status = recorder.status()
    assert status.path == first and "cannot start the next file" in status.error
    assert recorder.record(CMD_VEL, encode(Twist(linear_x=0.2)))
    out.unlink()
    moved.rename(out)
    clock[0] += 1 * 10**9
    recorder.tick()  # the directory is back: the rotation happens
    after = recorder.status()
    assert after.path != first and after.error == "" and after.messages == 2
    recorder.finish()
    assert len(read_recording(Path(first)).messages) == 2


def test_a_file_made_by_another_recorder_between_the_look_and_the_open_is_not_fatal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two recorders of one robot and output_dir rotating in the same second: the name looked free,
    the other made it, and the open raised FileExistsError out of the recorder."""
    looked = recorder_module.unused_path

    def taken_meanwhile(path: Path, twin: Any = None) -> Path:
        free = looked(path, twin)
        if not list(tmp_path.glob("*.mcap")):
            free.write_bytes(b"the other recorder's")  # it got there first
        return free

    monkeypatch.setattr(recorder_module, "unused_path", taken_meanwhile)
    recorder = Recorder(RecorderConfig(output_dir=str(tmp_path)), Provenance(ROBOT))
    other = sorted(tmp_path.glob("*.mcap"))[0]
    assert recorder.status().path != str(other) and other.read_bytes() == b"the other recorder's"
    recorder.finish()


def test_a_file_removed_while_it_is_written_is_followed_by_a_new_one(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The output directory cleaned away mid-file: recording went on into a deleted file, the status
    saying all was well, and nothing of it was left after finish."""
    out = tmp_path / "out"
    recorder = Recorder(RecorderConfig(output_dir=str(out)), Provenance(ROBOT))
    assert recorder.record(CMD_VEL, encode(Twist(linear_x=0.1)))
    lost = recorder.status().path
    shutil.rmtree(out)
    recorder.tick()
    status = recorder.status()
    assert len(status.files) == 2 and Path(status.path).exists(), "a new file (its name may be the same)"
    assert lost == status.files[0]
    assert any("was removed while it was written" in r.getMessage() for r in caplog.records)
    assert recorder.record(CMD_VEL, encode(Twist(linear_x=0.2)))
    recorder.finish()
    assert len(read_recording(Path(recorder.status().path)).messages) == 1
