"""Teleop from Foxglove through `tether view`: what a client message becomes, what is refused, the deadman."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import foxglove
import pytest
from foxglove.websocket import Capability

from schemas.robot import Twist
from schemas.safety import EstopState, SafetyStatus
from tether.view import Listener, TeleopBridge, shut_down, teleop_loop
from tether.viewteleop import (
    BURST,
    DEADMAN,
    MAX_CHANNELS,
    MAX_CHANNELS_PER_CLIENT,
    RATE_HZ,
    TELEOP_TOPIC,
    RateLimited,
    Rearming,
    Refused,
    TeleopGate,
    check_channel,
    to_twist,
)


def twist_json(lx: Any = 0.0, az: Any = 0.0, **more: Any) -> bytes:
    message: dict[str, dict[str, Any]] = {"linear": {"x": lx, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": az}}
    for name, value in more.items():
        part, axis = name.split("_")
        message[part][axis] = value
    return json.dumps(message).encode()


def test_a_twist_from_the_teleop_panel_becomes_linear_x_and_angular_z() -> None:
    assert to_twist(twist_json(0.3, -0.8)) == (Twist(linear_x=0.3, angular_z=-0.8), [])
    # Integers, missing parts, unknown extra fields: as the panel or a hand-written client sends them.
    assert to_twist(b'{"linear":{"x":1}}') == (Twist(linear_x=1.0), [])
    assert to_twist(b"{}") == (Twist(), [])
    # A value between the robot's limits and the schema's bound passes: safety clamps and reports it.
    assert to_twist(twist_json(5.0))[0].linear_x == 5.0


def test_the_axes_a_ground_robot_lacks_are_ignored_and_named() -> None:
    twist, ignored = to_twist(twist_json(0.2, 0.0, linear_y=0.5, angular_x=-1.0))
    assert twist == Twist(linear_x=0.2)
    assert ignored == ["linear.y", "angular.x"]


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b"not json", "not a geometry_msgs/Twist in JSON"),
        (b'{"linear":', "not a geometry_msgs/Twist in JSON"),
        (b'{"linear":{"x":"fast"}}', "not a geometry_msgs/Twist in JSON"),
        (b'{"linear":{"x":null}}', "not a geometry_msgs/Twist in JSON"),  # JSON.stringify(NaN)
        (b'{"linear":{"x":NaN}}', "not a geometry_msgs/Twist in JSON"),
        (b'{"linear":{"x":1e999}}', "not a geometry_msgs/Twist in JSON"),
        (b'{"linear":[1,2,3]}', "not a geometry_msgs/Twist in JSON"),
        (b"[" * 2000, "not a geometry_msgs/Twist in JSON"),
        (b"[" * 5000, "5000 bytes"),
        (b"\xff\xfe", "not a geometry_msgs/Twist in JSON"),
        (twist_json(1e6), "linear.x is 1e+06, beyond +-100"),
        (twist_json(0.0, -101.0), "angular.z is -101, beyond +-100"),
        (twist_json(0.0, 0.0, linear_z=1e300), "linear.z is 1e+300, beyond +-100"),
        (b" " * 4096, "4096 bytes"),
    ],
)
def test_anything_but_a_sane_twist_is_refused_with_its_reason(data: bytes, why: str) -> None:
    with pytest.raises(Refused, match=why.replace("+", r"\+")):
        to_twist(data)


def test_only_a_json_twist_on_the_teleop_topic_is_taken() -> None:
    check_channel(TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    check_channel(TELEOP_TOPIC, "json", "geometry_msgs/msg/Twist")
    with pytest.raises(Refused, match="teleop is taken on '/cmd_vel' only"):
        check_channel("tether/robot1/cmd/teleop/cmd_vel", "json", "geometry_msgs/Twist")
    with pytest.raises(Refused, match="encoding 'cdr'"):
        check_channel(TELEOP_TOPIC, "cdr", "geometry_msgs/Twist")
    with pytest.raises(Refused, match="schema 'std_msgs/String'"):
        check_channel(TELEOP_TOPIC, "json", "std_msgs/String")


def test_a_message_on_a_channel_not_taken_is_refused() -> None:
    gate = TeleopGate()
    with pytest.raises(Refused, match="channel 7 was not taken"):
        gate.message(1, 7, twist_json(0.2), 0.0)
    with pytest.raises(Refused):
        gate.advertise(1, 8, "/elsewhere", "json", "geometry_msgs/Twist")
    with pytest.raises(Refused, match="channel 8 was not taken"):
        gate.message(1, 8, twist_json(0.2), 0.0)
    # Another client cannot use a channel id that a first one was given.
    gate.advertise(1, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    with pytest.raises(Refused, match="channel 1 was not taken"):
        gate.message(2, 1, twist_json(0.2), 0.0)
    assert gate.accepted == 0 and gate.refused == 4


def test_a_client_advertising_many_channels_gets_a_few() -> None:
    gate = TeleopGate()
    refused = 0
    for channel in range(100):
        try:
            gate.advertise(1, channel, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
        except Refused as exc:
            assert "at most 4" in str(exc)
            refused += 1
    assert gate.channels == MAX_CHANNELS_PER_CLIENT and refused == 100 - MAX_CHANNELS_PER_CLIENT
    for client in range(2, 100):
        for channel in range(MAX_CHANNELS_PER_CLIENT):
            try:
                gate.advertise(client, channel, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
            except Refused as exc:
                assert f"at most {MAX_CHANNELS}" in str(exc)
    assert gate.channels == MAX_CHANNELS
    # A channel given back makes room.
    gate.unadvertise(1, 0)
    gate.advertise(99, 9, TELEOP_TOPIC, "json", "geometry_msgs/Twist")


def test_a_flood_is_cut_to_the_rate_and_counted() -> None:
    gate = TeleopGate()
    gate.advertise(1, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    gate.advertise(2, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    taken = dropped = 0
    for i in range(2000):  # 1000 a second for two seconds
        try:
            gate.message(1, 1, twist_json(0.1), i / 1000)
            taken += 1
        except RateLimited:
            dropped += 1
    assert taken == pytest.approx(BURST + 2 * RATE_HZ, abs=2)
    assert gate.rate_dropped == dropped == 2000 - taken
    # Each client has its own budget: the flood of one does not silence another.
    gate.message(2, 1, twist_json(0.1), 2.0)


def test_advertising_again_does_not_refill_a_clients_rate() -> None:
    gate = TeleopGate()
    taken = 0
    for i in range(100):  # 1000 a second for 0.1 s, the channel advertised afresh around each
        gate.advertise(7, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
        try:
            gate.message(7, 1, twist_json(0.3), i / 1000)
            taken += 1
        except RateLimited:
            pass
        gate.unadvertise(7, 1)
    assert taken == pytest.approx(BURST + 0.1 * RATE_HZ, abs=1)
    # Once it has saved up its burst again a client's bucket is as good as new: it is forgotten, so
    # clients coming and going leave nothing behind.
    gate.advertise(8, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    gate.message(8, 1, twist_json(0.3), 0.1 + BURST / RATE_HZ)
    assert set(gate._buckets) == {8}
    gate.unadvertise(8, 1)
    gate.advertise(7, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    for i in range(BURST):
        gate.message(7, 1, twist_json(0.3), 0.2 + BURST / RATE_HZ + i / 1000)


def test_the_deadman_stops_once_half_a_second_after_the_last_message() -> None:
    gate = TeleopGate()
    gate.advertise(1, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    for i in range(10):  # the panel at 10 Hz
        gate.message(1, 1, twist_json(0.3), i / 10)
        assert gate.expire(i / 10 + 0.09) is None
    assert gate.expire(0.9 + DEADMAN - 0.01) is None
    assert gate.expire(0.9 + DEADMAN + 1e-9) == Twist()
    assert gate.expire(5.0) is None  # one stop, not a stream of them
    # A stop sent by the client itself needs none from the view.
    gate.message(1, 1, twist_json(0.3), 6.0)
    gate.message(1, 1, twist_json(0.0), 6.1)
    assert gate.expire(10.0) is None and gate.stops == 1


def test_a_panel_held_through_an_estop_and_its_reset_drives_nothing_until_let_go() -> None:
    """The panel's messages, vetoed by safety while the e-stop was latched, drove the robot off again
    the moment someone ran `tether reset`, with the button still held."""
    gate = TeleopGate()
    gate.advertise(1, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    gate.message(1, 1, twist_json(0.3), 0.0)
    assert gate.estop(True) == Twist(), "driving when the e-stop latched: no stop"
    assert gate.estop(True) is None  # one stop, not one a heartbeat
    held = [i / 10 for i in range(1, 30)]  # the panel at 10 Hz for 3 s; reset at 1 s
    for now in held:
        if now >= 1.0:
            assert gate.estop(False) is None
        with pytest.raises(Rearming, match="let go of the teleop panel's buttons"):
            gate.message(1, 1, twist_json(0.3), now)
        assert gate.expire(now + 0.05) is None
    assert gate.rearming
    gate.expire(held[-1] + DEADMAN + 1e-9)  # let go: quiet for the deadman's time, the e-stop clear
    assert not gate.rearming
    assert gate.message(1, 1, twist_json(0.3), 4.0).twist == Twist(linear_x=0.3)


def test_the_bridge_stops_on_the_heartbeat_that_latches_and_tells_foxglove_users(
    bridge: tuple[TeleopBridge, Fakes],
) -> None:
    teleop, fakes = bridge
    listener = Listener(view=None, teleop=teleop)  # type: ignore[arg-type]
    listener.on_client_advertise(Client(3), Channel(1))  # type: ignore[arg-type]
    listener.on_message_data(Client(3), 1, twist_json(0.3))  # type: ignore[arg-type]
    latched = SafetyStatus(seq=1, stamp=0.0, estop=EstopState(latched=True, source="operator", reason="x"))
    teleop.heartbeat(latched)
    teleop.heartbeat(latched)
    assert fakes.sent[1:] == [Twist(stamp=1000.0)]
    assert [n for n in teleop.notices if "e-stop latched" in n] == [
        "tether view: the e-stop latched; after its reset, let go of the buttons, then drive"
    ]
    listener.on_message_data(Client(3), 1, twist_json(0.3))  # type: ignore[arg-type]
    assert len(fakes.sent) == 2


def test_the_driving_channel_gone_stops_at_once_another_does_not() -> None:
    gate = TeleopGate()
    gate.advertise(1, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    gate.advertise(2, 5, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    gate.message(1, 1, twist_json(0.3), 0.0)
    assert gate.unadvertise(2, 5) is None  # not the one driving
    assert gate.unadvertise(1, 1) == Twist()
    assert gate.expire(1.0) is None
    with pytest.raises(Refused):
        gate.message(1, 1, twist_json(0.3), 1.0)


def test_refused_messages_do_not_hold_the_deadman_off() -> None:
    gate = TeleopGate()
    gate.advertise(1, 1, TELEOP_TOPIC, "json", "geometry_msgs/Twist")
    gate.message(1, 1, twist_json(0.3), 0.0)
    for i in range(1, 10):
        with pytest.raises(Refused):
            gate.message(1, 1, b"garbage", i / 20)
    assert gate.expire(DEADMAN + 1e-9) == Twist()


@dataclass
class Fakes:
    sent: list[Twist]
    now: list[float]


@pytest.fixture
def bridge() -> tuple[TeleopBridge, Fakes]:
    fakes = Fakes([], [0.0])
    return TeleopBridge(fakes.sent.append, clock=lambda: fakes.now[0], wall=lambda: 1000.0 + fakes.now[0]), fakes


@dataclass
class Channel:
    """What the SDK hands the listener for a client channel."""

    id: int
    topic: str = TELEOP_TOPIC
    encoding: str = "json"
    schema_name: str = "geometry_msgs/Twist"


@dataclass
class Client:
    id: int


def test_the_bridge_sends_stamped_twists_and_the_deadmans_stop(
    bridge: tuple[TeleopBridge, Fakes], caplog: pytest.LogCaptureFixture
) -> None:
    teleop, fakes = bridge
    listener = Listener(view=None, teleop=teleop)  # type: ignore[arg-type]
    listener.on_client_advertise(Client(3), Channel(1))  # type: ignore[arg-type]
    with caplog.at_level(logging.WARNING, "tether.view"):
        for i in range(3):
            fakes.now[0] = i / 10
            listener.on_message_data(Client(3), 1, twist_json(0.3, 0.1, linear_y=0.2))  # type: ignore[arg-type]
    assert fakes.sent == [Twist(linear_x=0.3, angular_z=0.1, stamp=1000.0 + i / 10) for i in range(3)]
    assert sum("linear.y is ignored" in r.message for r in caplog.records) == 1
    fakes.now[0] = 0.2 + DEADMAN + 1e-9
    teleop.tick()
    assert fakes.sent[-1] == Twist(stamp=1000.0 + fakes.now[0]) and len(fakes.sent) == 4
    teleop.tick()
    assert len(fakes.sent) == 4


def test_the_listener_never_raises_and_says_why_it_refused(
    bridge: tuple[TeleopBridge, Fakes], caplog: pytest.LogCaptureFixture
) -> None:
    teleop, fakes = bridge
    listener = Listener(view=None, teleop=teleop)  # type: ignore[arg-type]
    with caplog.at_level(logging.WARNING, "tether.view"):
        listener.on_client_advertise(Client(1), Channel(1, topic="/other"))  # type: ignore[arg-type]
        listener.on_message_data(Client(1), 1, b"garbage")  # type: ignore[arg-type]
        listener.on_client_advertise(Client(1), Channel(2))  # type: ignore[arg-type]
        listener.on_message_data(Client(1), 2, b"{{{")  # type: ignore[arg-type]
        listener.on_message_data(Client(1), 2, twist_json(float("nan")).replace(b"NaN", b"null"))  # type: ignore[arg-type]
    text = "\n".join(r.message for r in caplog.records)
    assert "client 1 channel 1 not taken: topic '/other'" in text
    assert "client 1 channel 1: channel 1 was not taken" in text
    assert "client 1 channel 2: not a geometry_msgs/Twist in JSON" in text
    assert fakes.sent == []
    # Foxglove's user is told why the panel's channel was refused.
    assert list(teleop.notices) == [
        "tether view: client 1 channel 1 not taken: topic '/other': teleop is taken on '/cmd_vel' only"
    ]

    # A send that fails (Zenoh closing) is logged, not raised into the server.
    def broken(twist: Twist) -> None:
        raise RuntimeError("session closed")

    listener.teleop = TeleopBridge(broken)
    listener.on_client_advertise(Client(2), Channel(1))  # type: ignore[arg-type]
    with caplog.at_level(logging.ERROR, "tether.view"):
        listener.on_message_data(Client(2), 1, twist_json(0.2))  # type: ignore[arg-type]
    assert "teleop callback failed" in caplog.text


def test_each_refused_channel_is_told_to_its_foxglove_user_and_logged_once(
    bridge: tuple[TeleopBridge, Fakes], caplog: pytest.LogCaptureFixture
) -> None:
    teleop, _ = bridge
    listener = Listener(view=None, teleop=teleop)  # type: ignore[arg-type]
    with caplog.at_level(logging.WARNING, "tether.view"):
        listener.on_client_advertise(Client(1), Channel(1, topic="/joy"))  # type: ignore[arg-type]
        # Another Foxglove window, within the same few seconds: its user is told too.
        listener.on_client_advertise(Client(2), Channel(1, encoding="cdr"))  # type: ignore[arg-type]
        listener.on_client_advertise(Client(2), Channel(2, schema_name="std_msgs/String"))  # type: ignore[arg-type]
    assert [notice.removeprefix("tether view: ").split(":")[0] for notice in teleop.notices] == [
        "client 1 channel 1 not taken",
        "client 2 channel 1 not taken",
        "client 2 channel 2 not taken",
    ]
    assert sum("not taken" in r.message for r in caplog.records) == 1  # the log is throttled, the notices not
    for client in range(3, 100):  # a flood keeps the newest few
        listener.on_client_advertise(Client(client), Channel(1, topic="/joy"))  # type: ignore[arg-type]
    assert len(teleop.notices) == teleop.notices.maxlen and "client 99 " in teleop.notices[-1]


def test_a_disconnect_while_driving_stops_at_once(bridge: tuple[TeleopBridge, Fakes]) -> None:
    teleop, fakes = bridge
    listener = Listener(view=None, teleop=teleop)  # type: ignore[arg-type]
    listener.on_client_advertise(Client(4), Channel(1))  # type: ignore[arg-type]
    listener.on_message_data(Client(4), 1, twist_json(0.3))  # type: ignore[arg-type]
    fakes.now[0] = 0.05
    listener.on_client_unadvertise(Client(4), 1)  # type: ignore[arg-type]  # the SDK's call on disconnect
    assert fakes.sent[-1] == Twist(stamp=1000.05)
    teleop.close()  # not moving: no second stop
    assert len(fakes.sent) == 2


def test_closing_the_view_stops_a_moving_robot_and_nothing_goes_out_after(bridge: tuple[TeleopBridge, Fakes]) -> None:
    teleop, fakes = bridge
    teleop.advertise(1, Channel(1))  # type: ignore[arg-type]
    teleop.message(1, 1, twist_json(0.0, 0.5))
    teleop.close()
    assert fakes.sent[-1] == Twist(stamp=1000.0) and len(fakes.sent) == 2
    # The server takes messages until it stops: none is sent, nor another stop.
    teleop.message(1, 1, twist_json(0.3))
    teleop.advertise(1, Channel(2))  # type: ignore[arg-type]
    teleop.message(1, 2, twist_json(0.3))
    fakes.now[0] = 2 * DEADMAN
    teleop.tick()
    teleop.unadvertise(1, 1)
    teleop.close()
    assert len(fakes.sent) == 2


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        time.sleep(0.005)


def test_from_the_moment_the_view_ends_the_panels_twists_are_dropped_and_the_robot_told_to_stop() -> None:
    """The view's end waits for its helpers (a camera picture may take seconds) before the server
    stops; meanwhile the server still takes the panel's twists, and the deadman's thread has ended."""
    sent: list[Twist] = []
    teleop = TeleopBridge(sent.append)
    listener = Listener(view=None, teleop=teleop)  # type: ignore[arg-type]
    server = foxglove.start_server(
        name="test",
        host="127.0.0.1",
        port=0,
        context=foxglove.Context(),
        server_listener=listener,
        capabilities=[Capability.ClientPublish],
        supported_encodings=["json"],
    )
    stop = threading.Event()
    camera_answered = threading.Event()  # a camera picture in flight: its helper ends when it comes
    helpers = [
        threading.Thread(target=teleop_loop, args=(teleop, server, stop), daemon=True),
        threading.Thread(target=camera_answered.wait, daemon=True),
    ]
    for helper in helpers:
        helper.start()
    ending = threading.Thread(target=shut_down, args=(teleop, stop, helpers, server), daemon=True)
    try:
        listener.on_client_advertise(Client(1), Channel(1))  # type: ignore[arg-type]
        listener.on_message_data(Client(1), 1, twist_json(0.3))  # type: ignore[arg-type]
        assert [t.linear_x for t in sent] == [0.3]
        ending.start()  # Ctrl-C
        wait_until(lambda: not helpers[0].is_alive(), "the deadman's thread ended")
        for _ in range(5):  # the panel's button still held
            listener.on_message_data(Client(1), 1, twist_json(0.3))  # type: ignore[arg-type]
        assert ending.is_alive(), "the view's end did not wait for the camera's helper"
        assert [(t.linear_x, t.angular_z) for t in sent] == [(0.3, 0.0), (0.0, 0.0)]
    finally:
        camera_answered.set()
        if ending.ident is None:
            shut_down(teleop, stop, helpers, server)
        else:
            ending.join(timeout=10.0)
    assert not ending.is_alive()


def test_the_shipped_layouts_teleop_panel_drives_through_the_view() -> None:
    layout = json.loads((Path(__file__).resolve().parents[2] / "deploy" / "foxglove-layout.json").read_text())
    [panel] = [config for name, config in layout["configById"].items() if name.startswith("Teleop!")]
    assert panel["topic"] == TELEOP_TOPIC
    # A held button repeats often enough that the deadman never stops a drive in between.
    assert 1 / panel["publishRate"] < DEADMAN / 2
    assert {panel[b]["field"] for b in ("upButton", "downButton", "leftButton", "rightButton")} == {
        "linear-x",
        "angular-z",
    }
