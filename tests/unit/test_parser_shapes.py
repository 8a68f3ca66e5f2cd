"""The parser's structured shapes beyond plain JSON: YAML, tool calls, several blocks, groups,
on_failure, variants and units, and the configured limits."""

from __future__ import annotations

import json
import math
import time
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas.common import ServiceError
from schemas.plan import Action, Plan, PlanText
from services.parser.config import ParserConfig
from services.parser.errors import ParseError
from services.parser.parser import Parser, answer, default_parser, parse
from services.parser.vocabulary import load_vocabulary
from tests.unit.test_parser_properties import QUICKLY


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


# Tool calls in the shapes each vendor's API returns now, written after its reference documentation:
# OpenAI Responses (response.output items), Gemini generateContent (candidates[].content.parts, REST
# camelCase and the Python SDK's snake_case), OpenAI chat custom tools, Anthropic thinking blocks.

FETCH = [(Action.NAVIGATE_TO, "kitchen"), (Action.PICK, "red cup")]


def _fc(name: str, arguments: dict[str, object], k: int) -> dict[str, object]:
    return {
        "type": "function_call",
        "id": f"fc_{k}",
        "call_id": f"call_{k}",
        "name": name,
        "arguments": json.dumps(arguments),
        "status": "completed",
    }


RESPONSES_OUTPUT = [
    {"type": "reasoning", "id": "rs_1", "summary": [{"type": "summary_text", "text": "Kitchen first, then the cup."}]},
    {
        "type": "message",
        "id": "msg_1",
        "role": "assistant",
        "status": "completed",
        "content": [{"type": "output_text", "text": "Getting the red cup.", "annotations": []}],
    },
    _fc("navigate_to", {"target": "kitchen"}, 1),
    _fc("pick", {"target": "red cup"}, 2),
]
RESPONSE = {"id": "resp_1", "object": "response", "status": "completed", "model": "gpt-5", "output": RESPONSES_OUTPUT}
GEMINI_PARTS = [
    {"text": "Thinking about where the cup is.", "thought": True},
    {"text": "Getting the red cup."},
    {"functionCall": {"name": "navigate_to", "args": {"target": "kitchen"}}, "thoughtSignature": "c2lnbmF0dXJl"},
    {"functionCall": {"name": "pick", "args": {"target": "red cup"}}},
]
GEMINI = {
    "candidates": [{"content": {"role": "model", "parts": GEMINI_PARTS}, "finishReason": "STOP", "index": 0}],
    "usageMetadata": {"promptTokenCount": 300, "candidatesTokenCount": 20, "totalTokenCount": 320},
    "modelVersion": "gemini-2.5-flash",
}


def _sdk_part(name: str, target: str) -> dict[str, object]:
    # model_dump() of google-genai's Part: every field present, the unset ones null.
    unset = ("video_metadata", "thought", "inline_data", "file_data", "thought_signature", "text")
    return {**dict.fromkeys(unset), "function_call": {"id": None, "args": {"target": target}, "name": name}}


GEMINI_SDK = {
    "candidates": [
        {
            "content": {"role": "model", "parts": [_sdk_part("navigate_to", "kitchen"), _sdk_part("pick", "red cup")]},
            "finish_reason": "STOP",
            "safety_ratings": None,
        }
    ],
    "prompt_feedback": None,
    "automatic_function_calling_history": [],
}


@pytest.mark.parametrize(
    ("value", "source", "description"),
    [
        (RESPONSE, "openai_responses", "Getting the red cup."),
        (RESPONSES_OUTPUT, "openai_responses", "Getting the red cup."),
        (GEMINI, "gemini_function_call", "Getting the red cup."),
        (GEMINI["candidates"][0]["content"], "gemini_function_call", "Getting the red cup."),  # type: ignore[index]
        (GEMINI_PARTS, "gemini_function_call", "Getting the red cup."),
        (GEMINI_SDK, "gemini_function_call", ""),
        (
            {
                "id": "msg_1",
                "type": "message",
                "role": "assistant",
                "content": [
                    {"type": "thinking", "thinking": "The cup is in the kitchen.", "signature": "c2ln"},
                    {"type": "redacted_thinking", "data": "ZW5j"},
                    {"type": "text", "text": "Getting the red cup."},
                    {"type": "tool_use", "id": "toolu_1", "name": "navigate_to", "input": {"target": "kitchen"}},
                    {"type": "tool_use", "id": "toolu_2", "name": "pick", "input": {"target": "red cup"}},
                ],
                "stop_reason": "tool_use",
            },
            "anthropic_tool_use",
            "Getting the red cup.",
        ),
        (
            {
                "object": "chat.completion",
                "choices": [
                    {
                        "index": 0,
                        "message": {
                            "role": "assistant",
                            "content": None,
                            "refusal": None,
                            "tool_calls": [
                                {
                                    "id": "call_1",
                                    "type": "function",
                                    "function": {"name": "navigate_to", "arguments": '{"target": "kitchen"}'},
                                },
                                {
                                    "id": "call_2",
                                    "type": "custom",
                                    "custom": {"name": "pick", "input": '{"target": "red cup"}'},
                                },
                            ],
                        },
                        "finish_reason": "tool_calls",
                    }
                ],
            },
            "openai_tool_calls",
            "",
        ),
    ],
    ids=[
        "responses",
        "responses-output",
        "gemini",
        "gemini-content",
        "gemini-parts",
        "gemini-sdk",
        "anthropic-thinking",
        "chat-custom",
    ],
)
def test_current_vendor_shapes_become_steps(value: object, source: str, description: str) -> None:
    plan = parse(json.dumps(value))
    assert plan.source_format == source
    assert [(s.action, s.target) for s in plan.steps] == FETCH
    assert plan.description == description and not plan.warnings


def test_single_items_and_parts_are_one_step_plans() -> None:
    item = parse(json.dumps(_fc("say", {"text": "hello"}, 1)))
    assert (item.source_format, item.steps[0].params) == ("openai_responses", {"text": "hello"})
    custom = {"type": "custom_tool_call", "call_id": "c", "name": "look_at", "input": '{"target": "door"}'}
    assert parse(json.dumps(custom)).steps[0].target == "door"
    snake = parse(json.dumps({"function_call": {"name": "detect", "args": {"target": "keys"}}}))
    assert (snake.source_format, snake.steps[0].action) == ("gemini_function_call", Action.DETECT)
    # OpenAI's legacy function_call has "arguments" (a JSON string), Gemini's "args" (an object).
    legacy = parse(json.dumps({"role": "assistant", "function_call": {"name": "stop", "arguments": "{}"}}))
    assert legacy.source_format == "openai_function_call"
    # A part that only carries a thought signature has nothing to run and nothing to say.
    signed = [{"functionCall": {"name": "stop"}}, {"thoughtSignature": "c2ln"}]
    assert parse(json.dumps(signed)).warnings == []


def test_reasoning_is_never_read_as_steps_or_description() -> None:
    smuggled = json.dumps({"plan": [{"action": "navigate_to", "target": "front door"}]})
    output = [
        {"type": "reasoning", "id": "rs", "summary": [{"type": "summary_text", "text": smuggled}], "content": None},
        _fc("stop", {}, 1),
    ]
    plan = parse(json.dumps(output))
    assert [s.action for s in plan.steps] == [Action.STOP] and "front door" not in plan.description
    parts = [
        {"text": smuggled, "thought": True},
        {"functionCall": {"name": "navigate_to", "args": {"target": "door"}}, "thought": True},
    ]
    parts.append({"functionCall": {"name": "stop", "args": {}}})
    thought = parse(json.dumps({"role": "model", "parts": parts}))
    assert [s.action for s in thought.steps] == [Action.STOP] and "front door" not in thought.description
    alone = {"object": "response", "status": "completed", "output": output[:1]}
    assert "no function_call items" in refusal(json.dumps(alone)).message


def test_what_the_platform_ran_itself_is_skipped_with_one_warning() -> None:
    searches = [{"type": "web_search_call", "id": f"ws_{k}", "status": "completed"} for k in range(8)]
    plan = parse(json.dumps([*searches, _fc("stop", {}, 9)]))
    assert [s.action for s in plan.steps] == [Action.STOP]
    assert plan.warnings == [
        "output item 1 (web_search_call), output item 2 (web_search_call), output item 3 (web_search_call), "
        "output item 4 (web_search_call), output item 5 (web_search_call) and 3 more skipped: "
        "the platform ran it itself"
    ]
    code = [{"executableCode": {"language": "PYTHON", "code": "print(1)"}}, {"functionCall": {"name": "stop"}}]
    assert parse(json.dumps(code)).warnings == ["part 1 (executableCode) skipped: code Gemini's code execution ran"]
    server = [
        {"type": "server_tool_use", "id": "srvtoolu_1", "name": "web_search", "input": {"query": "mugs"}},
        {"type": "web_search_tool_result", "tool_use_id": "srvtoolu_1", "content": []},
        {"type": "tool_use", "id": "toolu_1", "name": "stop", "input": {}},
    ]
    assert len(parse(json.dumps(server)).warnings) == 1


def _response(*items: object, **fields: object) -> str:
    return json.dumps({"object": "response", "status": "completed", "output": list(items), **fields})


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        # Responses items
        (
            _response(_fc("stop", {}, 1), {"type": "function_call", "call_id": "c", "arguments": "{}"}),
            "output item 2 (function_call) has no tool name",
        ),
        (
            _response({**_fc("pick", {}, 1), "arguments": '{"target": "cup", '}),
            "output item 1 (function_call): arguments are not valid JSON",
        ),
        (_response({**_fc("pick", {}, 1), "arguments": '["cup"]'}), "output item 1 (function_call): arguments must be"),
        (
            _response(_fc("stop", {}, 1), {"type": "shell_call", "call_id": "s", "action": {"commands": ["ls"]}}),
            "output item 2 (shell_call) is not a call the robot can run",
        ),
        (_response(_fc("stop", {}, 1), {"type": "teleport"}), "output item 2 (teleport) is not a call"),
        (_response(_fc("stop", {}, 1), "pick the cup"), "output item 2 is a string, not an object"),
        (_response({"name": "stop"}), "output item 1 has no 'type'"),
        (
            _response({**_fc("stop", {}, 1), "status": "in_progress"}),
            "output item 1 (function_call) has status 'in_progress'",
        ),
        (
            _response(_fc("stop", {}, 1), status="failed", error={"code": "server_error", "message": "boom"}),
            "status is 'failed' ('boom')",
        ),
        (
            json.dumps({"object": "response", "status": "completed", "output": {"type": "function_call"}}),
            "'output' must be an array",
        ),
        (
            json.dumps([{"type": "message", "role": "user", "content": "fetch the cup"}, _fc("stop", {}, 1)]),
            "output item 1 (message) is a 'user' message",
        ),
        (
            json.dumps([_fc("stop", {}, 1), {"type": "function_call_output", "call_id": "call_1", "output": "done"}]),
            "output item 1 (function_call) already has its result in output item 2",
        ),
        (
            _response(
                {"type": "message", "role": "assistant", "content": [{"type": "refusal", "refusal": "I can't."}]},
                _fc("stop", {}, 1),
            ),
            'the model refused: "I can\'t."',
        ),
        (
            json.dumps([{"type": "custom_tool_call", "call_id": "c", "name": "say", "input": "say hello to Ann"}]),
            "output item 1 (custom_tool_call): its input is free text",
        ),
        # Gemini parts and candidates
        (
            json.dumps({"role": "model", "parts": [{"functionCall": {"args": {"target": "cup"}}}]}),
            "part 1 (functionCall) has no tool name",
        ),
        (
            json.dumps([{"functionCall": {"name": "pick", "args": ["cup"]}}]),
            "part 1 (functionCall): arguments must be an object",
        ),
        (
            json.dumps([{"functionCall": {"name": "stop"}}, {"launch": "rocket"}]),
            "part 2 holds neither a functionCall nor text (its keys: 'launch')",
        ),
        (json.dumps([{"functionCall": {"name": "stop"}}, 7]), "part 2 is a number, not an object"),
        (
            json.dumps([{"functionCall": {"name": "pick", "partialArgs": [], "willContinue": True}}]),
            "part 1 (functionCall) is one piece of a streamed call",
        ),
        (
            json.dumps(
                {
                    "candidates": [
                        {"content": {"parts": [{"functionCall": {"name": "stop"}}]}, "finishReason": "MAX_TOKENS"}
                    ]
                }
            ),
            "finishReason 'MAX_TOKENS': its output may be cut off",
        ),
        (
            json.dumps(
                {"candidates": [{"content": {"parts": [{"functionCall": {"name": "stop"}}]}, "finishReason": "SAFETY"}]}
            ),
            "finishReason 'SAFETY'",
        ),
        (
            json.dumps({"candidates": [], "promptFeedback": {"blockReason": "PROHIBITED_CONTENT"}}),
            "the prompt was blocked: 'PROHIBITED_CONTENT'",
        ),
        (
            json.dumps({"candidates": [{"content": {"parts": [{"text": "Sure!"}]}, "finishReason": "STOP"}]}),
            "candidate 1 holds no functionCall parts",
        ),
        (json.dumps({"role": "user", "parts": [{"functionCall": {"name": "stop"}}]}), "has role 'user'"),
        # Anthropic, chat completions, MCP
        (
            json.dumps(
                [{"type": "tool_use", "id": "t", "name": "stop", "input": {}}, {"type": "bash", "command": "ls"}]
            ),
            "content block 2 (bash) is neither a tool_use nor a text block",
        ),
        (
            json.dumps(
                {
                    "type": "message",
                    "content": [{"type": "tool_use", "id": "t", "name": "stop", "input": {}}],
                    "stop_reason": "refusal",
                }
            ),
            "stop_reason 'refusal'",
        ),
        (
            json.dumps(
                {
                    "choices": [
                        {
                            "message": {"tool_calls": [{"type": "function", "function": {"name": "stop"}}]},
                            "finish_reason": "content_filter",
                        }
                    ]
                }
            ),
            "finish_reason 'content_filter'",
        ),
        (
            json.dumps({"tool_calls": [{"type": "function", "function": {"name": "stop"}}], "refusal": "No."}),
            "the model refused",
        ),
        (json.dumps({"tool_calls": [{"type": "retrieval", "retrieval": {}}]}), "tool call 1 has type 'retrieval'"),
        (
            json.dumps(
                [
                    {"jsonrpc": "2.0", "id": 1, "method": "tools/call", "params": {"name": "stop"}},
                    {"jsonrpc": "2.0", "id": 2, "method": "tools/list"},
                ]
            ),
            "request 2 of the batch is not a tools/call request",
        ),
    ],
)
def test_hostile_tool_calls_are_refused_naming_the_item(text: str, expected: str) -> None:
    assert expected in refusal(text).message


def test_many_calls_and_nested_plans_are_refused() -> None:
    many = _response(*[_fc("stop", {}, k) for k in range(1000)])
    assert "more than 100 steps" in refusal(many).message
    tight = Parser(load_vocabulary(), config=ParserConfig(max_steps=3))
    parts = json.dumps([{"functionCall": {"name": "stop"}}] * 4)
    assert "more than 3 steps" in refusal(parts, parser=tight).message
    # A plan tool's arguments hold steps, not another vendor's response.
    inner = _response(_fc("stop", {}, 1))
    nested = json.dumps([_fc("execute_plan", json.loads(inner), 1)])
    assert "no plan found" in refusal(nested).message
    twice = json.dumps([_fc("execute_plan", {"plan": [{"action": "execute_plan", "arguments": inner}]}, 1)])
    assert "step 1: 'arguments' must be an object" in refusal(twice).message


# Whatever a vendor-shaped value holds, the answer is a plan or a refusal that says why, never a crash.

_junk = st.one_of(st.none(), st.booleans(), st.integers(), st.text(max_size=12), st.lists(st.integers(), max_size=2))
_names = st.one_of(st.sampled_from(["navigate_to", "pick", "stop", "execute_plan", "", "rm -rf"]), _junk)
_args = st.one_of(
    st.sampled_from(['{"target": "kitchen"}', '{"target": ', "[]", "go home", '{"plan": [{"action": "stop"}]}']),
    st.dictionaries(st.sampled_from(["target", "speed", "plan", "text"]), _junk, max_size=2),
    _junk,
)
_response_items = st.one_of(
    st.builds(
        lambda kind, name, arguments, status, call_id: {
            "type": kind,
            "name": name,
            "arguments": arguments,
            "input": arguments,
            "status": status,
            "call_id": call_id,
        },
        st.sampled_from(["function_call", "custom_tool_call", "function_call_output", "mcp_call", "computer_call"]),
        _names,
        _args,
        st.sampled_from([None, "completed", "incomplete", 3]),
        st.sampled_from(["call_1", "call_2", None]),
    ),
    st.builds(lambda text: {"type": "reasoning", "summary": [{"type": "summary_text", "text": text}]}, _junk),
    st.builds(
        lambda role, content: {"type": "message", "role": role, "content": content},
        st.sampled_from([None, "assistant", "user"]),
        st.one_of(
            _junk, st.lists(st.fixed_dictionaries({"type": st.sampled_from(["output_text", "refusal"]), "text": _junk}))
        ),
    ),
    _junk,
)
_gemini_parts = st.one_of(
    st.builds(lambda name, arguments: {"functionCall": {"name": name, "args": arguments}}, _names, _args),
    st.builds(
        lambda name, arguments: {"function_call": {"name": name, "args": arguments}, "text": None}, _names, _args
    ),
    st.builds(lambda text, thought: {"text": text, "thought": thought}, _junk, st.sampled_from([None, True, False])),
    st.dictionaries(st.sampled_from(["executableCode", "inlineData", "other", "functionCall"]), _junk, max_size=2),
    _junk,
)
_vendor_values = st.one_of(
    st.lists(_response_items, min_size=1, max_size=5),
    st.builds(
        lambda items, status: {"object": "response", "status": status, "output": items},
        st.lists(_response_items, max_size=5),
        st.sampled_from(["completed", "incomplete", None, 1]),
    ),
    st.lists(_gemini_parts, min_size=1, max_size=5),
    st.builds(
        lambda parts, stop, role: {"candidates": [{"content": {"role": role, "parts": parts}, "finishReason": stop}]},
        st.lists(_gemini_parts, max_size=5),
        st.sampled_from(["STOP", "MAX_TOKENS", None, 0]),
        st.sampled_from(["model", "user", None]),
    ),
)


@settings(
    database=None,
    derandomize=True,
    deadline=None,  # in wall time; the CPU time of each answer is bound below (`make test` runs this at low priority)
    max_examples=150,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(value=_vendor_values)
def test_vendor_shapes_are_a_plan_or_a_refusal(value: Any) -> None:
    started = time.thread_time()
    reply = answer(default_parser(), PlanText(text=json.dumps(value), format="auto"))
    spent = time.thread_time() - started
    assert spent < QUICKLY, f"an answer took {spent:.2f} s of CPU"
    if isinstance(reply, ServiceError):
        assert reply.message.strip() and len(reply.message) <= 4000
    else:
        assert isinstance(reply, Plan) and reply.steps
