"""Generated agent tool schemas: valid JSON Schema, within OpenAI's strict rules, and read by the real parser."""

from __future__ import annotations

import json
import re
from typing import Any

import jsonschema
import mcp.types
import msgspec
import pytest
import typer
from typer.testing import CliRunner

from schemas.plan import Action, Plan, Step
from schemas.planner import MAX_REQUEST_CHARS
from services.agent.tools import (
    FORMATS,
    REFUSED,
    UNIT_WORDS,
    ToolSpec,
    all_tools,
    render,
    strict_schema,
)
from services.parser.errors import ParseError
from services.parser.parser import parse
from services.parser.vocabulary import Vocabulary, load_vocabulary
from tether.schema import schema as schema_command

VOCABULARY = load_vocabulary()
TOOLS = all_tools()
BY_NAME = {t.name: t for t in TOOLS}
ACTION_TOOLS = [t for t in TOOLS if t.kind == "action" and t.name in {a.value for a in Action}]

JSON_TYPES = {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}
# Names from the default world, by the argument they fill.
NAMES = {
    ("navigate_to", "target"): "kitchen",
    ("look_at", "target"): "me",
    ("pick", "target"): "red cup",
    ("pick", "location"): "kitchen counter",
    ("place", "target"): "coffee table",
    ("detect", "target"): "blue book",
    ("detect", "location"): "coffee table",
}
# Where the parser puts each name argument in the Step.
NAME_FIELDS = {("place", "target"): "location", ("pick", "location"): "location", ("detect", "location"): "location"}


# OpenAI's strict rules (Structured Outputs "Supported schemas"; function calling with strict: true),
# written from the documentation, independently of services.agent.tools.strict_schema.
STRICT_TYPES = {"string", "number", "integer", "boolean", "object", "array", "null"}
STRICT_FORMATS = {"date-time", "time", "date", "duration", "email", "hostname", "ipv4", "ipv6", "uuid"}
STRICT_KEYWORDS = {
    *("type", "description", "properties", "required", "additionalProperties", "items", "enum", "anyOf"),
    *("$ref", "$defs", "pattern", "format", "minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"),
    *("multipleOf", "minItems", "maxItems"),
}
MAX_PROPERTIES, MAX_DEPTH, MAX_ENUM_VALUES, MAX_NAME_CHARS = 5000, 10, 1000, 120_000


def strict_violations(root: dict[str, Any]) -> list[str]:
    """Every way `root` breaks OpenAI's strict rules; empty when it keeps them."""
    problems: list[str] = []
    totals = {"properties": 0, "enum": 0, "chars": 0}
    if root.get("type") != "object" or "anyOf" in root:
        problems.append("$: the root must be an object schema, not anyOf")

    def walk(node: Any, path: str, depth: int) -> None:
        if not isinstance(node, dict):
            problems.append(f"{path}: not a schema object")
            return
        problems.extend(f"{path}: keyword {k!r} is not supported" for k in node if k not in STRICT_KEYWORDS)
        if "$ref" in node:
            ref = node["$ref"]
            if len(node) > 1:
                problems.append(f"{path}: $ref with other keywords")
            if not (isinstance(ref, str) and ref.startswith("#/$defs/") and ref[8:] in root.get("$defs", {})):
                problems.append(f"{path}: $ref {ref!r} does not name a $defs entry of the root")
            return
        if depth > MAX_DEPTH:
            problems.append(f"{path}: nested deeper than {MAX_DEPTH} levels")
        types = node.get("type", [])
        types = [types] if isinstance(types, str) else types
        if not types and "anyOf" not in node and "enum" not in node:
            problems.append(f"{path}: no type")
        problems.extend(f"{path}: type {t!r} is not supported" for t in types if t not in STRICT_TYPES)
        if "format" in node and node["format"] not in STRICT_FORMATS:
            problems.append(f"{path}: format {node['format']!r} is not supported")
        if "object" in types or "properties" in node:
            properties = node.get("properties", {})
            if node.get("additionalProperties") is not False:
                problems.append(f"{path}: an object needs additionalProperties false")
            required = node.get("required", [])
            if sorted(required) != sorted(properties):
                missing = sorted(set(properties) - set(required))
                problems.append(f"{path}: every property must be required (missing {missing})")
            totals["properties"] += len(properties)
            totals["chars"] += sum(len(n) for n in properties)
            for name, sub in properties.items():
                walk(sub, f"{path}.{name}", depth + 1)
        if "items" in node:
            walk(node["items"], f"{path}[]", depth)
        for i, branch in enumerate(node.get("anyOf", [])):
            walk(branch, f"{path}.anyOf[{i}]", depth)
        for value in node.get("enum", []):
            totals["enum"] += 1
            totals["chars"] += len(str(value))

    walk(root, "$", 1)
    for name, sub in root.get("$defs", {}).items():
        walk(sub, f"$defs.{name}", 1)
    if totals["properties"] > MAX_PROPERTIES:
        problems.append(f"more than {MAX_PROPERTIES} properties")
    if totals["enum"] > MAX_ENUM_VALUES:
        problems.append(f"more than {MAX_ENUM_VALUES} enum values")
    if totals["chars"] > MAX_NAME_CHARS:
        problems.append(f"names and enum values longer than {MAX_NAME_CHARS} characters")
    return problems


def rendered_schemas(fmt: str, strict: bool) -> list[dict[str, Any]]:
    out = render(TOOLS, fmt, strict=strict)  # type: ignore[arg-type]
    if fmt == "openai":
        return [t["function"]["parameters"] for t in out]
    if fmt == "anthropic":
        return [t["input_schema"] for t in out]
    if fmt == "mcp":
        return [t["inputSchema"] for t in out]
    return [out]


def example_value(action: str, name: str, schema: dict[str, Any]) -> Any:
    """A value inside the schema's bounds; numbers positive, so that a direction may sign them."""
    if (action, name) in NAMES:
        return NAMES[(action, name)]
    if "anyOf" in schema:
        schema = schema["anyOf"][0]
    if "enum" in schema:
        return schema["enum"][0]
    if schema["type"] in ("number", "integer"):
        high = schema.get("maximum", 1.0)
        return high / 2 if high > 0 else (schema.get("minimum", high - 1) + high) / 2
    if schema["type"] == "boolean":
        return True
    return "hello there"


def example_arguments(tool: ToolSpec, full: bool) -> dict[str, Any]:
    params = tool.parameters
    names = list(params["properties"]) if full else params["required"]
    return {n: example_value(tool.name, n, params["properties"][n]) for n in names}


def strict_arguments(tool: ToolSpec) -> dict[str, Any]:
    """What a strict-mode model writes: every property, null for those it leaves out."""
    required = tool.parameters["required"]
    return {
        n: example_value(tool.name, n, s) if n in required else None for n, s in tool.parameters["properties"].items()
    }


def expected_step(action: str, arguments: dict[str, Any]) -> Step:
    spec = VOCABULARY.actions[Action(action)]
    fields: dict[str, Any] = {}
    params: dict[str, Any] = {}
    for name, value in arguments.items():
        if name in ("target", "location"):
            fields[NAME_FIELDS.get((action, name), name)] = value
        elif name not in {s.signed_by for s in spec.params.values()}:
            signer = spec.params[name].signed_by
            negative = signer is not None and arguments.get(signer) in spec.params[signer].negative
            params[name] = -value if negative else value
    units = {n: spec.params[n].unit for n, v in params.items() if spec.params[n].unit and not isinstance(v, str)}
    return Step(action=Action(action), params=params, units=units, **fields)


def openai_call(name: str, arguments: dict[str, Any]) -> str:
    call = {"type": "function", "function": {"name": name, "arguments": json.dumps(arguments)}}
    return json.dumps({"role": "assistant", "content": None, "tool_calls": [call]})


def parse_call(name: str, arguments: dict[str, Any]) -> Plan:
    return parse(openai_call(name, arguments))


# The set of tools


def test_every_action_the_robot_can_do_is_a_tool() -> None:
    """A new action in vocabulary.yaml shows up as a tool, or this fails."""
    assert {t.name for t in ACTION_TOOLS} == {a.value for a in VOCABULARY.actions} - {a.value for a in REFUSED}
    assert set(REFUSED) == {Action.GESTURE, Action.MOVE_ARM}
    assert not {a.value for a in REFUSED} & set(BY_NAME)


def test_tool_names_kinds_and_descriptions() -> None:
    assert len(BY_NAME) == len(TOOLS)
    kinds = {t.name: t.kind for t in TOOLS if t not in ACTION_TOOLS}
    assert kinds == {
        "execute_plan": "action",
        "plan_and_execute": "action",
        "get_goal_status": "read",
        "get_robot_state": "read",
        "describe_scene": "read",
        "list_objects": "read",
        "get_camera_image": "read",
        "cancel_goal": "control",
        "emergency_stop": "control",
    }
    for tool in TOOLS:
        assert re.fullmatch(r"[a-zA-Z0-9_-]{1,64}", tool.name)
        assert 20 < len(tool.description) <= 1024
        if tool.kind == "action":
            assert "get_goal_status" in tool.description


FORBIDDEN = re.compile(
    r"reset|unlatch|unlock|override|bypass|disable|polic(y|ies)|limit|permission|allowlist|whitelist|rearm|re-arm",
    re.IGNORECASE,
)


def property_names(schema: Any) -> list[str]:
    if isinstance(schema, dict):
        names = list(schema.get("properties", {}))
        return names + [n for v in schema.values() for n in property_names(v)]
    if isinstance(schema, list):
        return [n for v in schema for n in property_names(v)]
    return []


def test_no_tool_resets_the_estop_or_changes_safety() -> None:
    """Invariant 3: no path from an agent resets the e-stop; nor may a tool lift a limit or swap the policy."""
    for tool in TOOLS:
        for text in (tool.name, tool.description, *property_names(tool.parameters)):
            assert not FORBIDDEN.search(text), f"{tool.name}: {text!r} suggests changing safety"
    assert {t.name for t in TOOLS if t.kind == "control"} == {"cancel_goal", "emergency_stop"}


def test_the_forbidden_words_are_caught() -> None:
    for name in ("reset_estop", "set_policy", "raise_speed_limit", "override_safety", "unlock_robot"):
        assert FORBIDDEN.search(name)


# Parameters from the vocabulary and the Structs


def test_action_parameters_follow_the_vocabulary() -> None:
    for tool in ACTION_TOOLS:
        spec = VOCABULARY.actions[Action(tool.name)]
        properties = tool.parameters["properties"]
        assert set(spec.params) <= set(properties)
        for name, pspec in spec.params.items():
            schema = properties[name]
            assert (
                schema["type"] == {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}[pspec.type]
            )
            assert schema.get("minimum") == pspec.min and schema.get("maximum") == pspec.max
            assert schema.get("enum", []) == pspec.choices
            if pspec.unit:
                assert f"{UNIT_WORDS[pspec.unit]} ({pspec.unit})" in schema["description"]
            if pspec.required:
                assert name in tool.parameters["required"]
    speed = BY_NAME["navigate_to"].parameters["properties"]["speed"]
    assert "metres per second" in speed["description"] and speed["maximum"] == 1.0


def test_every_unit_has_words() -> None:
    assert set(VOCABULARY.units) <= set(UNIT_WORDS)


def test_bounds_come_from_the_structs() -> None:
    goal_id = BY_NAME["get_goal_status"].parameters["properties"]["goal_id"]
    assert goal_id["maxLength"] == 64 and goal_id["pattern"] == "^[A-Za-z0-9_-]+$"
    assert re.fullmatch(goal_id["pattern"], "all")  # cancel_goal's "all"
    assert BY_NAME["emergency_stop"].parameters["properties"]["reason"]["maxLength"] == 4000
    assert BY_NAME["navigate_to"].parameters["properties"]["target"]["maxLength"] == 200
    request = BY_NAME["plan_and_execute"].parameters["properties"]["request"]
    assert (request["minLength"], request["maxLength"]) == (1, MAX_REQUEST_CHARS)
    plan = BY_NAME["execute_plan"].parameters["properties"]["plan"]
    assert (plan["minItems"], plan["maxItems"]) == (1, 100)


# Valid JSON Schema, in every format


@pytest.mark.parametrize("strict", [False, True])
@pytest.mark.parametrize("fmt", FORMATS)
def test_every_schema_is_valid_json_schema(fmt: str, strict: bool) -> None:
    schemas = rendered_schemas(fmt, strict)
    assert len(schemas) == (1 if fmt == "jsonschema" else len(TOOLS))
    for schema in schemas:
        jsonschema.Draft202012Validator.check_schema(schema)
    json.dumps(render(TOOLS, fmt, strict=strict))  # type: ignore[arg-type]


@pytest.mark.parametrize("strict", [False, True])
def test_mcp_tools_are_mcp_tool_objects(strict: bool) -> None:
    for item in render(TOOLS, "mcp", strict=strict):
        tool = mcp.types.Tool.model_validate(item)
        assert tool.input_schema["type"] == "object"
    read = {t["name"]: t["annotations"]["readOnlyHint"] for t in render(TOOLS, "mcp")}
    assert read["describe_scene"] and not read["navigate_to"] and not read["emergency_stop"]


def test_render_shapes() -> None:
    openai = render(TOOLS, "openai")
    assert openai[0]["type"] == "function" and "strict" not in openai[0]["function"]
    assert all(t["function"]["strict"] is True for t in render(TOOLS, "openai", strict=True))
    anthropic = render(TOOLS, "anthropic")
    assert set(anthropic[0]) == {"name", "description", "input_schema"}
    document = render(TOOLS, "jsonschema")
    assert document["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert set(document["$defs"]) == set(BY_NAME)
    with pytest.raises(ValueError, match="unknown format"):
        render(TOOLS, "yaml")  # type: ignore[arg-type]


# OpenAI's strict rules


@pytest.mark.parametrize("fmt", FORMATS)
def test_strict_output_keeps_openais_strict_rules(fmt: str) -> None:
    if fmt == "jsonschema":
        document = rendered_schemas(fmt, True)[0]
        # Inside the document the references point at it; the per-tool formats are checked standalone.
        schemas = [json.loads(json.dumps(s).replace(f'"#/$defs/{n}/', '"#/')) for n, s in document["$defs"].items()]
    else:
        schemas = rendered_schemas(fmt, True)
    for schema in schemas:
        assert strict_violations(schema) == []


NOT_STRICT = [
    {"type": "object", "properties": {"a": {"type": "string"}}, "required": []},
    {"type": "object", "properties": {"a": {"type": "string"}}, "required": ["a"]},
    {
        "type": "object",
        "properties": {"a": {"type": "string", "minLength": 1}},
        "required": ["a"],
        "additionalProperties": False,
    },
    {"anyOf": [{"type": "object", "properties": {}, "required": [], "additionalProperties": False}]},
    {
        "type": "object",
        "properties": {"a": {"type": "string", "format": "uri"}},
        "required": ["a"],
        "additionalProperties": False,
    },
    {
        "type": "object",
        "properties": {"a": {"$ref": "#/$defs/a", "description": "x"}},
        "required": ["a"],
        "additionalProperties": False,
        "$defs": {"a": {"type": "string"}},
    },
]


@pytest.mark.parametrize("schema", NOT_STRICT)
def test_the_strict_checker_fails_schemas_that_break_the_rules(schema: dict[str, Any]) -> None:
    assert strict_violations(schema)


def test_the_strict_checker_fails_the_plain_schemas() -> None:
    broken = [t.name for t in TOOLS if strict_violations(t.parameters)]
    assert "execute_plan" in broken and "navigate_to" in broken


def test_strict_moves_unsupported_keywords_into_the_description() -> None:
    target = strict_schema(BY_NAME["navigate_to"].parameters)["properties"]["target"]
    assert "maxLength" not in target and "at most 200 characters" in target["description"]
    speed = strict_schema(BY_NAME["navigate_to"].parameters)["properties"]["speed"]
    assert speed["anyOf"][1] == {"type": "null"} and "metres per second" in speed["description"]
    assert BY_NAME["navigate_to"].parameters["properties"]["target"]["maxLength"] == 200  # not mutated


# The parser reads what the schemas describe


@pytest.mark.parametrize("full", [False, True])
@pytest.mark.parametrize("tool", ACTION_TOOLS, ids=lambda t: t.name)
def test_example_arguments_become_the_expected_step(tool: ToolSpec, full: bool) -> None:
    arguments = example_arguments(tool, full)
    jsonschema.Draft202012Validator(tool.parameters).validate(arguments)
    plan = parse_call(tool.name, arguments)
    assert plan.warnings == [], plan.warnings  # every argument understood, none ignored
    assert plan.source_format == "openai_tool_calls"
    assert plan.steps == [expected_step(tool.name, arguments)]


@pytest.mark.parametrize("tool", ACTION_TOOLS, ids=lambda t: t.name)
def test_strict_arguments_become_the_expected_step(tool: ToolSpec) -> None:
    arguments = strict_arguments(tool)
    jsonschema.Draft202012Validator(strict_schema(tool.parameters)).validate(arguments)
    # The nulls a strict-mode model writes for what it leaves out go to the parser as they are.
    plan = parse_call(tool.name, arguments)
    assert plan.steps == [expected_step(tool.name, present(arguments))]


def out_of_bounds() -> list[tuple[str, str, float]]:
    cases = []
    for tool in ACTION_TOOLS:
        for name, schema in tool.parameters["properties"].items():
            if "maximum" in schema:
                cases.append((tool.name, name, schema["maximum"] + 4.0))
            if "minimum" in schema:
                cases.append((tool.name, name, schema["minimum"] - 4.0))
    return cases


@pytest.mark.parametrize(("action", "param", "value"), out_of_bounds())
def test_arguments_out_of_bounds_are_refused_by_schema_and_parser(action: str, param: str, value: float) -> None:
    tool = BY_NAME[action]
    arguments = {**example_arguments(tool, False), param: value}
    assert not jsonschema.Draft202012Validator(tool.parameters).is_valid(arguments)
    with pytest.raises(ParseError, match=param):
        parse_call(action, arguments)


def test_speed_of_5_metres_per_second_is_refused() -> None:
    arguments = {"target": "kitchen", "speed": 5}
    assert not jsonschema.Draft202012Validator(BY_NAME["navigate_to"].parameters).is_valid(arguments)
    with pytest.raises(ParseError, match="speed"):
        parse_call("navigate_to", arguments)


def test_a_missing_required_argument_is_refused_by_schema_and_parser() -> None:
    for tool in ACTION_TOOLS:
        for name in tool.parameters["required"]:
            arguments = {k: v for k, v in example_arguments(tool, True).items() if k != name}
            assert not jsonschema.Draft202012Validator(tool.parameters).is_valid(arguments)
            with pytest.raises(ParseError):
                parse_call(tool.name, arguments)


def plan_arguments(strict: bool) -> dict[str, Any]:
    def step(tool: ToolSpec) -> dict[str, Any]:
        arguments = strict_arguments(tool) if strict else example_arguments(tool, False)
        extra = {"description": None, "on_failure": None} if strict else {}
        return {"action": tool.name, **arguments, **extra}

    steps = [step(t) for t in ACTION_TOOLS]
    steps[0] = {**steps[0], "description": "go first", "on_failure": [step(BY_NAME["say"])]}
    return {"plan": steps, "description": "every action once" if not strict else None}


@pytest.mark.parametrize("strict", [False, True])
def test_a_plan_for_execute_plan_is_read_by_the_parser(strict: bool) -> None:
    tool = BY_NAME["execute_plan"]
    arguments = plan_arguments(strict)
    schema = strict_schema(tool.parameters) if strict else tool.parameters
    jsonschema.Draft202012Validator(schema).validate(arguments)
    plan = parse_call("execute_plan", arguments)
    assert plan.warnings == [], plan.warnings
    assert [s.action.value for s in plan.steps if s.action] == [t.name for t in ACTION_TOOLS]
    first = plan.steps[0]
    assert first.description == "go first" and first.on_failure[0].action is Action.SAY
    for step, tool in zip(plan.steps, ACTION_TOOLS, strict=True):
        arguments = present(strict_arguments(tool)) if strict else example_arguments(tool, False)
        assert without_plan_fields(step) == expected_step(tool.name, arguments)


def without_plan_fields(step: Step) -> Step:
    """The step without the plan-only fields the single-action examples do not have."""
    return msgspec.structs.replace(step, description="", on_failure=[])


def test_a_plan_step_out_of_bounds_is_refused_by_schema_and_parser() -> None:
    arguments = {"plan": [{"action": "drive", "distance": 1.0, "speed": 5.0}]}
    assert not jsonschema.Draft202012Validator(BY_NAME["execute_plan"].parameters).is_valid(arguments)
    with pytest.raises(ParseError, match="speed"):
        parse_call("execute_plan", arguments)


def test_a_plan_step_with_the_wrong_arguments_for_its_action_is_refused_by_the_schema() -> None:
    arguments = {"plan": [{"action": "wait", "distance": 1.0}]}
    assert not jsonschema.Draft202012Validator(BY_NAME["execute_plan"].parameters).is_valid(arguments)


def present(arguments: dict[str, Any]) -> dict[str, Any]:
    """The arguments given a value (strict mode writes null for the others)."""
    return {k: v for k, v in arguments.items() if v is not None}


def test_a_smaller_vocabulary_gives_fewer_tools() -> None:
    fewer = {a: s for a, s in VOCABULARY.actions.items() if a is not Action.SAY}
    vocabulary: Vocabulary = msgspec.structs.replace(VOCABULARY, actions=fewer)
    names = {t.name for t in all_tools(vocabulary)}
    assert "say" not in names and "navigate_to" in names


# tether schema


def schema_app() -> typer.Typer:
    app = typer.Typer()
    app.command(name="schema")(schema_command)

    @app.callback()
    def main() -> None:
        """A stand-in for tether's app."""

    return app


@pytest.mark.parametrize("strict", [False, True])
@pytest.mark.parametrize("fmt", FORMATS)
def test_tether_schema_prints_json(fmt: str, strict: bool) -> None:
    args = ["schema", "--format", fmt, *(["--strict"] if strict else [])]
    result = CliRunner().invoke(schema_app(), args)
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout) == render(TOOLS, fmt, strict=strict)  # type: ignore[arg-type]


def test_tether_schema_is_a_tether_command() -> None:
    from tether.cli import app

    result = CliRunner().invoke(app, ["schema", "--format", "mcp"])
    assert result.exit_code == 0, result.output
    assert [t["name"] for t in json.loads(result.stdout)] == list(BY_NAME)


def test_tether_schema_refuses_an_unknown_format() -> None:
    result = CliRunner().invoke(schema_app(), ["schema", "--format", "xml"])
    assert result.exit_code == 2
