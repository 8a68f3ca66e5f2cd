"""`tether mcp` against a model that sends what it should not, driven by the MCP SDK's own client over
stdio against a real stack: a stop is never refused over its arguments, a cancel or an e-stop is never
held up behind a flood of slow calls, a plan too long for the executor is refused by its size; and
`tether ask` refuses a request that is not UTF-8 with an error, not a traceback."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any, TypeVar

import anyio
import mcp_types as types
import pytest
from mcp import Client

from schemas import keys
from services.runtime import SERVICES
from tests.fastsim import FAST_SIM
from tests.integration.conftest import Stack, start_stack, stop_stack
from tests.integration.test_agents import text, with_client
from tests.loopback_http import LoopbackServer, QuietHandler
from tests.watch import Watch
from tether.client import reset_estop
from tether.mcpserver import CALL_LIMITER

T = TypeVar("T")
# The scripted model holds each request this long at most, unless released first (under the planner's
# 60 s timeout for the model, set below: each answer is then the test's own).
HOLD = 55.0
KEY_VARIABLE = "TETHER_TEST_HELD_LLM_KEY"


class HeldLLM:
    """A chat-completions endpoint on loopback that refuses the first `free` requests at once, then
    answers nothing until released (a model that thinks for a long time), then refuses each at once."""

    def __init__(self, free: int = 0) -> None:
        self.released = threading.Event()
        self.received = 0
        self.free = free
        self._lock = threading.Lock()
        llm = self

        class Handler(QuietHandler):
            def do_POST(self) -> None:
                self.rfile.read(int(self.headers.get("content-length", "0")))
                with llm._lock:
                    llm.received += 1
                    held = llm.received > llm.free
                if held:
                    llm.released.wait(HOLD)
                self.reply(400, b'{"error": {"message": "released by the test"}}')

        # A flood of connections at once: the server's backlog takes them (tests/loopback_http.py).
        self.server = LoopbackServer(Handler, "held-llm")
        self.url = self.server.url

    def close(self) -> None:
        self.released.set()
        self.server.close()


@pytest.fixture(scope="module")
def held_llm() -> Iterator[HeldLLM]:
    llm = HeldLLM(free=1)
    try:
        yield llm
    finally:
        llm.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, held_llm: HeldLLM) -> Iterator[Stack]:
    """Every service but the recorder; the planner's model is `held_llm`."""
    tmp = tmp_path_factory.mktemp("mcp_hostile")
    services = tuple(s for s in SERVICES if s not in ("recorder", "planner"))
    stack = start_stack(tmp, realtime_factor=10.0, services=services, sim_options=FAST_SIM)
    try:
        config = tmp / "tether.toml"
        planner = (
            f'\n[planner]\nurl = "{held_llm.url}"\nmodel = "held"\napi_key_env = "{KEY_VARIABLE}"\ntimeout = 60.0\n'
        )
        config.write_text(config.read_text() + planner)
        stack.supervisor.extra_env[KEY_VARIABLE] = "sk-held-test-key"
        stack.supervisor.start("planner")
        missing = stack.node.wait_alive(["planner"], 60.0)
        assert not missing, stack.supervisor.log_tail("planner")
        yield stack
    finally:
        stop_stack(stack)


def reset(stack: Stack) -> None:
    replied = reset_estop(stack.node, str(stack.token_file))
    assert replied.ok, replied.message


@pytest.mark.parametrize(
    "arguments",
    [{}, {"reason": "a child ran in " * 400}, {"reason": 5}, {"reason": "smoke", "urgent": True}],
    ids=["no-reason", "reason-too-long", "reason-not-text", "extra-argument"],
)
def test_an_emergency_stop_latches_whatever_its_arguments(stack: Stack, arguments: dict[str, Any]) -> None:
    """It was refused over them ("'reason' is a required property") and the robot went on moving."""
    beats = Watch(stack.node, keys.HEARTBEAT)
    clear = beats.wait_for(lambda b: not b.estop.latched, timeout=10.0)
    assert clear is not None, "the e-stop was latched before the call"

    async def body(client: Client) -> types.CallToolResult:
        return await client.call_tool("emergency_stop", arguments)

    try:
        stopped = with_client(stack, body)
        assert not stopped.is_error, text(stopped)
        assert text(stopped).startswith("e-stop latched"), text(stopped)
        assert "the arguments were not used" in text(stopped), text(stopped)
        latched = beats.wait_for(lambda b: b.estop.latched, timeout=5.0)
        assert latched is not None and latched.estop.reason == "emergency stop by an agent", latched
    finally:
        reset(stack)


def test_stopping_is_not_held_up_behind_a_flood_of_slow_calls(stack: Stack, held_llm: HeldLLM) -> None:
    """Forty plan_and_execute calls, each waiting on a model that thinks, took every worker of anyio's
    default pool, through which the stdio transport reads and writes: no later request was read, the
    cancel of a running goal and the e-stop waited behind them (up to 55 s) with the goal going on."""
    flood = 45
    answered: list[types.CallToolResult] = []

    async def body(client: Client) -> tuple[str, float, float, int, float]:
        # The first asks of a fresh process, many at once, all found "nothing answered" (a call on its
        # own first, answered at once by the model, goes before them).
        warm = await client.call_tool("plan_and_execute", {"request": "say hello", "dry_run": True})
        assert "llm_error" in text(warm), text(warm)
        # Ten minutes of waiting (on the sim's clock, ten times real time): running until canceled.
        started = await client.call_tool("execute_plan", {"plan": [{"action": "wait", "duration": 60.0}] * 10})
        assert not started.is_error, text(started)
        found = re.search(r"goal ([0-9a-f]{8,})", text(started))
        assert found, text(started)
        goal = found.group(1)

        async def ask() -> None:
            answered.append(await client.call_tool("plan_and_execute", {"request": "say hello", "dry_run": True}))

        async with anyio.create_task_group() as group:
            flooded = time.monotonic()
            for _ in range(flood):
                group.start_soon(ask)
            with anyio.fail_after(30.0):
                while held_llm.received <= held_llm.free + 30:  # most of the flood is with the model
                    await anyio.sleep(0.05)
            asked = time.monotonic()
            canceled = await client.call_tool("cancel_goal", {"goal_id": goal})
            cancel_took = time.monotonic() - asked
            asked = time.monotonic()
            stopped = await client.call_tool("emergency_stop", {"reason": "testing a stop behind a flood"})
            stop_took, pending = time.monotonic() - asked, flood - len(answered)
            held_for = time.monotonic() - flooded
            held_llm.released.set()
        assert not canceled.is_error and text(canceled).startswith("canceling"), text(canceled)
        assert not stopped.is_error and text(stopped).startswith("e-stop latched"), text(stopped)
        with anyio.fail_after(30.0):
            while "canceled" not in (status := text(await client.call_tool("get_goal_status", {"goal_id": goal}))):
                await anyio.sleep(0.2)  # an agent's polling interval, within the deadline above
        return status, cancel_took, stop_took, pending, held_for

    try:
        status, cancel_took, stop_took, pending, held_for = with_client(stack, body)
    finally:
        held_llm.released.set()
        reset(stack)
    assert cancel_took < 10.0, f"the cancel took {cancel_took:.1f} s behind the flood"
    assert stop_took < 10.0, f"the e-stop took {stop_took:.1f} s behind the flood"
    assert pending == flood, (
        f"only {pending} of the flood were still waiting when the stop was answered ({held_for:.1f} s after "
        f"the flood began): it did not hold all the tools' {CALL_LIMITER.total_tokens} threads; "
        f"the answers: {sorted({text(r) for r in answered})}"
    )
    assert "canceled" in status
    assert all(r.is_error for r in answered)


def test_a_plan_too_long_for_the_executor_is_refused_by_its_size(stack: Stack) -> None:
    """It came back "the executor is not reachable", which it was."""
    long_plan = {"plan": [{"action": "say", "text": "hi", "description": "d" * 4000} for _ in range(100)]}

    async def body(client: Client) -> types.CallToolResult:
        return await client.call_tool("execute_plan", long_plan)

    too_long = with_client(stack, body)
    assert too_long.is_error, text(too_long)
    # Refused before its schema is checked (tether/mcpserver.py: arguments over MAX_PLAN_BYTES as JSON).
    assert text(too_long).startswith("execute_plan: arguments: ") and "the limit is 262144" in text(too_long)
    assert "reachable" not in text(too_long)


def test_a_plan_of_accented_text_within_the_bounds_is_checked_as_any_plan(stack: Stack) -> None:
    """Each letter went to the executor escaped, six bytes for two, and the plan over its limit."""
    stairs = {"action": "navigate_to", "target": "stairs"}
    accented = {"plan": [stairs] + [{"action": "say", "text": "hi", "description": "é" * 1000} for _ in range(50)]}
    assert len(json.dumps(accented)) > 262144 > len(json.dumps(accented, ensure_ascii=False).encode())

    async def body(client: Client) -> types.CallToolResult:
        return await client.call_tool("execute_plan", accented)

    checked = with_client(stack, body)
    # Refused for the stairs, as any plan would be: not for its size.
    assert checked.is_error and "rejected at safety" in text(checked) and "stairs" in text(checked), text(checked)


def test_ask_refuses_a_request_that_is_not_utf8(stack: Stack, held_llm: HeldLLM) -> None:
    """Bytes that are not UTF-8, piped in or in the argument, ended in a traceback (UnicodeEncodeError)
    when the request was sent to the planner."""
    asked_before = held_llm.received
    tether = [sys.executable.encode(), b"-m", b"tether", b"ask"]
    for args, piped in (([b"-", b"--dry-run"], b"bring the \xff cup"), ([b"bring the \xff cup", b"--dry-run"], b"")):
        run = subprocess.run(
            [*tether, *args],
            env=stack.supervisor.env(),
            input=piped,
            capture_output=True,
            timeout=120,
            start_new_session=True,
        )
        assert run.returncode == 2, run.stderr.decode(errors="replace")[-2000:]
        assert b"the request is not UTF-8 text (a byte at character 11)" in run.stderr
        assert b"UnicodeEncodeError" not in run.stderr
    assert held_llm.received == asked_before, "the model was asked"
