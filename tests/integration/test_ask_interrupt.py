"""A Ctrl-C (or SIGTERM) to `tether ask` and `tether send --recover` with an endpoint in this process,
and to `tether ask` through the planner service: the plan the planner sent is canceled by its id and
its end printed as one JSON object, with `tether send`'s exit codes. The executor is played by this
test (a real action server on real Zenoh) and holds the plan until it is canceled; the model is the
scripted one of test_agents; the planner service, when there is one, is the real one. Short: no
stack to start."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field

import msgspec
import pytest

from schemas import keys
from schemas.actions import GoalState
from schemas.common import Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus
from schemas.incidents import IncidentList
from schemas.planner import AskReply, AskRequest, AskStatus, RecoveryOutcome
from schemas.trace import TraceRecord
from schemas.world import SceneDescription
from services.actionlib import ActionClient, ActionServer, GoalHandle, Outcome
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.integration import test_agents
from tests.integration.test_agents import ScriptedLLM, text_reply
from tests.procs import output_of, tether_process
from tests.sessions import free_ports

WAIT = 30.0
PLAN = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen"}]})

llm_server = test_agents.llm_server


@dataclass
class StandIn:
    """The executor: a dry run passes at once; a plan sent for real runs (`running` names it) until
    canceled, then ends as `ended` says."""

    running: threading.Event = field(default_factory=threading.Event)
    goal_id: str = ""
    ended: list[GoalState] = field(default_factory=list)

    def execute(self, handle: GoalHandle[ExecutePlanGoal, ExecutePlanFeedback]) -> Outcome[ExecutePlanResult]:
        if handle.goal.dry_run:
            passed = ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.SAFETY)
            return Outcome(GoalState.SUCCEEDED, passed, "")
        self.goal_id = handle.goal_id
        self.running.set()
        stopped = handle.cancel_requested.wait(WAIT)
        state = GoalState.CANCELED if stopped else GoalState.SUCCEEDED
        self.ended.append(state)
        status = PlanStatus.CANCELED if stopped else PlanStatus.SUCCEEDED
        return Outcome(state, ExecutePlanResult(status=status, stage=Stage.EXECUTE, reason=state), state)


@pytest.fixture
def executor(llm_server: ScriptedLLM) -> Iterator[tuple[StandIn, dict[str, str]]]:
    with serving(llm_server) as (stand_in, _, env):
        yield stand_in, env


@contextlib.contextmanager
def serving(llm_server: ScriptedLLM) -> Iterator[tuple[StandIn, Node, dict[str, str]]]:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    node = Node("executor", settings)
    try:
        stand_in = StandIn()
        ActionServer(node, keys.EXECUTE_PLAN, stand_in.execute, concurrent=lambda goal: goal.dry_run)
        # What the planner reads for its prompt, answered at once.
        node.serve(keys.SCENE, lambda _: SceneDescription(stamp=0.0, text="a kitchen"))
        node.serve(keys.INCIDENTS, lambda _: IncidentList())
        node.declare_alive()
        env = {
            **os.environ,
            "TETHER_ROBOT": settings.robot,
            "TETHER_BASE_PORT": str(settings.base_port),
            "TETHER_LLM_URL": llm_server.url,
            "TETHER_LLM_MODEL": "scripted",
        }
        yield stand_in, node, env
    finally:
        node.close()


def stopped_while_running(
    stand_in: StandIn, env: dict[str, str], stop: signal.Signals, *args: str
) -> tuple[int, dict[str, object], str]:
    """Run the command until the plan it sent runs, then `stop` it: its exit code, its JSON, its stderr."""
    with tether_process(env, *args) as process:
        assert stand_in.running.wait(WAIT), process.communicate()
        os.kill(process.pid, stop)
        out, err = output_of(process, WAIT)
    try:
        document = json.loads(out)
    except ValueError:
        pytest.fail(f"no JSON object (exit {process.returncode}): {out!r} {err!r}")
    return process.returncode, document, err


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupted_ask_cancels_the_plan_it_sent(
    executor: tuple[StandIn, dict[str, str]], llm_server: ScriptedLLM, stop: signal.Signals
) -> None:
    """`tether ask` waits for the plan's end in this process (recoveries allowed): a Ctrl-C printed
    click's 'Aborted!' and no JSON, and the plan drove on with nobody to cancel it."""
    stand_in, env = executor
    llm_server.play(text_reply(PLAN))
    code, document, err = stopped_while_running(stand_in, env, stop, "ask", "go to the kitchen", "--json")
    assert (code, document["status"], document["goal_id"]) == (1, "canceled", stand_in.goal_id), (document, err)
    assert stand_in.ended == [GoalState.CANCELED], err


def test_an_interrupted_send_recover_cancels_the_plan_it_sent(executor: tuple[StandIn, dict[str, str]]) -> None:
    """The same for `tether send --recover` with an endpoint here: its JSON is `tether send`'s."""
    stand_in, env = executor
    code, document, err = stopped_while_running(stand_in, env, signal.SIGINT, "send", PLAN, "--recover", "--json")
    assert (code, document["status"], document["goal_id"]) == (1, "canceled", stand_in.goal_id), (document, err)
    assert document["final_goal_id"] == stand_in.goal_id and document["recoveries"] == [], document
    assert stand_in.ended == [GoalState.CANCELED], err


@contextlib.contextmanager
def planner_service(llm_server: ScriptedLLM) -> Iterator[tuple[StandIn, Node, dict[str, str]]]:
    """The stand-in executor and a real planner service asking the scripted model; the environment
    for a `tether ask` that has no endpoint of its own, so goes through the service."""
    with serving(llm_server) as (stand_in, node, env):
        planner_env = {**env, "TETHER_LOG_LEVEL": "WARNING"}
        cli_env = {k: v for k, v in env.items() if not k.startswith("TETHER_LLM_")}
        planner = subprocess.Popen([sys.executable, "-m", "services.planner"], env=planner_env, start_new_session=True)
        try:
            assert node.is_alive("planner", WAIT), "the planner service did not come up"
            yield stand_in, node, cli_env
        finally:
            planner.terminate()
            planner.wait(WAIT)


def planner_answers(node: Node) -> queue.Queue[AskReply]:
    """The planner service's answers to plan/ask, as its trace publishes them once each has gone: what
    it did with a request whose caller is gone."""
    answers: queue.Queue[AskReply] = queue.Queue()
    topic = keys.Topic(f"_trace/planner/{keys.PLAN_ASK.path}", TraceRecord)
    node.subscribe(topic, lambda record: answers.put(msgspec.json.decode(record.reply, type=AskReply)))
    return answers


def test_an_ask_waiting_through_the_planner_service_is_stopped_by_a_ctrl_c(llm_server: ScriptedLLM) -> None:
    """`tether ask --wait` through the planner service: the goal was named only at the plan's end, so a
    Ctrl-C exited 3 ("a plan it sent may be moving") and the robot drove on. Now the request is
    canceled by the id the command chose: its goal ends canceled, nothing follows it."""
    with planner_service(llm_server) as (stand_in, node, cli_env):
        answers = planner_answers(node)
        llm_server.play(text_reply(PLAN))
        args = ("ask", "go to the kitchen", "--wait", "--json")
        code, document, err = stopped_while_running(stand_in, cli_env, signal.SIGINT, *args)
        assert (code, document["status"], document["goal_id"]) == (1, "canceled", stand_in.goal_id), (document, err)
        assert stand_in.ended == [GoalState.CANCELED], err
        # The planner's own answer, for no one now: the plan canceled, no recovery asked for or sent.
        answer = answers.get(timeout=WAIT)
        assert answer.status is AskStatus.FAILED and answer.goal_id == stand_in.goal_id, answer
        assert "canceled" in answer.reason and [r.outcome for r in answer.recoveries] == [RecoveryOutcome.STOPPED]
        assert document["request_id"] == answer.request_id != "", "the command's JSON names the request it stopped"
    assert stand_in.ended == [GoalState.CANCELED] and len(llm_server.received) == 1


def test_a_send_recover_waiting_through_the_planner_service_is_stopped_by_a_ctrl_c(llm_server: ScriptedLLM) -> None:
    """`tether send --recover --wait` through the planner service: the request is canceled by the id
    the command chose, as `tether ask`'s, and its JSON names that request (it said "")."""
    with planner_service(llm_server) as (stand_in, node, cli_env):
        answers = planner_answers(node)
        llm_server.play()  # nothing to answer: the plan is given, and no recovery follows a cancel
        args = ("send", PLAN, "--recover", "--wait", "--json")
        code, document, err = stopped_while_running(stand_in, cli_env, signal.SIGINT, *args)
        assert (code, document["status"], document["goal_id"]) == (1, "canceled", stand_in.goal_id), (document, err)
        assert document["final_goal_id"] == stand_in.goal_id and stand_in.ended == [GoalState.CANCELED], err
        answer = answers.get(timeout=WAIT)
        assert answer.status is AskStatus.FAILED and answer.goal_id == stand_in.goal_id, answer
        assert [r.outcome for r in answer.recoveries] == [RecoveryOutcome.STOPPED], answer
        assert document["request_id"] == answer.request_id != "", "the command's JSON names the request it stopped"
    assert stand_in.ended == [GoalState.CANCELED] and llm_server.received == [], "the model was asked"


def test_an_ask_interrupted_before_the_planner_service_answered_sends_no_plan(llm_server: ScriptedLLM) -> None:
    """Through the planner service the goal sent was named only in its answer, which came once the
    executor took the plan: a Ctrl-C while the model thought waited for that answer, then canceled a
    plan already moving. Now the request is canceled by its id at once, and the plan the model
    gives after that is never sent."""
    asked, interrupted = threading.Event(), threading.Event()

    def thinking() -> None:
        asked.set()
        interrupted.wait(WAIT)

    with planner_service(llm_server) as (stand_in, node, cli_env):
        answers = planner_answers(node)
        # The model answers only once the command has been interrupted and has exited.
        llm_server.play(text_reply(PLAN), meanwhile=thinking)
        try:
            with tether_process(cli_env, "ask", "go to the kitchen", "--json", "--max-recoveries", "0") as process:
                deadline = threading.Timer(WAIT, process.kill)
                deadline.start()
                try:
                    assert asked.wait(WAIT), process.communicate()
                    os.kill(process.pid, signal.SIGINT)
                    out, err = output_of(process, WAIT)
                finally:
                    deadline.cancel()
        finally:
            interrupted.set()
        document = json.loads(out)
        assert (process.returncode, document["status"], document["goal_id"]) == (1, "canceled", ""), err
        answer = answers.get(timeout=WAIT)
    assert answer.status is AskStatus.REJECTED and "canceled" in answer.reason and not answer.goal_id, answer
    assert stand_in.goal_id == "" and stand_in.ended == [], "a plan was sent for a canceled request"


def test_an_ask_through_an_older_planner_service_falls_back_to_cancel_the_goal_its_answer_names(
    llm_server: ScriptedLLM,
) -> None:
    """A planner service that does not serve plan/ask_cancel (an older one, played here by a node of
    the test answering plan/ask at acceptance): a Ctrl-C waits for its answer, then cancels the goal
    it names, as before."""
    asked, interrupted = threading.Event(), threading.Event()
    with serving(llm_server) as (stand_in, _, env):
        cli_env = {k: v for k, v in env.items() if not k.startswith("TETHER_LLM_")}
        planner = Node("planner", NodeSettings(robot=env["TETHER_ROBOT"], base_port=int(env["TETHER_BASE_PORT"])))
        try:
            executor = ActionClient(planner, keys.EXECUTE_PLAN)

            def ask(request: AskRequest) -> AskReply:
                asked.set()
                assert interrupted.wait(WAIT)  # thinking until the command is interrupted and waits for this
                handle = executor.send(ExecutePlanGoal(text=PLAN), timeout=WAIT)
                return AskReply(status=AskStatus.ACCEPTED, request_id="older", goal_id=handle.goal_id)

            planner.serve(keys.PLAN_ASK, ask, waits=True)
            planner.declare_alive()
            with tether_process(cli_env, "ask", "go to the kitchen", "--json") as process:
                assert process.stderr is not None
                deadline = threading.Timer(WAIT, process.kill)
                deadline.start()
                try:
                    assert asked.wait(WAIT), process.communicate()
                    os.kill(process.pid, signal.SIGINT)
                    said = ""
                    while "waiting for the planner" not in said and (line := process.stderr.readline()):
                        said += line
                    interrupted.set()
                    out, err = output_of(process, WAIT)
                finally:
                    deadline.cancel()
        finally:
            interrupted.set()
            planner.close()
    assert "waiting for the planner's answer" in said and out, (process.returncode, said, out, err)
    document = json.loads(out)
    assert (process.returncode, document["status"], document["goal_id"]) == (1, "canceled", stand_in.goal_id), err
    assert stand_in.ended == [GoalState.CANCELED], err
