"""A tool call whose MCP client goes before the answer (it cancels the call, its timeout fires, it
disconnects) leaves no goal running that nobody knows of: the goal id was only in the answer nobody
got; a plan_and_execute whose client goes while the planner still thinks is canceled in the planner,
which then sends no plan. The MCP server in this process over the SDK's JSON-RPC transport (as over
stdio), its tools over real Zenoh sessions against an executor that holds the goal as long as the
test wants."""

from __future__ import annotations

import contextlib
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import anyio
import pytest
from mcp import Client

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalResponse, ResultResponse, SendGoal
from schemas.common import ErrorKind, ServiceError
from schemas.executor import ExecutePlanGoal, ExecutePlanResult
from schemas.planner import AskCancel, AskCancelReply, AskReply, AskRequest, AskStatus
from schemas.world import Empty, PerceivedObject, SceneDescription, Vec3
from services.agent.feedback import DATA_CLOSE, DATA_OPEN
from services.errors import CallError
from services.runtime import Node, NodeSettings
from tests.sessions import free_port
from tether.agentapi import AgentAPI
from tether.mcpserver import build_server

WAIT = 10.0
# Claude Code keeps a tool result over this many characters out of the conversation.
HOST_LIMIT_CHARS = 50_000


@dataclass
class Executor:
    """Accepts every goal (once `admit` is set), never starts one, ends one only when it is canceled."""

    admit: threading.Event = field(default_factory=threading.Event)
    sending: threading.Event = field(default_factory=threading.Event)
    sent: list[str] = field(default_factory=list)
    canceled: list[str] = field(default_factory=list)
    asked: threading.Event = field(default_factory=threading.Event)
    answer: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)
    ended: threading.Event = field(default_factory=threading.Event)
    fetching: threading.Event = field(default_factory=threading.Event)  # someone waits for a result
    asked_as: list[str] = field(default_factory=list)  # the request ids the planner was asked with
    ask_canceled: list[str] = field(default_factory=list)  # and the ones plan/ask_cancel named
    replied: threading.Event = field(default_factory=threading.Event)  # the planner has answered

    def send(self, request: SendGoal[ExecutePlanGoal]) -> GoalResponse:
        self.sending.set()
        self.admit.wait(WAIT)
        with self.lock:
            self.sent.append(request.goal_id)
        return GoalResponse(goal_id=request.goal_id, accepted=True)

    def cancel(self, request: CancelGoal) -> CancelResponse:
        with self.lock:
            self.canceled.append(request.goal_id)
        self.ended.set()
        return CancelResponse(goal_id=request.goal_id, accepted=True)

    def result(self, request: GetResult) -> ResultResponse[ExecutePlanResult]:
        self.fetching.set()
        self.ended.wait(WAIT)
        raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message="ended by the test"))

    def scene(self, request: Empty) -> SceneDescription:
        """The world model: a flat full of things."""
        things = [
            PerceivedObject(
                id=f"cup_{i}", name=f"cup {i}", cls="cup", color="red", position=Vec3(i % 50 * 0.1, 0.0, 0.0)
            )
            for i in range(3000)
        ]
        return SceneDescription(stamp=1.0, objects=things, text="a flat full of cups")

    def ask(self, request: AskRequest) -> AskReply:
        """The planner: sends a plan once the test says so (its model thought for a while), unless the
        request was canceled by then."""
        with self.lock:
            self.asked_as.append(request.request_id)
        self.asked.set()
        self.answer.wait(WAIT)
        goal_id = uuid.uuid4().hex
        with self.lock:
            self.replied.set()
            if request.request_id in self.ask_canceled:
                return AskReply(status=AskStatus.REJECTED, request_id=request.request_id, reason="canceled")
            self.sent.append(goal_id)
        return AskReply(status=AskStatus.ACCEPTED, request_id="r1", goal_id=goal_id, attempts=1)

    def ask_cancel(self, request: AskCancel) -> AskCancelReply:
        with self.lock:
            self.ask_canceled.append(request.request_id)
        return AskCancelReply(request_id=request.request_id, known=True, running=True, reason="canceled")


@contextlib.contextmanager
def rigged(planner_cancels: bool) -> Iterator[tuple[Executor, AgentAPI]]:
    """The stand-ins on one node, the agent's API on another; `planner_cancels`: the planner serves
    plan/ask_cancel (an older one does not)."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    executor = Executor()
    with Node("executor", settings) as node, Node("mcp", settings) as mcp:
        node.serve(keys.EXECUTE_PLAN.send_goal, executor.send)
        node.serve(keys.EXECUTE_PLAN.cancel_goal, executor.cancel)
        node.serve(keys.EXECUTE_PLAN.get_result, executor.result, waits=True)
        node.serve(keys.PLAN_ASK, executor.ask)
        if planner_cancels:
            node.serve(keys.PLAN_ASK_CANCEL, executor.ask_cancel)
        node.serve(keys.SCENE, executor.scene)
        node.declare_alive()
        assert not mcp.wait_alive(["executor"], WAIT)
        try:
            yield executor, AgentAPI(mcp)
        finally:
            executor.admit.set()
            executor.answer.set()
            executor.ended.set()


@pytest.fixture
def rig() -> Iterator[tuple[Executor, AgentAPI]]:
    with rigged(planner_cancels=True) as parts:
        yield parts


@pytest.fixture
def older_planner_rig() -> Iterator[tuple[Executor, AgentAPI]]:
    with rigged(planner_cancels=False) as parts:
        yield parts


async def until(condition: Callable[[], object], timeout: float = WAIT) -> None:
    with anyio.fail_after(timeout):
        while not condition():
            await anyio.sleep(0.02)


def give_up_on(
    api: AgentAPI,
    tool: str,
    arguments: dict[str, object],
    when: threading.Event,
    then: threading.Event | None = None,
    once: Callable[[], object] | None = None,
) -> None:
    """Call `tool` over MCP (JSON-RPC, as over stdio), cancel the call once `when` is set, then set `then`
    (once `once` holds, when given)."""

    async def main() -> None:
        async with Client(build_server(api), mode="legacy") as client:
            async with anyio.create_task_group() as group:
                group.start_soon(client.call_tool, tool, arguments)
                await until(when.is_set)
                group.cancel_scope.cancel()
            if once is not None:
                await until(once)
            if then is not None:
                then.set()

    anyio.run(main)


def test_a_plan_whose_call_is_canceled_while_it_is_checked_is_canceled(rig: tuple[Executor, AgentAPI]) -> None:
    """The plan went on, its id in an answer the client never got: nobody could follow or cancel it."""
    executor, api = rig
    executor.admit.set()
    give_up_on(api, "say", {"text": "hello"}, executor.fetching)
    anyio.run(until, lambda: executor.canceled)
    assert executor.canceled == executor.sent, (executor.sent, executor.canceled)


def test_a_plan_whose_call_is_canceled_before_the_executor_answers_is_canceled(
    rig: tuple[Executor, AgentAPI],
) -> None:
    """The caller goes while the executor still decides: the goal is canceled once it is known."""
    executor, api = rig
    give_up_on(api, "execute_plan", {"plan": [{"action": "say", "text": "hello"}]}, executor.sending, executor.admit)
    anyio.run(until, lambda: executor.canceled)
    assert len(executor.sent) == 1 and executor.canceled == executor.sent, (executor.sent, executor.canceled)


def test_a_request_whose_call_is_canceled_while_the_planner_thinks_is_canceled_there(
    rig: tuple[Executor, AgentAPI],
) -> None:
    """plan_and_execute: the client gave up (its own timeout under the planner's 50 s) while the
    planner's model thought; the planner sent the plan later, to no one, and the robot started before
    the goal was canceled. Now the request is canceled in the planner at once: no plan is sent."""
    executor, api = rig

    async def main() -> None:
        async with Client(build_server(api), mode="legacy") as client:
            async with anyio.create_task_group() as group:
                group.start_soon(client.call_tool, "plan_and_execute", {"request": "say hello", "dry_run": False})
                await until(executor.asked.is_set)
                group.cancel_scope.cancel()
            await until(lambda: executor.ask_canceled)  # while the model still thinks
            executor.answer.set()  # its plan comes now, for a request canceled

    anyio.run(main)
    anyio.run(until, executor.replied.is_set)
    assert executor.ask_canceled == executor.asked_as and executor.asked_as[0], executor.asked_as
    assert not executor.sent and not executor.canceled, (executor.sent, executor.canceled)


def test_a_plan_an_older_planner_sends_after_its_call_was_canceled_is_canceled(
    older_planner_rig: tuple[Executor, AgentAPI], caplog: pytest.LogCaptureFixture
) -> None:
    """A planner that does not serve plan/ask_cancel sends the plan later, to no one: the goal its
    answer names is canceled as the answer comes."""
    executor, api = older_planner_rig
    # The planner answers once the server has taken the call as abandoned: answered before, the request
    # was over and there was nothing to cancel by its id (a loaded machine did that now and then).
    abandoned = "the agent that made it went before the answer"
    arguments: dict[str, object] = {"request": "say hello", "dry_run": False}
    give_up_on(api, "plan_and_execute", arguments, executor.asked, executor.answer, lambda: abandoned in caplog.text)
    anyio.run(until, lambda: executor.canceled)
    assert len(executor.sent) == 1 and executor.canceled == executor.sent, (executor.sent, executor.canceled)
    # Its cancel by request id was tried, and failed with a warning.
    anyio.run(until, lambda: f"did not cancel request {executor.asked_as[0]}" in caplog.text)


def test_a_call_answered_cancels_nothing(rig: tuple[Executor, AgentAPI]) -> None:
    """The client heard the goal id: the plan is its to follow, and stays."""
    executor, api = rig
    executor.admit.set()
    executor.answer.set()

    async def main() -> str:
        async with Client(build_server(api), mode="legacy") as client:
            answered = await client.call_tool("plan_and_execute", {"request": "say hello", "dry_run": False})
        return str(answered.content)

    answered = anyio.run(main)
    assert executor.sent and executor.sent[0] in answered, answered
    assert not executor.canceled


def test_a_tool_result_is_cut_to_what_a_model_takes(rig: tuple[Executor, AgentAPI]) -> None:
    """A world model listing 3000 objects came back as 480 kB of text (Claude Code refuses a result over
    25,000 tokens; other hosts fill the model's context with it, for every later request too)."""
    _, api = rig

    async def main() -> str:
        async with Client(build_server(api), mode="legacy") as client:
            listed = await client.call_tool("list_objects", {})
        assert not listed.is_error
        return "\n".join(c.text for c in listed.content if hasattr(c, "text"))

    listed = anyio.run(main)
    assert len(listed) < HOST_LIMIT_CHARS, len(listed)
    last_line = listed.rsplit("\n", 1)[1]
    assert "more characters cut" in last_line, last_line
    # The note is ours, after the data block it cut, which is closed.
    before = listed.rsplit("\n", 1)[0]
    assert before.endswith(DATA_CLOSE) and before.rfind(DATA_OPEN.split("{")[0]) < before.rfind(DATA_CLOSE)
