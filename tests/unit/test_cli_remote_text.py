"""What others wrote, as the CLI's commands print it in words: a peer that answers as the executor,
safety, the robot, the simulator, the resolver and the planner, with ESC sequences in every text it
may choose, never reaches the operator's terminal with a control character. The peer is a real Zenoh
session; the CLI runs in this process on another."""

from __future__ import annotations

import json
import os
import secrets
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from typer.testing import CliRunner

from schemas import keys
from schemas.actions import CancelResponse, GetResult, GoalProgress, GoalResponse, GoalState
from schemas.common import ErrorKind, Pose2D, ServiceError, Stage, Vec3
from schemas.executor import ExecutePlanFeedback, ExecutePlanResult, PlanStatus, StepResult, StepStatus
from schemas.incidents import (
    CautionZone,
    ForgetAction,
    ForgetIncident,
    ForgetReply,
    Incident,
    IncidentKind,
    IncidentList,
    IncidentQuery,
)
from schemas.planner import AskReply, AskRequest, AskStatus, Recovery, RecoveryOutcome
from schemas.process import ProcessStatus
from schemas.robot import Odometry, RobotDiagnostics, RobotProblem
from schemas.safety import EstopState, ResetReply, SafetyStatus
from schemas.trace import RecorderStatus
from schemas.world import (
    FaultInjected,
    FaultKind,
    MoveEntity,
    PerceivedObject,
    PerceivedObjects,
    SceneDescription,
)
from services.errors import CallError
from services.robotlink import Signer
from services.runtime import ALL_SERVICES, Node, NodeSettings, encode
from tests.sessions import free_ports
from tests.unit.test_operator_hostile import controls
from tether import cli

# Retitles the terminal, clears the screen, and the same with the 8-bit CSI.
HOSTILE = "x\x1b]0;pwned\x07\x1b[2J\x9b2J"
ESCAPED = "x\\x1b]0;pwned\\x07\\x1b[2J\\x9b2J"
# A service name a peer may hold a liveliness token and answer a process status for.
INTRUDER = f"intruder{HOSTILE}"


@dataclass
class Peer:
    settings: NodeSettings
    token_file: Path

    def cli(self, *args: str) -> tuple[int, str]:
        base = ["--robot", self.settings.robot, "--base-port", str(self.settings.base_port)]
        result = CliRunner().invoke(cli.app, [*base, *args])
        assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
        return result.exit_code, result.stdout + result.stderr


def progress(request: GetResult) -> GoalProgress[ExecutePlanFeedback, ExecutePlanResult]:
    if request.goal_id == "unknown":
        raise CallError(ServiceError(kind=ErrorKind.INVALID_REQUEST, message=HOSTILE))
    if request.goal_id == "running":
        step = ExecutePlanFeedback(stage=Stage.EXECUTE, step=0, action=HOSTILE, message=HOSTILE, label=HOSTILE)
        return GoalProgress(goal_id=request.goal_id, state=GoalState.EXECUTING, message=HOSTILE, feedback=step)
    step_result = StepResult(
        index=0, action=HOSTILE, status=StepStatus.FAILED, message=HOSTILE, label=HOSTILE, searched=[HOSTILE]
    )
    result = ExecutePlanResult(
        status=PlanStatus.FAILED, stage=Stage.EXECUTE, reason=HOSTILE, steps=[step_result], warnings=[HOSTILE]
    )
    return GoalProgress(goal_id=request.goal_id, state=GoalState.ABORTED, message=HOSTILE, result=result)


def incidents(query: IncidentQuery) -> IncidentList:
    incident = Incident(
        id=1,
        stamp=time.time() - 5.0,
        kind=IncidentKind.ESTOP,
        reason=HOSTILE,
        x=1.0,
        y=2.0,
        source=HOSTILE,
        rule=HOSTILE,
        goal_id=HOSTILE,
        step=0,
        label=HOSTILE,
        objects=[HOSTILE],
        people=[HOSTILE],
        recording=f"/nowhere/{HOSTILE}.mcap",
    )
    zone = CautionZone(x=1.0, y=2.0, radius=1.0, count=1, speed_scale=0.5, incidents=[1], kinds=[IncidentKind.ESTOP])
    return IncidentList(incidents=[incident], total=1, zones=[zone], store=HOSTILE)


def ask(request: AskRequest) -> AskReply:
    recovery = Recovery(
        request_id="r1",
        number=1,
        stamp=0.0,
        outcome=RecoveryOutcome.REJECTED,
        failure=HOSTILE,
        step=0,
        reason=HOSTILE,
    )
    plan = f'{{"plan": [{{"action": "stop", "description": "{HOSTILE}"}}]}}\nsecond line'
    return AskReply(
        status=AskStatus.FAILED,
        request_id="r1",
        reason=HOSTILE,
        plan=plan,
        goal_id=HOSTILE,
        recoveries=[recovery],
        stage=Stage.EXECUTE,
    )


def serve_everything(peer: Node) -> None:
    """Every service the commands below ask, each answering with HOSTILE wherever a text goes."""
    peer.serve(
        keys.EXECUTE_PLAN.send_goal,
        lambda r: GoalResponse(goal_id=r.goal_id, accepted=False, reason=HOSTILE),
    )
    peer.serve(
        keys.EXECUTE_PLAN.cancel_goal, lambda r: CancelResponse(goal_id=r.goal_id, accepted=False, reason=HOSTILE)
    )
    peer.serve(keys.EXECUTE_PLAN.get_status, progress)
    peer.serve(keys.RESET, lambda r: ResetReply(ok=False, message=HOSTILE))
    problem = RobotProblem(text=HOSTILE, last_seen=time.time())
    peer.serve(
        keys.ROBOT_DIAGNOSTICS,
        lambda r: RobotDiagnostics(stamp=time.time(), backend="ros2", window=60.0, problems=[problem]),
    )

    def move(request: MoveEntity) -> ServiceError:
        return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=HOSTILE, candidates=[HOSTILE])

    peer.serve(keys.SIM_MOVE, move)  # type: ignore[arg-type]
    peer.serve(keys.SIM_FAULT, lambda r: FaultInjected(kind=FaultKind.BLOCK, target=HOSTILE, message=HOSTILE))
    scene = SceneDescription(stamp=time.time(), objects=[hostile_object()], text=f"{HOSTILE}\nthe flat")
    peer.serve(keys.SCENE, lambda r: scene)
    peer.serve(keys.PLAN_ASK, ask)
    peer.serve(keys.INCIDENTS, incidents)

    def forget(request: ForgetIncident) -> ForgetReply:
        return ForgetReply(ok=request.action is ForgetAction.FORGET, message=HOSTILE)

    peer.serve(keys.FORGET_INCIDENT, forget)
    # A recorder whose disk is full: `tether status` says so (it showed only that the recorder was up).
    failing = RecorderStatus(path=f"/rec/{HOSTILE}.mcap", messages=5, started=0.0, dropped=7, error=HOSTILE)
    peer.serve(keys.RECORDER_STATUS, lambda r: failing)


def hostile_object() -> PerceivedObject:
    return PerceivedObject(id="cup", name=HOSTILE, cls=HOSTILE, color=HOSTILE, position=Vec3(x=1.0, y=2.0, z=0.8))


def declare_intruder(peer: Node) -> list[object]:
    """A liveliness token and a process status under a name of the peer's choosing (no ACL forbids it
    outside a secured deployment)."""
    token = peer.session.liveliness().declare_token(keys.alive_key(peer.robot, INTRUDER))
    key = keys.process_key(peer.robot, INTRUDER)
    status = ProcessStatus(
        service=INTRUDER, host="h", pid=1, rss_bytes=1, peak_rss_bytes=1, cpu_seconds=0.0, uptime_seconds=0.0
    )

    def answer(query: object) -> None:
        try:
            query.reply(key, encode(status))  # type: ignore[attr-defined]
        finally:
            query.drop()  # type: ignore[attr-defined]

    return [token, peer.session.declare_queryable(key, answer)]


@pytest.fixture(scope="module")
def peer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Peer]:
    token_file = tmp_path_factory.mktemp("operator") / "operator.token"
    token_file.write_text("token")
    os.chmod(token_file, 0o600)
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    stop = threading.Event()
    with Node("executor", settings) as node:
        node.signer = Signer(secrets.token_bytes(32))  # a MAC-shaped attachment: `status` takes the beat
        serve_everything(node)
        declared = declare_intruder(node)  # kept: an undeclared token is gone
        for service in ALL_SERVICES:
            if service != "executor":
                declared.append(node.session.liveliness().declare_token(keys.alive_key(settings.robot, service)))
        node.declare_alive()

        def publish() -> None:
            latch = EstopState(latched=True, source=HOSTILE, reason=HOSTILE)
            while not stop.wait(0.02):
                now = time.time()
                node.publish(keys.HEARTBEAT, SafetyStatus(seq=1, stamp=now, estop=latch))
                node.publish(
                    keys.ODOM, Odometry(stamp=now, sim_time=0.0, pose=Pose2D(x=1.0, y=2.0), linear_x=0.0, angular_z=0.0)
                )
                node.publish(keys.OBJECTS, PerceivedObjects(stamp=now, objects=[hostile_object()]))

        publisher = threading.Thread(target=publish, daemon=True)
        publisher.start()
        try:
            yield Peer(settings, token_file)
        finally:
            stop.set()
            publisher.join()


@pytest.mark.parametrize(
    ("args", "code", "seen"),
    [
        (["cancel", "g1"], 0, "nothing to cancel"),
        (["goal", "running"], 0, "goal running: executing"),
        (["goal", "aborted"], 1, "failed at stage execute"),
        (["goal", "unknown"], 2, "results are kept for"),
        (["send", '{"plan": [{"action": "stop"}]}'], 2, "rejected"),
        (["estop", "--reason", "test"], 0, "E-STOP latched by"),
        (["status"], 0, "robot problems"),
        (["status"], 0, "recording FAILING"),
        (["status", "--check"], 0, "healthy:"),
        (["world", "move", "cup", "1", "2"], 2, "invalid_request"),
        (["world", "fault", "block", "kitchen"], 0, "block:"),
        (["world", "scene"], 0, "relations:"),
        (["ask", "bring me the cup"], 4, "recovery 1"),
        (["send", "--recover", '{"plan": [{"action": "stop"}]}'], 1, "failed at stage execute"),
        (["incidents"], 0, "1 of 1 incidents"),
        (["incidents", "show", "1"], 0, "incident 1: estop"),
        (["incidents", "forget", "1", "--reason", "r", "--token-file", "TOKEN"], 0, ""),
        (["incidents", "clear", "1", "--reason", "r", "--token-file", "TOKEN"], 2, "refused"),
        (["reset", "--token-file", "TOKEN"], 2, "refused"),
    ],
    ids=lambda value: " ".join(value) if isinstance(value, list) else None,
)
def test_what_a_peer_wrote_is_printed_with_its_control_characters_escaped(
    peer: Peer, monkeypatch: pytest.MonkeyPatch, args: list[str], code: int, seen: str
) -> None:
    for variable in ("TETHER_LLM_URL", "TETHER_LLM_MODEL", "TETHER_LLM_API_KEY"):
        monkeypatch.delenv(variable, raising=False)
    args = [str(peer.token_file) if arg == "TOKEN" else arg for arg in args]
    exit_code, said = peer.cli(*args)
    assert exit_code == code, said
    assert seen in said
    assert ESCAPED in said, said  # the text is shown, its controls as \x1b
    assert controls(said) == [], said


def test_json_still_carries_the_text_as_it_came(peer: Peer) -> None:
    """--json output is one JSON object, whose encoder escapes control characters itself: unchanged."""
    exit_code, said = peer.cli("cancel", "g1", "--json")
    assert exit_code == 0 and json.loads(said)["reason"] == HOSTILE


def test_a_service_log_shown_when_it_did_not_come_up_is_escaped(tmp_path: Path) -> None:
    """`tether up` shows the log of a service that did not come up, at once when it exited (it waited
    out the timeout before): what it wrote (a traceback quoting a peer's text, a library's own
    output) reaches the terminal with its controls escaped."""
    (tmp_path / "parser.log").write_text(f"Traceback: {HOSTILE}\n")
    # A config the parser refuses: it exits at once, so it never comes up, however quick the machine.
    (tmp_path / "bad.toml").write_text("[parser]\nno_such_option = 1\n")
    settings = ["--robot", f"t{uuid.uuid4().hex[:8]}", "--base-port", str(free_ports(len(ALL_SERVICES)))]
    up = [
        "up",
        "--only",
        "parser",
        "--timeout",
        "30",
        "--log-dir",
        str(tmp_path),
        "--config",
        str(tmp_path / "bad.toml"),
    ]
    result = CliRunner().invoke(cli.app, [*settings, *up])
    said = result.stdout + result.stderr
    assert result.exit_code == 1 and "parser did not come up: it exited with code 2" in said, said
    assert f"Traceback: {ESCAPED}" in said and controls(said) == [], said
