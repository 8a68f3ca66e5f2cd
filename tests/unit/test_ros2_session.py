"""The ros2 backend's Zenoh session on the robot's network, against a real peer there: a message over
what any report may weigh is dropped by Zenoh before it is reassembled, and the link stays up."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest
import zenoh

from services.ros2 import node
from services.ros2.backend import REPORT_MAX_BYTES
from services.ros2.config import Ros2Config
from services.ros2.rmw import MAX_PAYLOAD
from tests.sessions import free_port

WAIT = 5.0
SECURED = Path(__file__).parents[2] / "deploy" / "ros2-client.json5"
TOPIC = "0/chatter/std_msgs::msg::dds_::String_/RIHS01_test"


def peer(port: int) -> zenoh.Config:
    """A peer on the robot's network (its router's place), listening where the backend connects."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("connect/endpoints", "[]")
    return conf


def test_every_report_fits_under_the_largest_message_taken_and_the_secured_config_says_the_same() -> None:
    assert max(MAX_PAYLOAD, *REPORT_MAX_BYTES.values()) <= node.ROBOT_MAX_MESSAGE
    secured = zenoh.Config.from_file(str(SECURED))
    assert json.loads(secured.get_json("transport/link/rx/max_message_size")) == node.ROBOT_MAX_MESSAGE


def test_a_message_over_the_largest_a_report_may_weigh_is_dropped_before_it_is_reassembled(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Zenoh's default took messages up to 1 GiB: anyone on the robot's network could make the backend
    hold that much per message before its own size check dropped it."""
    # The same bound, at a size a test sends quickly (raising=False: on code without it, the test fails
    # on what the session took, not on the name).
    monkeypatch.setattr(node, "ROBOT_MAX_MESSAGE", 1 << 20, raising=False)
    port = free_port()
    heard: list[int] = []
    arrived = threading.Condition()

    def on_sample(sample: zenoh.Sample) -> None:
        with arrived:
            heard.append(len(sample.payload.to_bytes()))
            arrived.notify_all()

    with zenoh.open(peer(port)) as robot_side:
        config = Ros2Config(endpoint=f"tcp/127.0.0.1:{port}")
        with zenoh.open(node.robot_session_config(config)) as backend:
            backend.declare_subscriber(TOPIC, on_sample)
            deadline = time.monotonic() + WAIT
            with arrived:  # linked and matched once a small probe comes through
                while not heard:
                    assert time.monotonic() < deadline, "the backend's session never heard the robot's peer"
                    robot_side.put(TOPIC, b"p")
                    arrived.wait(0.1)
                heard.clear()
            robot_side.put(TOPIC, b"x" * (2 << 20))
            robot_side.put(TOPIC, b"after")
            with arrived:
                assert arrived.wait_for(lambda: len(b"after") in heard, WAIT), f"the link went down: {heard}"
    assert heard == [len(b"after")], f"a message of {heard[0]} bytes was taken"


@pytest.mark.parametrize(
    ("given", "taken"), [(None, node.ROBOT_MAX_MESSAGE), (1 << 30, node.ROBOT_MAX_MESSAGE), (4096, 4096)]
)
def test_a_zenoh_config_of_ones_own_takes_no_more_than_the_backend_reads(
    tmp_path: Path, given: int | None, taken: int
) -> None:
    """A `[ros2] zenoh_config` file (TLS, a login) was used as written: without the limit, Zenoh's 1 GiB."""
    link = "" if given is None else f"link: {{ rx: {{ max_message_size: {given} }} }},"
    path = tmp_path / "robot.json5"
    path.write_text(f'{{ mode: "client", connect: {{ endpoints: ["tcp/127.0.0.1:7447"] }}, transport: {{ {link} }} }}')
    conf = node.robot_session_config(Ros2Config(zenoh_config=str(path)))
    assert json.loads(conf.get_json("transport/link/rx/max_message_size")) == taken
