"""A client for OpenAI-compatible chat completions (Ollama, llama.cpp server, vLLM, hosted ones)."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import httpx2 as httpx

from services.planner.config import Endpoint
from services.planner.errors import LLMError

log = logging.getLogger(__name__)
# httpx logs each request's full URL at INFO, and a URL may carry a key (?key=, user:password@).
logging.getLogger("httpx2").setLevel(logging.WARNING)

# How much of a bad answer goes into an error message.
SNIPPET = 300


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


class ChatClient:
    """Calls one endpoint. Every failure is an LLMError naming what was wrong; the key never shows."""

    def __init__(self, endpoint: Endpoint, transport: httpx.BaseTransport | None = None) -> None:
        self.endpoint = endpoint
        headers = {"Accept": "application/json"}
        if endpoint.api_key is not None:
            headers["Authorization"] = f"Bearer {endpoint.api_key.reveal()}"
        self._http = httpx.Client(timeout=endpoint.timeout, headers=headers, transport=transport)

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
            status, content_type, raw = self._post(body)
        except httpx.TimeoutException:
            raise self._fail(f"the LLM endpoint {where} did not answer within {ep.timeout:g} s") from None
        except httpx.ConnectError as exc:
            raise self._fail(f"cannot connect to the LLM endpoint {where}: {exc}") from None
        except httpx.HTTPError as exc:
            raise self._fail(f"the request to the LLM endpoint {where} failed: {type(exc).__name__}: {exc}") from None
        if status >= 400:
            detail = error_detail(raw)
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
                f"the LLM endpoint {where} answered with something that is not JSON ({content_type}): {snippet(raw)}"
            ) from None
        return self._scrubbed_reply(parse_completion(data, where))

    def _post(self, body: dict[str, Any]) -> tuple[int, str, bytes]:
        """Status, content type and body. The body is read as it comes and refused once it passes
        max_reply_bytes, or once the whole answer has taken longer than the timeout, checked as bytes
        arrive (httpx's timeout is per read: an endpoint sending a byte at a time would never reach
        it). A silent endpoint fails on httpx's read timeout, so a call ends within twice the timeout."""
        ep = self.endpoint
        deadline = time.monotonic() + ep.timeout
        with self._http.stream("POST", ep.chat_url, json=body) as response:
            chunks: list[bytes] = []
            size = 0
            for chunk in response.iter_bytes():
                size += len(chunk)
                if size > ep.max_reply_bytes:
                    raise self._fail(
                        f"the LLM endpoint {ep.shown_url} answered more than {ep.max_reply_bytes} bytes (the limit)"
                    )
                if time.monotonic() > deadline:
                    raise httpx.ReadTimeout("the answer did not end within the timeout")
                chunks.append(chunk)
            if time.monotonic() > deadline:
                raise httpx.ReadTimeout("the answer did not end within the timeout")
            return response.status_code, response.headers.get("content-type", "no content type"), b"".join(chunks)

    def _scrubbed_reply(self, reply: ChatReply) -> ChatReply:
        # A model that echoes its own Authorization header must not get the key into a recording.
        key = self.endpoint.api_key
        if key is None or not key.reveal():
            return reply
        text = json.dumps(reply.tool_calls)
        if key.reveal() not in reply.content and key.reveal() not in text:
            return reply
        return ChatReply(self._scrub(reply.content), json.loads(self._scrub(text)))


def snippet(raw: bytes) -> str:
    text = raw[:SNIPPET].decode(errors="replace").strip()
    return repr(text) + ("..." if len(raw) > SNIPPET else "") if text else "(an empty body)"


def error_detail(raw: bytes) -> str:
    """The `error.message` of an OpenAI-style error body, else the start of the body."""
    try:
        data = json.loads(raw)
    except (ValueError, UnicodeDecodeError):
        return snippet(raw)
    if isinstance(data, dict):
        error = data.get("error")
        if isinstance(error, dict) and isinstance(error.get("message"), str):
            return error["message"][:SNIPPET]
        if isinstance(error, str):
            return error[:SNIPPET]
    return snippet(raw)


def parse_completion(data: Any, where: str) -> ChatReply:
    """The first choice's message of a chat-completions answer; LLMError for any other shape."""
    if not isinstance(data, dict):
        raise LLMError(f"the LLM endpoint {where} answered JSON that is not an object: {type(data).__name__}")
    choices = data.get("choices")
    if not isinstance(choices, list) or not choices:
        error = data.get("error")
        detail = f": {error_detail(json.dumps(data).encode())}" if error else ""
        raise LLMError(f"the LLM endpoint {where} answered with no choices{detail}")
    choice = choices[0]
    message = choice.get("message") if isinstance(choice, dict) else None
    if not isinstance(message, dict):
        raise LLMError(f"the LLM endpoint {where} answered a choice with no message")
    refusal = message.get("refusal")
    if isinstance(refusal, str) and refusal.strip():
        raise LLMError(f"the model refused: {refusal.strip()[:SNIPPET]}")
    content = message.get("content")
    if isinstance(content, list):  # content parts
        content = "".join(p.get("text", "") for p in content if isinstance(p, dict) and isinstance(p.get("text"), str))
    if content is not None and not isinstance(content, str):
        raise LLMError(f"the LLM endpoint {where} answered a message whose content is a {type(content).__name__}")
    tool_calls = message.get("tool_calls") or []
    if not isinstance(tool_calls, list) or not all(isinstance(c, dict) for c in tool_calls):
        raise LLMError(f"the LLM endpoint {where} answered tool_calls that are not a list of objects")
    if not tool_calls and isinstance(message.get("function_call"), dict):
        # The legacy single function call.
        tool_calls = [{"id": "call_0", "type": "function", "function": message["function_call"]}]
    if choice.get("finish_reason") == "content_filter" and not content and not tool_calls:
        raise LLMError(f"the LLM endpoint {where} filtered the model's answer (finish_reason content_filter)")
    return ChatReply(content or "", tool_calls)
