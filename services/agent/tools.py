"""Tool definitions for LLM agents, generated from the parser's vocabulary and the Structs. Pure logic."""

from __future__ import annotations

import copy
import json
import re
from dataclasses import dataclass
from typing import Any, Literal

import msgspec

from schemas.actions import CANCEL_ALL, GoalId, GoalState
from schemas.common import Name, Text
from schemas.plan import Action, Plan
from schemas.planner import AskRequest
from schemas.safety import EStop
from services.parser.vocabulary import ActionSpec, ParamSpec, Vocabulary, load_vocabulary

Format = Literal["openai", "anthropic", "mcp", "jsonschema"]
FORMATS: tuple[Format, ...] = ("openai", "anthropic", "mcp", "jsonschema")
JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"


@dataclass(frozen=True)
class ToolSpec:
    name: str
    description: str
    parameters: dict[str, Any]  # a JSON Schema object for the arguments
    kind: Literal["action", "read", "control"]


# Actions the parser knows but the robot cannot do: the resolver refuses every step with them
# (services/resolver/resolver.py), so offering them as tools would only invite refusals.
REFUSED: dict[Action, str] = {
    Action.GESTURE: "the robot has no gestures yet",
    Action.MOVE_ARM: "the arm moves only within pick and place, and stows itself after each",
}


# What a parameter means, beyond its type, unit and bounds: by (action, name), then by name.
PARAM_HINTS: dict[tuple[Action, str] | str, str] = {
    (Action.DRIVE, "distance"): "Positive drives forward, negative backward.",
    (Action.TURN, "angle"): "Positive turns left (counter-clockwise), negative right, as in ROS.",
    (Action.SAY, "text"): "The words to say.",
    # Taken (models write them) but carried out by nothing: the resolver warns of each given
    # (services/resolver/resolver.py UNUSED_PARAMS), and the hint says so, so a model need not send one.
    (Action.SAY, "volume"): "Not used: this robot has no speaker.",
    (Action.OPEN_GRIPPER, "width"): "Not used: the gripper opens fully.",
    (Action.CLOSE_GRIPPER, "force"): "Not used: the gripper closes with its own force.",
    "approach": "Not used: the robot chooses how the hand comes to it.",
    "speed": "Left out, the robot's own speed; safety may slow it further near people.",
}
# The SI unit symbols of the vocabulary, in words.
UNIT_WORDS: dict[str, str] = {
    "m": "metres",
    "m/s": "metres per second",
    "rad": "radians",
    "rad/s": "radians per second",
    "s": "seconds",
    "N": "newtons",
}


# Parameters the parser needs although the vocabulary does not mark them required: say needs its
# words, which the vocabulary lets come from the step's target too (services/parser/parser.py, _names).
EXTRA_REQUIRED: dict[Action, tuple[str, ...]] = {Action.SAY: ("text",)}

# What every action tool returns; the agent polls with get_goal_status.
_RETURNS = (
    "Everything is checked first (names against the world model, numbers against their bounds, safety); "
    "a refusal says what to fix. Returns a goal id at once: call get_goal_status with it until the goal ends."
)
_JSON_TYPES = {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}


# An id's pattern ends so in the schemas (schemas.common.Id): Python's `$` also matches before a last
# newline. A JSON Schema regex is ECMA's, whose `$` is the end of the text already, and constrained
# decoding (strict mode) may not take a lookahead: tools get the plain `$`, which means the same there.
_WHOLE_TEXT = "(?!\\n)$"


def _ecma(schema: dict[str, Any]) -> dict[str, Any]:
    pattern = schema.get("pattern")
    if isinstance(pattern, str) and pattern.endswith(_WHOLE_TEXT):
        schema["pattern"] = pattern.removesuffix(_WHOLE_TEXT) + "$"
    return schema


def _struct_field(struct: type[msgspec.Struct], field: str) -> dict[str, Any]:
    """The JSON Schema of one field of a Struct, with its bounds (maxLength, pattern, minItems...)."""
    document = msgspec.json.schema(struct)
    schema = dict(document["$defs"][struct.__name__]["properties"][field])
    schema.pop("default", None)  # the Struct's default, not the tool's: an agent says what it means
    return _ecma(schema)


def _type_schema(type_: Any) -> dict[str, Any]:
    """The JSON Schema of a bounded scalar type (schemas.common.Name, Text, GoalId)."""
    return _ecma(dict(msgspec.json.schema(type_)))


def _number(value: float) -> str:
    return f"{value:g}"


def _param_schema(action: Action, name: str, spec: ParamSpec, action_spec: ActionSpec) -> dict[str, Any]:
    schema: dict[str, Any] = {"type": _JSON_TYPES[spec.type]}
    words: list[str] = []
    unit = UNIT_WORDS.get(spec.unit, spec.unit)
    if spec.type in ("float", "int"):
        if spec.min is not None:
            schema["minimum"] = spec.min
        if spec.max is not None:
            schema["maximum"] = spec.max
        label = name.replace("_", " ").capitalize()
        words.append(f"{label} in {unit} ({spec.unit})" if spec.unit else f"{label}")
        if spec.min is not None and spec.max is not None:
            words[-1] += f", from {_number(spec.min)} to {_number(spec.max)}"
        elif spec.min is not None:
            words[-1] += f", at least {_number(spec.min)}"
        elif spec.max is not None:
            words[-1] += f", at most {_number(spec.max)}"
        words[-1] += "."
        if spec.signed_by is not None:
            negative = ", ".join(action_spec.params[spec.signed_by].negative)
            words.append(f"With '{spec.signed_by}' given, write a positive number; {negative} make it negative.")
    elif spec.type == "str":
        if spec.choices:
            schema["enum"] = list(spec.choices)
            words.append(f"{name.replace('_', ' ').capitalize()}: one of {', '.join(spec.choices)}.")
        else:
            schema["maxLength"] = spec.max_length
            words.append(f"{name.replace('_', ' ').capitalize()}.")
        signs = [n for n, s in action_spec.params.items() if s.signed_by == name]
        if signs and spec.negative:
            words.append(f"Sets the sign of {', '.join(signs)}: {', '.join(spec.negative)} mean negative.")
    else:
        words.append(f"{name.replace('_', ' ').capitalize()}.")
    hint = PARAM_HINTS.get((action, name), PARAM_HINTS.get(name))
    if hint is not None and spec.type == "str" and not spec.choices:
        words[0] = hint  # "Text." says nothing the hint does not
    elif hint is not None:
        words.insert(1, hint)
    schema["description"] = " ".join(words)
    return schema


def _action_arguments(action: Action, spec: ActionSpec) -> tuple[dict[str, Any], list[str]]:
    """The properties and required names of one action's arguments (also one plan step's fields)."""
    properties: dict[str, Any] = {}
    required: list[str] = []
    for field, arg in spec.names.items():
        properties[field] = {**_type_schema(Name), "description": arg.description}
        if arg.required:
            required.append(field)
    for name, pspec in spec.params.items():
        properties[name] = _param_schema(action, name, pspec, spec)
        if pspec.required or name in EXTRA_REQUIRED.get(action, ()):
            required.append(name)
    return properties, required


def _object(properties: dict[str, Any], required: list[str], description: str = "") -> dict[str, Any]:
    schema: dict[str, Any] = {"type": "object"}
    if description:
        schema["description"] = description
    schema.update(properties=properties, required=required, additionalProperties=False)
    return schema


def robot_actions(vocabulary: Vocabulary) -> list[Action]:
    """The vocabulary's actions the robot can do, in vocabulary order."""
    return [a for a in vocabulary.actions if a not in REFUSED]


def action_description(spec: ActionSpec) -> str:
    return f"{spec.summary} {_RETURNS}"


STEP_REF = "#/$defs/step"


def _step_schema(action: Action, spec: ActionSpec) -> dict[str, Any]:
    properties, required = _action_arguments(action, spec)
    step_properties: dict[str, Any] = {
        "action": {"type": "string", "enum": [action.value]},
        **properties,
        "description": {**_type_schema(Text), "description": "Optional: why this step, in a few words."},
        "on_failure": {
            "type": "array",
            "items": {"$ref": STEP_REF},
            "description": "Optional: steps to run instead when this step fails; the plan then goes on after it.",
        },
    }
    first = spec.summary.split(". ")[0].rstrip(".")
    return _object(step_properties, ["action", *required], f"{action.value}: {first}.")


def _plan_tool(vocabulary: Vocabulary, actions: list[Action]) -> ToolSpec:
    # One step schema per action, told apart by "action"; on_failure alternatives refer back to them.
    step = {
        "description": "One step: an action with its arguments.",
        "anyOf": [_step_schema(a, vocabulary.actions[a]) for a in actions],
    }
    plan = {
        **_struct_field(Plan, "steps"),
        "items": {"$ref": STEP_REF},
        "description": "The steps, run in order. Each is one action with its arguments.",
    }
    description = {
        **_struct_field(Plan, "description"),
        "description": "What the plan is for, in one sentence.",
    }
    parameters = _object({"plan": plan, "description": description}, ["plan"])
    parameters["$defs"] = {"step": step}
    return ToolSpec(
        name="execute_plan",
        description=(
            "Run a whole plan: a list of steps, each one of the robot's actions with its arguments, "
            "and optional on_failure alternatives per step. Better than single actions for a task of "
            f"several steps, since it is checked as a whole before anything moves. {_RETURNS}"
        ),
        parameters=parameters,
        kind="action",
    )


def _plan_and_execute_tool() -> ToolSpec:
    request = {
        **_struct_field(AskRequest, "text"),
        "description": "The task in plain language, as the user asked it ('bring the red cup to the coffee table').",
    }
    dry_run = {
        **_struct_field(AskRequest, "dry_run"),
        "description": "True: only plan and check, the robot does not move. False: plan, check and run.",
    }
    return ToolSpec(
        name="plan_and_execute",
        description=(
            "Hand a task in plain language to tether's own planner, which writes the plan from what the "
            f"robot knows of the world, then checks and runs it. {_RETURNS}"
        ),
        parameters=_object({"request": request, "dry_run": dry_run}, ["request", "dry_run"]),
        kind="action",
    )


def _read_tools() -> list[ToolSpec]:
    states = ", ".join(s.value for s in GoalState)
    goal_id = {**_type_schema(GoalId), "description": "The goal id an action tool returned."}
    return [
        ToolSpec(
            name="get_goal_status",
            description=(
                f"Where a goal started by an action tool is now: its state ({states}), the step it is on "
                "and, once it has ended, the result with a reason for each step. Call it until the state "
                "is succeeded, canceled, aborted or rejected."
            ),
            parameters=_object({"goal_id": goal_id}, ["goal_id"]),
            kind="read",
        ),
        ToolSpec(
            name="get_robot_state",
            description=(
                "The robot now: its pose in the map (x, y in metres, yaw in radians), what the gripper "
                "holds, whether the emergency stop is latched and why, and which services are up."
            ),
            parameters=_object({}, []),
            kind="read",
        ),
        ToolSpec(
            name="describe_scene",
            description=(
                "What the robot knows of the world, as text: rooms, furniture, and each object where it was "
                "last seen; then the known hazards near the robot (incidents safety remembers there: e-stops, "
                "near-misses, dropped objects; caution zones where the robot drives slower). Use these names in "
                "actions."
            ),
            parameters=_object({}, []),
            kind="read",
        ),
        ToolSpec(
            name="list_objects",
            description=(
                "The objects the robot has seen, each with its name, room, what it stands on (or 'gripper') "
                "and its position in metres."
            ),
            parameters=_object({}, []),
            kind="read",
        ),
        ToolSpec(
            name="get_camera_image",
            description="A picture from the robot's camera, taken now.",
            parameters=_object({}, []),
            kind="read",
        ),
    ]


def _control_tools() -> list[ToolSpec]:
    goal_id = {
        **_type_schema(GoalId),
        "description": f"The goal id an action tool returned, or '{CANCEL_ALL}' for every running goal.",
    }
    reason = {**_struct_field(EStop, "reason"), "description": "Why, in a sentence: it goes into the log."}
    return [
        ToolSpec(
            name="cancel_goal",
            description=(
                "Cancel a running goal: the robot brings itself to a standstill and the goal ends canceled. "
                "For an ordinary change of plan; in danger use emergency_stop."
            ),
            parameters=_object({"goal_id": goal_id}, ["goal_id"]),
            kind="control",
        ),
        ToolSpec(
            name="emergency_stop",
            description=(
                "Latch the emergency stop now: all motion stops and every new goal is refused until a human "
                "operator at the robot decides otherwise; no tool can undo it. Use it when someone or something "
                "is in danger."
            ),
            parameters=_object({"reason": reason}, ["reason"]),
            kind="control",
        ),
    ]


def all_tools(vocabulary: Vocabulary | None = None) -> list[ToolSpec]:
    """Every tool an agent gets: one per action the robot can do, the plan tools, reads and controls."""
    vocabulary = vocabulary or load_vocabulary()
    actions = robot_actions(vocabulary)
    tools: list[ToolSpec] = []
    for action in actions:
        spec = vocabulary.actions[action]
        properties, required = _action_arguments(action, spec)
        tools.append(
            ToolSpec(
                name=action.value,
                description=action_description(spec),
                parameters=_object(properties, required),
                kind="action",
            )
        )
    tools.append(_plan_tool(vocabulary, actions))
    tools.append(_plan_and_execute_tool())
    return [*tools, *_read_tools(), *_control_tools()]


# OpenAI's strict mode (Structured Outputs; function calling with "strict": true) accepts a subset
# of JSON Schema: every object lists all its properties in `required` and has additionalProperties
# false, an optional property becomes a union with null, and only these keywords are supported.
STRICT_KEYWORDS = frozenset(
    {
        "type",
        "description",
        "properties",
        "required",
        "additionalProperties",
        "items",
        "enum",
        "anyOf",
        "$ref",
        "$defs",
        "pattern",
        "format",
        "minimum",
        "maximum",
        "exclusiveMinimum",
        "exclusiveMaximum",
        "multipleOf",
        "minItems",
        "maxItems",
    }
)
_NOTES = {"minLength": "at least {} characters", "maxLength": "at most {} characters", "default": "default {}"}


def _note(key: str, value: Any) -> str:
    if key == "minLength" and value == 1:
        return "not empty"
    return _NOTES.get(key, key + " {}").format(json.dumps(value))


def strict_schema(schema: dict[str, Any]) -> dict[str, Any]:
    """`schema` within OpenAI's strict rules. Keywords it does not support move into the description."""
    return _strict(copy.deepcopy(schema))


def _strict(node: dict[str, Any]) -> dict[str, Any]:
    if "const" in node:
        node["enum"] = [node.pop("const")]
    notes = []
    for key in [k for k in node if k not in STRICT_KEYWORDS]:
        value = node.pop(key)
        notes.append(_note(key, value))
    if notes:
        text = node.get("description", "")
        node["description"] = (f"{text} " if text else "") + f"({'; '.join(notes)})"
    if isinstance(node.get("properties"), dict):
        required = set(node.get("required", []))
        node["properties"] = {
            name: _strict(sub) if name in required else _nullable(_strict(sub))
            for name, sub in node["properties"].items()
        }
        node["required"] = list(node["properties"])
        node["additionalProperties"] = False
    elif node.get("type") == "object":
        node.update(properties={}, required=[], additionalProperties=False)
    if isinstance(node.get("items"), dict):
        node["items"] = _strict(node["items"])
    if isinstance(node.get("anyOf"), list):
        node["anyOf"] = [_strict(branch) for branch in node["anyOf"]]
    if isinstance(node.get("$defs"), dict):
        node["$defs"] = {name: _strict(sub) for name, sub in node["$defs"].items()}
    return node


def _nullable(node: dict[str, Any]) -> dict[str, Any]:
    """An optional property as strict mode writes it: the value or null ("leave it out" = null)."""
    description = node.pop("description", None)
    out: dict[str, Any] = {"anyOf": [node, {"type": "null"}]}
    if description is not None:
        out["description"] = description
    return out


def _title(name: str) -> str:
    return re.sub(r"_+", " ", name).capitalize()


def _rebase(node: Any, base: str) -> Any:
    """A tool's schema moved to `base` inside a bigger document: its "#/..." references follow it."""
    if isinstance(node, dict):
        return {
            k: base + v[1:] if k == "$ref" and isinstance(v, str) and v.startswith("#/") else _rebase(v, base)
            for k, v in node.items()
        }
    if isinstance(node, list):
        return [_rebase(v, base) for v in node]
    return node


def render(tools: list[ToolSpec], fmt: Format, strict: bool = False) -> Any:
    """The tools as one API expects them. `strict` brings every schema within OpenAI's strict rules
    (in every format); for openai it also sets "strict": true on each function."""

    def parameters(tool: ToolSpec) -> dict[str, Any]:
        return strict_schema(tool.parameters) if strict else copy.deepcopy(tool.parameters)

    if fmt == "openai":
        functions = []
        for tool in tools:
            function: dict[str, Any] = {
                "name": tool.name,
                "description": tool.description,
                "parameters": parameters(tool),
            }
            if strict:
                function["strict"] = True
            functions.append({"type": "function", "function": function})
        return functions
    if fmt == "anthropic":
        return [{"name": t.name, "description": t.description, "input_schema": parameters(t)} for t in tools]
    if fmt == "mcp":
        return [
            {
                "name": t.name,
                "title": _title(t.name),
                "description": t.description,
                "inputSchema": parameters(t),
                # Without readOnlyHint a client assumes a tool may change the world: it does, it moves a robot.
                "annotations": {"readOnlyHint": t.kind == "read"},
            }
            for t in tools
        ]
    if fmt == "jsonschema":
        return {
            "$schema": JSON_SCHEMA_DIALECT,
            "title": "tether tools",
            "description": "The arguments of each tool an agent can call, under $defs by tool name.",
            "$defs": {
                t.name: _rebase({**parameters(t), "description": t.description}, f"#/$defs/{t.name}") for t in tools
            },
        }
    raise ValueError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
