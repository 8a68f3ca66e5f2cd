"""`tether mcp` as an MCP host runs it, its clients going away: over stdio, a host that quits while a
plan it sent is being checked leaves no goal running that nobody knows of, and the server exits; a
host that quits while the planner service asks its model for a plan_and_execute leaves nothing to
send: the request is canceled in the planner, which sends no plan; over
HTTP, a client that opens session after session and never closes one holds no memory in the server
(there were up to 10,000 kept for 30 minutes each, and then no agent could connect, to stop the robot
either). The executor on the other side holds the goal until it is canceled."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import urllib.request
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import anyio
import msgspec
import pytest
from mcp import Client
from mcp.client.stdio import StdioServerParameters

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalResponse, ResultResponse, SendGoal
from schemas.common import ErrorKind, ServiceError
from schemas.executor import ExecutePlanGoal, ExecutePlanResult
from schemas.planner import AskCancel, AskCancelReply, AskReply, AskRequest, AskStatus
from schemas.trace import TraceRecord
from services.errors import CallError
from services.runtime import Node, NodeSettings
from tests.integration import test_agents
from tests.integration.test_agents import ScriptedLLM, text_reply, wait_listening
from tests.integration.test_ask_interrupt import PLAN, planner_service
from tests.sessions import free_port

WAIT = 10.0
SESSIONS = 1500
# What the server may grow by for them: each session kept took about 40 kB.
SESSIONS_GROWTH_KB = 20_000

llm_server = test_agents.llm_server


@dataclass
class Executor:
    """Accepts every goal, never starts one, ends one only when it is canceled."""

    sending: threading.Event = field(default_factory=threading.Event)
    sent: list[str] = field(default_factory=list)
    canceled: list[str] = field(default_factory=list)
    ended: threading.Event = field(default_factory=threading.Event)

    def send(self, request: SendGoal[ExecutePlanGoal]) -> GoalResponse:
        self.sent.append(request.goal_id)
        self.sending.set()
        return GoalResponse(goal_id=request.goal_id, accepted=True)

    def cancel(self, request: CancelGoal) -> CancelResponse:
        self.canceled.append(request.goal_id)
        self.ended.set()
        return CancelResponse(goal_id=request.goal_id, accepted=True)

    def result(self, request: GetResult) -> ResultResponse[ExecutePlanResult]:
        self.ended.wait(WAIT)
        raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message="ended by the test"))


@pytest.fixture
def executor() -> Iterator[tuple[Executor, dict[str, str]]]:
    """The executor, and the environment a `tether mcp` on its robot runs with."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    held = Executor()
    with Node("executor", settings) as node:
        node.serve(keys.EXECUTE_PLAN.send_goal, held.send)
        node.serve(keys.EXECUTE_PLAN.cancel_goal, held.cancel)
        node.serve(keys.EXECUTE_PLAN.get_result, held.result, waits=True)
        node.declare_alive()
        env = {**os.environ, "TETHER_ROBOT": settings.robot, "TETHER_BASE_PORT": str(settings.base_port)}
        try:
            yield held, env
        finally:
            held.ended.set()


def test_a_host_that_quits_mid_call_leaves_no_plan_running(executor: tuple[Executor, dict[str, str]]) -> None:
    """The plan went on, its id only in the answer to a host that was gone; the server stayed up
    until the call's wait for the plan to start ran out."""
    held, env = executor
    params = StdioServerParameters(command=sys.executable, args=["-m", "tether", "mcp"], env=env)
    pids: list[int] = []

    async def main() -> None:
        async with Client(params, read_timeout_seconds=30.0) as client:
            await client.list_tools()  # the server is up and has its tools
            pids.extend(server_pids(env["TETHER_ROBOT"]))
            async with anyio.create_task_group() as group:
                group.start_soon(client.call_tool, "say", {"text": "hello"})
                with anyio.fail_after(WAIT):
                    while not held.sending.is_set():
                        await anyio.sleep(0.02)
                group.cancel_scope.cancel()  # the host quits: the client closes the server's stdin

    anyio.run(main)
    deadline = time.monotonic() + WAIT
    while not held.canceled and time.monotonic() < deadline:
        time.sleep(0.02)
    assert held.sent and held.canceled == held.sent, (held.sent, held.canceled)
    assert len(pids) == 1, pids
    while alive(pids[0]) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not alive(pids[0]), "tether mcp still runs after its host quit"


def test_a_host_that_quits_while_the_planner_thinks_leaves_no_plan_to_send(llm_server: ScriptedLLM) -> None:
    """plan_and_execute through the real planner service: the host quit while the model thought; the
    planner sent the plan it wrote later, to no one, the robot started, and only then was the goal
    canceled. Now the server cancels the request by its id (plan/ask_cancel) at once: no plan goes."""
    thinking, answer = threading.Event(), threading.Event()

    def think() -> None:
        thinking.set()
        answer.wait(WAIT)

    with planner_service(llm_server) as (stand_in, node, env):
        asks: queue.Queue[TraceRecord] = queue.Queue()
        cancels: queue.Queue[TraceRecord] = queue.Queue()
        node.subscribe(keys.Topic(f"_trace/planner/{keys.PLAN_ASK.path}", TraceRecord), asks.put)
        node.subscribe(keys.Topic(f"_trace/planner/{keys.PLAN_ASK_CANCEL.path}", TraceRecord), cancels.put)
        llm_server.play(text_reply(PLAN), meanwhile=think)
        params = StdioServerParameters(command=sys.executable, args=["-m", "tether", "mcp"], env=env)

        async def main() -> None:
            async with Client(params, read_timeout_seconds=30.0) as client:
                await client.list_tools()
                async with anyio.create_task_group() as group:
                    arguments = {"request": "go to the kitchen", "dry_run": False}
                    group.start_soon(client.call_tool, "plan_and_execute", arguments)
                    with anyio.fail_after(WAIT):
                        while not thinking.is_set():
                            await anyio.sleep(0.02)
                    group.cancel_scope.cancel()  # the host quits while the model thinks

        try:
            anyio.run(main)
            canceled = cancels.get(timeout=WAIT)  # while the model still thinks
        finally:
            answer.set()  # the model's plan comes now
        asked = asks.get(timeout=WAIT)
    request = msgspec.json.decode(asked.query, type=AskRequest)
    reply = msgspec.json.decode(asked.reply, type=AskReply)
    cancel = msgspec.json.decode(canceled.query, type=AskCancel)
    found = msgspec.json.decode(canceled.reply, type=AskCancelReply)
    assert request.request_id and cancel.request_id == request.request_id, (request, cancel)
    assert found.running and not found.goal_id, found
    assert reply.status is AskStatus.REJECTED and "canceled" in reply.reason and not reply.goal_id, reply
    assert stand_in.goal_id == "" and stand_in.ended == [], "the executor was sent a plan for a canceled request"


def server_pids(robot: str) -> list[int]:
    """The `tether mcp` processes serving `robot` (from /proc: their environment names it)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            cmdline = (entry / "cmdline").read_bytes().split(b"\0")
            environ = (entry / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if cmdline[1:4] == [b"-m", b"tether", b"mcp"] and f"TETHER_ROBOT={robot}".encode() in environ:
            found.append(int(entry.name))
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_sessions_opened_and_never_closed_hold_nothing(
    executor: tuple[Executor, dict[str, str]], tmp_path: Path
) -> None:
    _, env = executor
    port = free_port()
    log = (tmp_path / "mcp.log").open("wb")
    server = subprocess.Popen(
        [sys.executable, "-m", "tether", "mcp", "--http", "--port", str(port)],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}/mcp"
    initialize = {
        "jsonrpc": "2.0",
        "id": 1,
        "method": "initialize",
        "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "t", "version": "1"}},
    }
    headers = {"accept": "application/json, text/event-stream", "content-type": "application/json"}
    try:
        wait_listening(port, timeout=30.0)
        before = rss_kb(server.pid)
        for _ in range(SESSIONS):
            request = urllib.request.Request(url, json.dumps(initialize).encode(), headers, method="POST")
            with urllib.request.urlopen(request, timeout=WAIT) as reply:
                assert reply.status == 200
                reply.read()
        grew = rss_kb(server.pid) - before

        async def stop() -> str:
            async with Client(url, read_timeout_seconds=30.0) as client:
                names = [t.name for t in (await client.list_tools()).tools]
            return " ".join(names)

        assert "emergency_stop" in anyio.run(stop)  # an agent still gets in
        assert grew < SESSIONS_GROWTH_KB, f"{SESSIONS} sessions left open took {grew} kB"
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)
        log.close()
        print((tmp_path / "mcp.log").read_text(errors="replace")[-3000:])  # shown when the test failed


def rss_kb(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(status.split("VmRSS:")[1].split()[0])
