"""Prove secured.json5 with real Zenoh sessions: a router with it, and clients logged in as different users.

    python deploy/check_acl.py      exits 0 and prints one line per check, or fails on the first wrong one

Everything is in one process on a free loopback port; ordering, not sleeping, decides what was dropped:
a denied put is followed by an allowed marker from the same client on the same link, so once the
marker arrives, the denied put would have too.
"""

from __future__ import annotations

import contextlib
import json
import queue
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import zenoh

HERE = Path(__file__).resolve().parent
ROBOT = "tether/r1"
USERS = {"safety": "pw-safety", "sim": "pw-sim", "executor": "pw-executor", "operator": "pw-operator"}
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


def received_before_marker(reader: zenoh.Session, writer: zenoh.Session, key: str) -> bool:
    """Does `writer`'s put on `key` reach `reader`? A marker put after it tells when to stop waiting."""
    marker = f"{ROBOT}/plan/marker"
    got: queue.Queue[str] = queue.Queue()
    sub = reader.declare_subscriber(f"{ROBOT}/**", lambda s: got.put(str(s.key_expr)))
    try:
        # The subscription must be known on the writer's side before the real test: repeat a marker until seen.
        deadline = time.monotonic() + DEADLINE
        while True:
            writer.put(marker, b"{}")
            with contextlib.suppress(queue.Empty):
                if got.get(timeout=0.05) == marker:
                    break
            if time.monotonic() > deadline:
                raise SystemExit("subscriber never saw the marker")
        while not got.empty():
            got.get_nowait()
        writer.put(key, b"{}")
        writer.put(marker, b"{}")
        seen = []
        while (k := got.get(timeout=DEADLINE)) != marker:
            seen.append(k)
        return key in seen
    finally:
        sub.undeclare()


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
