"""A client for OpenAI-compatible chat completions (Ollama, llama.cpp server, vLLM, hosted ones)."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import httpx2 as httpx

from schemas.plan import MAX_STEPS
from services.planner.config import Endpoint
from services.planner.errors import LLMError

log = logging.getLogger(__name__)
# httpx logs each request's full URL at INFO, and a URL may carry a key (?key=, user:password@).
logging.getLogger("httpx2").setLevel(logging.WARNING)

# How much of a bad answer goes into an error message.
SNIPPET = 300
# finish_reason values saying the answer stopped at the token limit, not where the model meant to end.
CUT_OFF = frozenset({"length", "max_tokens"})

# Takes the key out of a text (ChatClient._scrub); before any cut, so that no part of the key is left.
Scrub = Callable[[str], str]


def _as_is(text: str) -> str:
    return text


@dataclass(frozen=True)
class ChatReply:
    """The assistant's message: its text and its tool calls (OpenAI shape), as the model gave them."""

    content: str = ""
    tool_calls: list[dict[str, Any]] = field(default_factory=list)

    def message(self) -> dict[str, Any]:
        """The reply as an assistant message, to go back into the conversation."""
        out: dict[str, Any] = {"role": "assistant", "content": self.content or None}
        if self.tool_calls:
            out["tool_calls"] = self.tool_calls
        return out


class CallDeadline:
    """Cuts one call's connection once `seconds` have passed without the whole answer. httpx's timeout is
    per read: an endpoint sending its headers or its body a byte at a time would never reach it, and the
    read blocks the caller's thread, so the cut comes from a timer's thread. The sockets are named by
    httpcore's trace (the client keeps no idle connection, so each call connects anew)."""

    # The trace events whose return value is the call's network stream: after the TCP connect and after TLS.
    STREAMS = frozenset({"connection.connect_tcp.complete", "connection.start_tls.complete"})

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.expired = False
        self._sockets: list[socket.socket] = []
        self._ended = False
        self._lock = threading.Lock()
        self._timer = threading.Timer(seconds, self._cut)
        self._timer.daemon = True

    def trace(self, event: str, info: dict[str, Any]) -> None:
        """httpcore's `trace` extension."""
        if event not in self.STREAMS:
            return
        stream = info.get("return_value")
        sock = stream.get_extra_info("socket") if stream is not None else None
        if not isinstance(sock, socket.socket):
            return
        with self._lock:
            self._sockets.append(sock)
            expired = self.expired
        if expired:  # the time ran out while it connected
            _shut(sock)

    def _cut(self) -> None:
        with self._lock:
            if self._ended:
                return
            self.expired = True
            sockets = list(self._sockets)
        for sock in sockets:
            _shut(sock)

    def __enter__(self) -> CallDeadline:
        self._timer.start()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, traceback: TracebackType | None
    ) -> None:
        with self._lock:
            self._ended = True
        self._timer.cancel()


def _shut(sock: socket.socket) -> None:
    # shutdown, not close: it wakes the read blocked in the caller's thread at once, and frees no file
    # descriptor that another thread could be given while that read still uses it. The plain socket's
    # method also for a TLS one: ssl.SSLSocket.shutdown would drop its SSL object under the reading thread.
    with contextlib.suppress(OSError):  # already closed: the call ended meanwhile
        socket.socket.shutdown(sock, socket.SHUT_RDWR)


class ChatClient:
    """Calls one endpoint. Every failure is an LLMError naming what was wrong; the key never shows."""

    def __init__(self, endpoint: Endpoint, transport: httpx.BaseTransport | None = None) -> None:
        self.endpoint = endpoint
        headers = {"Accept": "application/json", "Content-Type": "application/json"}
        if endpoint.api_key is not None:
            headers["Authorization"] = f"Bearer {endpoint.api_key.reveal()}"
        # No idle connections kept: each call connects, so CallDeadline knows the socket to cut.
        limits = httpx.Limits(max_keepalive_connections=0)
        self._http = httpx.Client(timeout=endpoint.timeout, headers=headers, transport=transport, limits=limits)

    def close(self) -> None:
        self._http.close()

    def _scrub(self, text: str) -> str:
        key = self.endpoint.api_key
        if key is not None and key.reveal():
            text = text.replace(key.reveal(), "***")
        return text

    def _fail(self, message: str) -> LLMError:
        return LLMError(self._scrub(message))

    def chat(self, messages: list[dict[str, Any]], tools: list[dict[str, Any]] | None = None) -> ChatReply:
        ep = self.endpoint
        body: dict[str, Any] = {
            "model": ep.model,
            "messages": messages,
            "temperature": ep.temperature,
            "stream": False,
        }
        if tools:
            body["tools"] = tools
        where = ep.shown_url
        try:
            # As httpx would encode it. NaN or Infinity (a model's 1e999, fed back) is no JSON: named here.
            payload = json.dumps(body, ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode()
        except (ValueError, TypeError, RecursionError) as exc:
            raise self._fail(f"the request to the LLM endpoint {where} cannot be encoded as JSON: {exc}") from None
        try:
            status, content_type, raw = self._post(payload)
        except httpx.TimeoutException:
            raise self._fail(f"the LLM endpoint {where} did not answer within {ep.timeout:g} s") from None
        except httpx.ConnectError as exc:
            raise self._fail(f"cannot connect to the LLM endpoint {where}: {exc}") from None
        except httpx.HTTPError as exc:
            raise self._fail(f"the request to the LLM endpoint {where} failed: {type(exc).__name__}: {exc}") from None
        except httpx.InvalidURL:  # not an HTTPError; an Endpoint made without resolve_endpoint's check
            raise self._fail(f"the LLM endpoint {where} is not a valid URL: {ep.url_error()}") from None
        if status >= 400:
            detail = error_detail(raw, self._scrub)
            hint = ""
            if status in (401, 403):
                hint = (
                    f" (check the API key in ${ep.key_source})"
                    if ep.key_source
                    else " (no API key was sent: set TETHER_LLM_API_KEY or [planner] api_key_env)"
                )
            raise self._fail(f"the LLM endpoint {where} answered HTTP {status}{hint}: {detail}")
        try:
            data = json.loads(raw)
        except (ValueError, UnicodeDecodeError, RecursionError):  # RecursionError: nested too deep to be a reply
            raise self._fail(
                f"the LLM endpoint {where} answered with something that is not JSON ({content_type}): "
                f"{snippet(raw, self._scrub)}"
            ) from None
        try:
            reply = parse_completion(data, where, self._scrub)
        except LLMError as exc:  # an `error` body or a refusal may echo the key
            raise self._fail(str(exc)) from None
        return self._scrubbed_reply(reply)

    def _post(self, payload: bytes) -> tuple[int, str, bytes]:
        """Status, content type and body. The body is read as it comes and refused once it passes
        max_reply_bytes; the whole call (connect, headers, body) is cut once it has taken longer than the
        timeout (CallDeadline), also when the endpoint sends a byte at a time."""
        ep = self.endpoint

        def late() -> LLMError:
            return self._fail(
                f"the LLM endpoint {ep.shown_url} did not answer within {ep.timeout:g} s (no whole answer)"
            )

        deadline = time.monotonic() + ep.timeout
        with CallDeadline(ep.timeout) as cut:
            try:
                with self._http.stream(
                    "POST", ep.chat_url, content=payload, extensions={"trace": cut.trace}
                ) as response:
                    chunks: list[bytes] = []
                    size = 0
                    for chunk in response.iter_bytes():
                        size += len(chunk)
                        if size > ep.max_reply_bytes:
                            raise self._fail(
                                f"the LLM endpoint {ep.shown_url} answered more than {ep.max_reply_bytes} bytes "
                                "(the limit)"
                            )
                        # Also here: a transport given to the client has no socket CallDeadline could cut.
                        if time.monotonic() > deadline:
                            raise late()
                        chunks.append(chunk)
                    if cut.expired or time.monotonic() > deadline:
                        raise late()
                    content_type = response.headers.get("content-type", "no content type")
                    return response.status_code, content_type, b"".join(chunks)
            except LLMError:
                raise
            except Exception:
                if cut.expired:  # whatever the cut connection raised (disconnected, reset, a read error)
                    raise late() from None
                raise

    def _scrubbed_reply(self, reply: ChatReply) -> ChatReply:
        # A model that echoes its own Authorization header must not get the key into a recording.
        key = self.endpoint.api_key
        if key is None or not key.reveal():
            return reply
        text = json.dumps(reply.tool_calls)
        if key.reveal() not in reply.content and key.reveal() not in text:
            return reply
        return ChatReply(self._scrub(reply.content), json.loads(self._scrub(text)))


def snippet(raw: bytes, scrub: Scrub = _as_is) -> str:
    """The start of a body, for a message: scrubbed whole, then cut (a key across the cut would show but its end)."""
    text = scrub(raw.decode(errors="replace")).strip()
    if not text:
        return "(an empty body)"
    return repr(text[:SNIPPET]) + ("..." if len(text) > SNIPPET else "")


def error_detail(raw: bytes, scrub: Scrub = _as_is) -> str:
    """The `error.message` of an OpenAI-style error body, else the start of the body; scrubbed, then cut."""
    try:
        data = json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return snippet(raw, scrub)
    if isinstance(data, dict):
        error = data.get("error")
        if isinstance(error, dict) and isinstance(error.get("message"), str):
            return scrub(error["message"])[:SNIPPET]
        if isinstance(error, str):
            return scrub(error)[:SNIPPET]
    return snippet(raw, scrub)


def parse_completion(data: Any, where: str, scrub: Scrub = _as_is) -> ChatReply:
    """The first choice's message of a chat-completions answer; LLMError for any other shape, for an
    answer cut at the token limit, for more tool calls than a plan has steps, and for a refusal. `scrub`
    takes the key out of what the endpoint wrote before it is cut for the message."""
    if not isinstance(data, dict):
        raise LLMError(f"the LLM endpoint {where} answered JSON that is not an object: {type(data).__name__}")
    choices = data.get("choices")
    if not isinstance(choices, list) or not choices:
        error = data.get("error")
        detail = f": {error_detail(json.dumps(data).encode(), scrub)}" if error else ""
        raise LLMError(f"the LLM endpoint {where} answered with no choices{detail}")
    choice = choices[0]
    message = choice.get("message") if isinstance(choice, dict) else None
    if not isinstance(message, dict):
        raise LLMError(f"the LLM endpoint {where} answered a choice with no message")
    refusal = message.get("refusal")
    if isinstance(refusal, str) and refusal.strip():
        raise LLMError(f"the model refused: {scrub(refusal.strip())[:SNIPPET]}")
    finish = choice.get("finish_reason")
    if finish in CUT_OFF:
        # Cut at a line end, the first steps of a plan parse as a whole plan: the robot would run a prefix of it.
        raise LLMError(
            f"the LLM endpoint {where}: the answer was cut at the model's token limit (finish_reason {finish}): "
            "raise max_tokens (or the context size) on the server"
        )
    content = message.get("content")
    if isinstance(content, list):  # content parts
        content = "".join(p.get("text", "") for p in content if isinstance(p, dict) and isinstance(p.get("text"), str))
    if content is not None and not isinstance(content, str):
        raise LLMError(f"the LLM endpoint {where} answered a message whose content is a {type(content).__name__}")
    tool_calls = message.get("tool_calls") or []
    if not isinstance(tool_calls, list) or not all(isinstance(c, dict) for c in tool_calls):
        raise LLMError(f"the LLM endpoint {where} answered tool_calls that are not a list of objects")
    if len(tool_calls) > MAX_STEPS:
        # Not a plan (it holds at most MAX_STEPS steps), and each call would want its own tool result in the
        # conversation: 100,000 empty calls (300 KB) made every later request 22 MB bigger.
        raise LLMError(
            f"the LLM endpoint {where} answered {len(tool_calls)} tool calls; a plan holds at most {MAX_STEPS} "
            "steps (split the task)"
        )
    if not tool_calls and isinstance(message.get("function_call"), dict):
        # The legacy single function call.
        tool_calls = [{"id": "call_0", "type": "function", "function": message["function_call"]}]
    if finish == "content_filter" and not content and not tool_calls:
        raise LLMError(f"the LLM endpoint {where} filtered the model's answer (finish_reason content_filter)")
    return ChatReply(content or "", tool_calls)
