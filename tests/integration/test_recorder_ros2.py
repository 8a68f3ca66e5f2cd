"""The recorder with `[recorder.ros2]`, as a real process: a ROS 2 node speaking rmw_zenoh's wire publishes
Twist and Odometry, hostile samples among them, and the ros2-profile twin of the tether recording holds
what was sent, read back with Foxglove's decoder (mcap-ros2-support), not with the typestore that wrote it.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from schemas import keys
from schemas.trace import RecorderStatus, Ros2RecorderStatus
from schemas.world import Empty
from services.recorder.reader import read_recording
from services.recorder.ros2file import ros2_path
from services.ros2.rmw import RosNode
from services.ros2.types import RosTypes
from services.ros2.wire import Attachment, Naming, Style
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.integration.conftest import dump_logs, run_tether, write_config
from tests.sessions import free_port, free_ports
from tether.supervisor import Supervisor

DOMAIN = 7  # not 0: the recorder must take it from ROS_DOMAIN_ID
TWIST = "geometry_msgs/msg/Twist"
ODOMETRY = "nav_msgs/msg/Odometry"
STARTUP = 30.0
SETTLE = 15.0  # seconds for samples on their way to be counted by the recorder
POLL = 0.05  # seconds between two status queries


def ros_session(endpoint: str) -> zenoh.Session:
    """The robot's side: a peer listening where rmw_zenoh's router would, nothing else."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def wait_matched(session: zenoh.Session, key: str, timeout: float) -> bool:
    """Until a subscriber elsewhere (the recorder's) covers `key`: what is put after that reaches it."""
    matched = threading.Event()
    publisher = session.declare_publisher(key)
    # The listener is called at once with the current status, then on every change.
    listener = publisher.declare_matching_listener(lambda status: matched.set() if status.matching else None)
    try:
        return matched.wait(timeout)
    finally:
        listener.undeclare()
        publisher.undeclare()


def wait_status(node: Node, done: Callable[[RecorderStatus], bool], timeout: float) -> RecorderStatus:
    """The recorder's status once `done` holds; fails with the last status seen at the deadline."""
    deadline = time.monotonic() + timeout
    while True:
        status: RecorderStatus = node.call(keys.RECORDER_STATUS, Empty(), timeout=5.0)
        if done(status):
            return status
        assert time.monotonic() < deadline, f"recorder status never got there: {status}"
        time.sleep(POLL)  # pacing the queries (each one is recorded), not waiting for an outcome


def ros2_of(status: RecorderStatus) -> Ros2RecorderStatus:
    assert status.ros2 is not None, "the status does not report the ROS 2 side"
    return status.ros2


@dataclass
class Robot:
    """The ROS 2 robot's session and node, and a recorder process whose [recorder.ros2] points at it."""

    tmp: Path
    endpoint: str
    supervisor: Supervisor
    types: RosTypes = field(default_factory=RosTypes)
    node: Node | None = None
    session: zenoh.Session | None = None
    ros: RosNode | None = None

    def open(self) -> RosNode:
        """The robot comes up: a ROS 2 node listening on the endpoint."""
        self.session = ros_session(self.endpoint)
        self.ros = RosNode(self.session, self.types, Naming(Style.RMW_ZENOH, DOMAIN), "tether_standin")
        return self.ros

    def start_recorder(self) -> Node:
        self.supervisor.start("recorder")
        self.node = Node("cli", self.supervisor.settings)
        assert not self.node.wait_alive(["recorder"], STARTUP), self.supervisor.log_tail("recorder")
        return self.node

    def key(self, topic: str, ros_type: str) -> str:
        return Naming(Style.RMW_ZENOH, DOMAIN).topic(topic, ros_type, self.types.hash(ros_type))

    def log(self) -> str:
        return (self.tmp / "logs" / "recorder.log").read_text()

    def close(self) -> None:
        self.supervisor.stop_all()
        dump_logs(self.supervisor, ("recorder",))
        if self.ros is not None:
            self.ros.close()
        if self.session is not None:
            self.session.close()
        if self.node is not None:
            self.node.close()


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Robot]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = write_config(tmp_path / "tether.toml", 1.0)
    config.write_text(config.read_text() + f'\n[recorder.ros2]\nendpoint = "{endpoint}"\n')
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    supervisor = Supervisor(settings, tmp_path / "logs", config, extra_env={"ROS_DOMAIN_ID": str(DOMAIN)})
    robot = Robot(tmp_path, endpoint, supervisor)
    try:
        yield robot
    finally:
        robot.close()


def twist(types: RosTypes, x: float, yaw_rate: float) -> Any:
    message = types.new(TWIST)
    message.linear.x, message.angular.z = x, yaw_rate
    return message


def odometry(types: RosTypes, x: float, y: float, stamp_ns: int) -> Any:
    message = types.new(ODOMETRY)
    message.header.frame_id, message.child_frame_id = "odom", "base_link"
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    message.pose.pose.position.x, message.pose.pose.position.y = x, y
    message.pose.pose.orientation.w = 1.0
    message.twist.twist.linear.x = 0.25
    return message


def test_ros2_traffic_is_recorded_beside_tether_s_in_the_ros2_profile(robot: Robot) -> None:
    ros = robot.open()
    cmd_vel, odom = ros.publisher("cmd_vel", TWIST), ros.publisher("odom", ODOMETRY)
    cmd_vel_key, odom_key = robot.key("cmd_vel", TWIST), robot.key("odom", ODOMETRY)
    node = robot.start_recorder()
    status = wait_status(node, lambda s: ros2_of(s).error == "", STARTUP)
    tether_file, twin = Path(status.path), Path(ros2_of(status).path)
    assert twin == ros2_path(tether_file) and twin.exists()
    assert wait_matched(ros.session, cmd_vel_key, SETTLE), robot.supervisor.log_tail("recorder")

    sent: list[tuple[str, Any, int, int]] = []  # topic, message, sent between these two times
    for i in range(20):
        before = time.time_ns()
        if i % 2:
            message = odometry(robot.types, 0.1 * i, -0.2 * i, before)
            odom.put(message)
            sent.append(("/odom", message, before, time.time_ns()))
        else:
            message = twist(robot.types, 0.05 * i, 0.01 * i)
            cmd_vel.put(message)
            sent.append(("/cmd_vel", message, before, time.time_ns()))

    # Hostile samples on the robot's network: none of them may stop the recorder or reach the file.
    session = ros.session
    cdr = robot.types.encode(TWIST, twist(robot.types, 9.0, 9.0))
    good_attachment = Attachment(1, time.time_ns(), bytes(16)).encode()
    hostile = [
        (f"{DOMAIN}/garbage", cdr, good_attachment),
        (f"{DOMAIN}/thing/acme_msgs::msg::dds_::Thing_/RIHS01_{'1' * 64}", cdr, good_attachment),
        (f"{DOMAIN}/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_{'0' * 64}", cdr, good_attachment),
        (cmd_vel_key, b"not cdr at all", good_attachment),
        (odom_key, b"", None),
    ]
    for key, payload, attachment in hostile:
        session.put(key, payload, attachment=attachment)
    # A malformed attachment costs only the publish time: the sample is recorded.
    last = twist(robot.types, -0.3, 0.0)
    session.put(cmd_vel_key, robot.types.encode(TWIST, last), attachment=b"\x01\x02\x03")

    expected = len(sent) + 1
    status = wait_status(node, lambda s: ros2_of(s).messages >= expected and ros2_of(s).skipped >= len(hostile), SETTLE)
    assert (ros2_of(status).messages, ros2_of(status).skipped) == (expected, len(hostile))
    assert status.messages > 0 and robot.supervisor.exited() == {}
    assert robot.supervisor.stop("recorder") == 0

    log = robot.log()
    assert f"to {twin}" in log, "the log does not name the ROS 2 file"
    assert log.count("acme_msgs/msg/Thing") == 1, "not one warning for the unknown type"

    with twin.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == expected
        assert {s.name: s.encoding for s in summary.schemas.values()} == {TWIST: "ros2msg", ODOMETRY: "ros2msg"}
        assert {c.topic: c.message_encoding for c in summary.channels.values()} == {"/cmd_vel": "cdr", "/odom": "cdr"}
        recorded = list(reader.iter_decoded_messages(log_time_order=False))

    for (_, channel, message, decoded), (topic, value, before, after) in zip(recorded, sent, strict=False):
        assert channel.topic == topic
        assert message.data == robot.types.encode(TWIST if topic == "/cmd_vel" else ODOMETRY, value)
        assert before <= message.publish_time <= after and message.publish_time <= message.log_time
        if topic == "/cmd_vel":
            assert (decoded.linear.x, decoded.angular.z) == (value.linear.x, value.angular.z)
        else:
            pose = decoded.pose.pose
            assert (pose.position.x, pose.position.y, pose.orientation.w) == (
                value.pose.pose.position.x,
                value.pose.pose.position.y,
                1.0,
            )
            assert (decoded.header.frame_id, decoded.child_frame_id) == ("odom", "base_link")
            assert (decoded.header.stamp.sec, decoded.header.stamp.nanosec) == (
                value.header.stamp.sec,
                value.header.stamp.nanosec,
            )
            assert decoded.twist.twist.linear.x == 0.25
    _, _, final, decoded_final = recorded[-1]
    assert decoded_final.linear.x == -0.3 and final.publish_time == final.log_time

    # tether's own file is whole and reads as before.
    assert read_recording(tether_file).complete
    done = run_tether(robot.supervisor, "inspect", str(tether_file), "--json")
    assert done.returncode == 0, done.stderr
    refused = run_tether(robot.supervisor, "inspect", str(twin))
    assert refused.returncode != 0 and "ROS 2 recording" in refused.stderr


def test_a_robot_not_up_yet_is_an_error_in_the_status_until_it_comes_and_then_is_recorded(robot: Robot) -> None:
    node = robot.start_recorder()
    status = wait_status(node, lambda s: "cannot open" in ros2_of(s).error, STARTUP)
    assert robot.endpoint in ros2_of(status).error
    # tether's side records all along: each status query leaves its trace in the file.
    status = wait_status(node, lambda s: s.messages >= 2, SETTLE)

    ros = robot.open()
    cmd_vel = ros.publisher("cmd_vel", TWIST)
    wait_status(node, lambda s: ros2_of(s).error == "", SETTLE)
    assert wait_matched(ros.session, robot.key("cmd_vel", TWIST), SETTLE)
    cmd_vel.put(twist(robot.types, 0.4, 0.0))
    status = wait_status(node, lambda s: ros2_of(s).messages >= 1, SETTLE)
    assert ros2_of(status).messages == 1

    # The robot goes away: the status says so until it is back.
    ros.close()
    ros.session.close()
    status = wait_status(node, lambda s: "no connection" in ros2_of(s).error, SETTLE)
    robot.open()
    wait_status(node, lambda s: ros2_of(s).error == "", SETTLE)
    assert robot.supervisor.stop("recorder") == 0
    log = robot.log()
    assert "lost the ROS 2 robot" in log and "is back" in log
    assert log.count("cannot open a client session to the ROS 2 robot") == 1, "the failure not logged once"
    with Path(ros2_of(status).path).open("rb") as f:
        decoded = [d for _, _, _, d in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    assert [d.linear.x for d in decoded] == [0.4]
