"""Tool calls as plans, in the shapes the OpenAI, Anthropic, Gemini and MCP APIs return (README: "Shapes it reads")."""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from schemas.plan import SourceFormat
from services.parser.errors import ParseError, kind_of

# Arguments given as a JSON string (OpenAI) are decoded with this; it raises ParseError.
Decode = Callable[[str, str], tuple[Any, list[str]]]

SHOWN_CHARS = 60
MAX_LABELS = 5

# OpenAI Responses output items that are calls, with the field that holds their arguments; a custom
# tool's input is free text unless the model wrote a JSON object there.
_RESPONSES_CALLS = {"function_call": ("arguments", False), "custom_tool_call": ("input", True)}
# Items the platform ran itself (hosted tools, remote MCP servers): done already, not steps.
_RESPONSES_HOSTED = {
    "web_search_call",
    "file_search_call",
    "code_interpreter_call",
    "image_generation_call",
    "mcp_call",
    "mcp_list_tools",
}
# Anthropic blocks the API ran on its side (server tools, the MCP connector) and their results.
_ANTHROPIC_HOSTED = {"server_tool_use", "mcp_tool_use"}
_ANTHROPIC_THINKING = {"thinking", "redacted_thinking"}
# Why a stop reason means the calls cannot be trusted to be all the model meant.
_CUT_OFF = "its output may be cut off; ask again with a larger token limit"
_ANTHROPIC_STOPS = {
    "max_tokens": _CUT_OFF,
    "model_context_window_exceeded": _CUT_OFF,
    "refusal": "the model refused",
    "pause_turn": "the turn was paused before it finished; send the finished response",
}
_CHAT_STOPS = {"length": _CUT_OFF, "content_filter": "a content filter stopped the output"}
_GEMINI_STOPS = {
    "MAX_TOKENS": _CUT_OFF,
    "MALFORMED_FUNCTION_CALL": "the model wrote a function call the API could not read",
}
# Gemini part fields that only describe the part (REST and Python SDK spellings).
_GEMINI_METADATA = {
    "thought",
    "thoughtSignature",
    "thought_signature",
    "partMetadata",
    "part_metadata",
    "videoMetadata",
    "video_metadata",
    "mediaResolution",
    "media_resolution",
}
# Gemini part fields that are no step, and why they are skipped.
_GEMINI_SKIPPED = {
    "executableCode": "code Gemini's code execution ran",
    "codeExecutionResult": "code Gemini's code execution ran",
    "functionResponse": "a function's result, not a call",
    "inlineData": "media, not a step",
    "fileData": "media, not a step",
}


@functools.cache
def _snake(name: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()


def _get(obj: dict[Any, Any], camel: str) -> Any:
    """A Gemini field by its REST (camelCase) or Python SDK (snake_case) name; null is absent."""
    value = obj.get(camel)
    return obj.get(_snake(camel)) if value is None else value


def _shown(value: object) -> str:
    text = value if isinstance(value, str) else repr(value)
    return repr(text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS] + "...")


def _type(item: Any) -> str | None:
    kind = item.get("type") if isinstance(item, dict) else None
    return kind if isinstance(kind, str) else None


@dataclass
class ToolCall:
    name: Any
    arguments: Any
    where: str
    # A custom tool's input (OpenAI): free text, read only when it holds a JSON object.
    free_text: bool = False


@dataclass
class ToolCalls:
    """The calls found in a value, in order, and the model's text around them."""

    format: SourceFormat
    calls: list[ToolCall] = field(default_factory=list)
    text: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    _skipped: dict[str, list[str]] = field(default_factory=dict)

    def skip(self, where: str, why: str) -> None:
        self._skipped.setdefault(why, []).append(where)

    def done(self) -> ToolCalls:
        for why, labels in self._skipped.items():
            shown = ", ".join(labels[:MAX_LABELS])
            more = f" and {len(labels) - MAX_LABELS} more" if len(labels) > MAX_LABELS else ""
            self.warnings.append(f"{shown}{more} skipped: {why}")
        self._skipped = {}
        return self


# OpenAI Chat Completions: {"choices": [{"message": ...}]}, a message, or its tool_calls list.


def _is_chat_call(item: Any) -> bool:
    kind = _type(item)
    return (kind == "function" and isinstance(item.get("function"), dict)) or (
        kind == "custom" and isinstance(item.get("custom"), dict)
    )


def _chat_call(item: Any, number: int) -> ToolCall:
    where = f"tool call {number}"
    if not isinstance(item, dict):
        raise ParseError(f"{where} is {kind_of(item)}, not an object")
    kind = item.get("type", "function")
    if kind == "custom":
        custom = item.get("custom")
        if not isinstance(custom, dict):
            raise ParseError(f"{where} (custom) has no 'custom' object")
        return ToolCall(custom.get("name"), custom.get("input"), f"{where} (custom)", free_text=True)
    if kind != "function":
        raise ParseError(f"{where} has type {_shown(kind)}; expected 'function' (or 'custom')")
    function = item.get("function")
    if not isinstance(function, dict):
        raise ParseError(f"{where} has no 'function' object")
    return ToolCall(function.get("name"), function.get("arguments"), where)


def _chat_message(message: dict[Any, Any]) -> ToolCalls | None:
    tool_calls = message.get("tool_calls")
    function_call = message.get("function_call")
    if isinstance(tool_calls, list) and tool_calls:
        found = ToolCalls("openai_tool_calls", [_chat_call(c, i) for i, c in enumerate(tool_calls, 1)])
    elif isinstance(function_call, dict) and not _is_gemini_call(function_call):
        found = ToolCalls(
            "openai_function_call",
            [ToolCall(function_call.get("name"), function_call.get("arguments"), "function_call")],
        )
    else:
        return None
    refusal = message.get("refusal")
    if isinstance(refusal, str) and refusal.strip():
        raise ParseError(f"the model refused: {_shown(refusal)}")
    if isinstance(message.get("content"), str):
        found.text.append(message["content"])
    return found


def _chat_completion(choices: list[Any]) -> ToolCalls | None:
    choice = choices[0]
    message = choice.get("message")
    found = _chat_message(message) if isinstance(message, dict) else None
    if found is None:
        return None
    stop = choice.get("finish_reason")
    if isinstance(stop, str) and stop in _CHAT_STOPS:
        raise ParseError(f"choice 1 stopped with finish_reason {_shown(stop)}: {_CHAT_STOPS[stop]}")
    if len(choices) > 1:
        found.warnings.append(f"only the first of {len(choices)} choices was read")
    return found


# OpenAI Responses: {"object": "response", "output": [...]}, or the output list.


def _is_responses_output(items: list[Any]) -> bool:
    return any(_type(item) in _RESPONSES_CALLS for item in items)


def _responses_message(item: dict[Any, Any], where: str, found: ToolCalls) -> None:
    role = item.get("role")
    if role not in (None, "assistant"):
        raise ParseError(f"{where} is a {_shown(role)} message; send the model's response, not the conversation")
    content = item.get("content")
    if isinstance(content, str):
        found.text.append(content)
        return
    for part in content if isinstance(content, list) else []:
        kind = _type(part)
        if kind == "refusal":
            raise ParseError(f"{where}: the model refused: {_shown(part.get('refusal'))}")
        if kind in ("output_text", "text") and isinstance(part.get("text"), str):
            found.text.append(part["text"])


def _responses_output(items: list[Any]) -> ToolCalls:
    found = ToolCalls("openai_responses")
    answered: dict[str, int] = {}  # call_id -> the output item that holds its result
    call_ids: dict[str, str] = {}  # call_id -> where the call is
    for number, item in enumerate(items, 1):
        label = f"output item {number}"
        if not isinstance(item, dict):
            raise ParseError(f"{label} is {kind_of(item)}, not an object")
        kind = _type(item)
        if kind is None:
            raise ParseError(f"{label} has no 'type'")
        where = f"{label} ({kind[:SHOWN_CHARS]})"
        if kind in _RESPONSES_CALLS:
            status = item.get("status")
            if status not in (None, "completed"):
                raise ParseError(
                    f"{where} has status {_shown(status)}: its arguments may be incomplete; only completed calls run"
                )
            arguments, free_text = _RESPONSES_CALLS[kind]
            found.calls.append(ToolCall(item.get("name"), item.get(arguments), where, free_text=free_text))
            if isinstance(item.get("call_id"), str):
                call_ids[item["call_id"]] = where
        elif kind == "message":
            _responses_message(item, where, found)
        elif kind == "reasoning":
            continue  # the model's reasoning is never read as steps
        elif kind.endswith("_output"):
            if isinstance(item.get("call_id"), str):
                answered[item["call_id"]] = number
            found.skip(where, "a tool's result, not a call")
        elif kind in _RESPONSES_HOSTED:
            found.skip(where, "the platform ran it itself")
        else:
            raise ParseError(
                f"{where} is not a call the robot can run: a plan's steps are function_call items "
                "(message, reasoning and the platform's own tool items are skipped)"
            )
    for call_id, where in call_ids.items():
        if call_id in answered:
            raise ParseError(
                f"{where} already has its result in output item {answered[call_id]}; "
                "send the model's latest response, not the conversation"
            )
    return found.done()


def _responses(value: dict[Any, Any]) -> ToolCalls:
    status = value.get("status")
    if status not in (None, "completed"):
        details = value.get("incomplete_details")
        error = value.get("error")
        reason = details.get("reason") if isinstance(details, dict) else None
        reason = reason or (error.get("message") if isinstance(error, dict) else None)
        why = f" ({_shown(reason)})" if reason else ""
        cut = "; was the output cut off?" if reason == "max_output_tokens" else ""
        raise ParseError(f"the response's status is {_shown(status)}{why}: only a completed response runs{cut}")
    output = value.get("output")
    if not isinstance(output, list):
        raise ParseError(f"the response's 'output' must be an array of items, got {kind_of(output)}")
    found = _responses_output(output)
    if not found.calls:
        hint = "; if its message text is the plan, send that text" if found.text else ""
        raise ParseError(f"the response holds no function_call items{hint}")
    return found


# Anthropic Messages: {"type": "message", "content": [...]}, the content list, or one tool_use block.


def _is_anthropic(blocks: list[Any]) -> bool:
    return any(_type(block) == "tool_use" for block in blocks)


def _anthropic(blocks: list[Any]) -> ToolCalls:
    found = ToolCalls("anthropic_tool_use")
    for number, block in enumerate(blocks, 1):
        label = f"content block {number}"
        kind = _type(block)
        if kind is None:
            raise ParseError(f"{label} is not a content block (an object with a 'type')")
        where = f"{label} ({kind[:SHOWN_CHARS]})"
        if kind == "tool_use":
            found.calls.append(ToolCall(block.get("name"), block.get("input"), where))
        elif kind == "text":
            if isinstance(block.get("text"), str):
                found.text.append(block["text"])
        elif kind in _ANTHROPIC_THINKING:
            continue  # the model's reasoning is never read as steps
        elif kind in _ANTHROPIC_HOSTED or kind.endswith("_tool_result"):
            found.skip(where, "the API ran it on its side")
        else:
            raise ParseError(f"{where} is neither a tool_use nor a text block; the robot cannot run it")
    return found.done()


def _anthropic_message(value: dict[Any, Any]) -> ToolCalls:
    stop = value.get("stop_reason")
    if isinstance(stop, str) and stop in _ANTHROPIC_STOPS:
        raise ParseError(f"the message stopped with stop_reason {_shown(stop)}: {_ANTHROPIC_STOPS[stop]}")
    return _anthropic(value["content"])


# Gemini generateContent: {"candidates": [{"content": {"parts": [...]}}]}, a content, or its parts.


def _is_gemini_call(call: dict[Any, Any]) -> bool:
    """A Python SDK function_call ({"name", "args"}), not OpenAI's legacy one ({"name", "arguments"})."""
    return "args" in call and "arguments" not in call


def _is_gemini_part(item: Any) -> bool:
    return isinstance(item, dict) and isinstance(_get(item, "functionCall"), dict)


def _gemini_parts(parts: list[Any]) -> ToolCalls:
    found = ToolCalls("gemini_function_call")
    for number, part in enumerate(parts, 1):
        label = f"part {number}"
        if not isinstance(part, dict):
            raise ParseError(f"{label} is {kind_of(part)}, not an object")
        if _get(part, "thought") is True:
            continue  # a thought summary: the model's reasoning is never read as steps
        call = _get(part, "functionCall")
        if call is not None:
            where = f"{label} (functionCall)"
            if not isinstance(call, dict):
                raise ParseError(f"{where} is {kind_of(call)}, not an object")
            if _get(call, "willContinue") is True or _get(call, "partialArgs") is not None:
                raise ParseError(f"{where} is one piece of a streamed call; send the whole response")
            found.calls.append(ToolCall(call.get("name"), call.get("args"), where))
            continue
        if isinstance(part.get("text"), str):
            found.text.append(part["text"])
            continue
        skipped = next((name for name in _GEMINI_SKIPPED if _get(part, name) is not None), None)
        # The part's own keys, as given: any of them (even a YAML number) may be there.
        if skipped is None and all(value is None for k, value in part.items() if k not in _GEMINI_METADATA):
            continue  # only metadata (a thought signature): nothing to run or read
        if skipped is None:
            keys = ", ".join(_shown(k) for k in list(part)[:MAX_LABELS]) or "none"
            raise ParseError(f"{label} holds neither a functionCall nor text (its keys: {keys})")
        found.skip(f"{label} ({skipped})", _GEMINI_SKIPPED[skipped])
    return found.done()


def _gemini_content(content: dict[Any, Any], where: str) -> ToolCalls:
    role = content.get("role")
    if role not in (None, "model"):
        raise ParseError(f"{where} has role {_shown(role)}; send the model's response, not the conversation")
    parts = content.get("parts")
    if not isinstance(parts, list):
        raise ParseError(f"{where} has no 'parts' array")
    return _gemini_parts(parts)


def _is_gemini_response(value: dict[Any, Any]) -> bool:
    candidates = value.get("candidates")
    if not isinstance(candidates, list):
        return False
    if not candidates:
        return _get(value, "promptFeedback") is not None
    first = candidates[0]
    return isinstance(first, dict) and any(_get(first, k) is not None for k in ("content", "finishReason"))


def _gemini_response(value: dict[Any, Any]) -> ToolCalls:
    candidates = value["candidates"]
    if not candidates:
        feedback = _get(value, "promptFeedback")
        blocked = _get(feedback, "blockReason") if isinstance(feedback, dict) else None
        raise ParseError(
            "the response has no candidates" + (f" (the prompt was blocked: {_shown(blocked)})" if blocked else "")
        )
    candidate = candidates[0]
    stop = _get(candidate, "finishReason")
    if stop not in (None, "STOP"):
        why = _GEMINI_STOPS.get(stop, "only a candidate that finished (STOP) runs") if isinstance(stop, str) else ""
        raise ParseError(f"candidate 1 stopped with finishReason {_shown(stop)}: {why}")
    content = candidate.get("content")
    if not isinstance(content, dict):
        raise ParseError("candidate 1 has no 'content' object")
    found = _gemini_content(content, "candidate 1's content")
    if not found.calls:
        hint = "; if its text is the plan, send that text" if found.text else ""
        raise ParseError(f"candidate 1 holds no functionCall parts{hint}")
    if len(candidates) > 1:
        found.warnings.append(f"only the first of {len(candidates)} candidates was read")
    return found


# MCP: a tools/call JSON-RPC request, or a batch of them.


def _is_mcp(item: Any) -> bool:
    return isinstance(item, dict) and item.get("method") == "tools/call"


def _mcp(requests: list[Any]) -> ToolCalls:
    found = ToolCalls("mcp_tools_call")
    for number, request in enumerate(requests, 1):
        where = f"tools/call request {number}"
        if not _is_mcp(request):
            method = request.get("method") if isinstance(request, dict) else None
            raise ParseError(
                f"request {number} of the batch is not a tools/call request (method {_shown(method)}); "
                "only tools/call requests are steps"
            )
        params = request.get("params")
        if not isinstance(params, dict):
            raise ParseError(f"{where} has no 'params' object")
        found.calls.append(ToolCall(params.get("name"), params.get("arguments"), where))
    return found


# Which shape a value has


def _from_list(value: list[Any]) -> ToolCalls | None:
    if all(_is_chat_call(v) for v in value):
        return ToolCalls("openai_tool_calls", [_chat_call(c, i) for i, c in enumerate(value, 1)])
    if _is_responses_output(value):
        return _responses_output(value)
    if any(_is_mcp(v) for v in value):
        return _mcp(value)
    if _is_anthropic(value):
        return _anthropic(value)
    if any(_is_gemini_part(v) for v in value):
        return _gemini_parts(value)
    return None


def _from_dict(value: dict[Any, Any]) -> ToolCalls | None:
    choices = value.get("choices")
    if isinstance(choices, list) and choices and isinstance(choices[0], dict):
        return _chat_completion(choices)
    output = value.get("output")
    if value.get("object") == "response" or (isinstance(output, list) and _is_responses_output(output)):
        return _responses(value)
    if _is_gemini_response(value):
        return _gemini_response(value)
    found = _chat_message(value)
    if found is not None:
        return found
    if _is_gemini_part(value):
        return _gemini_parts([value])
    if _is_mcp(value):
        return _mcp([value])
    content = value.get("content")
    if isinstance(content, list) and _is_anthropic(content):
        return _anthropic_message(value)
    parts = value.get("parts")
    if isinstance(parts, list) and any(_is_gemini_part(p) for p in parts):
        return _gemini_content(value, "the content")
    kind = _type(value)
    if kind == "tool_use":
        return _anthropic([value])
    if kind in _RESPONSES_CALLS:
        return _responses_output([value])
    return None


def find_tool_calls(value: Any) -> ToolCalls | None:
    """The tool calls in a decoded JSON/YAML value, or None when it is not tool-call shaped.

    Raises ParseError when the value has a tool-call shape that cannot be run as it stands.
    """
    if isinstance(value, list):
        return _from_list(value) if value else None
    if isinstance(value, dict):
        return _from_dict(value)
    return None


def call_arguments(call: ToolCall, decode: Decode) -> tuple[dict[Any, Any], list[str]]:
    """The call's arguments as an object: decoded from a JSON string where needed."""
    arguments: Any = call.arguments
    warnings: list[str] = []
    if arguments is None:
        return {}, []
    if isinstance(arguments, str):
        if not arguments.strip():
            return {}, []
        try:
            arguments, warnings = decode(arguments, call.where)
        except ParseError:
            if not call.free_text or arguments.lstrip().startswith("{"):
                raise
            raise ParseError(
                f"{call.where}: its input is free text, not a JSON object of arguments; "
                "declare the robot's tools as function tools"
            ) from None
    if not isinstance(arguments, dict):
        raise ParseError(f"{call.where}: arguments must be an object")
    return arguments, warnings
