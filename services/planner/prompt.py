"""The conversation sent to the model: instructions, the robot's capabilities, the tools, the scene as
data, the request; and the short message a refusal goes back as. Pure logic."""

from __future__ import annotations

import json
import time
from typing import Any

from schemas.common import Pose2D, Stage
from schemas.incidents import IncidentList, IncidentQuery
from schemas.plan import MAX_PLAN_BYTES, MAX_STEPS
from services.agent.feedback import as_data
from services.safety.hazards import incident_line, zone_line

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
# At most this many known hazards (incidents and caution zones) go into a prompt.
MAX_HAZARDS = 20
# How far around the robot the planner asks safety for known hazards (metres).
HAZARD_RADIUS = 5.0


def scene_block(scene_text: str) -> str:
    """The scene marked as data, in the same block the MCP tools use (services.agent.feedback.as_data):
    nothing in the scene (an object's name, a label read by the camera) can close the block early."""
    return as_data("world model", scene_text.strip()[:MAX_SCENE_CHARS] or "(no scene available)")


def hazards_query(robot: Pose2D | None) -> IncidentQuery:
    """What to ask safety (keys.INCIDENTS) for the known hazards near the robot: within HAZARD_RADIUS of
    its pose, or the newest anywhere when its pose is unknown; at most MAX_HAZARDS. The planner's prompts
    and the MCP scene tool ask the same."""
    if robot is None:
        return IncidentQuery(limit=MAX_HAZARDS)
    return IncidentQuery(x=robot.x, y=robot.y, radius=HAZARD_RADIUS, limit=MAX_HAZARDS)


def hazard_lines(incidents: IncidentList | None, now: float | None = None, cap: int = MAX_HAZARDS) -> list[str]:
    """Safety's answer to an incident query (keys.INCIDENTS) as lines: each caution zone, then each
    incident (what, where, how long ago, why), at most `cap`; None: safety did not answer."""
    if incidents is None:
        return ["safety did not answer: the known hazards near the robot are unknown"]
    now = time.time() if now is None else now
    lines = [zone_line(zone) for zone in incidents.zones]
    lines += [incident_line(incident, now) for incident in incidents.incidents]
    more = max(len(lines) - cap, 0) + max(incidents.total - len(incidents.incidents), 0)
    lines = lines[:cap]
    if more:
        lines.append(f"and {more} more")
    if incidents.store:
        lines.insert(0, f"safety's incident memory has a fault ({incidents.store}): what it remembers may be missing")
    return lines or ["no incidents remembered near the robot"]


def hazards_block(incidents: IncidentList | None, now: float | None = None) -> str:
    """The known hazards near the robot (safety's memory of incidents: keys.INCIDENTS queried around
    the robot's pose, HAZARD_RADIUS), marked as data like the scene: a reason a person gave for an
    e-stop cannot close the block or pass for an instruction."""
    return as_data("incident memory", "\n".join(hazard_lines(incidents, now)))


HAZARD_NOTE = """Known hazards are places where something went wrong before (an e-stop, a near-miss, a dropped
object); a caution zone slows the robot. Prefer plans that avoid them when another way does the job."""


def system_message(
    tools: list[dict[str, Any]], native_tools: bool, scene_text: str, hazards: str = ""
) -> dict[str, Any]:
    """`hazards`: hazards_block's text ("" leaves the section out)."""
    parts = [INSTRUCTIONS, CAPABILITIES]
    if not native_tools:
        parts.append("The actions, as tool schemas (JSON):\n" + json.dumps(tools, separators=(",", ":")))
    parts.append(scene_block(scene_text))
    if hazards:
        parts += [HAZARD_NOTE, hazards]
    return {"role": "system", "content": "\n\n".join(parts)}


def initial_messages(
    request: str, tools: list[dict[str, Any]], native_tools: bool, scene_text: str, hazards: str = ""
) -> list[dict[str, Any]]:
    return [system_message(tools, native_tools, scene_text, hazards), {"role": "user", "content": request}]


def refusal_text(stage: Stage | None, reason: str) -> str:
    """What a refusal goes back to the model as: short, with the stage, then the reason as data: it
    quotes names from the world model (perceived objects, people) and the model's own plan."""
    where = f"rejected at stage {stage}" if stage is not None else "rejected"
    return f"{where}: fix the plan and answer with the whole corrected plan. Why:\n" + as_data(
        "the refusal", reason.strip()
    )


def feedback_messages(reply_message: dict[str, Any], stage: Stage | None, reason: str) -> list[dict[str, Any]]:
    """The assistant's reply, then the refusal: as a tool result for each tool call when the model
    called tools (the protocol wants one per call), else as the next user message. A reply that cannot
    go back whole (left_out) goes back as a short note of what it was: the conversation stays bounded
    and encodable."""
    text = refusal_text(stage, reason)
    calls = reply_message.get("tool_calls") or []
    left_out = unrepeatable(reply_message)
    if left_out:
        note = {"role": "assistant", "content": f"(my answer, not repeated here: {left_out})"}
        return [note, {"role": "user", "content": text}]
    if not calls:
        return [reply_message, {"role": "user", "content": text}]
    results = [
        {"role": "tool", "tool_call_id": str(call.get("id") or f"call_{i}"), "content": text}
        for i, call in enumerate(calls)
    ]
    return [reply_message, *results]


def unrepeatable(reply_message: dict[str, Any]) -> str:
    """Why a reply cannot go back into the conversation as it is ("" when it can): more tool calls than a
    plan holds steps (each would want its own tool result: 100,000 empty calls, 300 KB, became 22 MB a
    request), bigger than a plan can be (refused before any dry run), or a number JSON cannot carry
    (NaN, Infinity: the next request could not be encoded)."""
    calls = reply_message.get("tool_calls") or []
    if len(calls) > MAX_STEPS:
        return f"{len(calls)} tool calls, more than the {MAX_STEPS} steps a plan can hold"
    try:
        size = len(json.dumps(reply_message, ensure_ascii=False, allow_nan=False).encode())
    except ValueError:
        return "it held a number that is not finite (NaN or Infinity)"
    except RecursionError:
        return "it was nested too deep"
    if size > MAX_PLAN_BYTES:
        return f"{size} bytes, more than a plan can be ({MAX_PLAN_BYTES})"
    return ""


def normalize_calls(tool_calls: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Tool calls with an `id` and a `type`, so that results can refer to them: an id that is missing, not
    a non-empty string or a repeat of an earlier one becomes call_N (N the call's place), a type that is
    not a string "function"."""
    taken: set[str] = set()
    out = []
    for i, call in enumerate(tool_calls):
        call_id = call.get("id")
        if not isinstance(call_id, str) or not call_id or call_id in taken:
            call_id = f"call_{i}"
            suffix = 0
            while call_id in taken:  # a model's own id was already call_N
                suffix += 1
                call_id = f"call_{i}_{suffix}"
        taken.add(call_id)
        kind = call.get("type")
        out.append({**call, "id": call_id, "type": kind if isinstance(kind, str) and kind else "function"})
    return out


def plan_text(content: str, tool_calls: list[dict[str, Any]]) -> str:
    """The plan the parser reads: the tool calls in OpenAI shape when there are any, else the text."""
    if not tool_calls:
        return content.strip()
    return json.dumps({"tool_calls": tool_calls})
