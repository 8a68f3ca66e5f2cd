"""Prove ros2-router.json5 with real Zenoh sessions: the robot's router, its nodes, tether and an intruder.

    python deploy/check_ros2_acl.py      exits 0 and prints one line per check, or fails on the first wrong one

One process, a free loopback port, a temporary users file. `robot` stands for the robot's own nodes (a
peer, as rmw_zenoh's nodes are), `tether` for tether's ros2 backend and `intruder` for any other host
that has credentials; both are clients, so everything they send passes the router's rules.

Ordering, not sleeping, decides what was dropped (as in tests/integration/test_deploy_acl.py): denied
messages are followed by an allowed marker from the same session on the same link (puts and queries
travel in order at data priority, declarations ahead of them at control priority), so once the marker
arrives, anything the router let through would have arrived before it. Access control filters what a
session sends before the router routes it anywhere, so one observer per sender is enough.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import socket
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import zenoh

HERE = Path(__file__).resolve().parent
USERS = {"tether": "pw-tether", "robot": "pw-robot", "intruder": "pw-intruder"}
DEADLINE = 10.0


def ros_key(name: str, dds_type: str, type_hash: str) -> str:
    """rmw_zenoh's key for a topic or service in domain 0."""
    return f"0/{name}/{dds_type}/RIHS01_{type_hash}"


# Real keys (hashes as services/ros2/types.py computes them for Jazzy; the rules match any type and hash).
CMD_VEL = ros_key(
    "cmd_vel", "geometry_msgs::msg::dds_::Twist_", "9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
)
SPEED_LIMIT = ros_key(
    "speed_limit",
    "nav2_msgs::msg::dds_::SpeedLimit_",
    "83d8e4e842559f4d9a988b19d31b162216ec738536389f98438d1a166f91845a",
)
ESTOP = ros_key(
    "emergency_stop", "std_msgs::msg::dds_::Bool_", "feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9"
)
ODOM = ros_key(
    "odom", "nav_msgs::msg::dds_::Odometry_", "3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
)
CANCEL = ("action_msgs::srv::dds_::CancelGoal_", "573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a")
SEND_GOAL = ros_key(
    "navigate_to_pose/_action/send_goal",
    "nav2_msgs::action::dds_::NavigateToPose_SendGoal_",
    "a4fcb3bee1bf32e21a0e541a943b221aa0826996e2c98f079b47022b256f48b5",
)
GET_RESULT = ros_key(
    "navigate_to_pose/_action/get_result",
    "nav2_msgs::action::dds_::NavigateToPose_GetResult_",
    "c407920357d566771e8882b4ef4d1f1a84ee922d609920ccd57faa6d6e391dc5",
)
GOAL_SERVICES = (
    SEND_GOAL,
    ros_key("navigate_to_pose/_action/cancel_goal", *CANCEL),
    ros_key(
        "arm_controller/follow_joint_trajectory/_action/send_goal",
        "control_msgs::action::dds_::FollowJointTrajectory_SendGoal_",
        "b13789dddc325a7a962825c45e28c77d37237ec129dd0c34dc5994562938c57f",
    ),
    ros_key("arm_controller/follow_joint_trajectory/_action/cancel_goal", *CANCEL),
    ros_key(
        "gripper_controller/gripper_cmd/_action/send_goal",
        "control_msgs::action::dds_::GripperCommand_SendGoal_",
        "6bf8cc4ce80cd499e7dd3258c03c50c3fa6672b469ff8355339ef1df77fcd212",
    ),
    ros_key("gripper_controller/gripper_cmd/_action/cancel_goal", *CANCEL),
)
COMMAND_TOPICS = (CMD_VEL, SPEED_LIMIT, ESTOP)


@dataclass(frozen=True)
class Seen:
    """A put or a query as it reached a session."""

    key: str
    payload: bytes


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def router_config(port: int, users_file: Path) -> zenoh.Config:
    conf = zenoh.Config.from_file(str(HERE / "ros2-router.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users_file)))
    return conf


def client_config(port: int, user: str, password: str) -> zenoh.Config:
    """ros2-client.json5 (tether's side) with this port and user; the intruder's differs only in its login."""
    conf = zenoh.Config.from_file(str(HERE / "ros2-client.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return conf


def node_config(port: int, user: str | None = None, password: str | None = None, mode: str = "peer") -> zenoh.Config:
    """A robot node's session as rmw_zenoh opens it: a peer connecting to the router; nobody connects to it."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return conf


def check(what: str, ok: bool) -> None:
    print(f"{'ok  ' if ok else 'FAIL'} {what}")
    if not ok:
        raise SystemExit(1)


class Watch:
    """What reaches one session, in the order it arrives: puts under domain 0 and, if it serves them,
    queries to the goal services and get_result.

    zenoh-python runs each subscriber's and queryable's callbacks on a thread of its own by default, so
    a put and a query that arrived in order could be recorded out of order; these callbacks run on the
    thread that received them (indirect=False) instead.
    """

    def __init__(self, session: zenoh.Session, *, serve: bool = False) -> None:
        self.seen: queue.Queue[Seen] = queue.Queue()
        self._declared: list[zenoh.Subscriber[None] | zenoh.Queryable[None]] = [
            session.declare_subscriber("0/**", zenoh.handlers.Callback(self._record, indirect=False))
        ]
        if serve:
            for key in (*GOAL_SERVICES, GET_RESULT):
                self._declared.append(
                    session.declare_queryable(key, zenoh.handlers.Callback(self._answer, indirect=False))
                )

    def _record(self, sample: zenoh.Sample) -> None:
        self.seen.put(Seen(str(sample.key_expr), _bytes(sample.payload)))

    def _answer(self, query: zenoh.Query) -> None:
        self.seen.put(Seen(str(query.key_expr), _bytes(query.payload)))
        query.reply(query.key_expr, b"robot")

    def until(self, payload: bytes, resend: Callable[[], object]) -> list[Seen] | None:
        """Everything seen before a message carrying `payload`, calling `resend` until one arrives;
        None if none did within DEADLINE.

        `resend` sends that message; it is repeated because the router may not know this session's
        subscription or queryable yet. Each one follows what it vouches for, so one arriving is enough.
        """
        seen: list[Seen] = []
        deadline = time.monotonic() + DEADLINE
        while time.monotonic() < deadline:
            resend()
            with contextlib.suppress(queue.Empty):
                end = time.monotonic() + 0.2
                while (left := end - time.monotonic()) > 0:
                    item = self.seen.get(timeout=left)
                    if item.payload == payload:
                        return seen
                    seen.append(item)
        return None

    def before_marker(self, mark: bytes, resend: Callable[[bytes], object]) -> set[str]:
        """The keys of what arrived carrying `mark` before the marker `resend` sends."""
        done = tag()
        seen = self.until(done, lambda: resend(done))
        if seen is None:
            raise SystemExit(f"the marker never arrived within {DEADLINE:g} s: nothing can be concluded")
        return {item.key for item in seen if item.payload == mark}

    def close(self) -> None:
        for entity in self._declared:
            entity.undeclare()


def _bytes(payload: zenoh.ZBytes | None) -> bytes:
    return b"" if payload is None else payload.to_bytes()


def tag() -> bytes:
    return os.urandom(8).hex().encode()


def answered(session: zenoh.Session, key: str) -> list[bytes]:
    """What `key` answers `session`, asked again until something answers or DEADLINE passes: a queryable
    declared a moment ago may reach the asker through the router a moment later (for allowed queries
    only; a denied one is proven by ordering, not by waiting)."""
    end = time.monotonic() + DEADLINE
    while True:
        replies = ok_replies(session.get(key, timeout=max(0.1, end - time.monotonic())))
        if replies or time.monotonic() >= end:
            return replies
        time.sleep(0.05)  # nothing answered at once: not reached yet; ask again within the deadline


def ok_replies(replies: zenoh.Handler[zenoh.Reply]) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]


@contextlib.contextmanager
def deployment() -> Iterator[tuple[int, dict[str, zenoh.Session]]]:
    with tempfile.TemporaryDirectory() as tmp:
        users_file = Path(tmp) / "users.txt"
        users_file.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
        port = free_port()
        with contextlib.ExitStack() as stack:
            stack.enter_context(zenoh.open(router_config(port, users_file)))
            sessions = {
                user: stack.enter_context(
                    zenoh.open(node_config(port, user, pw) if user == "robot" else client_config(port, user, pw))
                )
                for user, pw in USERS.items()
            }
            yield port, sessions


def main() -> None:
    zenoh.init_log_from_env_or("off")  # the refused logins log an ERROR by design
    with deployment() as (port, s):
        try:
            zenoh.open(client_config(port, "tether", "wrong")).close()
            check("a wrong password is refused", False)
        except zenoh.ZError:
            check("a wrong password is refused", True)
        try:
            zenoh.open(node_config(port, mode="client")).close()
            check("a client without credentials is refused", False)
        except zenoh.ZError:
            check("a client without credentials is refused", True)

        tether, robot, intruder = s["tether"], s["robot"], s["intruder"]
        at_robot, at_tether = Watch(robot, serve=True), Watch(tether)
        try:
            prove(tether, robot, intruder, at_robot, at_tether)
        finally:
            at_robot.close()
            at_tether.close()


def prove(
    tether: zenoh.Session, robot: zenoh.Session, intruder: zenoh.Session, at_robot: Watch, at_tether: Watch
) -> None:
    # Tether drives: each command topic's put reaches the robot, each goal service answers it.
    for key in COMMAND_TOPICS:
        mark = tag()
        check(f"tether may put {name_of(key)}", at_robot.until(mark, partial(tether.put, key, mark)) is not None)
    for key in GOAL_SERVICES:
        check(f"tether may query {name_of(key)}", answered(tether, key) == [b"robot"])

    # The robot reports: its odom reaches tether; its graph token reaches tether and tether's the robot.
    mark = tag()
    check("the robot's odom reaches tether", at_tether.until(mark, partial(robot.put, ODOM, mark)) is not None)
    check("the robot's graph token reaches tether", graph_sees(tether, robot, "base_controller"))
    check("tether's graph token reaches the robot", graph_sees(robot, tether, "tether"))

    # The intruder's commands never reach the robot: a get_result query (everyone may) marks the end.
    mark = tag()
    goals = {key: intruder.get(key, payload=mark, timeout=1.0) for key in GOAL_SERVICES}
    for key in (*COMMAND_TOPICS, ODOM):
        intruder.put(key, mark)
    arrived = at_robot.before_marker(mark, lambda done: intruder.get(GET_RESULT, payload=done))
    for key in COMMAND_TOPICS:
        check(f"intruder may not put {name_of(key)}", key not in arrived)
    check("intruder may not fake odom", ODOM not in arrived)
    for key, replies in goals.items():
        check(
            f"intruder may not query {name_of(key)} (never arrives, no reply)",
            key not in arrived and not ok_replies(replies),
        )

    # Nor can it pose as the robot's action server to catch tether's goals: once a marker sent after
    # its declaration arrives, the router has handled the declaration.
    caught: list[str] = []
    with intruder.declare_queryable(SEND_GOAL, lambda q: caught.append(str(q.key_expr))):
        at_robot.before_marker(tag(), lambda done: intruder.get(GET_RESULT, payload=done))
        answers = ok_replies(tether.get(SEND_GOAL, target=zenoh.QueryTarget.ALL, timeout=DEADLINE))
        check(
            "intruder may not serve send_goal (tether's goal reaches only the robot)",
            answers == [b"robot"] and not caught,
        )

    # The robot's own identity may not command either, not even with a wildcard put; odom marks the end.
    mark = tag()
    for key in (*COMMAND_TOPICS, "0/**"):
        robot.put(key, mark)
    arrived = at_tether.before_marker(mark, lambda done: robot.put(ODOM, done))
    check("robot may not put cmd_vel", CMD_VEL not in arrived)
    check("robot may not put speed_limit or emergency_stop", not arrived & {SPEED_LIMIT, ESTOP})
    check("robot may not put a wildcard key (0/**) that would reach cmd_vel", "0/**" not in arrived)

    # And tether may not pose as the robot; its cmd_vel marks the end.
    mark = tag()
    tether.put(ODOM, mark)
    check("tether may not fake odom", ODOM not in at_robot.before_marker(mark, lambda done: tether.put(CMD_VEL, done)))


def name_of(key: str) -> str:
    """The ROS name in an rmw_zenoh key: `0/cmd_vel/<type>/<hash>` -> `cmd_vel`."""
    return "/".join(key.split("/")[1:-2])


def graph_sees(looker: zenoh.Session, node: zenoh.Session, name: str) -> bool:
    """Does `node`'s rmw_zenoh node token reach `looker`?

    The token's form: @ros2_lv/<domain>/<zid>/<node id>/<entity id>/NN/<enclave>/<namespace>/<name>.
    """
    key = f"@ros2_lv/0/{node.info.zid()}/0/0/NN/%/%/{name}"
    with node.liveliness().declare_token(key):
        deadline = time.monotonic() + DEADLINE
        while time.monotonic() < deadline:
            if any(
                r.ok is not None and str(r.ok.key_expr) == key
                for r in looker.liveliness().get("@ros2_lv/0/**", timeout=1.0)
            ):
                return True
    return False


if __name__ == "__main__":
    main()
