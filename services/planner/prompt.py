"""The conversation sent to the model: instructions, the robot's capabilities, the tools, the scene as
data, the request; and the short message a refusal goes back as. Pure logic."""

from __future__ import annotations

import json
from typing import Any

from schemas.common import Stage
from services.agent.feedback import as_data

CAPABILITIES = """The robot: a mobile base carrying a 7-DOF arm with a parallel gripper, in a flat (kitchen,
living room, bedroom, office, hallway with stairs fenced off as a keep-out zone, a charging dock).
It can drive to rooms, furniture, objects and people, pick up an object it can lift and place it on
a surface, look, detect objects, turn, drive short distances and say things. Units are SI: metres, radians, seconds,
kilograms. Every plan is parsed, every name grounded in the world model and every motion checked by
a safety service before anything moves; a plan that is refused comes back to you with the reason."""

INSTRUCTIONS = """You turn a person's request into a plan for a robot. Answer with the plan only: either call
the tools, one call per step in order, or write one JSON object
{"plan": [{"action": "...", "target": "...", ...}, ...], "description": "..."}
using the actions the tools describe. Name things as the scene names them. Never plan into a keep-out
zone, never lift what is too heavy, never reset an emergency stop."""

# Scene text longer than this is cut: a prompt has room for a flat's worth of objects.
MAX_SCENE_CHARS = 8000


def scene_block(scene_text: str) -> str:
    """The scene marked as data, in the same block the MCP tools use (services.agent.feedback.as_data):
    nothing in the scene (an object's name, a label read by the camera) can close the block early."""
    return as_data("world model", scene_text.strip()[:MAX_SCENE_CHARS] or "(no scene available)")


def system_message(tools: list[dict[str, Any]], native_tools: bool, scene_text: str) -> dict[str, Any]:
    parts = [INSTRUCTIONS, CAPABILITIES]
    if not native_tools:
        parts.append("The actions, as tool schemas (JSON):\n" + json.dumps(tools, separators=(",", ":")))
    parts.append(scene_block(scene_text))
    return {"role": "system", "content": "\n\n".join(parts)}


def initial_messages(
    request: str, tools: list[dict[str, Any]], native_tools: bool, scene_text: str
) -> list[dict[str, Any]]:
    return [system_message(tools, native_tools, scene_text), {"role": "user", "content": request}]


def refusal_text(stage: Stage | None, reason: str) -> str:
    """What a refusal goes back to the model as: short, with the stage and the reason."""
    where = f"rejected at stage {stage}" if stage is not None else "rejected"
    return f"{where}: {reason.strip()}; fix the plan and answer with the whole corrected plan"


def feedback_messages(reply_message: dict[str, Any], stage: Stage | None, reason: str) -> list[dict[str, Any]]:
    """The assistant's reply, then the refusal: as a tool result for each tool call when the model
    called tools (the protocol wants one per call), else as the next user message."""
    text = refusal_text(stage, reason)
    calls = reply_message.get("tool_calls") or []
    if not calls:
        return [reply_message, {"role": "user", "content": text}]
    results = [
        {"role": "tool", "tool_call_id": str(call.get("id") or f"call_{i}"), "content": text}
        for i, call in enumerate(calls)
    ]
    return [reply_message, *results]


def normalize_calls(tool_calls: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Tool calls with the `id` and `type` some servers leave out, so that results can refer to them."""
    return [{"id": f"call_{i}", "type": "function", **call} for i, call in enumerate(tool_calls)]


def plan_text(content: str, tool_calls: list[dict[str, Any]]) -> str:
    """The plan the parser reads: the tool calls in OpenAI shape when there are any, else the text."""
    if not tool_calls:
        return content.strip()
    return json.dumps({"tool_calls": tool_calls})
