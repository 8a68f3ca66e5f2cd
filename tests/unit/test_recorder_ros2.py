"""The ROS 2 side of the recorder offline: config, keys to topics, attachments, the ros2-profile file, rotation."""

from __future__ import annotations

import datetime as dt
import io
import logging
from pathlib import Path
from typing import Any

import msgspec
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from services.recorder.config import RecorderConfig, Ros2RecordConfig
from services.recorder.mcapfile import Provenance
from services.recorder.reader import RecordingError, read_recording
from services.recorder.recorder import Recorder
from services.recorder.ros2file import (
    Ros2Recording,
    Ros2Source,
    RosKeys,
    RosTopic,
    Skipped,
    WarnOnce,
    publish_time,
    ros2_path,
)
from services.ros2.types import RosTypes
from services.ros2.wire import Attachment, Naming, Style
from services.runtime import ConfigError, load_config

SECOND = 1_000_000_000
TWIST = "geometry_msgs/msg/Twist"
ODOMETRY = "nav_msgs/msg/Odometry"
# Published by ROS 2 (rmw_zenoh's design doc and `ros2 topic info -v`); the typestore must agree.
TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
ODOMETRY_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
CMD_VEL_KEY = f"0/cmd_vel/geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}"
ODOM_KEY = f"0/robot1/odom/nav_msgs::msg::dds_::Odometry_/{ODOMETRY_HASH}"
GID = bytes(range(16))


@pytest.fixture(scope="module")
def types() -> RosTypes:
    return RosTypes("jazzy")


@pytest.fixture
def rmw_keys(types: RosTypes) -> RosKeys:
    return RosKeys(types, Naming(Style.RMW_ZENOH, 0))


class Clock:
    def __init__(self) -> None:
        self.now = 1_800_000_000 * SECOND

    def __call__(self) -> int:
        return self.now


def twist(types: RosTypes, x: float, yaw_rate: float) -> Any:
    message = types.new(TWIST)
    message.linear.x, message.angular.z = x, yaw_rate
    return message


def read_ros2(data: bytes) -> tuple[str, list[tuple[Any, Any, Any, Any]]]:
    """The header profile and every (schema, channel, message, decoded) of a ros2-profile file, read with
    Foxglove's decoder (mcap-ros2-support), not with the typestore that wrote it."""
    reader = make_reader(io.BytesIO(data), decoder_factories=[DecoderFactory()])
    profile = reader.get_header().profile
    return profile, list(reader.iter_decoded_messages(log_time_order=False))


# Config


def test_the_ros2_table_is_optional_and_its_defaults_reach_an_rmw_zenoh_router_on_this_machine() -> None:
    assert RecorderConfig().ros2 is None
    config = msgspec.convert({"ros2": {}}, RecorderConfig).ros2
    assert config is not None
    assert (config.endpoint, config.mode, config.style, config.distro) == (
        "tcp/127.0.0.1:7447",
        "client",
        Style.RMW_ZENOH,
        "jazzy",
    )


def test_the_domain_is_ros_domain_id_else_the_configured_one_else_zero() -> None:
    assert Ros2RecordConfig().domain({}) == 0
    assert Ros2RecordConfig(domain_id=3).domain({}) == 3
    assert Ros2RecordConfig(domain_id=3).domain({"ROS_DOMAIN_ID": "7"}) == 7
    assert Ros2RecordConfig().domain({"ROS_DOMAIN_ID": " "}) == 0
    for bad in ("x", "-1", "233"):
        with pytest.raises(ValueError, match="ROS_DOMAIN_ID"):
            Ros2RecordConfig().domain({"ROS_DOMAIN_ID": bad})


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ('style = "bridge"', "needs \\[recorder.ros2.topics\\]"),
        ('[recorder.ros2.topics]\nodom = "nav_msgs/msg/Odometry"', 'topics is for style "bridge"'),
        ('style = "bridge"\n[recorder.ros2.topics]\n"a//b" = "nav_msgs/msg/Odometry"', "not a valid ROS name"),
        ('style = "bridge"\n[recorder.ros2.topics]\nodom = "Odometry"', "ros2.topics"),
        ('style = "dds"', "ros2.style"),
        ("domain_id = 300", "ros2.domain_id"),
        ('distro = "rolling"', "ros2.distro"),
        ('endpoint = "127.0.0.1:7447"', "ros2.endpoint"),
        ("typo = 1", "typo"),
    ],
)
def test_a_bad_ros2_table_is_refused_naming_the_file_and_the_value(tmp_path: Path, table: str, message: str) -> None:
    path = tmp_path / "tether.toml"
    path.write_text(f"[recorder.ros2]\n{table}\n")
    with pytest.raises(ConfigError, match=message) as raised:
        load_config(RecorderConfig, path, "recorder")
    assert str(path) in str(raised.value)


# Keys, types and attachments


def test_the_typestore_hashes_match_the_ones_ros_2_publishes(types: RosTypes) -> None:
    assert types.hash(TWIST) == TWIST_HASH and types.hash(ODOMETRY) == ODOMETRY_HASH


def test_an_rmw_zenoh_key_names_the_topic_as_ros2_bag_does_and_its_type(rmw_keys: RosKeys) -> None:
    assert rmw_keys.key_exprs() == ["0/**"]
    assert rmw_keys.resolve(CMD_VEL_KEY) == RosTopic("/cmd_vel", TWIST, TWIST_HASH)
    assert rmw_keys.resolve(ODOM_KEY) == RosTopic("/robot1/odom", ODOMETRY, ODOMETRY_HASH)
    schema = rmw_keys.schema(TWIST)
    assert schema is not None and schema.startswith(b"geometry_msgs/Vector3 linear\n")
    assert b"MSG: geometry_msgs/Vector3" in schema


@pytest.mark.parametrize(
    ("key", "kind"),
    [
        ("0/cmd_vel", "not an rmw_zenoh topic key"),
        ("1/" + CMD_VEL_KEY[2:], "not an rmw_zenoh topic key"),  # another domain
        ("0//geometry_msgs::msg::dds_::Twist_/" + TWIST_HASH, "not an rmw_zenoh topic key"),
        ("0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_xyz", "not an rmw_zenoh topic key"),
        ("0/thing/acme_msgs::msg::dds_::Thing_/RIHS01_" + "0" * 64, "type acme_msgs/msg/Thing"),
        ("0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_" + "0" * 64, f"type {TWIST} RIHS01_{'0' * 64}"),
    ],
)
def test_a_key_without_a_topic_or_schema_here_is_skipped_by_kind(rmw_keys: RosKeys, key: str, kind: str) -> None:
    with pytest.raises(Skipped) as skipped:
        rmw_keys.resolve(key)
    assert skipped.value.kind == kind


def test_bridge_keys_are_the_bare_names_and_take_their_types_from_the_config(types: RosTypes) -> None:
    keys = RosKeys(types, Naming(Style.BRIDGE, 0), {"cmd_vel": TWIST, "/robot1/odom": ODOMETRY})
    assert keys.key_exprs() == ["cmd_vel", "robot1/odom"]
    assert keys.resolve("robot1/odom") == RosTopic("/robot1/odom", ODOMETRY, ODOMETRY_HASH)
    with pytest.raises(Skipped):
        keys.resolve("scan")
    with pytest.raises(ValueError, match="acme_msgs/msg/Thing"):
        RosKeys(types, Naming(Style.BRIDGE, 0), {"thing": "acme_msgs/msg/Thing"})


def test_publish_time_is_the_attachments_source_timestamp_when_it_is_valid() -> None:
    assert publish_time(Attachment(1, 1_700_000_000 * SECOND, GID).encode()) == 1_700_000_000 * SECOND
    assert publish_time(None) is None
    assert publish_time(b"") is None
    assert publish_time(Attachment(1, 0, GID).encode()) is None
    assert publish_time(Attachment(1, 5, GID).encode()[:-1]) is None
    assert publish_time(b"\xff" * 33) is None  # negative numbers


# The file


def test_samples_are_written_as_received_in_the_ros2_profile_and_decode_with_foxglove_s_reader(
    types: RosTypes, rmw_keys: RosKeys
) -> None:
    out, clock = io.BytesIO(), Clock()
    recording = Ros2Recording(out, rmw_keys, clock=clock, metadata={"robot": "r1"})
    sent = [twist(types, 0.1 * i, -0.05 * i) for i in range(5)]
    stamps = []
    for i, message in enumerate(sent):
        clock.now += SECOND // 10
        stamps.append(clock.now - 3_000_000)
        attachment = Attachment(i + 1, stamps[-1], GID).encode()
        assert recording.record(CMD_VEL_KEY, types.encode(TWIST, message), attachment)
    odom = types.new(ODOMETRY)
    odom.header.frame_id, odom.child_frame_id = "odom", "base_link"
    odom.pose.pose.position.x, odom.pose.pose.orientation.w = 1.5, 1.0
    clock.now += SECOND
    assert recording.record(ODOM_KEY, types.encode(ODOMETRY, odom), None)  # no attachment: bridge-like
    recording.finish()

    profile, messages = read_ros2(out.getvalue())
    assert profile == "ros2"
    assert [(c.topic, s.name, s.encoding, c.message_encoding) for s, c, _, _ in messages] == [
        ("/cmd_vel", TWIST, "ros2msg", "cdr")
    ] * 5 + [("/robot1/odom", ODOMETRY, "ros2msg", "cdr")]
    for (_, channel, message, decoded), value, stamp in zip(messages, sent, stamps, strict=False):
        assert (decoded.linear.x, decoded.angular.z) == (value.linear.x, value.angular.z)
        assert message.data == types.encode(TWIST, value)  # the bytes as they came, header and all
        assert message.publish_time == stamp and message.log_time == stamp + 3_000_000
        assert channel.metadata == {"offered_qos_profiles": "", "topic_type_hash": TWIST_HASH}
    _, _, last, decoded_odom = messages[-1]
    assert decoded_odom.header.frame_id == "odom" and decoded_odom.pose.pose.position.x == 1.5
    assert last.publish_time == last.log_time == clock.now
    assert [m.sequence for _, _, m, _ in messages] == list(range(6))
    summary = make_reader(io.BytesIO(out.getvalue())).get_summary()
    assert summary is not None and [m.name for m in summary.metadata_indexes] == ["tether_ros2"]


def test_what_has_no_place_in_the_file_is_skipped_and_warned_about_once_per_kind(
    types: RosTypes, rmw_keys: RosKeys, caplog: pytest.LogCaptureFixture
) -> None:
    out = io.BytesIO()
    recording = Ros2Recording(out, rmw_keys)
    cdr = types.encode(TWIST, twist(types, 0.2, 0.0))
    unknown = "0/thing/acme_msgs::msg::dds_::Thing_/RIHS01_" + "1" * 64
    with caplog.at_level(logging.WARNING):
        for _ in range(3):
            assert not recording.record(unknown, cdr)
            assert not recording.record("0/garbage", cdr)
            assert not recording.record(CMD_VEL_KEY, b"")
            assert not recording.record(CMD_VEL_KEY, b"{not cdr}")
        # A malformed attachment loses only the publish time.
        assert recording.record(CMD_VEL_KEY, cdr, b"\x00" * 7)
    assert (recording.messages, recording.skipped) == (1, 12)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 3, warnings
    assert any("typestore does not know acme_msgs/msg/Thing" in w for w in warnings)
    assert any("not CDR" in w and "/cmd_vel" in w for w in warnings)
    recording.finish()
    assert not recording.record(CMD_VEL_KEY, cdr)
    _, messages = read_ros2(out.getvalue())
    assert len(messages) == 1 and messages[0][2].publish_time == messages[0][2].log_time


def test_an_action_s_status_and_feedback_are_recorded_with_schemas_readers_parse(
    types: RosTypes, rmw_keys: RosKeys
) -> None:
    naming = Naming(Style.RMW_ZENOH, 0)
    action = naming.action("navigate_to_pose", "nav2_msgs/action/NavigateToPose", types)
    out = io.BytesIO()
    recording = Ros2Recording(out, rmw_keys)
    status = types.new(action.status.ros_type)
    feedback = types.new(action.feedback.ros_type)
    feedback.feedback.distance_remaining = 2.5
    assert recording.record(action.status.key, types.encode(action.status.ros_type, status))
    assert recording.record(action.feedback.key, types.encode(action.feedback.ros_type, feedback))
    recording.finish()

    reader = make_reader(io.BytesIO(out.getvalue()), decoder_factories=[DecoderFactory()])
    status_topic = "/navigate_to_pose/_action/status"
    [(_, _, _, decoded)] = list(reader.iter_decoded_messages(topics=[status_topic]))
    assert decoded.status_list == []
    # Foxglove's Python decoder refuses "_" in type names (NavigateToPose_FeedbackMessage), which
    # Foxglove itself and ros2 bag accept; rosbags' reader, given only the file's schema, decodes it.
    [(schema, channel, message)] = list(reader.iter_messages(topics=["/navigate_to_pose/_action/feedback"]))
    assert (schema.name, channel.message_encoding) == (action.feedback.ros_type, "cdr")
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(schema.data.decode(), schema.name))
    assert store.deserialize_cdr(message.data, schema.name).feedback.distance_remaining == 2.5


def test_only_plain_cdr_as_ros_2_sends_it_has_a_place_in_the_file(types: RosTypes, rmw_keys: RosKeys) -> None:
    recording = Ros2Recording(io.BytesIO(), rmw_keys)
    body = types.encode(TWIST, twist(types, 0.1, 0.0))[4:]
    for header, kept in ((b"\x00\x01\x00\x00", True), (b"\x00\x00\x00\x00", True), (b"\x00\x03\x00\x00", False)):
        assert recording.record(CMD_VEL_KEY, header + body) is kept
    recording.finish()


def test_warn_once_forgets_nothing_but_stops_remembering_new_kinds_past_its_bound(
    caplog: pytest.LogCaptureFixture,
) -> None:
    warn = WarnOnce()
    with caplog.at_level(logging.WARNING):
        for i in range(3000):
            warn(f"kind {i}", "x")
        warn("kind 0", "x")
    assert len(caplog.records) == 1024


# The recorder: the twin beside each file, rotated with it


def test_each_tether_file_has_a_ros2_twin_rotated_with_it_and_named_in_the_status(
    tmp_path: Path, types: RosTypes, rmw_keys: RosKeys
) -> None:
    clock = Clock()
    config = RecorderConfig(output_dir=str(tmp_path), max_file_seconds=10.0)
    recorder = Recorder(
        config, Provenance("r1"), clock=clock, monotonic=clock, ros2=Ros2Source(rmw_keys, "tcp/127.0.0.1:7447")
    )
    cdr = types.encode(TWIST, twist(types, 0.3, 0.0))
    assert recorder.record_ros2(CMD_VEL_KEY, cdr, Attachment(1, clock.now, GID).encode())
    recorder.record("tether/r1/a", b"{}")
    clock.now += 11 * SECOND
    recorder.tick()  # a new pair of files
    assert recorder.record_ros2(CMD_VEL_KEY, cdr)
    assert not recorder.record_ros2("0/garbage", cdr)
    status = recorder.status()
    recorder.finish()

    assert len(recorder.files) == 2 and recorder.ros2_files == [ros2_path(p) for p in recorder.files]
    assert recorder.ros2_files[0].name == recorder.files[0].stem + ".ros2.mcap"
    assert status.ros2 is not None
    assert status.ros2.path == str(recorder.ros2_files[1]) and status.ros2.files == [
        str(p) for p in recorder.ros2_files
    ]
    assert (status.ros2.messages, status.ros2.skipped, status.ros2.error) == (2, 1, "")
    for part, path in enumerate(recorder.ros2_files):
        with path.open("rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            assert reader.get_header().profile == "ros2"
            meta = next(reader.iter_metadata()).metadata
            assert meta["part"] == str(part) and meta["run"] == recorder.run
            assert meta["tether_file"] == recorder.files[part].name and meta["domain_id"] == "0"
            assert [d.linear.x for _, _, _, d in reader.iter_decoded_messages()] == [0.3]
    # tether's own files are untouched by it, and tether's reader says what the twin is.
    assert [m.key for m in read_recording(recorder.files[0]).messages] == ["tether/r1/a"]
    with pytest.raises(RecordingError, match="ROS 2 recording"):
        read_recording(recorder.ros2_files[0])


def test_a_name_is_taken_only_when_both_files_are_free(tmp_path: Path, rmw_keys: RosKeys) -> None:
    clock = Clock()
    config = RecorderConfig(output_dir=str(tmp_path))
    first = config.path_for("r1", dt.datetime.fromtimestamp(clock.now / 1e9, dt.UTC))
    ros2_path(first).write_bytes(b"left over")
    recorder = Recorder(
        config, Provenance("r1"), clock=clock, monotonic=clock, ros2=Ros2Source(rmw_keys, "tcp/127.0.0.1:7447")
    )
    recorder.finish()
    assert recorder.files == [first.with_name(first.stem + "_1.mcap")]
    assert ros2_path(first).read_bytes() == b"left over"


def test_a_twin_that_cannot_be_written_leaves_tether_s_recording_going(
    tmp_path: Path, rmw_keys: RosKeys, types: RosTypes, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(*_args: Any, **_kwargs: Any) -> None:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Ros2Recording, "__init__", refuse)
    recorder = Recorder(
        RecorderConfig(output_dir=str(tmp_path)), Provenance("r1"), ros2=Ros2Source(rmw_keys, "tcp/x:1")
    )
    assert recorder.record("tether/r1/a", b"{}")
    assert not recorder.record_ros2(CMD_VEL_KEY, types.encode(TWIST, twist(types, 0.1, 0.0)))
    recorder.ros2_link_failed("cannot open a client session to the ROS 2 robot at tcp/x:1")
    status = recorder.status()
    recorder.finish()
    assert status.messages == 1 and status.ros2 is not None and status.ros2.path == ""
    assert "tcp/x:1" in status.ros2.error and "Permission denied" in status.ros2.error
    assert read_recording(recorder.files[0]).complete


def test_a_twin_whose_disk_fails_is_an_error_in_the_status_and_tether_s_recording_goes_on(
    tmp_path: Path, rmw_keys: RosKeys, monkeypatch: pytest.MonkeyPatch
) -> None:
    def full(_self: Ros2Recording) -> None:
        raise OSError(28, "No space left on device")

    recorder = Recorder(
        RecorderConfig(output_dir=str(tmp_path)), Provenance("r1"), ros2=Ros2Source(rmw_keys, "tcp/x:1")
    )
    monkeypatch.setattr(Ros2Recording, "flush", full)
    recorder.record("tether/r1/a", b"{}")
    recorder.tick()
    status = recorder.status()
    recorder.finish()
    assert status.ros2 is not None and "No space left on device" in status.ros2.error
    assert read_recording(recorder.files[0]).complete


def test_without_the_ros2_table_nothing_changes(tmp_path: Path) -> None:
    recorder = Recorder(RecorderConfig(output_dir=str(tmp_path)), Provenance("r1"))
    assert not recorder.record_ros2(CMD_VEL_KEY, b"\x00\x01\x00\x00")
    assert recorder.status().ros2 is None
    recorder.finish()
    assert list(tmp_path.iterdir()) == recorder.files
