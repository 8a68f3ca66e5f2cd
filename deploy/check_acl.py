"""Prove secured.json5 with real Zenoh sessions: a router with it, and clients logged in as different users.

    python deploy/check_acl.py      exits 0 and prints one line per check, or fails on the first wrong one

Everything is in one process on a free loopback port; ordering, not sleeping, decides what was dropped:
a denied put or declaration is followed by an allowed marker put from the same client on the same link,
so once the marker arrives, the router has handled what came before it. Puts and queries travel in
order at data priority; declarations go at control priority, so they cannot fall behind the marker.
zenoh-python runs each subscriber's callbacks on its own thread, so a put and its marker are watched
by one subscriber.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import zenoh

HERE = Path(__file__).resolve().parent
ROBOT = "tether/r1"
USERS = {
    "safety": "pw-safety",
    "sim": "pw-sim",
    "ros2": "pw-ros2",
    "ros2sim": "pw-ros2sim",
    "executor": "pw-executor",
    "planner": "pw-planner",
    "operator": "pw-operator",
}
MARKER = f"{ROBOT}/plan/marker"
DEADLINE = 10.0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def router_config(port: int, users_file: Path) -> zenoh.Config:
    conf = zenoh.Config.from_file(str(HERE / "secured.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users_file)))
    return conf


def client_config(port: int, user: str, password: str) -> zenoh.Config:
    conf = zenoh.Config.from_file(str(HERE / "secured-client.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return conf


def check(what: str, ok: bool) -> None:
    print(f"{'ok  ' if ok else 'FAIL'} {what}")
    if not ok:
        raise SystemExit(1)


Seen = queue.Queue[tuple[str, bytes]]


def until_marker(seen: Seen, writer: zenoh.Session) -> list[tuple[str, bytes]]:
    """Put markers from `writer` until `seen` shows one; return the (key, payload) seen before it.

    The marker is repeated because the router may not know the reader's subscription yet; each one
    was put after everything `writer` sent before, so any one arriving is enough.
    """
    nonce = os.urandom(8)
    before: list[tuple[str, bytes]] = []
    deadline = time.monotonic() + DEADLINE
    while time.monotonic() < deadline:
        writer.put(MARKER, nonce)
        with contextlib.suppress(queue.Empty):
            end = time.monotonic() + 0.05
            while (left := end - time.monotonic()) > 0:
                key, payload = seen.get(timeout=left)
                if (key, payload) == (MARKER, nonce):
                    return before
                before.append((key, payload))
    raise SystemExit("the reader never saw the marker")


def watch(reader: zenoh.Session, key: str, seen: Seen) -> zenoh.Subscriber[None]:
    return reader.declare_subscriber(key, lambda s: seen.put((str(s.key_expr), s.payload.to_bytes())))


def settle(reader: zenoh.Session, writer: zenoh.Session) -> None:
    """Return once the router has handled everything `writer` sent so far (a marker reached `reader`)."""
    seen: Seen = queue.Queue()
    with watch(reader, MARKER, seen):
        until_marker(seen, writer)


def received_before_marker(reader: zenoh.Session, writer: zenoh.Session, key: str) -> bool:
    """Does `writer`'s put on `key` reach `reader`? A marker put after it tells when to stop waiting.

    One subscriber sees both, so its callback gets them in the order they arrived.
    """
    seen: Seen = queue.Queue()
    with watch(reader, f"{ROBOT}/**", seen):
        until_marker(seen, writer)  # the subscription is known to the router
        nonce = os.urandom(8)
        writer.put(key, nonce)
        return (key, nonce) in until_marker(seen, writer)


def served(caller: zenoh.Session, server: zenoh.Session, key: str) -> bool:
    """Does the router let `server` answer `caller`'s queries on `key`, i.e. accept its queryable?"""
    with server.declare_queryable(key, lambda q: q.reply(key, b"{}")):
        settle(caller, server)
        return answered(caller, key)


def answered(caller: zenoh.Session, key: str, timeout: float = 1.0) -> bool:
    return any(r.ok is not None for r in caller.get(key, timeout=timeout))


@contextlib.contextmanager
def deployment() -> Iterator[tuple[int, dict[str, zenoh.Session]]]:
    with tempfile.TemporaryDirectory() as tmp:
        users_file = Path(tmp) / "users.txt"
        users_file.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
        port = free_port()
        with contextlib.ExitStack() as stack:
            stack.enter_context(zenoh.open(router_config(port, users_file)))
            sessions = {u: stack.enter_context(zenoh.open(client_config(port, u, p))) for u, p in USERS.items()}
            yield port, sessions


def main() -> None:
    zenoh.init_log_from_env_or("off")  # the refused login logs an ERROR by design
    with deployment() as (port, s):
        try:
            zenoh.open(client_config(port, "executor", "wrong")).close()
            check("a wrong password is refused", False)
        except zenoh.ZError:
            check("a wrong password is refused", True)

        anonymous = zenoh.Config.from_file(str(HERE / "client.json5"))
        anonymous.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        try:
            zenoh.open(anonymous).close()
            check("a client without credentials is refused", False)
        except zenoh.ZError:
            check("a client without credentials is refused", True)

        observer = s["operator"]
        check("safety may put robot/cmd_vel", received_before_marker(observer, s["safety"], f"{ROBOT}/robot/cmd_vel"))
        check(
            "executor may not put robot/cmd_vel",
            not received_before_marker(observer, s["executor"], f"{ROBOT}/robot/cmd_vel"),
        )
        check("sim may not put robot/cmd_vel", not received_before_marker(observer, s["sim"], f"{ROBOT}/robot/cmd_vel"))
        check("executor may put cmd/cmd_vel", received_before_marker(observer, s["executor"], f"{ROBOT}/cmd/cmd_vel"))
        check("sim may put robot/odom", received_before_marker(observer, s["sim"], f"{ROBOT}/robot/odom"))
        check(
            "executor may not fake the heartbeat",
            not received_before_marker(observer, s["executor"], f"{ROBOT}/safety/heartbeat"),
        )
        check("anyone may put safety/estop", received_before_marker(observer, s["executor"], f"{ROBOT}/safety/estop"))
        teleop = f"{ROBOT}/cmd/teleop/cmd_vel"
        check("operator may drive by hand", received_before_marker(s["safety"], s["operator"], teleop))
        check("executor may not drive by hand", not received_before_marker(observer, s["executor"], teleop))
        humans = f"{ROBOT}/world/humans"
        check("sim may report people", received_before_marker(observer, s["sim"], humans))
        check("executor may not report people", not received_before_marker(observer, s["executor"], humans))
        odom = f"{ROBOT}/robot/odom"
        check("ros2 may put robot/odom", received_before_marker(observer, s["ros2"], odom))
        check("executor may not put robot/odom", not received_before_marker(observer, s["executor"], odom))
        check("ros2sim may not put robot/odom", not received_before_marker(observer, s["ros2sim"], odom))
        check(
            "ros2 may not put robot/cmd_vel", not received_before_marker(observer, s["ros2"], f"{ROBOT}/robot/cmd_vel")
        )
        check(
            "ros2sim may put sim/** (as everyone may)",
            received_before_marker(observer, s["ros2sim"], f"{ROBOT}/sim/move"),
        )

        gripper_goal = f"{ROBOT}/robot/gripper_command/_action/send_goal"
        check("ros2 may serve robot/**", served(s["safety"], s["ros2"], gripper_goal))
        check("executor may not serve robot/**", not served(s["safety"], s["executor"], gripper_goal))
        check("planner may not serve robot/**", not served(s["safety"], s["planner"], gripper_goal))
        check("ros2sim may not serve robot/**", not served(s["safety"], s["ros2sim"], gripper_goal))
        check("ros2sim may serve sim/**", served(s["executor"], s["ros2sim"], f"{ROBOT}/sim/ground_truth"))

        goal = f"{ROBOT}/robot/navigate_to_pose/_action/send_goal"
        reset = f"{ROBOT}/safety/reset"
        with (
            s["sim"].declare_queryable(goal, lambda q: q.reply(goal, b"{}")),
            s["safety"].declare_queryable(reset, lambda q: q.reply(reset, b"{}")),
        ):
            deadline = time.monotonic() + DEADLINE
            while not answered(s["safety"], goal, timeout=0.2):
                if time.monotonic() > deadline:
                    check("safety may send a robot goal", False)
            check("safety may send a robot goal", True)
            check("executor may not send a robot goal", not answered(s["executor"], goal))
            deadline = time.monotonic() + DEADLINE
            while not answered(s["operator"], reset, timeout=0.2):
                if time.monotonic() > deadline:
                    check("operator may reset the e-stop", False)
            check("operator may reset the e-stop", True)
            check("executor may not reset the e-stop", not answered(s["executor"], reset))
            # Not `safety` itself: its own session answers its own query without passing the router.
            check("sim may not reset the e-stop", not answered(s["sim"], reset))


if __name__ == "__main__":
    main()
