"""The access rules `tether deploy init` writes, proven with real sessions: its router, its clients' files.

The router runs in this process from DIR/router.json5, and its own session watches what gets past the
access rules: a subscriber on tether/**, a liveliness subscriber and, for queries, a queryable. A denied
put, query or declaration is followed by an allowed marker put from the same client on the same link,
so once the router's session sees the marker, it has handled what came before (declarations travel
at control priority, ahead of the data). The router's callbacks run directly on the thread that routes the messages
(indirect=False), so they see them in the order the router handled them.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh

from services.bundled import DEFAULT_POLICY
from services.runtime import zenoh_config_file
from tests.integration.conftest import LOADED_MACHINE_HEARTBEAT
from tests.logs import print_tails
from tests.sessions import LOADED_HEARTBEAT_MAX_AGE, free_port
from tether import deployment

DEADLINE = 10.0
ROBOTS = ("r1", "r2")


@dataclass
class Fleet:
    directory: Path
    tls: bool
    port: int
    router: zenoh.Session
    sessions: dict[str, zenoh.Session] = field(default_factory=dict)
    seen: queue.Queue[tuple[str, str, bytes]] = field(default_factory=queue.Queue)
    queried: set[str] = field(default_factory=set)

    def s(self, robot: str, identity: str) -> zenoh.Session:
        return self.sessions[deployment.username(robot, identity)]

    def config(self, robot: str, identity: str) -> zenoh.Config:
        return zenoh_config_file(self.directory / robot / f"{identity}.json5")


@pytest.fixture(scope="module", params=[False, True], ids=["tcp", "tls"])
def fleet(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    zenoh.init_log_from_env_or("off")  # refused logins log errors by design
    tls: bool = request.param
    directory = tmp_path_factory.mktemp("deploy-tls" if tls else "deploy")
    port = free_port()
    deployment.init(directory, ROBOTS, tls=tls, router=deployment.RouterAddress("127.0.0.1", port))
    with contextlib.ExitStack() as stack:
        router = stack.enter_context(zenoh.open(zenoh_config_file(directory / deployment.ROUTER_CONFIG)))
        f = Fleet(directory, tls, port, router)

        def on_sample(sample: zenoh.Sample) -> None:
            f.seen.put(("sample", str(sample.key_expr), sample.payload.to_bytes()))

        def on_token(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                f.seen.put(("token", str(sample.key_expr), b""))

        def on_query(query: zenoh.Query) -> None:
            f.seen.put(("query", str(query.key_expr), b""))
            query.reply(query.key_expr, b"{}")

        direct = {"indirect": False}
        stack.enter_context(router.declare_subscriber("tether/**", zenoh.handlers.Callback(on_sample, **direct)))
        stack.enter_context(
            router.liveliness().declare_subscriber("tether/**", zenoh.handlers.Callback(on_token, **direct))
        )
        stack.enter_context(router.declare_queryable("tether/**", zenoh.handlers.Callback(on_query, **direct)))
        for robot in ROBOTS:
            for identity in deployment.IDENTITIES:
                name = deployment.username(robot, identity)
                f.sessions[name] = stack.enter_context(zenoh.open(f.config(robot, identity)))
        yield f


def until_marker(f: Fleet, writer: zenoh.Session, marker: str) -> list[tuple[str, str, bytes]]:
    """Put markers from `writer` until the router's session sees one; return what it saw before it."""
    nonce = os.urandom(8)
    before: list[tuple[str, str, bytes]] = []
    deadline = time.monotonic() + DEADLINE
    while time.monotonic() < deadline:
        writer.put(marker, nonce)
        with contextlib.suppress(queue.Empty):
            end = time.monotonic() + 0.05
            while (left := end - time.monotonic()) > 0:
                event = f.seen.get(timeout=left)
                if event == ("sample", marker, nonce):
                    return before
                before.append(event)
    raise AssertionError(f"the router never saw the marker {marker}")


def passes(f: Fleet, writer: zenoh.Session, act: Callable[[], object], marker: str) -> list[tuple[str, str, bytes]]:
    """What of `act` (done by `writer`) got past the router's access rules, known once a marker follows it."""
    until_marker(f, writer, marker)  # everything earlier is out of the way; the writer knows the subscriber
    act()
    return until_marker(f, writer, marker)


def put_passes(f: Fleet, writer: zenoh.Session, key: str, marker: str) -> bool:
    nonce = os.urandom(8)
    return ("sample", key, nonce) in passes(f, writer, lambda: writer.put(key, nonce), marker)


def query_passes(f: Fleet, writer: zenoh.Session, key: str, marker: str) -> bool:
    # Not waiting for a reply: the marker says whether the query reached the router's queryable.
    return ("query", key, b"") in passes(f, writer, lambda: writer.get(key, timeout=1.0), marker)


def token_passes(f: Fleet, writer: zenoh.Session, key: str, marker: str) -> bool:
    tokens: list[zenoh.LivelinessToken] = []
    try:
        return ("token", key, b"") in passes(
            f, writer, lambda: tokens.append(writer.liveliness().declare_token(key)), marker
        )
    finally:
        for token in tokens:
            token.undeclare()


# The marker: the e-stop, which every identity may put (nothing here listens to it but the router).
def marker_of(robot: str, identity: str) -> str:
    return f"tether/{robot}/safety/estop"


def test_the_agent_may_send_plans_and_stop_the_robot_and_nothing_else(fleet: Fleet) -> None:
    agent, marker = fleet.s("r1", "agent"), marker_of("r1", "agent")
    assert put_passes(fleet, agent, "tether/r1/safety/estop", marker)
    assert query_passes(fleet, agent, "tether/r1/plan/execute/_action/send_goal", marker)
    assert query_passes(fleet, agent, "tether/r1/robot/camera/image", marker)
    assert not put_passes(fleet, agent, "tether/r1/robot/cmd_vel", marker)
    assert not put_passes(fleet, agent, "tether/r1/world/humans", marker)
    assert not put_passes(fleet, agent, "tether/r1/cmd/teleop/cmd_vel", marker)
    assert not put_passes(fleet, agent, "tether/r1/cmd/cmd_vel", marker)
    assert not put_passes(fleet, agent, "tether/r1/safety/heartbeat", marker)
    assert not query_passes(fleet, agent, "tether/r1/safety/reset", marker)
    assert not query_passes(fleet, agent, "tether/r1/robot/navigate_to_pose/_action/send_goal", marker)
    assert not token_passes(fleet, agent, "tether/r1/alive/safety", marker)


def test_only_safety_drives_the_robot_and_the_sim_receives_it(fleet: Fleet) -> None:
    received: queue.Queue[tuple[str, bytes]] = queue.Queue()
    sim, safety = fleet.s("r1", "sim"), fleet.s("r1", "safety")
    with sim.declare_subscriber("tether/r1/**", lambda s: received.put((str(s.key_expr), s.payload.to_bytes()))):
        nonce, marker = os.urandom(8), "tether/r1/safety/estop"
        deadline = time.monotonic() + DEADLINE
        while (marker, b"ready") not in drain(received):  # the sim's subscription is known to the router
            assert time.monotonic() < deadline, "the sim never received safety's marker"
            safety.put(marker, b"ready")
        safety.put("tether/r1/robot/cmd_vel", nonce)
        safety.put(marker, b"after")
        got: list[tuple[str, bytes]] = []
        while (marker, b"after") not in got:
            got.append(received.get(timeout=DEADLINE))
        assert ("tether/r1/robot/cmd_vel", nonce) in got
    assert put_passes(fleet, safety, "tether/r1/robot/cmd_vel", "tether/r1/safety/estop")
    assert query_passes(fleet, safety, "tether/r1/robot/navigate_to_pose/_action/send_goal", "tether/r1/safety/estop")
    for identity in ("sim", "executor", "planner", "operator", "ros2"):
        assert not put_passes(fleet, fleet.s("r1", identity), "tether/r1/robot/cmd_vel", marker_of("r1", identity))


def drain(q: queue.Queue[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
    items = []
    with contextlib.suppress(queue.Empty):
        items.append(q.get(timeout=0.05))
        while True:
            items.append(q.get_nowait())
    return items


def test_only_the_operator_resets_and_only_the_robot_reports_people(fleet: Fleet) -> None:
    assert query_passes(fleet, fleet.s("r1", "operator"), "tether/r1/safety/reset", "tether/r1/safety/estop")
    assert not query_passes(fleet, fleet.s("r1", "executor"), "tether/r1/safety/reset", "tether/r1/safety/estop")
    assert put_passes(fleet, fleet.s("r1", "sim"), "tether/r1/world/humans", "tether/r1/safety/estop")
    assert not put_passes(fleet, fleet.s("r1", "planner"), "tether/r1/world/humans", "tether/r1/safety/estop")


def test_only_the_operator_forgets_an_incident_and_only_the_robot_side_reports_one(fleet: Fleet) -> None:
    forget, report, listing = (
        "tether/r1/safety/incidents/forget",
        "tether/r1/safety/incidents/report",
        "tether/r1/safety/incidents",
    )
    assert query_passes(fleet, fleet.s("r1", "operator"), forget, "tether/r1/safety/estop")
    agent, agent_marker = fleet.s("r1", "agent"), marker_of("r1", "agent")
    assert not query_passes(fleet, agent, forget, agent_marker)
    assert query_passes(fleet, agent, listing, agent_marker)  # the agent may read what is remembered
    assert not put_passes(fleet, agent, report, agent_marker)  # but not make up an incident
    for identity in ("executor", "sim"):
        assert put_passes(fleet, fleet.s("r1", identity), report, "tether/r1/safety/estop"), identity
    assert not query_passes(fleet, fleet.s("r1", "planner"), forget, "tether/r1/safety/estop")


def test_each_liveliness_token_only_from_its_own_service(fleet: Fleet) -> None:
    assert token_passes(fleet, fleet.s("r1", "safety"), "tether/r1/alive/safety", "tether/r1/safety/estop")
    assert token_passes(fleet, fleet.s("r1", "executor"), "tether/r1/alive/executor", "tether/r1/safety/estop")
    for identity in ("executor", "sim", "operator", "agent"):
        key, marker = "tether/r1/alive/safety", marker_of("r1", identity)
        assert not token_passes(fleet, fleet.s("r1", identity), key, marker), identity
    assert not token_passes(fleet, fleet.s("r2", "safety"), "tether/r1/alive/safety", "tether/r2/safety/estop")


def test_one_robots_identities_can_neither_drive_nor_hear_another_robot(fleet: Fleet) -> None:
    for identity in deployment.IDENTITIES:
        other, marker = fleet.s("r2", identity), marker_of("r2", identity)
        for key in ("tether/r1/robot/cmd_vel", "tether/r1/safety/estop", "tether/r1/cmd/cmd_vel"):
            assert not put_passes(fleet, other, key, marker), (identity, key)
        for key in ("tether/r1/safety/reset", "tether/r1/plan/execute/_action/send_goal"):
            assert not query_passes(fleet, other, key, marker), (identity, key)
    # The same rights on its own robot: the rules are the same, scoped to tether/r2/.
    assert put_passes(fleet, fleet.s("r2", "safety"), "tether/r2/robot/cmd_vel", "tether/r2/safety/estop")

    # What the router sends: r1's traffic reaches r1's operator and not r2's. The router's own session
    # writes r1's odometry, then each operator's marker, round after round. r1's operator hears both;
    # one make test run saw its marker a round before the odometry, so the order is not relied on.
    # r2's operator, told only its marker, goes on for as many rounds as r1's took, and hears no odometry.
    heard: dict[str, queue.Queue[tuple[str, bytes]]] = {"r1": queue.Queue(), "r2": queue.Queue()}
    with contextlib.ExitStack() as stack:
        for robot, q in heard.items():

            def on_sample(sample: zenoh.Sample, q: queue.Queue[tuple[str, bytes]] = q) -> None:
                q.put((str(sample.key_expr), sample.payload.to_bytes()))

            listener = fleet.s(robot, "operator")
            callback = zenoh.handlers.Callback(on_sample, indirect=False)
            # In this order: once the router knows the second, it knows the first (one link, in order).
            stack.enter_context(listener.declare_subscriber("tether/r1/robot/**", callback))
            stack.enter_context(listener.declare_subscriber(f"tether/{robot}/plan/**", callback))
        nonce = os.urandom(8)
        odom = ("tether/r1/robot/odom", nonce)
        needed = 0  # the rounds r1's operator took to hear both
        for robot, q in heard.items():
            marker = f"tether/{robot}/plan/router-marker"
            wanted = {(marker, nonce), odom} if robot == "r1" else {(marker, nonce)}
            got: list[tuple[str, bytes]] = []
            deadline, rounds = time.monotonic() + DEADLINE, 0
            while not wanted <= set(got) or rounds < needed:
                assert time.monotonic() < deadline, f"{robot}'s operator heard only {sorted({k for k, _ in got})}"
                fleet.router.put(odom[0], nonce)
                fleet.router.put(marker, nonce)
                rounds += 1
                got += drain(q)
            needed = max(needed, rounds)
            assert (odom in got) == (robot == "r1"), robot


def refused(conf: zenoh.Config) -> bool:
    conf.insert_json5("connect/timeout_ms", "0")
    conf.insert_json5("connect/exit_on_failure", "true")
    try:
        zenoh.open(conf).close()
    except zenoh.ZError:
        return True
    return False


def test_a_session_without_credentials_or_certificate_is_refused(fleet: Fleet) -> None:
    anonymous = fleet.config("r1", "operator")
    anonymous.insert_json5("transport/auth/usrpwd", json.dumps({"user": None, "password": None}))
    assert refused(anonymous)
    wrong = fleet.config("r1", "operator")
    wrong.insert_json5("transport/auth/usrpwd/password", json.dumps("not-the-password"))
    assert refused(wrong)
    if fleet.tls:
        no_cert = fleet.config("r1", "operator")
        no_cert.insert_json5(
            "transport/link/tls", json.dumps({"root_ca_certificate": str(fleet.directory / "r1" / "ca.pem")})
        )
        assert refused(no_cert)
        in_the_clear = fleet.config("r1", "operator")
        in_the_clear.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{fleet.port}"]))
        assert refused(in_the_clear)
    # And the same files, untouched, are let in: the refusals above are about what was taken away.
    assert not refused(fleet.config("r1", "operator"))


def test_the_rights_each_identity_has_and_has_not(fleet: Fleet) -> None:
    # What deploy/check_acl.py proved of the hand-written example router it replaced, on the generated rules.
    m = "tether/r1/safety/estop"
    assert put_passes(fleet, fleet.s("r1", "executor"), "tether/r1/cmd/cmd_vel", m)
    assert put_passes(fleet, fleet.s("r1", "executor"), "tether/r1/safety/estop", m)
    assert not put_passes(fleet, fleet.s("r1", "executor"), "tether/r1/safety/heartbeat", m)
    for backend in ("sim", "ros2"):
        assert put_passes(fleet, fleet.s("r1", backend), "tether/r1/robot/odom", m), backend
    assert not put_passes(fleet, fleet.s("r1", "executor"), "tether/r1/robot/odom", m)
    assert put_passes(fleet, fleet.s("r1", "operator"), "tether/r1/cmd/teleop/cmd_vel", m)
    assert not put_passes(fleet, fleet.s("r1", "executor"), "tether/r1/cmd/teleop/cmd_vel", m)
    assert not put_passes(fleet, fleet.s("r1", "executor"), "tether/r1/world/humans", m)
    assert not query_passes(fleet, fleet.s("r1", "executor"), "tether/r1/robot/navigate_to_pose/_action/send_goal", m)
    assert not query_passes(fleet, fleet.s("r1", "sim"), "tether/r1/safety/reset", m)


def test_nobody_forges_anothers_publication_or_sends_motion_past_the_executor(fleet: Fleet) -> None:
    s, m = (lambda i: fleet.s("r1", i)), "tether/r1/safety/estop"
    plan_status = "tether/r1/plan/execute/_action/status"
    nav_status, nav_feedback = (
        "tether/r1/cmd/navigate_to_pose/_action/status",
        "tether/r1/cmd/navigate_to_pose/_action/feedback",
    )
    # Safety ends a plan's approval on the plan's status (services/safety/node.py): the executor's alone.
    assert put_passes(fleet, s("executor"), plan_status, m)
    assert not put_passes(fleet, s("parser"), plan_status, m)
    # A command's status and feedback: safety's, which the executor waits on.
    assert put_passes(fleet, s("safety"), nav_status, m)
    assert not put_passes(fleet, s("parser"), nav_status, m)
    assert not put_passes(fleet, s("recorder"), nav_feedback, m)
    assert put_passes(fleet, s("planner"), "tether/r1/planner/attempts", m)
    assert not put_passes(fleet, s("recorder"), "tether/r1/planner/attempts", m)
    # Motion goals reach safety from the executor (and a person), never from the parser or the planner.
    goal = "tether/r1/cmd/navigate_to_pose/_action/send_goal"
    assert query_passes(fleet, s("executor"), goal, m)
    for identity in ("parser", "planner"):
        assert not query_passes(fleet, s(identity), goal, m), identity
    assert query_passes(fleet, s("operator"), "tether/r1/sim/move", m)
    assert not query_passes(fleet, s("recorder"), "tether/r1/sim/move", m)


def serves(
    f: Fleet,
    server: zenoh.Session,
    key: str,
    marker: str,
    asker: zenoh.Session,
    *,
    ask: str | None = None,
    reply_as: str | None = None,
) -> bool:
    """Does the router let `server` answer `asker`'s queries on `key` (accept its queryable and replies)?

    `asker` asks `ask` (default `key`); `server` replies under `reply_as` (default `key`). The router's
    own queryable answers every query too; the server's reply is known by its nonce."""
    nonce = os.urandom(8)
    with server.declare_queryable(key, lambda q: q.reply(reply_as or key, nonce)):
        until_marker(f, server, marker)  # the router has handled the declaration
        replies = asker.get(
            ask or key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0
        )
        return any(r.ok is not None and r.ok.payload.to_bytes() == nonce for r in replies)


def test_each_service_serves_only_its_own_keys(fleet: Fleet) -> None:
    s, m = (lambda i: fleet.s("r1", i)), "tether/r1/safety/estop"
    door, gripper = (
        "tether/r1/cmd/navigate_to_pose/_action/send_goal",
        "tether/r1/robot/gripper_command/_action/send_goal",
    )
    assert serves(fleet, s("parser"), "tether/r1/plan/parse", m, s("executor"))
    assert serves(fleet, s("safety"), door, m, s("executor"))
    # (Never the server asking itself: a session answers its own queries without the router.)
    assert serves(fleet, s("sim"), "tether/r1/sim/ground_truth", m, s("operator"))
    assert serves(fleet, s("ros2"), gripper, m, s("safety"))
    # A compromised planner (or any other service) cannot pose as the parser or as safety's command doors.
    for identity in ("planner", "executor", "resolver", "recorder", "operator"):
        if identity != "executor":  # the parser's only asker
            assert not serves(fleet, s(identity), "tether/r1/plan/parse", m, s("executor")), identity
        asker = s("executor" if identity == "operator" else "operator")
        assert not serves(fleet, s(identity), door, m, asker), identity
    assert not serves(fleet, s("parser"), "tether/r1/plan/execute/_action/send_goal", m, s("operator"))
    assert not serves(fleet, s("planner"), "tether/r1/safety/check_plan", m, s("executor"))
    for identity in ("executor", "planner"):
        assert not serves(fleet, s(identity), gripper, m, s("safety")), identity


def test_each_service_answers_for_its_own_process_only(fleet: Fleet) -> None:
    # `tether status` asks tether/<robot>/_process/*; each service answers on its own key (runtime.py).
    s, m = (lambda i: fleet.s("r1", i)), "tether/r1/safety/estop"
    every = "tether/r1/_process/*"
    assert serves(fleet, s("sim"), "tether/r1/_process/sim", m, s("operator"), ask=every)
    assert serves(fleet, s("safety"), "tether/r1/_process/safety", m, s("executor"), ask=every)
    # Asked by the operator and the services, not the agent.
    assert query_passes(fleet, s("recorder"), every, m)
    assert not query_passes(fleet, s("agent"), every, marker_of("r1", "agent"))
    # Nobody answers in another's place: not on its key, not under a wider one, not by a reply's key.
    for identity in ("sim", "planner", "recorder", "operator", "agent"):
        server, marker = s(identity), marker_of("r1", identity)
        assert not serves(fleet, server, "tether/r1/_process/safety", marker, s("executor"), ask=every), identity
        wide = serves(
            fleet,
            server,
            "tether/r1/_process/**",
            marker,
            s("executor"),
            ask=every,
            reply_as="tether/r1/_process/safety",
        )
        assert not wide, identity
    assert not serves(
        fleet, s("sim"), "tether/r1/_process/sim", m, s("operator"), ask=every, reply_as="tether/r1/_process/safety"
    )
    assert not serves(
        fleet, fleet.s("r2", "safety"), "tether/r1/_process/safety", "tether/r2/safety/estop", s("operator")
    )


def cmd_vel_passes_with(f: Fleet, conf: zenoh.Config) -> bool:
    """Does a robot/cmd_vel put from a session opened with `conf` pass the router? Known once the router
    saw that session's transport close: the close follows the put on the same link."""
    nonce = os.urandom(8)
    closed: queue.Queue[str] = queue.Queue()

    def on_event(event: zenoh.TransportEvent) -> None:
        if event.kind == zenoh.SampleKind.DELETE:
            closed.put(str(event.transport.zid))

    with f.router.info.declare_transport_events_listener(zenoh.handlers.Callback(on_event, indirect=False)):
        session = zenoh.open(conf)
        zid = str(session.info.zid())
        session.put("tether/r1/robot/cmd_vel", nonce)
        session.put("tether/r1/safety/estop", nonce)  # what any identity may
        session.close()
        while closed.get(timeout=DEADLINE) != zid:
            pass
    seen: list[tuple[str, str, bytes]] = []
    with contextlib.suppress(queue.Empty):
        while True:
            seen.append(f.seen.get_nowait())
    return ("sample", "tether/r1/robot/cmd_vel", nonce) in seen


@pytest.mark.parametrize("fleet", [True], ids=["tls"], indirect=True)  # certificates only with --tls
def test_a_password_with_another_identitys_certificate_gets_nothing(fleet: Fleet) -> None:
    assert fleet.tls
    passwords = dict(line.split(":", 1) for line in (fleet.directory / deployment.USERS_FILE).read_text().split())

    def login(certificate_of: str, password_of: str) -> zenoh.Config:
        conf = fleet.config("r1", certificate_of)  # its certificate and key
        user = deployment.username("r1", password_of)
        conf.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": passwords[user]}))
        return conf

    assert cmd_vel_passes_with(fleet, login("safety", "safety"))  # the check can see a put that passes
    assert not cmd_vel_passes_with(fleet, login("agent", "safety"))  # safety's stolen password
    assert not cmd_vel_passes_with(fleet, login("safety", "agent"))  # safety's stolen certificate


# One whole stack through a deployment: `tether router DIR`, `tether up --deploy DIR --robot r1`, and the
# command line as the operator and as the agent, each with its own file.

STACK_TIMEOUT = 120.0


def tether(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tether", *args], capture_output=True, text=True, timeout=timeout, env=clean_env()
    )


def clean_env() -> dict[str, str]:
    # Nothing of the caller's stack: each command names its robot and Zenoh config itself.
    drop = ("TETHER_ROBOT", "TETHER_ZENOH_CONFIG", "TETHER_BASE_PORT", "TETHER_OPERATOR_TOKEN_FILE")
    return {k: v for k, v in os.environ.items() if k not in drop}


@contextlib.contextmanager
def background(args: list[str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tether", *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=clean_env(),
            start_new_session=True,
        )
        try:
            yield proc
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)
            print(f"----- {log.name} -----\n{log.read_text(errors='replace')[-6000:]}")


def test_a_deployment_runs_a_plan_through_its_router_with_an_identity_per_service(tmp_path: Path) -> None:
    directory, port = tmp_path / "deploy", free_port()
    made = tether("deploy", "init", str(directory), "--robot", "r1", "--tls", "--router", f"127.0.0.1:{port}")
    assert made.returncode == 0, made.stderr
    # Timing for a loaded machine, as this test is not about it (the bounds at their defaults are the
    # realtime tests'): the heartbeat's, as in every stack of the parallel part (conftest), and safety's
    # watchdog's, the policy's monitor.state_max_age as old as the loaded heartbeat may be. A `make test`
    # run (beside a profiler) saw this plan's drive stopped by the watchdog, odometry 0.51 s apart.
    policy = directory / "r1" / "policy.toml"
    max_age = f"state_max_age = {LOADED_HEARTBEAT_MAX_AGE}"
    loaded, found = re.subn(r"^state_max_age = [0-9.]+", max_age, DEFAULT_POLICY.read_text(), flags=re.M)
    assert found == 1, "the default policy sets no monitor.state_max_age"
    policy.write_text(loaded)
    config = directory / "r1" / "tether.toml"
    text = config.read_text().replace("[sim]\n", f"[sim]\nrealtime_factor = 4.0\n{LOADED_MACHINE_HEARTBEAT}", 1)
    config.write_text(text.replace("[safety]\n", f'[safety]\npolicy = "{policy}"\n', 1))
    operator = ("--zenoh-config", str(directory / "r1" / "operator.json5"), "--robot", "r1")
    agent = ("--zenoh-config", str(directory / "r1" / "agent.json5"), "--robot", "r1")

    bad = tether("up", "--deploy", str(directory), "--robot", "r1", "--only", "sim,teleporter")
    assert bad.returncode == 2
    assert "teleporter" in bad.stderr

    with (
        background(["router", str(directory)], tmp_path / "router.log"),
        background(
            ["up", "--deploy", str(directory), "--robot", "r1", "--log-dir", str(tmp_path / "logs")],
            tmp_path / "up.log",
        ) as up,
    ):
        deadline = time.monotonic() + STACK_TIMEOUT
        while (check := tether(*operator, "status", "--check", "--json")).returncode != 0:
            assert up.poll() is None, "tether up --deploy exited"
            assert time.monotonic() < deadline, f"the stack never became healthy: {check.stdout} {check.stderr}"
        report = json.loads(check.stdout)
        assert report["ok"] and report["heartbeat"]
        assert {"sim", "safety", "parser", "resolver", "executor", "recorder"} <= set(report["alive"])
        one = tether(*agent, "status", "--check", "--service", "safety")
        assert one.returncode == 0, one.stderr
        # Each service's own figures cross the router to the operator (the `_process` rules).
        shown = tether(*operator, "status", "--json")
        processes = json.loads(shown.stdout)["processes"]
        assert set(report["alive"]) <= set(processes), shown.stdout
        assert all(p["rss_bytes"] > 0 for p in processes.values()), processes

        # A new deployment has no latch file yet, so safety starts latched; only the operator clears it.
        refused = tether(*agent, "reset", "--token-file", str(directory / "r1" / "operator.token"))
        assert refused.returncode != 0
        reset = tether(*operator, "reset", "--token-file", str(directory / "r1" / "operator.token"))
        assert reset.returncode == 0, reset.stdout + reset.stderr

        plan = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen table"}]})
        sent = tether(*agent, "send", plan, "--wait", "--json", timeout=STACK_TIMEOUT)
        result = json.loads(sent.stdout)
        if result["status"] != "succeeded":
            print_tails(tmp_path / "logs")
        assert (sent.returncode, result["status"]) == (0, "succeeded"), sent.stdout + sent.stderr

    down = tether(*operator, "status", "--check")
    assert down.returncode != 0
    assert "unhealthy" in down.stderr
