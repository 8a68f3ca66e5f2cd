"""Two RosNodes over real Zenoh on loopback: topics, services and ROS 2 actions in rmw_zenoh's format."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest
import zenoh

from services.ros2 import rmw
from services.ros2.rmw import (
    GoalStatus,
    RosActionClient,
    RosCallError,
    RosClientGoal,
    RosGoalRejected,
    RosNode,
    RosServerGoal,
)
from services.ros2.types import RosTypes
from services.ros2.wire import Attachment, EntityKind, Naming, Style
from tests.sessions import free_port

TWIST = "geometry_msgs/msg/Twist"
NAV = "nav2_msgs/action/NavigateToPose"
ADD = "example_interfaces/srv/AddTwoInts"
DEADLINE = 10.0  # generous: the machine is shared; every wait ends as soon as its condition holds

WRONG_HASH = "RIHS01_" + "ab" * 32


@dataclass
class Collected:
    """What a callback received, with a condition to wait on."""

    items: list[Any] = field(default_factory=list)
    changed: threading.Condition = field(default_factory=threading.Condition)

    def __call__(self, item: Any) -> None:
        with self.changed:
            self.items.append(item)
            self.changed.notify_all()

    def wait(self, predicate: Callable[[list[Any]], bool], timeout: float = DEADLINE) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: predicate(self.items), timeout)


def session_config(port: int, *, listen: bool) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    endpoints = f'["tcp/127.0.0.1:{port}"]'
    conf.insert_json5("listen/endpoints" if listen else "connect/endpoints", endpoints)
    if not listen:
        conf.insert_json5("listen/endpoints", "[]")
    return conf


@dataclass
class Pair:
    types: RosTypes
    robot: RosNode
    tether: RosNode
    robot_errors: Collected
    tether_errors: Collected
    robot_session: zenoh.Session
    tether_session: zenoh.Session


@pytest.fixture(scope="module")
def types() -> RosTypes:
    return RosTypes("jazzy")


@contextmanager
def node_pair(types: RosTypes, style: Style) -> Iterator[Pair]:
    port = free_port()
    naming = Naming(style, 0)
    with (
        zenoh.open(session_config(port, listen=True)) as robot_session,
        zenoh.open(session_config(port, listen=False)) as tether_session,
    ):
        robot_errors, tether_errors = Collected(), Collected()
        robot = RosNode(robot_session, types, naming, "standin", on_error=robot_errors)
        tether = RosNode(tether_session, types, naming, "tether", on_error=tether_errors)
        try:
            yield Pair(types, robot, tether, robot_errors, tether_errors, robot_session, tether_session)
        finally:
            tether.close()
            robot.close()


@pytest.fixture
def pair(types: RosTypes) -> Iterator[Pair]:
    with node_pair(types, Style.RMW_ZENOH) as nodes:
        yield nodes


def twist(types: RosTypes, x: float) -> Any:
    message = types.new(TWIST)
    message.linear.x = x
    return message


def put_until(condition: Callable[[], bool], put: Callable[[], None], timeout: float = DEADLINE) -> bool:
    """Publish until condition holds: a put can race the peer's routing of a new subscriber."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        put()
        if condition():
            return True
        time.sleep(0.02)  # pacing between retries, not a wait for readiness
    return condition()


def raw_put(pair: Pair, key: str, payload: bytes, attachment: bytes | None) -> None:
    if attachment is None:
        pair.tether_session.put(key, payload)
    else:
        pair.tether_session.put(key, payload, attachment=attachment)


def good_attachment() -> bytes:
    return Attachment(1, time.time_ns(), bytes(16)).encode()


# -- topics


def test_publish_subscribe_with_attachment_and_tokens(pair: Pair) -> None:
    received = Collected()
    pair.robot.subscribe("cmd_vel", TWIST, received)
    assert pair.tether.wait_for(EntityKind.SUBSCRIPTION, "/cmd_vel", DEADLINE)
    publisher = pair.tether.publisher("cmd_vel", TWIST)
    publisher.put(twist(pair.types, 0.5))
    assert received.wait(lambda items: len(items) >= 1)
    assert received.items[0].linear.x == 0.5

    # The raw sample carries rmw_zenoh's key and 33-byte attachment, sequence numbers from 1 up.
    raw = Collected()
    sub = pair.robot_session.declare_subscriber(publisher.endpoint.key, raw)
    try:
        assert put_until(lambda: len(raw.items) >= 2, lambda: publisher.put(twist(pair.types, 0.25)))
        first, second = (Attachment.decode(sample.attachment.to_bytes()) for sample in raw.items[:2])
        assert second.sequence_number == first.sequence_number + 1
        assert first.gid == second.gid and len(first.gid) == 16
        assert raw.items[0].payload.to_bytes()[:4] == b"\x00\x01\x00\x00"
        assert str(raw.items[0].key_expr) == (
            "0/cmd_vel/geometry_msgs::msg::dds_::Twist_/"
            "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
        )
    finally:
        sub.undeclare()

    # `ros2 node list` / `ros2 topic list` see tether: node and publisher tokens in rmw_zenoh's form.
    tokens = [str(reply.ok.key_expr) for reply in pair.robot_session.liveliness().get("@ros2_lv/0/**") if reply.ok]
    zid = str(pair.tether_session.info.zid())
    assert any(t.startswith(f"@ros2_lv/0/{zid}/") and t.endswith("/NN/%/%/tether") for t in tokens)
    assert any(
        f"/MP/%/%/tether/%cmd_vel/geometry_msgs::msg::dds_::Twist_/{publisher.endpoint.type_hash}/::,10:,:,:,," in t
        for t in tokens
    )
    assert not pair.robot_errors.items


def test_wrong_hash_garbage_and_bad_attachments_are_refused(pair: Pair) -> None:
    received = Collected()
    pair.robot.subscribe("cmd_vel", TWIST, received)
    assert pair.tether.wait_for(EntityKind.SUBSCRIPTION, "/cmd_vel", DEADLINE)
    good_key = pair.tether.naming.topic("cmd_vel", TWIST, pair.types.hash(TWIST))
    good_cdr = pair.types.encode(TWIST, twist(pair.types, 1.0))
    errors = pair.robot_errors

    def refused(key: str, payload: bytes, attachment: bytes | None, *words: str) -> None:
        before = len(errors.items)
        assert put_until(
            lambda: len(errors.items) > before, lambda: raw_put(pair, key, payload, attachment), timeout=3.0
        ), words
        text = errors.items[-1]
        assert "/cmd_vel" in text
        for word in words:
            assert word in text, text

    wrong_hash_key = good_key.rsplit("/", 1)[0] + "/" + WRONG_HASH
    refused(wrong_hash_key, good_cdr, good_attachment(), "type hash", WRONG_HASH, "expected RIHS01_9c45bf16")
    refused(good_key, b"\x00\x01\x00\x00garbage", good_attachment(), "undecodable")
    refused(good_key, good_cdr, None, "without rmw_zenoh attachment")
    refused(good_key, good_cdr, b"\x01\x02\x03", "malformed attachment")
    other_type_key = f"0/cmd_vel/std_msgs::msg::dds_::String_/{pair.types.hash('std_msgs/msg/String')}"
    refused(other_type_key, good_cdr, good_attachment(), "has type std_msgs/msg/String")
    assert received.items == []

    # Rate limited: a flood of garbage gives at most one more report per second on that fault.
    before = len(errors.items)
    for _ in range(50):
        raw_put(pair, good_key, b"\x00\x01\x00\x00garbage", good_attachment())
    raw_put(pair, good_key, good_cdr, good_attachment())
    assert received.wait(lambda items: len(items) == 1)  # a good sample still goes through
    assert len(errors.items) - before <= 1


# -- services


def test_service_call_timeout_and_wrong_type(pair: Pair) -> None:
    release = threading.Event()

    def add(request: Any) -> Any:
        if request.a < 0:
            release.wait(DEADLINE)
        return pair.types.new(f"{ADD}_Response", sum=request.a + request.b)

    pair.robot.serve("add_two_ints", ADD, add)
    client = pair.tether.client("add_two_ints", ADD)
    assert client.wait_for_service(DEADLINE)
    response = client.call(pair.types.new(f"{ADD}_Request", a=2, b=40), timeout=DEADLINE)
    assert response.sum == 42
    response = client.call(pair.types.new(f"{ADD}_Request", a=1, b=1), timeout=DEADLINE)
    assert response.sum == 2

    try:
        with pytest.raises(RosCallError, match=r"service /add_two_ints .*no answer within 0.3 s"):
            client.call(pair.types.new(f"{ADD}_Request", a=-1, b=0), timeout=0.3)
    finally:
        release.set()

    wrong = pair.tether.client("add_two_ints", "std_srvs/srv/Trigger")
    with pytest.raises(RosCallError, match=r"/add_two_ints.*std_srvs/srv/Trigger.*expected example_interfaces"):
        wrong.call(pair.types.new("std_srvs/srv/Trigger_Request"), timeout=DEADLINE)
    assert any("/add_two_ints" in text for text in pair.robot_errors.items)

    nobody = pair.tether.client("nobody_here", ADD)
    with pytest.raises(RosCallError, match=r"service /nobody_here .*no answer within 0.2 s"):
        nobody.call(pair.types.new(f"{ADD}_Request"), timeout=0.2)


def test_service_refuses_undecodable_request(pair: Pair) -> None:
    pair.robot.serve("add_two_ints", ADD, lambda request: pair.types.new(f"{ADD}_Response"))
    client = pair.tether.client("add_two_ints", ADD)
    assert client.wait_for_service(DEADLINE)
    replies = list(
        pair.tether_session.get(
            client.endpoint.key,
            payload=b"\x00\x01\x00\x00\x01",
            attachment=good_attachment(),
            target=zenoh.QueryTarget.ALL_COMPLETE,
            timeout=DEADLINE,
        )
    )
    assert len(replies) == 1 and replies[0].err is not None
    assert "undecodable request" in replies[0].err.payload.to_bytes().decode()
    assert pair.robot_errors.wait(lambda items: any("undecodable request" in text for text in items))


# -- actions


class Navigator:
    """A NavigateToPose server: feedback until released or canceled; rejects behavior_tree "reject"."""

    def __init__(self, pair: Pair) -> None:
        self.types = pair.types
        self.release = threading.Event()
        self.started = Collected()
        self.server = pair.robot.action_server("navigate_to_pose", NAV, accept=self.accept, execute=self.execute)

    def accept(self, goal: Any) -> bool:
        return bool(goal.behavior_tree != "reject")

    def execute(self, goal: RosServerGoal) -> None:
        self.started(goal.goal_id)
        remaining = 10.0
        while not goal.cancel_requested.is_set() and not self.release.is_set():
            goal.publish_feedback(self.types.new(f"{NAV}_Feedback", distance_remaining=remaining))
            remaining = max(0.0, remaining - 0.1)
            goal.cancel_requested.wait(0.02)  # the server's feedback period
        result = self.types.new(f"{NAV}_Result", error_code=0, error_msg="done")
        if goal.cancel_requested.is_set():
            goal.canceled(self.types.new(f"{NAV}_Result", error_msg="canceled"))
        else:
            goal.succeed(result)


def nav_goal(types: RosTypes, x: float, tree: str = "") -> Any:
    goal = types.new(f"{NAV}_Goal", behavior_tree=tree)
    goal.pose.header.frame_id = "map"
    goal.pose.pose.position.x = x
    goal.pose.pose.orientation.w = 1.0
    return goal


@pytest.fixture
def navigation(pair: Pair) -> Iterator[tuple[Navigator, RosActionClient]]:
    navigator = Navigator(pair)
    client = pair.tether.action_client("navigate_to_pose", NAV)
    assert client.wait_for_server(DEADLINE)
    try:
        yield navigator, client
    finally:
        navigator.release.set()


def test_action_goal_feedback_status_result(pair: Pair, navigation: tuple[Navigator, RosActionClient]) -> None:
    navigator, client = navigation
    feedback = Collected()
    goal = client.send_goal(nav_goal(pair.types, 2.0), feedback=feedback, timeout=DEADLINE)
    assert len(goal.goal_id) == 16
    assert goal.wait_status(lambda status: status is GoalStatus.EXECUTING, DEADLINE)
    assert feedback.wait(lambda items: len(items) >= 2)
    assert feedback.items[0].distance_remaining == pytest.approx(10.0)
    (server_goal,) = navigator.server.goals
    assert server_goal.goal_id == goal.goal_id and server_goal.goal.pose.pose.position.x == 2.0
    navigator.release.set()
    status, result = goal.result(DEADLINE)
    assert status == GoalStatus.SUCCEEDED and result.error_msg == "done"
    assert goal.wait_status(lambda status: status is GoalStatus.SUCCEEDED, DEADLINE)
    assert not goal.cancel(DEADLINE)  # a finished goal cannot be canceled
    assert not pair.robot_errors.items and not pair.tether_errors.items


def test_a_status_that_comes_before_send_goal_returns_is_not_lost(
    pair: Pair, navigation: tuple[Navigator, RosActionClient], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server says EXECUTING (and says nothing more until the goal ends) before this client has made
    the goal's handle, as on a loaded machine: the handle still knows it (a CI run waited 10 s for it)."""
    _, client = navigation
    feedback = Collected()
    make_handle = rmw.RosClientGoal.__init__

    def late(handle: rmw.RosClientGoal, *args: Any, **kwargs: Any) -> None:
        # Feedback follows the EXECUTING status on the server's goal thread: the status has come by now.
        assert feedback.wait(lambda items: len(items) >= 2)
        make_handle(handle, *args, **kwargs)

    monkeypatch.setattr(rmw.RosClientGoal, "__init__", late)
    goal = client.send_goal(nav_goal(pair.types, 2.0), feedback=feedback, timeout=DEADLINE)
    assert goal.wait_status(lambda status: status is GoalStatus.EXECUTING, DEADLINE)


def test_action_cancel_one_goal(pair: Pair, navigation: tuple[Navigator, RosActionClient]) -> None:
    navigator, client = navigation
    goal = client.send_goal(nav_goal(pair.types, 1.0), timeout=DEADLINE)
    assert navigator.started.wait(lambda ids: goal.goal_id in ids)
    assert goal.cancel(DEADLINE)
    status, result = goal.result(DEADLINE)
    assert status == GoalStatus.CANCELED and result.error_msg == "canceled"
    assert goal.wait_status(lambda status: status is GoalStatus.CANCELED, DEADLINE)


def test_action_cancel_all_goals(pair: Pair, navigation: tuple[Navigator, RosActionClient]) -> None:
    navigator, client = navigation
    goals = [client.send_goal(nav_goal(pair.types, float(x)), timeout=DEADLINE) for x in (1, 2)]
    assert navigator.started.wait(lambda ids: all(goal.goal_id in ids for goal in goals))
    canceling = client.cancel_all(DEADLINE)
    assert sorted(canceling) == sorted(goal.goal_id for goal in goals)
    for goal in goals:
        assert goal.result(DEADLINE)[0] == GoalStatus.CANCELED
    assert client.cancel_all(DEADLINE) == []  # nothing left to cancel


def test_action_rejected_goal(pair: Pair, navigation: tuple[Navigator, RosActionClient]) -> None:
    navigator, client = navigation
    with pytest.raises(RosGoalRejected, match="/navigate_to_pose"):
        client.send_goal(nav_goal(pair.types, 1.0, tree="reject"), timeout=DEADLINE)
    assert navigator.server.goals == []


def test_action_cancel_by_stamp_and_unknown_goals(pair: Pair, navigation: tuple[Navigator, RosActionClient]) -> None:
    navigator, client = navigation
    first = client.send_goal(nav_goal(pair.types, 1.0), timeout=DEADLINE)
    assert navigator.started.wait(lambda ids: first.goal_id in ids)
    second = client.send_goal(nav_goal(pair.types, 2.0), timeout=DEADLINE)
    assert navigator.started.wait(lambda ids: second.goal_id in ids)
    # zero goal id and a stamp: every goal accepted at or before it, here only the first
    response = client._cancel(bytes(16), first.stamp_ns, DEADLINE)
    assert [bytes(info.goal_id.uuid) for info in response.goals_canceling] == [first.goal_id]
    assert first.result(DEADLINE)[0] == GoalStatus.CANCELED
    assert second.wait_status(lambda status: status is GoalStatus.EXECUTING, DEADLINE)
    # an unknown goal id: nothing canceled; its result is "unknown", which is no result
    stranger = RosClientGoal(client, b"\x01" * 16, 0)
    assert not stranger.cancel(DEADLINE)
    with pytest.raises(RosCallError, match="not a final one"):
        stranger.result(DEADLINE)
    assert second.cancel(DEADLINE)


def test_action_execute_failure_aborts_the_goal(pair: Pair) -> None:
    def execute(goal: RosServerGoal) -> None:
        raise RuntimeError("motor driver gone")

    pair.robot.action_server("navigate_to_pose", NAV, accept=lambda goal: True, execute=execute)
    client = pair.tether.action_client("navigate_to_pose", NAV)
    assert client.wait_for_server(DEADLINE)
    goal = client.send_goal(nav_goal(pair.types, 1.0), timeout=DEADLINE)
    assert goal.result(DEADLINE)[0] == GoalStatus.ABORTED
    assert any("motor driver gone" in text for text in pair.robot_errors.items)


def test_undecodable_feedback_is_refused(pair: Pair, navigation: tuple[Navigator, RosActionClient]) -> None:
    _, client = navigation
    feedback = Collected()
    goal = client.send_goal(nav_goal(pair.types, 1.0), feedback=feedback, timeout=DEADLINE)
    assert feedback.wait(lambda items: len(items) >= 1)
    key = client.keys.feedback.key
    assert put_until(
        lambda: any("undecodable sample on /navigate_to_pose/_action/feedback" in t for t in pair.tether_errors.items),
        lambda: pair.robot_session.put(key, b"\x00\x01\x00\x00\x05", attachment=good_attachment()),
    )
    assert goal.cancel(DEADLINE)


def test_action_server_missing_times_out(pair: Pair) -> None:
    client = pair.tether.action_client("nowhere", NAV)
    with pytest.raises(RosCallError, match=r"service /nowhere/_action/send_goal .*no answer within 0.2 s"):
        client.send_goal(nav_goal(pair.types, 1.0), timeout=0.2)


# -- the other style


def test_bridge_style_topics_services_and_actions(types: RosTypes) -> None:
    """zenoh-bridge-ros2dds keys: bare names, no attachment, no rmw_zenoh tokens; the same API."""
    with node_pair(types, Style.BRIDGE) as nodes:
        received = Collected()
        nodes.robot.subscribe("odom", TWIST, received)
        publisher = nodes.tether.publisher("odom", TWIST)
        assert publisher.endpoint.key == "odom"
        assert put_until(lambda: len(received.items) >= 1, lambda: publisher.put(twist(types, 3.0)))
        assert received.items[0].linear.x == 3.0

        navigator = Navigator(nodes)  # declared before the service: routed once the service answers
        navigator.release.set()
        nodes.robot.serve("add_two_ints", ADD, lambda r: types.new(f"{ADD}_Response", sum=r.a + r.b))
        client = nodes.tether.client("add_two_ints", ADD)

        def answered() -> bool:
            try:
                return bool(client.call(types.new(f"{ADD}_Request", a=20, b=22), timeout=1.0).sum == 42)
            except RosCallError:
                return False  # the queryable may not be routed yet: there is no token to wait on

        assert put_until(answered, lambda: None)

        action = nodes.tether.action_client("navigate_to_pose", NAV)
        assert action.keys.send_goal.key == "navigate_to_pose/_action/send_goal"
        goal = action.send_goal(nav_goal(types, 1.0), timeout=DEADLINE)
        assert goal.result(DEADLINE)[0] == GoalStatus.SUCCEEDED
        tokens = [reply.ok for reply in nodes.robot_session.liveliness().get("@ros2_lv/**", timeout=1.0) if reply.ok]
        assert tokens == []
        assert not nodes.robot_errors.items and not nodes.tether_errors.items
