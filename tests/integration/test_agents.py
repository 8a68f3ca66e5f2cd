"""Agent interfaces as real processes: the natural-language planner against a scripted LLM endpoint, and
`tether mcp` driven by the MCP SDK's own client."""

from __future__ import annotations

import base64
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import anyio
import mcp_types as types
import pytest
from mcp import Client
from mcp.client.stdio import StdioServerParameters

from schemas import keys
from schemas.actions import GetResult
from schemas.common import Stage
from schemas.planner import AskRequest, AskStatus, AttemptOutcome
from schemas.safety import EstopSource
from schemas.world import Empty, GroundTruth
from services.runtime import SERVICES
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_SIM
from tests.integration.conftest import Stack, run_tether, start_stack, stop_stack, tether_cli
from tests.loopback_http import LoopbackServer, QuietHandler
from tests.sessions import free_port
from tests.watch import Watch
from tether.client import reset_estop, trigger_estop

API_KEY = "sk-tether-test-5f1c0e9a7b"
KEY_VARIABLE = "TETHER_TEST_LLM_KEY"
MODEL = "scripted-model"
REQUEST = "bring me the red cup"

GOOD = json.dumps(
    {
        "plan": [
            {"action": "navigate_to", "target": "kitchen counter"},
            {"action": "pick", "target": "red cup"},
            {"action": "navigate_to", "target": "coffee table"},
            {"action": "place", "target": "coffee table"},
        ]
    }
)
MALFORMED = 'Sure! {"plan": [{"action": "navigate_to", "target": '
STAIRS_CALL = {
    "id": "call_stairs",
    "type": "function",
    "function": {"name": "navigate_to", "arguments": json.dumps({"target": "stairs"})},
}
SAY = json.dumps({"plan": [{"action": "say", "text": "hello"}]})
T = TypeVar("T")
WORLD = WorldModel(load_world())
GOAL_TIMEOUT = 120.0


def text_reply(content: str) -> dict[str, Any]:
    return {"role": "assistant", "content": content}


def tool_reply(*calls: dict[str, Any]) -> dict[str, Any]:
    return {"role": "assistant", "content": None, "tool_calls": list(calls)}


@dataclass
class Received:
    headers: dict[str, str]
    body: dict[str, Any]


@dataclass
class ScriptedLLM:
    """An OpenAI-compatible chat-completions server on loopback answering from a script: each entry
    a message (answered 200 with one choice) or (status, body) for a broken endpoint."""

    url: str = ""
    script: list[dict[str, Any] | tuple[int, bytes]] = field(default_factory=list)
    received: list[Received] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    # Run as each request arrives, before it is answered (what happens while the model thinks).
    meanwhile: Callable[[], None] = lambda: None

    def play(self, *entries: dict[str, Any] | tuple[int, bytes], meanwhile: Callable[[], None] = lambda: None) -> None:
        with self.lock:
            self.script = list(entries)
            self.received = []
            self.meanwhile = meanwhile

    def answer(self, headers: dict[str, str], body: dict[str, Any]) -> tuple[int, bytes]:
        with self.lock:
            self.received.append(Received(headers, body))
            if not self.script:
                return 500, b'{"error": {"message": "the test script is exhausted"}}'
            entry = self.script.pop(0)
            meanwhile = self.meanwhile
        meanwhile()
        if isinstance(entry, tuple):
            return entry
        completion = {
            "id": f"chatcmpl-{uuid.uuid4().hex[:8]}",
            "object": "chat.completion",
            "model": body.get("model"),
            "choices": [{"index": 0, "message": entry, "finish_reason": "stop"}],
        }
        return 200, json.dumps(completion).encode()


@pytest.fixture(scope="module")
def llm_server() -> Iterator[ScriptedLLM]:
    llm = ScriptedLLM()

    class Handler(QuietHandler):
        def do_POST(self) -> None:
            length = int(self.headers.get("content-length", "0"))
            raw = self.rfile.read(length)
            if self.path != "/v1/chat/completions":
                status, reply = 404, b'{"error": {"message": "no such path"}}'
            else:
                try:
                    body = json.loads(raw)
                except ValueError:
                    status, reply = 400, b'{"error": {"message": "body is not JSON"}}'
                else:
                    status, reply = llm.answer({k.lower(): v for k, v in self.headers.items()}, body)
            self.reply(status, reply)

    server = LoopbackServer(Handler, "scripted-llm")
    llm.url = server.url
    try:
        yield llm
    finally:
        server.close()


AGENT_SERVICES = tuple(s for s in SERVICES if s != "recorder")


@pytest.fixture(scope="module")
def agent_stack(tmp_path_factory: pytest.TempPathFactory, llm_server: ScriptedLLM) -> Iterator[Stack]:
    """Every service but the recorder, the sim ten times faster than real time (its physics at
    FAST_SIM's 120 Hz, as the tours run it), the planner pointed at `llm_server` with its key in an
    environment variable named by `[planner] api_key_env`."""
    tmp = tmp_path_factory.mktemp("agents")
    without_planner = tuple(s for s in AGENT_SERVICES if s != "planner")
    stack = start_stack(tmp, realtime_factor=10.0, services=without_planner, sim_options=FAST_SIM)
    try:
        config = tmp / "tether.toml"
        config.write_text(
            config.read_text()
            + f'\n[planner]\nurl = "{llm_server.url}"\nmodel = "{MODEL}"\napi_key_env = "{KEY_VARIABLE}"\n'
            + "timeout = 10.0\n"
        )
        stack.supervisor.extra_env[KEY_VARIABLE] = API_KEY
        stack.supervisor.start("planner")
        missing = stack.node.wait_alive(["planner"], 60.0)
        assert not missing, stack.supervisor.log_tail("planner")
        yield stack
    finally:
        stop_stack(stack)


class Everything:
    """Every sample published under the robot's prefix, traces included, as raw bytes."""

    def __init__(self, stack: Stack) -> None:
        self.samples: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        stack.node.subscribe_raw(keys.all_keys(stack.settings.robot), self._on_sample)

    def _on_sample(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.samples.append((key, payload))

    def holding(self, secret: str) -> list[str]:
        with self._lock:
            return [key for key, payload in self.samples if secret.encode() in payload]


def messages_text(received: Received) -> str:
    return json.dumps(received.body["messages"])


def test_the_planner_recovers_from_a_malformed_and_an_unsafe_reply(agent_stack: Stack, llm_server: ScriptedLLM) -> None:
    attempts = Watch(agent_stack.node, keys.PLANNER_ATTEMPTS)
    everything = Everything(agent_stack)
    llm_server.play(text_reply(MALFORMED), tool_reply(STAIRS_CALL), text_reply(GOOD))

    asked = tether_cli(agent_stack, "ask", REQUEST, "--dry-run", "--json")
    assert asked.returncode == 0, asked.stderr
    outcome = json.loads(asked.stdout)
    assert (outcome["status"], outcome["attempts"]) == ("approved", 3), outcome
    assert json.loads(outcome["plan"]) == json.loads(GOOD)
    assert outcome["goal_id"] == ""

    # Every attempt is published, with the model's reply, the plan and the verdict.
    third = attempts.wait_for(lambda a: a.attempt == 3, timeout=5.0)
    assert third is not None
    mine = [a for a in attempts.messages if a.request_id == outcome["request_id"]]
    assert [(a.attempt, a.outcome, a.stage) for a in mine] == [
        (1, AttemptOutcome.REJECTED, "parse"),
        (2, AttemptOutcome.REJECTED, "safety"),
        (3, AttemptOutcome.APPROVED, "safety"),
    ]
    assert mine[0].reply == MALFORMED and "stairs" in mine[1].plan and "stairs" in mine[1].reason
    assert all(a.request == REQUEST and a.model == MODEL for a in mine)

    # The model saw the tools, the scene as data, and each refusal with its stage and reason.
    first, second, last = llm_server.received
    assert first.body["model"] == MODEL
    assert "navigate_to" in {t["function"]["name"] for t in first.body["tools"]}
    system = first.body["messages"][0]["content"]
    assert "<robot-data" in system and "never as instructions" in system and "red cup" in system
    assert first.body["messages"][-1] == {"role": "user", "content": REQUEST}
    assert second.body["messages"][-1]["role"] == "user"
    assert second.body["messages"][-1]["content"].startswith("rejected at stage parse: ")
    assert last.body["messages"][-1]["role"] == "tool" and last.body["messages"][-1]["tool_call_id"] == "call_stairs"
    assert last.body["messages"][-1]["content"].startswith("rejected at stage safety: ")
    assert "stairs" in last.body["messages"][-1]["content"]

    # The key goes as a Bearer header and nowhere else.
    assert {r.headers.get("authorization") for r in llm_server.received} == {f"Bearer {API_KEY}"}
    assert API_KEY not in json.dumps([r.body for r in llm_server.received])
    assert everything.holding(API_KEY) == []
    assert keys.PLANNER_ATTEMPTS.key(agent_stack.settings.robot) in {k for k, _ in everything.samples}
    assert API_KEY not in agent_stack.supervisor.log_tail("planner", 1000)


def test_the_planner_gives_up_after_n_bad_replies(agent_stack: Stack, llm_server: ScriptedLLM) -> None:
    llm_server.play(tool_reply(STAIRS_CALL), text_reply(MALFORMED), text_reply(GOOD))
    reply = agent_stack.node.call(keys.PLAN_ASK, AskRequest(text=REQUEST, dry_run=True, max_attempts=2), timeout=120.0)
    assert reply.status is AskStatus.REJECTED
    assert (reply.attempts, reply.stage) == (2, "parse")
    assert reply.reason.startswith("no plan passed after 2 attempts; the last: ")
    assert reply.goal_id == ""
    assert len(llm_server.received) == 2, "no third call"


def test_an_approved_plan_is_sent_and_its_goal_id_returned(agent_stack: Stack, llm_server: ScriptedLLM) -> None:
    llm_server.play(text_reply(SAY))
    reply = agent_stack.node.call(keys.PLAN_ASK, AskRequest(text="say hello"), timeout=120.0)
    assert reply.status is AskStatus.ACCEPTED, reply.reason
    assert reply.goal_id
    result = agent_stack.node.call(keys.EXECUTE_PLAN.get_result, GetResult(goal_id=reply.goal_id), timeout=60.0)
    assert result.result is not None and result.result.status == "succeeded", result


def test_an_approved_plan_longer_than_a_record_is_sent_whole(agent_stack: Stack, llm_server: ScriptedLLM) -> None:
    """The reply keeps 8,000 characters of the plan (RecordedText): the executor was sent that cut
    copy, not the plan the dry run approved, and ran its first steps only (a review's finding)."""
    words = "and this sentence is long enough that sixty of them make a plan of more than eight thousand characters"
    steps = [{"action": "say", "text": f"step {i}: {words}"} for i in range(60)]
    plan = json.dumps({"plan": steps})
    assert len(plan) > 8000
    llm_server.play(text_reply(plan))
    reply = agent_stack.node.call(keys.PLAN_ASK, AskRequest(text="say sixty things"), timeout=120.0)
    assert reply.status is AskStatus.ACCEPTED, reply.reason
    result = agent_stack.node.call(keys.EXECUTE_PLAN.get_result, GetResult(goal_id=reply.goal_id), timeout=60.0)
    assert result.result is not None and result.result.status == "succeeded", result
    assert len(result.result.steps) == 60


def test_endpoint_errors_are_named_and_the_cli_calls_an_endpoint_of_its_own(
    agent_stack: Stack, llm_server: ScriptedLLM
) -> None:
    """With TETHER_LLM_* set, `tether ask` calls the model itself; its attempts are published too."""
    everything = Everything(agent_stack)
    own_key = "sk-cli-own-key-77aa"
    env = agent_stack.supervisor.env() | {
        "TETHER_LLM_URL": llm_server.url,
        "TETHER_LLM_MODEL": "cli-model",
        "TETHER_LLM_API_KEY": own_key,
    }

    def ask(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "tether", "ask", REQUEST, "--dry-run", "--json", *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )

    llm_server.play((503, json.dumps({"error": {"message": f"overloaded; your key {own_key}"}}).encode()))
    failed = ask()
    assert failed.returncode == 1, failed.stderr
    outcome = json.loads(failed.stdout)
    assert outcome["status"] == "llm_error"
    assert "HTTP 503" in outcome["reason"] and "overloaded" in outcome["reason"]
    assert own_key not in failed.stdout + failed.stderr

    llm_server.play((200, b"<html>not an API</html>"))
    outcome = json.loads(ask().stdout)
    assert outcome["status"] == "llm_error" and "not JSON" in outcome["reason"]

    llm_server.play(text_reply(GOOD))
    approved = ask("--max-attempts", "1")
    assert approved.returncode == 0, approved.stderr
    assert json.loads(approved.stdout)["status"] == "approved"
    assert llm_server.received[0].headers["authorization"] == f"Bearer {own_key}"
    assert llm_server.received[0].body["model"] == "cli-model"
    assert everything.holding(own_key) == []


def test_ask_without_an_endpoint_says_how_to_configure_one(agent_stack: Stack, tmp_path: Path) -> None:
    # Another robot name: no planner service to ask, and no endpoint in the environment or a file.
    asked = run_tether(agent_stack.supervisor, "--robot", f"nobody{uuid.uuid4().hex[:6]}", "ask", REQUEST)
    assert asked.returncode == 2, asked.stderr
    for hint in ("no LLM endpoint is configured", "TETHER_LLM_URL", "TETHER_LLM_MODEL", "[planner]", "api_key_env"):
        assert hint in asked.stderr

    pasted = tmp_path / "pasted.toml"
    pasted.write_text('[planner]\nurl = "http://127.0.0.1:9/v1"\nmodel = "m"\napi_key_env = "sk-pasted-secret"\n')
    refused = run_tether(agent_stack.supervisor, "ask", REQUEST, "--config", str(pasted))
    assert refused.returncode == 2
    assert "api_key_env" in refused.stderr and "sk-pasted-secret" not in refused.stderr


# The MCP server, driven by the MCP SDK's own client over stdio (and HTTP), against the same stack.


def with_client(stack: Stack, body: Callable[[Client], Awaitable[T]]) -> T:
    """Run `body` with an MCP client connected to `tether mcp`, started over stdio as an MCP host does."""
    params = StdioServerParameters(command=sys.executable, args=["-m", "tether", "mcp"], env=stack.supervisor.env())

    async def main() -> T:
        async with Client(params, read_timeout_seconds=60.0) as client:
            return await body(client)

    return anyio.run(main)


def text(result: types.CallToolResult) -> str:
    return "\n".join(c.text for c in result.content if isinstance(c, types.TextContent))


def goal_id(result: types.CallToolResult) -> str:
    found = re.search(r"goal ([0-9a-f]{8,})", text(result))
    assert found, text(result)
    return found.group(1)


async def poll(client: Client, goal: str, until: Callable[[str], bool], timeout: float = GOAL_TIMEOUT) -> str:
    deadline = time.monotonic() + timeout
    while True:
        status = text(await client.call_tool("get_goal_status", {"goal_id": goal}))
        if until(status) or time.monotonic() > deadline:
            return status
        await anyio.sleep(0.2)  # the polling interval of an agent, not a wait for a condition


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=10.0)  # type: ignore[no-any-return]


def test_the_tools_are_listed_with_generated_schemas_and_none_clears_an_estop(agent_stack: Stack) -> None:
    async def body(client: Client) -> list[types.Tool]:
        return (await client.list_tools()).tools

    tools = {t.name: t for t in with_client(agent_stack, body)}
    for name in ("navigate_to", "pick", "place", "say", "execute_plan", "plan_and_execute"):
        assert name in tools and tools[name].input_schema["type"] == "object"
    for name in ("get_goal_status", "cancel_goal", "emergency_stop", "get_robot_state", "get_camera_image"):
        assert name in tools
    assert not [n for n in tools if re.search(r"reset|policy|limit|unlock|override", n)]
    assert tools["get_camera_image"].annotations is not None and tools["get_camera_image"].annotations.read_only_hint


def test_an_agent_navigates_polls_to_success_and_cancels_another(agent_stack: Stack) -> None:
    async def body(client: Client) -> tuple[str, str, str, str]:
        started = await client.call_tool("navigate_to", {"target": "coffee table"})
        assert not started.is_error, text(started)
        first = goal_id(started)
        done = await poll(client, first, lambda s: "succeeded" in s or "failed" in s)
        other = await client.call_tool("navigate_to", {"target": "bedroom"})
        assert not other.is_error, text(other)
        second = goal_id(other)
        canceled = text(await client.call_tool("cancel_goal", {"goal_id": second}))
        ended = await poll(client, second, lambda s: "canceled" in s or "succeeded" in s, timeout=30.0)
        return text(started), done, canceled, ended

    started, done, canceled, ended = with_client(agent_stack, body)
    assert started.startswith("started goal"), started
    assert "succeeded" in done, done
    here = truth(agent_stack).robot
    approach = WORLD.furniture["coffee_table"].approach
    assert math.hypot(here.x - approach.x, here.y - approach.y) < 0.05
    assert canceled.startswith("canceling"), canceled
    assert "canceled" in ended, ended


def test_a_refusal_comes_back_as_text_a_model_can_act_on(agent_stack: Stack) -> None:
    async def body(client: Client) -> list[types.CallToolResult]:
        return [
            await client.call_tool("execute_plan", {"plan": [{"action": "navigate_to", "target": "stairs"}]}),
            await client.call_tool("navigate_to", {"target": "coffee table", "speed": 5.0}),
            await client.call_tool("reset_estop", {}),
            # A harmless-looking tool cannot carry another action; arguments keep to their schema.
            await client.call_tool("say", {"text": "hi", "action": "drive", "distance": 1.0}),
            await client.call_tool("navigate_to", {"target": 5}),
            await client.call_tool("get_goal_status", {"goal_id": "x" * 100_000}),
        ]

    stairs, fast, unknown, smuggled, typed, huge = with_client(agent_stack, body)
    assert stairs.is_error and "rejected at safety" in text(stairs) and "stairs" in text(stairs), text(stairs)
    assert fast.is_error and "speed" in text(fast), text(fast)
    assert unknown.is_error and "unknown tool" in text(unknown)
    assert smuggled.is_error and "not allowed" in text(smuggled), text(smuggled)
    assert typed.is_error and "target" in text(typed), text(typed)
    assert huge.is_error and "goal_id" in text(huge) and len(text(huge)) < 1000, text(huge)[:200]


def test_reading_tools_mark_sensor_text_as_data_and_the_camera_is_an_image(agent_stack: Stack) -> None:
    async def body(client: Client) -> list[types.CallToolResult]:
        return [
            await client.call_tool("describe_scene", {}),
            await client.call_tool("list_objects", {}),
            await client.call_tool("get_robot_state", {}),
            await client.call_tool("get_camera_image", {}),
        ]

    scene, objects, state, image = with_client(agent_stack, body)
    for result in (scene, objects, state):
        assert not result.is_error and "<robot-data" in text(result) and "never as instructions" in text(result)
    assert "red cup" in text(objects)
    [picture] = [c for c in image.content if isinstance(c, types.ImageContent)]
    assert picture.mime_type == "image/png"
    assert base64.b64decode(picture.data)[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_agent_can_stop_the_robot_and_no_tool_starts_it_again(agent_stack: Stack, llm_server: ScriptedLLM) -> None:
    beats = Watch(agent_stack.node, keys.HEARTBEAT)
    everything = Everything(agent_stack)
    llm_server.play(text_reply(SAY))

    async def body(client: Client) -> list[types.CallToolResult]:
        stopped = await client.call_tool("emergency_stop", {"reason": "a child ran in"})
        # Every tool that could plausibly move the robot, after the e-stop.
        return [
            stopped,
            await client.call_tool("navigate_to", {"target": "kitchen"}),
            await client.call_tool("execute_plan", {"plan": [{"action": "say", "text": "hello"}]}),
            await client.call_tool("cancel_goal", {"goal_id": "all"}),
            await client.call_tool("plan_and_execute", {"request": "say hello", "dry_run": False}),
            await client.call_tool("emergency_stop", {"reason": "again"}),
        ]

    try:
        stopped, navigate, plan, cancel, asked, again = with_client(agent_stack, body)
        assert "latched" in text(stopped), text(stopped)
        assert navigate.is_error and "e-stop" in text(navigate), text(navigate)
        assert plan.is_error and "e-stop" in text(plan), text(plan)
        assert asked.is_error and "e-stop" in text(asked), text(asked)
        assert not cancel.is_error and not again.is_error
        latest = beats.latest(timeout=5.0)
        assert latest is not None and latest.estop.latched, "an agent's tool calls cleared the e-stop"
        assert not [k for k, _ in everything.samples if keys.RESET.path in k], "a tool reached safety/reset"
    finally:
        reset = reset_estop(agent_stack.node, str(agent_stack.token_file))
    assert reset.ok, reset.message


def test_an_estop_latched_while_the_model_thinks_ends_the_asking(agent_stack: Stack, llm_server: ScriptedLLM) -> None:
    """The e-stop was looked at once, before the first model call: latched during the loop, the
    model was asked four more times to fix its plan (a review's finding)."""

    def latch() -> None:
        assert trigger_estop(agent_stack.node, EstopSource.OPERATOR, "latched while the model thought") is not None

    llm_server.play(*[text_reply("not a plan at all")] * 5, meanwhile=latch)
    try:
        reply = agent_stack.node.call(keys.PLAN_ASK, AskRequest(text="say hello", max_attempts=5), timeout=120.0)
        assert reply.status is AskStatus.REJECTED and reply.stage is Stage.SAFETY, reply
        assert "e-stop is latched" in reply.reason and not reply.goal_id
        assert len(llm_server.received) == 1, "asked the model again after the e-stop latched"
    finally:
        reset = reset_estop(agent_stack.node, str(agent_stack.token_file))
    assert reset.ok, reset.message


def test_streamable_http_serves_the_same_tools_on_loopback(agent_stack: Stack, tmp_path: Path) -> None:
    port = free_port()
    log = (tmp_path / "mcp.log").open("wb")
    server = subprocess.Popen(
        [sys.executable, "-m", "tether", "mcp", "--http", "--port", str(port)],
        env=agent_stack.supervisor.env(),
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        bound = wait_listening(port, timeout=30.0)
        assert bound == "127.0.0.1", f"listening on {bound}"

        async def main() -> list[str]:
            async with Client(f"http://127.0.0.1:{port}/mcp", read_timeout_seconds=30.0) as client:
                state = await client.call_tool("get_robot_state", {})
                assert not state.is_error and "pose" in text(state)
                return [t.name for t in (await client.list_tools()).tools]

        names = anyio.run(main)
        assert "navigate_to" in names and "emergency_stop" in names
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)
        log.close()
        print((tmp_path / "mcp.log").read_text(errors="replace")[-3000:])  # shown when the test failed


def wait_listening(port: int, timeout: float) -> str:
    """The address a TCP listener on `port` is bound to, once there is one (from /proc/net/tcp)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            address, hex_port = local.split(":")
            if int(hex_port, 16) == port and state == "0A":  # LISTEN
                return socket.inet_ntoa(bytes.fromhex(address)[::-1])
        time.sleep(0.1)  # polling the kernel's table for the listener, with the deadline above
    raise AssertionError(f"nothing listened on port {port} within {timeout:g} s")


def test_plan_and_execute_goes_from_the_mcp_tool_through_the_planner(
    agent_stack: Stack, llm_server: ScriptedLLM
) -> None:
    llm_server.play(text_reply(SAY))

    async def body(client: Client) -> types.CallToolResult:
        return await client.call_tool("plan_and_execute", {"request": "say hello", "dry_run": True})

    result = with_client(agent_stack, body)
    assert not result.is_error, text(result)
    assert text(result).startswith("dry run approved after 1 attempt"), text(result)
    assert len(llm_server.received) == 1 and "say hello" in messages_text(llm_server.received[0])
