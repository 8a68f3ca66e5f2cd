"""Tool calls as plans: OpenAI tool_calls / function_call, Anthropic tool_use, MCP tools/call.

Each call becomes one step: the tool's name is the action and its arguments are the step's fields
and parameters. A call to a plan tool (execute_plan) carries a whole plan in its arguments.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from schemas.plan import SourceFormat
from services.parser.errors import ParseError

# Arguments given as a JSON string (OpenAI) are decoded with this; it raises ParseError.
Decode = Callable[[str, str], tuple[Any, list[str]]]


@dataclass
class ToolCall:
    name: Any
    arguments: Any
    where: str


@dataclass
class ToolCalls:
    """The calls found in a value, in order, and the model's text around them."""

    format: SourceFormat
    calls: list[ToolCall]
    text: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _openai_calls(items: list[Any]) -> list[ToolCall]:
    calls = []
    for i, item in enumerate(items):
        function = item.get("function") if isinstance(item, dict) else None
        if not isinstance(function, dict):
            raise ParseError(f"tool call {i + 1} has no 'function' object")
        calls.append(ToolCall(function.get("name"), function.get("arguments"), f"tool call {i + 1}"))
    return calls


def _is_openai_call(item: Any) -> bool:
    return isinstance(item, dict) and item.get("type") == "function" and isinstance(item.get("function"), dict)


def _is_block(item: Any) -> bool:
    return isinstance(item, dict) and item.get("type") in ("tool_use", "text")


def _anthropic(blocks: list[Any]) -> ToolCalls | None:
    if not blocks or not all(_is_block(b) for b in blocks):
        return None
    found = ToolCalls("anthropic_tool_use", [])
    for block in blocks:
        if block["type"] == "text":
            if isinstance(block.get("text"), str):
                found.text.append(block["text"])
        else:
            found.calls.append(
                ToolCall(block.get("name"), block.get("input"), f"tool_use block {len(found.calls) + 1}")
            )
    return found if found.calls else None


def _is_mcp(item: Any) -> bool:
    return isinstance(item, dict) and item.get("method") == "tools/call"


def _mcp(requests: list[Any]) -> ToolCalls:
    found = ToolCalls("mcp_tools_call", [])
    for i, request in enumerate(requests):
        params = request.get("params")
        if not isinstance(params, dict):
            raise ParseError(f"tools/call request {i + 1} has no 'params' object")
        found.calls.append(ToolCall(params.get("name"), params.get("arguments"), f"tools/call request {i + 1}"))
    return found


def find_tool_calls(value: Any) -> ToolCalls | None:
    """The tool calls in a decoded JSON/YAML value, or None when it is not tool-call shaped."""
    if isinstance(value, list):
        if value and all(_is_openai_call(v) for v in value):
            return ToolCalls("openai_tool_calls", _openai_calls(value))
        if value and all(_is_mcp(v) for v in value):
            return _mcp(value)
        return _anthropic(value)
    if not isinstance(value, dict):
        return None
    choices = value.get("choices")
    if isinstance(choices, list) and choices and isinstance(choices[0], dict):
        message = choices[0].get("message")
        found = find_tool_calls(message) if isinstance(message, dict) else None
        if found is not None and len(choices) > 1:
            found.warnings.append(f"only the first of {len(choices)} choices was read")
        return found
    if isinstance(value.get("tool_calls"), list) and value["tool_calls"]:
        found = ToolCalls("openai_tool_calls", _openai_calls(value["tool_calls"]))
        if isinstance(value.get("content"), str):
            found.text.append(value["content"])
        return found
    function_call = value.get("function_call")
    if isinstance(function_call, dict):
        call = ToolCall(function_call.get("name"), function_call.get("arguments"), "function_call")
        return ToolCalls("openai_function_call", [call])
    if _is_mcp(value):
        return _mcp([value])
    if isinstance(value.get("content"), list):
        return _anthropic(value["content"])
    if value.get("type") == "tool_use":
        return _anthropic([value])
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
        arguments, warnings = decode(arguments, call.where)
    if not isinstance(arguments, dict):
        raise ParseError(f"{call.where}: arguments must be an object")
    return arguments, warnings
