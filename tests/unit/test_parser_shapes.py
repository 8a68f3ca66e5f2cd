"""The parser's structured shapes beyond plain JSON: YAML, tool calls, several blocks, groups,
on_failure, variants and units, and the configured limits."""

from __future__ import annotations

import json
import math

import pytest

from schemas.common import ServiceError
from schemas.plan import Action, Plan, PlanText
from services.parser.config import ParserConfig
from services.parser.errors import ParseError
from services.parser.parser import Parser, answer, default_parser, parse
from services.parser.vocabulary import load_vocabulary


def refusal(text: str, fmt: str = "auto", parser: Parser | None = None) -> ServiceError:
    reply = answer(parser or default_parser(), PlanText(text=text, format=fmt))  # type: ignore[arg-type]
    assert isinstance(reply, ServiceError), reply
    return reply


def test_yaml_plans_are_read_safely() -> None:
    plan = parse("plan:\n  - action: goto\n    target: kitchen\n  - action: grab\n    object: red cup\n")
    assert plan.source_format == "yaml"
    assert [(s.action, s.target) for s in plan.steps] == [(Action.NAVIGATE_TO, "kitchen"), (Action.PICK, "red cup")]
    # A YAML tag that would build a Python object is an error, not an object.
    assert "YAML" in refusal("```yaml\nplan: !!python/object/apply:os.system ['true']\n```").message


def test_yaml_alias_bombs_self_references_and_duplicate_keys_are_refused() -> None:
    rows = ["a: &a [x, x, x, x, x, x, x, x, x, x]"]
    for i, name in enumerate("bcdefgh"):
        prev = "abcdefgh"[i]
        rows.append(f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 10) + "]")
    bomb = "\n".join([*rows, "plan: *h"]) + "\n"
    assert "aliases expand to more than" in refusal(bomb, "yaml").message
    assert "refers to a node that contains it" in refusal("plan: &p [*p]\n", "yaml").message
    assert "appears twice" in refusal("plan:\n  - action: stop\nplan:\n  - action: say\n", "yaml").message


def test_json_duplicate_keys_are_refused_not_overwritten() -> None:
    assert "appears twice" in refusal('[{"action": "pick", "action": "place", "target": "cup"}]').message


@pytest.mark.parametrize(
    ("value", "source"),
    [
        (
            {
                "choices": [
                    {
                        "message": {
                            "role": "assistant",
                            "tool_calls": [
                                {
                                    "id": "1",
                                    "type": "function",
                                    "function": {"name": "go_to", "arguments": '{"target": "kitchen"}'},
                                },
                                {
                                    "id": "2",
                                    "type": "function",
                                    "function": {"name": "grab", "arguments": '{"object": "red cup"}'},
                                },
                            ],
                        }
                    }
                ]
            },
            "openai_tool_calls",
        ),
        (
            {
                "function_call": {
                    "name": "execute_plan",
                    "arguments": json.dumps(
                        {"plan": [{"action": "goto", "target": "kitchen"}, {"action": "pick", "target": "red cup"}]}
                    ),
                }
            },
            "openai_function_call",
        ),
        (
            [
                {"type": "text", "text": "On my way."},
                {"type": "tool_use", "id": "t1", "name": "navigate_to", "input": {"target": "kitchen"}},
                {"type": "tool_use", "id": "t2", "name": "pick", "input": {"target": "red cup"}},
            ],
            "anthropic_tool_use",
        ),
        (
            [
                {
                    "jsonrpc": "2.0",
                    "id": 1,
                    "method": "tools/call",
                    "params": {"name": "navigate_to", "arguments": {"target": "kitchen"}},
                },
                {
                    "jsonrpc": "2.0",
                    "id": 2,
                    "method": "tools/call",
                    "params": {"name": "pick", "arguments": {"target": "red cup"}},
                },
            ],
            "mcp_tools_call",
        ),
    ],
)
def test_tool_calls_become_steps(value: object, source: str) -> None:
    plan = parse(json.dumps(value))
    assert plan.source_format == source
    assert [(s.action, s.target) for s in plan.steps] == [(Action.NAVIGATE_TO, "kitchen"), (Action.PICK, "red cup")]


def test_broken_tool_arguments_are_refused_naming_the_call() -> None:
    call = {"tool_calls": [{"type": "function", "function": {"name": "pick", "arguments": '{"target": "cup"'}}]}
    error = refusal(json.dumps(call))
    assert "tool call 1" in error.message and "cut off" in error.message
    nameless = {"type": "tool_use", "id": "x", "input": {"target": "cup"}}
    assert "has no tool name" in refusal(json.dumps(nameless)).message


def test_blocks_that_agree_are_read_once_and_blocks_that_differ_are_refused() -> None:
    block = '```json\n{"plan": [{"action": "pick", "target": "red cup"}]}\n```'
    other = '```json\n{"plan": [{"action": "pick", "target": "blue cup"}]}\n```'
    plan = parse(f"Plan:\n{block}\nAgain:\n{block}\n")
    assert len(plan.steps) == 1 and any("identical" in w for w in plan.warnings)
    error = refusal(f"Option A:\n{block}\nOption B:\n{other}\n")
    assert "2 conflicting plans" in error.message and error.line == 7
    # A block that is not a plan (a config snippet) is not a conflict.
    assert parse('```json\n{"verbose": true}\n```\n' + block).steps[0].target == "red cup"


def test_groups_and_on_failure_nest_and_are_labelled_in_refusals() -> None:
    value = {
        "plan": [
            {
                "name": "fetch the cup",
                "steps": [
                    {"action": "navigate_to", "target": "kitchen"},
                    {"action": "pick", "target": "red cup", "on_failure": [{"action": "say", "text": "no cup"}]},
                ],
            }
        ]
    }
    plan = parse(json.dumps(value))
    group = plan.steps[0]
    assert group.action is None and group.description == "fetch the cup"
    assert [s.action for s in group.substeps] == [Action.NAVIGATE_TO, Action.PICK]
    assert group.substeps[1].on_failure[0].params == {"text": "no cup"}
    value["plan"][0]["steps"][1]["on_failure"][0]["action"] = "sya"  # type: ignore[index]
    error = refusal(json.dumps(value))
    assert error.message.startswith("step 1.2 on_failure 1: unknown action 'sya'") and error.step == 0
    both = [{"action": "pick", "target": "cup", "steps": [{"action": "stop"}]}]
    assert "both an action ('pick') and sub-steps" in refusal(json.dumps(both)).message


def test_variants_fold_direction_into_the_sign_and_units_are_si() -> None:
    plan = parse(
        json.dumps(
            [
                {"action": "turn_right", "parameters": {"angle": "90 degrees"}},
                {"action": "turn", "parameters": {"degrees": 45, "direction": "left"}},
                {"action": "move_backward", "distance": "30 cm"},
                {"action": "drive", "distance": 1, "direction": "forward", "speed": "0.36 km/h"},
            ]
        )
    )
    right, left, back, forward = plan.steps
    assert math.isclose(float(right.params["angle"]), -math.pi / 2, rel_tol=1e-6) and right.units == {"angle": "rad"}
    assert math.isclose(float(left.params["angle"]), math.pi / 4, rel_tol=1e-6) and "direction" not in left.params
    assert math.isclose(float(back.params["distance"]), -0.3) and back.units == {"distance": "m"}
    assert (
        "allowed 0.05..1 m/s" in refusal(json.dumps([{"action": "drive", "distance": 1, "speed": "36 km/h"}])).message
    )
    assert forward.params["distance"] == 1.0 and math.isclose(float(forward.params["speed"]), 0.1, rel_tol=1e-4)
    conflict = [{"action": "turn_right", "parameters": {"angle": 1, "direction": "left"}}]
    assert "says direction 'right'" in refusal(json.dumps(conflict)).message
    bare = refusal(json.dumps([{"action": "turn", "angle": 90}])).message
    assert "a number without a unit is in rad" in bare and "'90 degrees'" in bare


def test_configured_limits_are_enforced() -> None:
    tight = Parser(
        load_vocabulary(), config=ParserConfig(max_steps=3, max_nesting=1, max_string_chars=20, max_input_bytes=2000)
    )
    nested = [{"name": "g", "steps": [{"name": "h", "steps": [{"action": "stop"}]}]}]
    assert "nested more than 1 levels" in refusal(json.dumps(nested), parser=tight).message
    many = [{"name": "g", "steps": [{"action": "stop"}] * 3}]
    assert "more than 3 steps" in refusal(json.dumps(many), parser=tight).message
    long_say = [{"action": "say", "text": "x" * 30}]
    assert "at most 20" in refusal(json.dumps(long_say), parser=tight).message
    assert "over 2000 bytes" in refusal("x" * 3000, parser=tight).message


def test_a_refusal_is_only_ever_a_parse_error() -> None:
    with pytest.raises(ParseError):
        parse("```yaml\n[[[[\n```", "yaml")
    assert isinstance(parse('{"action": "stop"}'), Plan)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        # A plan cut off inside prose: its complete steps are not a shorter plan.
        ('Here is the plan: {"plan": [{"action": "pick", "target": "cup"}, {"action": "place", "ta', "cut off"),
        # A key given twice stays refused when the JSON needs repair.
        ('{"plan": [{"action": "pick", "action": "place", "target": "cup",}]}', "appears twice"),
        # A YAML block and a JSON block that disagree.
        (
            '```yaml\nplan:\n  - action: stop\n```\n```json\n{"plan": [{"action": "wait", "duration": 2}]}\n```',
            "conflicting",
        ),
        # A sign and a direction that disagree are not silently overridden.
        ('[{"action": "drive", "direction": "forward", "distance": -0.3}]', "is negative and the direction"),
        # Broken YAML is reported as YAML, not as unreadable English.
        ("plan:\n  - action: pick\n    action: place\n    target: cup\n", "the key 'action' appears twice at line 3"),
    ],
)
def test_what_review_found_is_refused(text: str, expected: str) -> None:
    assert expected in refusal(text).message


def test_names_and_gestures_in_the_shapes_llms_use() -> None:
    gesture = parse('{"plan": [{"action": "gesture", "type": "wave"}]}').steps[0]
    assert (gesture.action, gesture.params) == (Action.GESTURE, {"gesture": "wave"})
    tool = parse('{"type": "tool_use", "id": "x", "name": "gesture", "input": {"type": "nod"}}').steps[0]
    assert tool.params == {"gesture": "nod"}
    inside = parse('[{"action": "pick", "parameters": {"object": "red cup"}}]').steps[0]
    assert inside.target == "red cup" and not parse('[{"action": "pick", "parameters": {"object": "cup"}}]').warnings
    planned = parse(
        json.dumps(
            {
                "function_call": {
                    "name": "execute_plan",
                    "arguments": json.dumps({"goal": "tidy", "steps": [{"action": "stop"}]}),
                }
            }
        )
    )
    assert planned.description == "tidy"
    assert "no plan found" in refusal("As noted in [1], the robot should pick up the cup.").message
