"""The planner's model client against hostile endpoints on loopback: keys echoed back, headers dripped,
numbers JSON cannot carry, answers cut at the token limit, floods of tool calls, bad URLs and ids."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from schemas.common import Stage
from schemas.plan import MAX_PLAN_BYTES, MAX_STEPS
from services.parser.errors import ParseError
from services.parser.parser import parse
from services.planner.config import Endpoint, PlannerConfig, Secret, resolve_endpoint
from services.planner.errors import LLMError, NotConfigured
from services.planner.llm import SNIPPET, ChatClient, ChatReply
from services.planner.loop import DryRunVerdict, LoopStatus, plan_loop
from services.planner.prompt import feedback_messages, initial_messages, normalize_calls
from tests.loopback_http import LoopbackServer, QuietHandler

KEY = "sk-proj-SECRET0123456789abcdefghijklmnopqrstuvwxyz"
GOOD = '{"plan": [{"action": "navigate_to", "target": "kitchen counter"}]}'
# An answer as (status, content type, body).
Answer = tuple[int, str, bytes]


def ok(body: dict[str, Any] | bytes) -> Answer:
    return 200, "application/json", body if isinstance(body, bytes) else json.dumps(body).encode()


def completion(finish_reason: str = "stop", **message: Any) -> dict[str, Any]:
    return {"choices": [{"index": 0, "message": {"role": "assistant", **message}, "finish_reason": finish_reason}]}


class ScriptedEndpoint:
    """A chat-completions endpoint on loopback: answers from a script, keeps every request body."""

    def __init__(self, *answers: Answer) -> None:
        self.answers = list(answers)
        self.requests: list[bytes] = []
        self.lock = threading.Lock()
        endpoint = self

        class Handler(QuietHandler):
            def do_POST(self) -> None:
                raw = self.rfile.read(int(self.headers.get("content-length", "0")))
                with endpoint.lock:
                    endpoint.requests.append(raw)
                    answer = endpoint.answers.pop(0) if endpoint.answers else (500, "text/plain", b"script exhausted")
                status, content_type, body = answer
                self.reply(status, body, content_type)

        self.server = LoopbackServer(Handler, "hostile-llm", poll_interval=0.05)
        self.url = self.server.url

    def client(self, key: str | None = KEY, timeout: float = 10.0) -> ChatClient:
        secret = Secret(key) if key else None
        return ChatClient(Endpoint(url=self.url, model="m", api_key=secret, key_source="K", timeout=timeout))

    def stop(self) -> None:
        self.server.close()


@pytest.fixture
def serve() -> Iterator[Callable[..., ScriptedEndpoint]]:
    started: list[ScriptedEndpoint] = []

    def start(*answers: Answer) -> ScriptedEndpoint:
        started.append(ScriptedEndpoint(*answers))
        return started[-1]

    yield start
    for endpoint in started:
        endpoint.stop()


def failure(client: ChatClient, messages: list[dict[str, Any]] | None = None) -> str:
    with pytest.raises(LLMError) as caught:
        client.chat(messages or [{"role": "user", "content": "bring me the red cup"}])
    return str(caught.value)


def shows_key(message: str) -> bool:
    """Whether any 8 characters in a row of the key are in the message."""
    return any(KEY[i : i + 8] in message for i in range(len(KEY) - 7))


# The key, however the endpoint echoes it


@pytest.mark.parametrize(
    "answer",
    [
        ok({"error": {"message": f"invalid api key {KEY}"}}),
        ok({"error": f"invalid api key {KEY}"}),
        ok(completion(content=None, refusal=f"I won't. (request authorized with Bearer {KEY})")),
    ],
    ids=["error-object-with-no-choices", "error-string-with-no-choices", "refusal"],
)
def test_a_key_echoed_in_an_answer_with_status_200_never_leaves_chat(
    serve: Callable[..., ScriptedEndpoint], answer: Answer
) -> None:
    message = failure(serve(answer).client())
    assert "***" in message and not shows_key(message), message


@pytest.mark.parametrize(
    "answer",
    [
        (500, "text/plain", ("x" * (SNIPPET - len(KEY) + 1) + KEY + " echoed").encode()),
        (401, "application/json", json.dumps({"error": {"message": "x" * (SNIPPET - len(KEY) + 1) + KEY}}).encode()),
        (200, "text/html", ("<html>" + "x" * (SNIPPET - len(KEY) - 5) + KEY + "</html>").encode()),
        ok({"error": {"message": "x" * (SNIPPET - len(KEY) + 1) + KEY}}),
        ok(completion(content=None, refusal="x" * (SNIPPET - len(KEY) + 1) + KEY)),
        (200, "application/json", ("x" * (SNIPPET - 10) + KEY * 12).encode()),  # a key past the cut, many times
    ],
    ids=["http-500-text", "http-401-error-message", "not-json", "no-choices", "refusal", "repeated"],
)
def test_a_key_across_the_cut_of_an_error_message_leaves_no_part_of_itself(
    serve: Callable[..., ScriptedEndpoint], answer: Answer
) -> None:
    message = failure(serve(answer).client())
    assert not shows_key(message), message


# The whole answer within the timeout


class HeaderDrip:
    """Answers the first request whole (keeping the connection open), then sends the next one's response
    headers a byte at a time, each well within the read timeout, until the client goes, the test ends or
    DRIP_FOR has passed (a client that never cuts it off fails the test then, instead of hanging it)."""

    DRIP_FOR = 10.0

    def __init__(self) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.stop = threading.Event()
        self.requests = 0
        self.thread = threading.Thread(target=self.run, name="header-drip", daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.listener.getsockname()[1]}/v1"

    def run(self) -> None:
        self.listener.settimeout(0.1)
        while not self.stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=self.talk, args=(conn,), daemon=True).start()

    def talk(self, conn: socket.socket) -> None:
        with conn:
            while not self.stop.is_set() and self.read_request(conn):
                self.requests += 1
                if self.requests == 1:
                    body = json.dumps(completion(content=GOOD)).encode()
                    head = f"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\n\r\n"
                    conn.sendall(head.encode() + body)
                    continue
                conn.sendall(b"HTTP/1.1 200 OK\r\nX-Pad: ")
                until = time.monotonic() + self.DRIP_FOR
                while (
                    not self.stop.wait(0.05) and time.monotonic() < until
                ):  # one byte every 50 ms: each read is well within the timeout
                    try:
                        conn.sendall(b"a")
                    except OSError:  # the client cut the connection
                        return
                return

    @staticmethod
    def read_request(conn: socket.socket) -> bool:
        data = b""
        conn.settimeout(5)
        try:
            while b"\r\n\r\n" not in data:
                chunk = conn.recv(65536)
                if not chunk:
                    return False
                data += chunk
            head, _, body = data.partition(b"\r\n\r\n")
            length = next(
                int(line.split(b":")[1]) for line in head.lower().split(b"\r\n") if line.startswith(b"content-length")
            )
            while len(body) < length:
                chunk = conn.recv(65536)
                if not chunk:
                    return False
                body += chunk
        except OSError:
            return False
        return True

    def close(self) -> None:
        self.stop.set()
        self.listener.close()
        self.thread.join(timeout=5)


def test_response_headers_sent_a_byte_at_a_time_are_cut_off_at_the_timeout() -> None:
    drip = HeaderDrip()
    client = ChatClient(Endpoint(url=drip.url, model="m", timeout=0.5))
    try:
        assert client.chat([{"role": "user", "content": "go"}]).content == GOOD
        begun = time.monotonic()
        with pytest.raises(LLMError, match=r"did not answer within 0.5 s \(no whole answer\)"):
            client.chat([{"role": "user", "content": "go"}])
        took = time.monotonic() - begun
        assert took < 4.0, f"chat() took {took:.1f} s at a timeout of 0.5 s"
        # The client is still usable: the cut ended one call, not the client.
        assert drip.requests == 2
    finally:
        client.close()
        drip.close()


# Numbers JSON cannot carry


def dry_run(text: str) -> DryRunVerdict:
    """The parser's part of a dry run: enough to refuse what no plan may hold."""
    try:
        parse(text)
    except ParseError as exc:
        return DryRunVerdict(False, Stage.PARSE, str(exc))
    return DryRunVerdict(True, Stage.PARSE, "parsed")


def test_a_tool_call_with_a_number_json_cannot_carry_is_refused_and_the_conversation_goes_on(
    serve: Callable[..., ScriptedEndpoint],
) -> None:
    def turn(angle: str) -> Answer:
        call = f'{{"id":"c1","type":"function","function":{{"name":"turn","arguments":{{"angle":{angle}}}}}}}'
        return ok(f'{{"choices":[{{"message":{{"role":"assistant","content":null,"tool_calls":[{call}]}}}}]}}'.encode())

    endpoint = serve(turn("1e999"), turn("NaN"), turn("-Infinity"), ok(completion(content=GOOD)))
    client = endpoint.client()
    messages = initial_messages("turn around", [], True, "a kitchen")
    result = plan_loop(messages, client.chat, dry_run, 4)

    assert result.status is LoopStatus.APPROVED, result.reason
    assert [a.status for a in result.attempts] == [LoopStatus.REJECTED] * 3 + [LoopStatus.APPROVED]
    assert all("finite" in a.reason for a in result.attempts[:3]), [a.reason for a in result.attempts]
    # Every request after a refusal is strict JSON and tells the model why.
    later = [json.loads(raw, parse_constant=lambda name: pytest.fail(f"{name} sent")) for raw in endpoint.requests[1:]]
    refusal = [m["content"] for m in later[-1]["messages"] if m["role"] == "user"][-1]
    assert refusal.startswith("rejected at stage parse: ") and "parameter 'angle' must be a finite number" in refusal


def test_a_conversation_that_cannot_be_encoded_is_an_llm_error(serve: Callable[..., ScriptedEndpoint]) -> None:
    client = serve(ok(completion(content=GOOD))).client()
    message = failure(client, [{"role": "assistant", "content": None, "x": float("nan")}])
    assert "cannot be encoded as JSON" in message


# Cut at the token limit


@pytest.mark.parametrize(
    "message",
    [
        {"content": "1. go to the kitchen counter\n2. pick up the knife\n"},
        {
            "content": None,
            "tool_calls": [{"id": "a", "type": "function", "function": {"name": "pick", "arguments": "{}"}}],
        },
    ],
    ids=["text", "tool-calls"],
)
def test_an_answer_cut_at_the_token_limit_is_never_a_plan(
    serve: Callable[..., ScriptedEndpoint], message: dict[str, Any]
) -> None:
    reason = failure(serve(ok(completion("length", **message))).client())
    assert "cut at the model's token limit (finish_reason length)" in reason and "max_tokens" in reason


# Floods of tool calls


def test_more_tool_calls_than_a_plan_has_steps_are_refused_at_once(serve: Callable[..., ScriptedEndpoint]) -> None:
    flood = b'{"choices":[{"message":{"role":"assistant","content":null,"tool_calls":[' + b",".join([b"{}"] * 100_000)
    endpoint = serve(ok(flood + b"]}}]}"))
    result = plan_loop([{"role": "user", "content": "x"}], endpoint.client().chat, dry_run, 2)
    assert result.status is LoopStatus.LLM_ERROR
    assert f"100000 tool calls; a plan holds at most {MAX_STEPS} steps" in result.reason
    assert len(endpoint.requests) == 1


def test_a_reply_too_big_for_a_plan_goes_back_as_a_short_note(serve: Callable[..., ScriptedEndpoint]) -> None:
    padding = "x" * (MAX_PLAN_BYTES // MAX_STEPS + 1000)
    calls = [
        {"id": f"c{i}", "type": "function", "function": {"name": "say", "arguments": json.dumps({"text": padding})}}
        for i in range(MAX_STEPS)
    ]
    big = ok(completion(content=None, tool_calls=calls))
    endpoint = serve(big, big, big)
    checked: list[str] = []

    def check(text: str) -> DryRunVerdict:
        checked.append(text)
        return DryRunVerdict(True)

    result = plan_loop([{"role": "user", "content": "x"}], endpoint.client().chat, check, 3)
    assert result.status is LoopStatus.REJECTED and checked == [], "refused before any dry run"
    sizes = [len(raw) for raw in endpoint.requests]
    assert len(big[2]) > MAX_PLAN_BYTES and max(sizes) < 4096, sizes
    last = json.loads(endpoint.requests[-1])["messages"]
    assert last[-2]["role"] == "assistant" and "not repeated here" in last[-2]["content"]
    assert last[-1]["role"] == "user" and last[-1]["content"].startswith("rejected at stage parse: ")
    assert "\nthe plan is " in last[-1]["content"]


# Tool call ids


def test_every_tool_call_gets_an_id_of_its_own_and_its_result_refers_to_it() -> None:
    given: list[Any] = [None, "", 7, "a", "a", "call_6", {"id": "x"}, "  b", None]
    calls = normalize_calls([{"id": i, "function": {"name": "say", "arguments": "{}"}} for i in given])
    ids = [c["id"] for c in calls]
    assert all(isinstance(i, str) and i for i in ids) and len(set(ids)) == len(ids), ids
    assert ids[:4] == ["call_0", "call_1", "call_2", "a"] and ids[5] == "call_6" and ids[7] == "  b"
    messages = feedback_messages(ChatReply("", calls).message(), Stage.PARSE, "bad")
    assert [m["tool_call_id"] for m in messages[1:]] == ids
    typed = normalize_calls([{"type": None, "function": {"name": "say"}}, {"type": "function"}])
    assert [c["type"] for c in typed] == ["function", "function"]


# URLs


def test_a_url_httpx_cannot_use_is_refused_at_start_without_its_credentials() -> None:
    with pytest.raises(NotConfigured, match=r"\[planner\] url http://\[::1/v1/chat/completions is not a valid URL"):
        resolve_endpoint(PlannerConfig(url="http://[::1/v1", model="m"), {})
    with pytest.raises(NotConfigured) as caught:
        resolve_endpoint(
            PlannerConfig(), {"TETHER_LLM_URL": "http://bob:hunter2@[::1/v1?key=SECRETKEY", "TETHER_LLM_MODEL": "m"}
        )
    assert "TETHER_LLM_URL" in str(caught.value)
    assert "hunter2" not in str(caught.value) and "SECRETKEY" not in str(caught.value)
    with pytest.raises(NotConfigured, match="port 99999"):
        resolve_endpoint(PlannerConfig(url="http://127.0.0.1:99999/v1", model="m"), {})


def test_a_url_httpx_cannot_use_is_an_llm_error_from_chat() -> None:
    client = ChatClient(Endpoint(url="http://bob:hunter2@[::1/v1?key=SECRETKEY", model="m", timeout=2))
    message = failure(client)
    assert "is not a valid URL" in message
    assert "hunter2" not in message and "SECRETKEY" not in message


def test_the_missing_model_error_leaves_out_the_urls_credentials() -> None:
    with pytest.raises(NotConfigured, match="has no model") as caught:
        resolve_endpoint(
            PlannerConfig(), {"TETHER_LLM_URL": "https://bob:hunter2@llm.example.com/v1?api-key=SECRETKEY"}
        )
    assert "hunter2" not in str(caught.value) and "SECRETKEY" not in str(caught.value)
    assert "https://llm.example.com/v1" in str(caught.value)
