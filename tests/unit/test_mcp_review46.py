"""`tether mcp` against hostile clients, review 46: arguments of millions of wrong items are refused
at once (their check held a worker, and the GIL, for 43 s); over streamable HTTP, a client that goes
mid-call leaves no goal running that nobody knows of, and a request naming another site is refused.
The server in this process on a loopback port (uvicorn, as `tether mcp --http` runs it), its tools
over real Zenoh sessions against the stand-in executor of test_mcp_races."""

from __future__ import annotations

import http.client
import json
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import anyio
import pytest
import uvicorn
from mcp import Client

from schemas.plan import MAX_PLAN_BYTES
from schemas.planner import AskCancel, AskCancelReply
from services.agent.tools import all_tools
from tests.sessions import free_port
from tests.unit.test_mcp_races import WAIT, Executor, rigged, until
from tether.mcpserver import CANCEL_LIMITER, ArgumentCheck, build_server, http_app

PLAN_TOOL = next(spec for spec in all_tools() if spec.name == "execute_plan")
# Each item 3 bytes as JSON ("1, "): just within the bound, and far beyond it (the 4 MiB an HTTP
# request may carry).
WITHIN = MAX_PLAN_BYTES // 3 - 100
BEYOND = 1_300_000


@pytest.mark.parametrize(
    ("arguments", "named"),
    [
        ({"plan": [1] * WITHIN}, "plan"),
        ({"plan": [{"action": "say", "text": "hi", "on_failure": [1] * WITHIN}]}, "plan/0/on_failure"),
        ({"plan": [1] * BEYOND}, f"arguments: {BEYOND * 3 + 10} bytes as JSON; the limit is {MAX_PLAN_BYTES}"),
    ],
)
def test_arguments_of_many_wrong_items_are_refused_at_once(arguments: dict[str, Any], named: str) -> None:
    """Every wrong item was found and sorted before the first was named: 43 s for the largest."""
    started = time.thread_time()
    problem = ArgumentCheck(PLAN_TOOL.parameters).problem(arguments)
    assert time.thread_time() - started < 0.5
    assert problem is not None and problem.startswith(named), problem


@pytest.fixture
def served() -> Iterator[tuple[Executor, int]]:
    """The stand-in executor, and the port of an MCP server over HTTP on loopback in front of it."""
    with rigged(planner_cancels=True) as (executor, api):
        port = free_port()
        app = http_app(build_server(api), "127.0.0.1")
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
        thread = threading.Thread(target=server.run, daemon=True)
        thread.start()
        try:
            anyio.run(until, lambda: server.started)
            yield executor, port
        finally:
            server.should_exit = True
            executor.ended.set()
            thread.join(WAIT)
            assert not thread.is_alive()


def call_request(tool: str, arguments: dict[str, object]) -> bytes:
    return json.dumps(
        {"jsonrpc": "2.0", "id": 1, "method": "tools/call", "params": {"name": tool, "arguments": arguments}}
    ).encode()


HEADERS = {"accept": "application/json, text/event-stream", "content-type": "application/json"}


def test_a_plan_whose_http_client_goes_mid_call_is_canceled(served: tuple[Executor, int]) -> None:
    """The client closed its connection while the plan was checked: the answer, with the only copy of
    the goal id, went nowhere, and the plan went on."""
    executor, port = served
    executor.admit.set()
    with socket.create_connection(("127.0.0.1", port), timeout=WAIT) as client:
        body = call_request("say", {"text": "hello"})
        head = "".join(f"{k}: {v}\r\n" for k, v in {**HEADERS, "host": f"127.0.0.1:{port}"}.items())
        client.sendall(f"POST /mcp HTTP/1.1\r\n{head}content-length: {len(body)}\r\n\r\n".encode() + body)
        anyio.run(until, executor.fetching.is_set)
    # Within START_WAIT, when the call would have answered the client that went.
    anyio.run(until, lambda: executor.canceled, 5.0)
    assert executor.canceled == executor.sent, (executor.sent, executor.canceled)


@pytest.mark.parametrize(
    "headers",
    [{"host": "attacker.example:{port}"}, {"host": "127.0.0.1:{port}", "origin": "http://attacker.example"}],
)
def test_a_request_from_another_site_is_refused_and_moves_nothing(
    served: tuple[Executor, int], headers: dict[str, str]
) -> None:
    """DNS rebinding: a page of another site, its name pointed at 127.0.0.1, posting to the server."""
    executor, port = served
    executor.admit.set()
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=WAIT)
    try:
        sent = {**HEADERS, **{k: v.format(port=port) for k, v in headers.items()}}
        connection.request("POST", "/mcp", call_request("say", {"text": "hello"}), sent)
        reply = connection.getresponse()
        assert reply.status in (403, 421), (reply.status, reply.read())
    finally:
        connection.close()
    assert not executor.sending.is_set()


def test_a_cancel_is_not_held_up_behind_planner_requests_being_canceled(monkeypatch: pytest.MonkeyPatch) -> None:
    """Clients gave up on plan_and_execute calls while the planner was sending a plan, which holds
    their cancel there up to 20 s: those cancels took every worker cancel_goal had, and an agent's
    cancel_goal waited for them, the robot moving."""
    canceling: list[str] = []
    release = threading.Event()

    def ask_cancel(self: Executor, request: AskCancel) -> AskCancelReply:
        canceling.append(request.request_id)
        release.wait(WAIT)
        return AskCancelReply(request_id=request.request_id, known=True, running=True, reason="canceled")

    monkeypatch.setattr(Executor, "ask_cancel", ask_cancel)
    calls = int(CANCEL_LIMITER.total_tokens)
    with rigged(planner_cancels=True) as (executor, api):

        async def main() -> str:
            async with Client(build_server(api), mode="legacy") as client:
                async with anyio.create_task_group() as group:
                    for _ in range(calls):
                        group.start_soon(client.call_tool, "plan_and_execute", {"request": "go", "dry_run": False})
                    await until(lambda: len(executor.asked_as) == calls)
                    group.cancel_scope.cancel()
                await until(lambda: len(canceling) == calls)
                with anyio.fail_after(3.0):
                    answer = await client.call_tool("cancel_goal", {"goal_id": "all"})
                release.set()
                return str(answer.content)

        try:
            assert "canceling all" in anyio.run(main)
        finally:
            release.set()
