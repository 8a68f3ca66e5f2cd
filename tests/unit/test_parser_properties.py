"""Property tests: whatever text arrives, the parser returns a valid Plan or refuses it with a ParseError, quickly."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from bench.parser import JSON_PLAN, TEXT_PLAN
from schemas.common import ServiceError, Stage
from schemas.plan import Action, Plan, PlanText
from services.parser.errors import ParseError
from services.parser.parser import Parser, answer, default_parser, parse
from services.parser.vocabulary import load_vocabulary

ROOT = Path(__file__).resolve().parents[2]
FORMATS = ("auto", "json", "yaml", "text")
MAX_MESSAGE_CHARS = 4000

# The most CPU time (of the test's thread, time.thread_time) a parse may take, however hostile its text:
# one that takes longer is a hang in the making. CPU time, not wall time: `make test` runs the unit
# tests at the lowest priority (tests/suite.py), where a parse may wait seconds for the CPU.
QUICKLY = 2.0

PROPERTIES = settings(
    database=None,  # nothing written into the repository
    derandomize=True,  # the same examples on every run, so CI is repeatable
    deadline=None,  # Hypothesis's is in wall time; `outcome` checks each parse against QUICKLY instead
    max_examples=200,
    suppress_health_check=[HealthCheck.too_slow],
)
# A true hang never returns to Hypothesis's deadline check; pytest-timeout ends it instead, after
# pyproject.toml's 300 s: `make test` runs these on idle CPU only (tests/conftest.py IDLE_UNIT), and
# beside the busiest stacks a test of 13 s of CPU can wait minutes for it.


# What every outcome must satisfy


def check_plan(plan: object) -> None:
    assert isinstance(plan, Plan), f"parse returned {type(plan).__name__}, not a Plan"
    assert msgspec.json.decode(msgspec.json.encode(plan), type=Plan) == plan


def check_refusal(error: object) -> None:
    assert isinstance(error, ServiceError), f"refused with {type(error).__name__}, not a ServiceError"
    assert error.stage is Stage.PARSE
    assert error.message.strip(), "a refusal must say why"
    assert len(error.message) <= MAX_MESSAGE_CHARS


def outcome(text: str, fmt: str) -> Plan | ParseError:
    """parse(text, fmt), checked: within QUICKLY, a Plan that survives the wire, or a ParseError with a
    usable message."""
    started = time.thread_time()
    try:
        plan: Plan | ParseError = parse(text, fmt)
    except ParseError as exc:
        plan = exc
    assert time.thread_time() - started < QUICKLY, f"a parse took {time.thread_time() - started:.2f} s of CPU"
    if isinstance(plan, ParseError):
        check_refusal(plan.error)
    else:
        check_plan(plan)
    return plan


# Valid plans, the seeds for mutation

STEPS: list[dict[str, Any]] = [
    {"action": "navigate_to", "target": "kitchen"},
    {"action": "pick", "target": "red cup", "target_location": "kitchen counter"},
    {"action": "navigate_to", "target": "living room"},
    {"action": "place", "target_object": "red cup", "target_location": "coffee table"},
    {"action": "say", "parameters": {"text": "here you are"}},
    {"action": "wait", "parameters": {"duration": 2}},
    {"action": "navigate_to", "parameters": {"x": 3.5, "y": 2.0}},
    {"action": "pick", "target": "apple", "position": [2.6, 3.1, 0.75], "pose": {"x": 2.6, "y": 3.1, "yaw": 0}},
]
ENGLISH = TEXT_PLAN  # the benchmark's ten-line English plan
ENGLISH_POINTS = "1. Go to (3.5, 2.0)\n2. go to the kitchen at x 2.5 y 250 cm\n3. look at 1, 2, 1.2\n"


def openai_calls(steps: list[dict[str, Any]]) -> dict[str, Any]:
    calls = []
    for i, step in enumerate(steps):
        arguments = {k: v for k, v in step.items() if k != "action"}
        function = {"name": step["action"], "arguments": json.dumps(arguments)}
        calls.append({"id": f"call_{i}", "type": "function", "function": function})
    return {"role": "assistant", "content": None, "tool_calls": calls}


def anthropic_calls(steps: list[dict[str, Any]]) -> dict[str, Any]:
    blocks: list[dict[str, Any]] = [{"type": "text", "text": "I'll fetch the cup."}]
    for i, step in enumerate(steps):
        arguments = {k: v for k, v in step.items() if k != "action"}
        blocks.append({"type": "tool_use", "id": f"toolu_{i}", "name": step["action"], "input": arguments})
    return {"role": "assistant", "content": blocks, "stop_reason": "tool_use"}


def mcp_call(step: dict[str, Any]) -> dict[str, Any]:
    arguments = {k: v for k, v in step.items() if k != "action"}
    return {
        "jsonrpc": "2.0",
        "id": 1,
        "method": "tools/call",
        "params": {"name": step["action"], "arguments": arguments},
    }


SEEDS: dict[str, tuple[str, str]] = {
    "json object": (json.dumps({"description": "Fetch the cup", "plan": STEPS}, indent=2), "json"),
    "json array": (json.dumps(STEPS), "auto"),
    "json in prose": (
        "Here is the plan:\n\n```json\n" + json.dumps({"steps": STEPS}, indent=2) + "\n```\nDone!",
        "auto",
    ),
    "yaml": (yaml.safe_dump({"plan": STEPS}, sort_keys=False), "yaml"),
    "yaml in prose": ("Sure:\n```yaml\n" + yaml.safe_dump({"plan": STEPS}, sort_keys=False) + "```\n", "auto"),
    "english": (ENGLISH, "text"),
    "english points": (ENGLISH_POINTS, "text"),
    "english in prose": ("Here's what I'll do:\n\n" + ENGLISH + "\n\nLet me know if that works.", "auto"),
    "openai tool calls": (json.dumps(openai_calls(STEPS)), "auto"),
    "anthropic tool_use": (json.dumps(anthropic_calls(STEPS)), "auto"),
    "mcp tools/call": (json.dumps(mcp_call(STEPS[0])), "auto"),
}


@pytest.mark.parametrize("name", SEEDS)
def test_seed_plans_parse(name: str) -> None:
    """The mutation seeds are real plans; each format here is documented as accepted."""
    text, fmt = SEEDS[name]
    assert isinstance(outcome(text, fmt), Plan)


# Strategies

ACTION_WORDS = [a.value for a in Action] + [
    "go", "go_to", "Go To", "pickUp", "pick-up", "grasp_object", "put_down", "speak_text", "pause", "halt",
    "turn_left", "rotate_right", "move_forward", "back_up", "wave", "release", "execute_plan", "run_plan",
    "fly", "self_destruct", "", " ", "PICK", "naviagte_to", "pick\u0000", "s\u0430y",
]  # fmt: skip
KEYS = [
    "plan", "steps", "actions", "tasks", "sequence", "action", "action_type", "skill", "type", "name", "tool",
    "target", "target_object", "target_location", "object", "destination", "location", "parameters", "params",
    "args", "arguments", "input", "description", "reason", "substeps", "children", "on_failure", "fallback",
    "speed", "distance", "angle", "direction", "duration", "text", "volume", "approach", "gesture", "width",
    "force", "x", "y", "z", "yaw", "pose", "position", "coordinates", "point", "goal_pose", "frame_id",
    "angle_deg", "distance_cm", "duration_ms", "seconds", "id", "step",
    "tool_calls", "function", "content", "tool_use", "method", "jsonrpc", "choices", "message", "",
]  # fmt: skip
PARAM_KEYS = [
    "speed", "distance", "angle", "direction", "duration", "text", "volume", "approach", "gesture", "width",
    "force", "x", "y", "yaw", "position", "coords", "angle_deg", "distance_cm", "duration_ms", "seconds", "unit",
    "Speed", "max-speed",
]  # fmt: skip
VALUE_STRINGS = [
    "kitchen", "red cup", "coffee table", "30 cm", "90 degrees", "90°", "2 seconds", "1.5 m/s", "-1e309 m",
    "1e400", "nan", "inf deg", "-inf", "2 minutes", "left", "right", "forward", "back", "top", " TRUE ",
    "false", "1_000", "0x10", "\u0663", "\U0001d7d7 m", "1.5.3 m", "1e-400 m", "5 km/h", "-0", "°", "3 parsecs",
    "here you are", "\u202ereversed", "line\nbreak", "tab\there", "bell\x07", "\ud800", "(3.5, 2.0)",
    "x=1, y=2", "1, 2, 3", "3.5 m, 20 cm", "[1e400, 2]", "(1, 2",
]  # fmt: skip
WORDS = [
    "go", "to", "the", "kitchen", "pick", "up", "red", "cup", "from", "counter", "put", "it", "on", "coffee",
    "table", "say", '"here you are"', "turn", "left", "right", "90", "degrees", "drive", "forward", "backward",
    "30", "cm", "wait", "2", "seconds", "open", "close", "gripper", "back", "and", "then", "if", "that", "fails",
    "otherwise", "wave", "look", "at", "stop", "-5", "1e309", "nan", "°", "m/s", "slowly", "twice", "…", "\n",
    "{", "}", "[", "]", ":", "-", "*", "&a", "*a", "```", "#", "1.", "2)", "Step", "3:", "(3.5,", "2.0)", "x", "y",
    "3.5,", "(1,", "x=1,", "y=2",
]  # fmt: skip
STRUCTURAL = "{}[]\",:\\ \n\t`'-#&*!|>%@0123456789.eE+aplnstu"

formats = st.sampled_from(FORMATS)
any_text = st.text(st.characters(codec=None, exclude_categories=()), max_size=300)
structural_text = st.text(STRUCTURAL, max_size=300)
sentences = st.lists(st.sampled_from(WORDS), min_size=1, max_size=14).map(" ".join)
numbered = st.lists(
    st.tuples(st.sampled_from(["{}. ", "{}) ", "- ", "* ", "Step {}: ", "", "{}.", "  {}. "]), sentences),
    min_size=1,
    max_size=12,
).map(lambda lines: "\n".join(style.format(i + 1) + s for i, (style, s) in enumerate(lines)))

# Built, not listed: Hypothesis prints strategies, and a 5000-character literal makes that slow.
long_strings = st.builds(str.__mul__, st.sampled_from(["x", "navigate_to", "é", "{"]), st.integers(100, 5000))
# Past Python's 4300-digit limit for int(str).
long_digits = st.builds(str.__mul__, st.sampled_from(["1", "9"]), st.integers(4000, 5000))
huge_ints = st.integers(min_value=-(10**400), max_value=10**400)
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    huge_ints,
    st.floats(),  # nan, inf, -0.0 and subnormals included
    st.text(max_size=30),
    st.sampled_from(VALUE_STRINGS),
    st.sampled_from(ACTION_WORDS),
    long_strings,
)
json_keys = st.one_of(st.sampled_from(KEYS), st.text(max_size=12))
json_values = st.recursive(
    scalars,
    lambda children: st.lists(children, max_size=5) | st.dictionaries(json_keys, children, max_size=5),
    max_leaves=30,
)
param_values = st.one_of(
    st.sampled_from(VALUE_STRINGS), st.floats(), st.integers(), huge_ints, st.booleans(), json_values
)
names = st.one_of(st.sampled_from(["kitchen", "red cup", "coffee table", "", " "]), st.text(max_size=20), long_strings)
leaf_steps = st.fixed_dictionaries(
    {"action": st.one_of(st.sampled_from(ACTION_WORDS), st.text(max_size=15))},
    optional={
        "target": names,
        "target_object": names,
        "target_location": names,
        "parameters": st.dictionaries(st.one_of(st.sampled_from(PARAM_KEYS), json_keys), param_values, max_size=4),
        "description": st.one_of(st.text(max_size=30), json_values),
        "extra": json_values,
    },
)


def _nest(children: st.SearchStrategy[list[Any]]) -> st.SearchStrategy[list[Any]]:
    nested = st.tuples(leaf_steps, st.sampled_from(["substeps", "on_failure", "steps", "fallback"]), children)
    return st.lists(st.one_of(leaf_steps, nested.map(lambda t: {**t[0], t[1]: t[2]})), min_size=1, max_size=5)


step_lists = st.recursive(st.lists(leaf_steps, min_size=1, max_size=6), _nest, max_leaves=20)
plans = st.one_of(
    step_lists,
    st.builds(
        lambda key, steps: {key: steps}, st.sampled_from(["plan", "steps", "actions", "tasks", "PLAN"]), step_lists
    ),
    st.fixed_dictionaries({"plan": step_lists}, optional={"description": json_values, "notes": json_values}),
    leaf_steps,
)


def slots(value: Any) -> list[tuple[Any, Any]]:
    """Every (container, key or index) in a nested value, outermost first."""
    found: list[tuple[Any, Any]] = []
    if isinstance(value, dict):
        found += [(value, k) for k in value]
        for child in value.values():
            found += slots(child)
    elif isinstance(value, list):
        found += [(value, i) for i in range(len(value))]
        for child in value:
            found += slots(child)
    return found


@st.composite
def perturbed(draw: st.DrawFn, base: st.SearchStrategy[Any]) -> Any:
    """A value with up to two of its sub-values replaced by arbitrary JSON values."""
    value = draw(base)
    for _ in range(draw(st.integers(0, 2))):
        places = slots(value)
        if not places:
            break
        parent, key = draw(st.sampled_from(places))
        parent[key] = draw(json_values)
    return value


def to_json(value: Any, indent: int | None, ascii_only: bool) -> str:
    # allow_nan: NaN and Infinity tokens are what a careless LLM library writes.
    return json.dumps(value, allow_nan=True, indent=indent, ensure_ascii=ascii_only)


WRAPPERS = [
    "{}",
    "```json\n{}\n```",
    "```\n{}\n```",
    "Here is the plan:\n\n```json\n{}\n```\n\nLet me know if you want changes.",
    "Sure! {} Hope that helps.",
    "<plan>{}</plan>",
    "```json\n{}",
    "{}\n```",
    "```yaml\n{}\n```",
    "Step one is below.\n{}\n[note: see above]",
]


@st.composite
def wrapped(draw: st.DrawFn, body: st.SearchStrategy[str]) -> str:
    """A body inside a fence or prose, as LLMs write it."""
    prefix = draw(st.one_of(st.just(""), st.text(max_size=40), sentences))
    suffix = draw(st.one_of(st.just(""), st.text(max_size=40), sentences))
    return prefix + draw(st.sampled_from(WRAPPERS)).replace("{}", draw(body), 1) + suffix


def encoded(values: st.SearchStrategy[Any]) -> st.SearchStrategy[str]:
    return st.builds(to_json, values, st.sampled_from([None, 2]), st.booleans())


json_texts = wrapped(encoded(st.one_of(json_values, plans, perturbed(plans))))

# Mutations

INSERTED = [
    "{", "}", "[", "]", '"', "'", "\\", ",", ":", "\n", "```", "\x00", "\x07", "\x1b", "\ud800", "\u202e",
    "\ufeff", "é", "漢", "😀", "*", "&", "!!", "#", "- ", "%", "\t", "\r", "1e999", "NaN", "...", "\\u0000",
]  # fmt: skip
INSERTS = st.one_of(st.sampled_from(INSERTED), st.characters(codec=None, exclude_categories=()), st.text(max_size=5))


@st.composite
def mutated(draw: st.DrawFn) -> tuple[str, str]:
    """A valid plan with a few characters deleted, inserted, duplicated, swapped or replaced, or cut short."""
    text, fmt = SEEDS[draw(st.sampled_from(sorted(SEEDS)))]
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["delete", "insert", "duplicate", "swap", "replace", "truncate"]))
        i = draw(st.integers(0, len(text)))
        if op == "delete":
            text = text[:i] + text[i + draw(st.integers(1, 8)) :]
        elif op == "insert":
            text = text[:i] + draw(INSERTS) + text[i:]
        elif op == "duplicate":
            j = min(len(text), i + draw(st.integers(1, 60)))
            text = text[:j] + text[i:j] * draw(st.integers(1, 3)) + text[j:]
        elif op == "swap" and len(text) >= 2:
            a, b = sorted((min(i, len(text) - 1), draw(st.integers(0, len(text) - 1))))
            text = text[:a] + text[b] + text[a + 1 : b] + text[a] + text[b + 1 :]
        elif op == "replace":
            text = text[:i] + draw(INSERTS) + text[i + 1 :]
        elif op == "truncate":
            text = text[:i]
    return text, draw(st.sampled_from([fmt, "auto"]))


# YAML

YAML_SCALARS = [
    "yes", "no", "on", "off", "~", "null", ".nan", ".inf", "-.inf", "0x1F", "0o17", "0b101", "1_000", "2024-01-01",
    "2001-12-14t21:59:43.10-05:00", "12:30:00", "1:20", "'quoted'", '"esc \\x00 \\ud800"', "[]", "{}",
    "[a, [b, [c]]]", "!!str 5", "!!int '7'", "!!float .inf", "!!binary aGVsbG8=", "!!set {a, b}", "!!omap [a: 1]",
    "!!python/object/apply:os.system ['true']", "!!python/name:os.system", "!custom x", "*undefined", "&", "@x",
    "`x", "30 cm", "90 degrees", "-1e400", "1e400", "kitchen", "red cup", "|\n      block text", ">\n      folded",
    "? [a, b]\n      : c", "{[1]: 2}", "{a: 1, a: 2}", "%", "\t", "'unterminated", '"also unterminated',
]  # fmt: skip


@st.composite
def yaml_documents(draw: st.DrawFn) -> str:
    """Plan-shaped YAML with anchors, aliases, merge keys, tags and the scalars YAML reads surprisingly."""
    anchors: list[str] = []

    def value() -> str:
        choice = draw(st.integers(0, 4))
        if choice == 0 and anchors:
            return "*" + draw(st.sampled_from(anchors))
        if choice == 1 and draw(st.booleans()):
            return draw(long_digits)
        text = draw(st.sampled_from(YAML_SCALARS)) if choice < 3 else json.dumps(draw(scalars), allow_nan=True)
        if draw(st.booleans()) and not text.startswith(("|", ">", "?")):
            name = f"a{len(anchors)}"
            anchors.append(name)
            return f"&{name} {text}"
        return text

    lines = []
    if draw(st.booleans()):
        lines += ["%YAML 1.1", "---"]
    if draw(st.booleans()):
        lines.append("defaults: &d {action: wait, parameters: {duration: 1}}")
        anchors.append("d")
    lines.append(draw(st.sampled_from(["plan:", "steps:", "plan: &p", "actions:"])))
    if lines[-1] == "plan: &p":
        anchors.append("p")
    for _ in range(draw(st.integers(1, 6))):
        lines.append(f"  - action: {draw(st.sampled_from(ACTION_WORDS[:20]))}")
        for _ in range(draw(st.integers(0, 3))):
            key = draw(st.sampled_from(["target", "target_object", "target_location", "description", "substeps"]))
            lines.append(f"    {key}: {value()}")
        if draw(st.booleans()):
            lines.append("    parameters:")
            for _ in range(draw(st.integers(1, 3))):
                lines.append(f"      {draw(st.sampled_from(PARAM_KEYS))}: {value()}")
        if anchors and draw(st.integers(0, 4)) == 0:
            lines.append(f"  - <<: *{draw(st.sampled_from(anchors))}")
    if draw(st.integers(0, 3)) == 0:
        lines += ["---", value()]
    return "\n".join(lines) + draw(st.sampled_from(["\n", "", "\n...\n"]))


def billion_laughs(width: int, depth: int) -> str:
    """Each level repeats the one before `width` times: width**depth strings once aliases are expanded."""
    lines = ['l0: &l0 "lol"']
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * width)}]" for i in range(1, depth + 1)]
    lines += ["plan:", "  - action: say", f"    target: *l{depth}", "  - action: wait", f"    duration: *l{depth}"]
    return "\n".join(lines) + "\n"


RECURSIVE_YAML = [
    "plan: &p\n  - action: wait\n    substeps: *p\n",
    "plan:\n  - &s\n    action: say\n    target: hi\n    on_failure: [*s]\n",
    "&a [*a]\n",
    "plan: &p [{action: stop, substeps: *p}]\n",
    "step: &s {action: say, parameters: &q {text: *q}}\nplan: [*s]\n",
]

yaml_texts = st.one_of(
    yaml_documents(),
    st.builds(lambda doc: f"Here you go:\n```yaml\n{doc}```\nThanks", yaml_documents()),
    st.builds(billion_laughs, st.integers(2, 10), st.integers(1, 10)),
    st.sampled_from(RECURSIVE_YAML),
    st.builds(
        lambda value, flow: yaml.safe_dump(value, default_flow_style=flow, allow_unicode=True),
        st.one_of(plans, json_values),
        st.sampled_from([None, True, False]),
    ),
)

# Tool calls, in the three shapes LLM APIs use

tool_names = st.one_of(
    st.sampled_from(ACTION_WORDS), st.sampled_from(["execute_plan", "plan", "robot.run", ""]), st.text(max_size=20)
)
tool_arguments = st.one_of(
    leaf_steps.map(lambda step: {k: v for k, v in step.items() if k != "action"}), plans, json_values
)
openai_arguments = st.one_of(
    st.builds(to_json, tool_arguments, st.none(), st.booleans()),  # a JSON string, as the API sends it
    st.text(max_size=40),  # a string that is not JSON
    st.sampled_from(['{"target": "kitchen"', "{'target': 'kitchen'}", "", "null", "[]", '{"a": NaN}']),
    tool_arguments,  # an object, as some wrappers pass it on
)
openai_call = st.builds(
    lambda name, arguments, i: {
        "id": f"call_{i}",
        "type": "function",
        "function": {"name": name, "arguments": arguments},
    },
    tool_names,
    openai_arguments,
    st.integers(0, 9),
)
openai_message = st.builds(
    lambda calls, content: {"role": "assistant", "content": content, "tool_calls": calls},
    st.lists(openai_call, max_size=4),
    st.one_of(st.none(), st.text(max_size=30)),
)
openai_shapes = st.one_of(
    openai_message,
    st.lists(openai_call, min_size=1, max_size=4),
    openai_message.map(lambda m: {"id": "chatcmpl-1", "object": "chat.completion", "choices": [{"message": m}]}),
    st.builds(
        lambda n, a: {"role": "assistant", "function_call": {"name": n, "arguments": a}}, tool_names, openai_arguments
    ),
)
anthropic_block = st.one_of(
    st.builds(
        lambda name, arguments, i: {"type": "tool_use", "id": f"toolu_{i}", "name": name, "input": arguments},
        tool_names,
        tool_arguments,
        st.integers(0, 9),
    ),
    st.builds(lambda text: {"type": "text", "text": text}, st.one_of(st.text(max_size=30), sentences)),
)
anthropic_shapes = st.one_of(
    st.builds(
        lambda blocks: {"role": "assistant", "content": blocks, "stop_reason": "tool_use"},
        st.lists(anthropic_block, max_size=4),
    ),
    st.lists(anthropic_block, min_size=1, max_size=4),
    anthropic_block,
)
mcp_request = st.builds(
    lambda name, arguments, i: {
        "jsonrpc": "2.0",
        "id": i,
        "method": "tools/call",
        "params": {"name": name, "arguments": arguments},
    },
    tool_names,
    tool_arguments,
    st.integers(0, 99),
)
mcp_shapes = st.one_of(mcp_request, st.lists(mcp_request, min_size=1, max_size=4))
tool_call_texts = wrapped(encoded(perturbed(st.one_of(openai_shapes, anthropic_shapes, mcp_shapes))))

every_text = st.one_of(
    any_text, structural_text, numbered, json_texts, mutated().map(lambda m: m[0]), yaml_texts, tool_call_texts
)


# The properties


@PROPERTIES
@given(text=st.one_of(any_text, structural_text, sentences, numbered), fmt=formats)
def test_random_text_is_a_plan_or_a_refusal(text: str, fmt: str) -> None:
    outcome(text, fmt)


@PROPERTIES
@given(text=json_texts, fmt=formats)
def test_json_values_in_fences_and_prose_are_a_plan_or_a_refusal(text: str, fmt: str) -> None:
    outcome(text, fmt)


@PROPERTIES
@given(mutation=mutated())
def test_mutated_plans_are_a_plan_or_a_refusal(mutation: tuple[str, str]) -> None:
    outcome(*mutation)


@PROPERTIES
@given(text=yaml_texts, fmt=st.sampled_from(["auto", "yaml"]))
def test_yaml_is_a_plan_or_a_refusal(text: str, fmt: str) -> None:
    outcome(text, fmt)


@PROPERTIES
@given(text=tool_call_texts, fmt=st.sampled_from(["auto", "json"]))
def test_tool_calls_are_a_plan_or_a_refusal(text: str, fmt: str) -> None:
    outcome(text, fmt)


@PROPERTIES
@given(text=every_text, fmt=formats)
def test_answer_is_always_a_plan_or_a_service_error(text: str, fmt: str) -> None:
    reply = answer(default_parser(), PlanText(text=text, format=fmt))  # type: ignore[arg-type]
    if isinstance(reply, ServiceError):
        check_refusal(reply)
    else:
        check_plan(reply)


@pytest.mark.parametrize("fmt", ["auto", "yaml"])
@pytest.mark.parametrize(("width", "depth"), [(9, 9), (10, 12), (2, 40), (1000, 3)])
def test_billion_laughs_is_refused_quickly(fmt: str, width: int, depth: int) -> None:
    started = time.thread_time()
    with pytest.raises(ParseError) as refused:
        parse(billion_laughs(width, depth), fmt)
    assert time.thread_time() - started < QUICKLY
    check_refusal(refused.value.error)


@pytest.mark.parametrize("text", RECURSIVE_YAML)
@pytest.mark.parametrize("fmt", ["auto", "yaml"])
def test_self_referencing_yaml_is_a_plan_or_a_refusal(text: str, fmt: str) -> None:
    outcome(text, fmt)


# Big inputs, each under MAX_PLAN_BYTES, built when the test runs.
HOSTILE: dict[str, Callable[[], str]] = {
    "100k-char action": lambda: json.dumps({"plan": [{"action": "x" * 100_000}]}),
    "50k-char key": lambda: json.dumps({"plan": [{"action": "say", "k" * 50_000: 1, "target": "hi"}]}),
    "5000 top-level keys": lambda: json.dumps({f"key{i}": i for i in range(5000)}),
    "2000 unknown actions": lambda: json.dumps({"plan": [{"action": f"unknown{i}"} for i in range(2000)]}),
    "5000 parameters": lambda: json.dumps(
        {"plan": [{"action": "wait", "parameters": {f"p{i}": i for i in range(5000)}}]}
    ),
    "5000-digit number": lambda: '{"plan": [{"action": "wait", "parameters": {"duration": ' + "1" * 5000 + "}}]}",
    "5000-digit yaml number": lambda: "plan:\n  - action: wait\n    duration: " + "1" * 5000 + "\n",
    "5000 code blocks": lambda: "```json\n{}\n```\n" * 5000,
    "5000 numbered lines": lambda: "1. go to the kitchen\n" * 5000,
    "20000 colons": lambda: "a: " * 20_000 + "b",
    "100k-char line": lambda: "Go to the " + "very " * 20_000 + "far kitchen",
}


@pytest.mark.parametrize("make", HOSTILE.values(), ids=HOSTILE.keys())
@pytest.mark.parametrize("fmt", FORMATS)
def test_hostile_input_gets_a_short_answer_quickly(make: Callable[[], str], fmt: str) -> None:
    outcome(make(), fmt)


# Nesting tens of thousands deep, where a recursive reader can overflow the C stack and kill the process
# (a segfault no test in this process could report): run in a child, one line of output per input.
DEEP = {
    "brackets": "[" * 100_000 + "]" * 100_000,
    "unclosed braces": "{" * 30_000,
    "unclosed plans": '{"plan": [' * 5000,
    "dashes": "- " * 50_000,
    "dashes under plan": "plan:\n" + "- " * 30_000,
    "brackets under plan": "plan: " + "[" * 30_000,
    "fenced yaml brackets": "```yaml\nplan: " + "[" * 30_000 + "\n```",
}
DEEP_CHILD = """
import sys
from services.parser.errors import ParseError
from services.parser.parser import parse
from tests.unit.test_parser_properties import DEEP, FORMATS
text = DEEP[sys.argv[1]]
for fmt in FORMATS:
    print(f"{fmt}: ", end="", flush=True)
    try:
        parse(text, fmt)
        print("plan", flush=True)
    except ParseError:
        print("refused", flush=True)
    except BaseException as exc:
        print(f"raised {type(exc).__name__}: {str(exc)[:200]}", flush=True)
"""


# A child that has not answered in this long (wall seconds) hangs: it runs on idle CPU only, as its
# test does (tests/conftest.py IDLE_UNIT), and needs about 3 s of it.
HANG = 240.0


@pytest.mark.parametrize("name", DEEP)
def test_deep_nesting_is_refused_without_crashing_the_process(name: str) -> None:
    child = subprocess.run(
        [sys.executable, "-c", DEEP_CHILD, name], cwd=ROOT, capture_output=True, text=True, timeout=HANG, check=False
    )
    lines = child.stdout.splitlines()
    if child.returncode != 0:
        died = f"signal {-child.returncode}" if child.returncode < 0 else f"exit code {child.returncode}"
        at = lines[-1] if lines else "start-up"
        pytest.fail(f"the process died with {died} at {at}\n{child.stderr[-2000:]}")
    assert [line for line in lines if not line.endswith(": refused")] == []
    assert len(lines) == len(FORMATS), child.stdout + child.stderr


# The plain path: plans written plainly are read by one msgspec conversion instead of field by field.
# It must give exactly what the general mapping gives, and hand everything else over to it.


class GeneralOnly(Parser):
    """The parser with its plain path switched off: every step mapped field by field."""

    def _plain_steps(self, value: Any) -> None:
        return None


GENERAL = GeneralOnly(load_vocabulary())


# Mostly plans the plain path takes, with now and then what it must hand over (a wrong type, a
# synonym spelled otherwise, a null, a bad unit, a name the action does not use, a missing target).
def mostly(good: list[Any], other: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    return st.integers(0, 4).flatmap(lambda i: other if i == 0 else st.sampled_from(good))


plain_params = st.dictionaries(
    mostly(["speed", "distance", "angle", "direction", "duration", "text", "gesture"], st.sampled_from(PARAM_KEYS)),
    mostly([0.5, 2, 90, "30 cm", "90 degrees", "2 seconds", "left", "forward", "here you are", "wave"], param_values),
    max_size=3,
)
plain_variants = st.fixed_dictionaries(
    {"action": mostly([*(a.value for a in Action), "go_to", "pick_up", "turn_left"], st.sampled_from(ACTION_WORDS))},
    optional={
        "target": mostly(["kitchen", "red cup"], names),
        "target_object": mostly(["red cup", " apple "], names),
        "target_location": mostly(["coffee table", "kitchen counter"], names),
        "parameters": st.one_of(plain_params, st.none()),
        "description": mostly(["go there", ""], st.one_of(st.none(), long_strings, scalars)),
        "id": scalars,
    },
)
# The benchmark's steps and the seeds' plain ones, as they are or with fields of a variant.
PLAIN_STEPS = [*json.loads(JSON_PLAN)["plan"], *STEPS[:6]]
# Copies: `perturbed` changes what it is given.
plain_seeds = st.sampled_from(PLAIN_STEPS).map(copy.deepcopy)
plain_steps = st.one_of(
    plain_seeds,
    st.builds(lambda step, other: {**step, **other}, plain_seeds, plain_variants),
    plain_variants,
)
plain_plans = st.one_of(
    st.lists(plain_steps, min_size=1, max_size=4),
    st.builds(
        lambda key, steps, description: {key: steps, **description},
        st.sampled_from(["plan", "steps"]),
        st.lists(plain_steps, max_size=4),
        st.fixed_dictionaries({}, optional={"description": st.one_of(st.text(max_size=20), json_values)}),
    ),
    # Two plan keys, either perhaps null, in either order: the general mapping reads the first it knows.
    st.builds(
        lambda keys, first, second: {keys[0]: first, keys[1]: second},
        st.permutations(["plan", "steps"]),
        st.one_of(st.none(), st.lists(plain_steps, max_size=2)),
        st.one_of(st.none(), st.lists(plain_steps, min_size=1, max_size=2)),
    ),
)


def both_ways(text: str, fmt: str) -> tuple[bytes | ServiceError, bytes | ServiceError]:
    """The outcome of the parser and of the general mapping alone: the encoded Plan or the refusal."""
    outcomes: list[bytes | ServiceError] = []
    for parser in (default_parser(), GENERAL):
        try:
            outcomes.append(msgspec.json.encode(parser.parse(text, fmt)))
        except ParseError as exc:
            outcomes.append(exc.error)
    return outcomes[0], outcomes[1]


@PROPERTIES
@given(value=st.one_of(plain_plans, perturbed(plain_plans)), fmt=st.sampled_from(["auto", "json", "yaml"]))
def test_the_plain_path_gives_what_the_general_mapping_gives(value: Any, fmt: str) -> None:
    if fmt == "yaml":
        try:
            text = yaml.safe_dump(value, sort_keys=False)
        except yaml.YAMLError:  # a lone surrogate: not YAML at all
            assume(False)
    else:
        text = to_json(value, 2, False)
    fast, general = both_ways(text, fmt)
    assert fast == general


def test_plain_plans_take_the_plain_path() -> None:
    """The property above compares something: the benchmark's plan and the seeds' plain steps are plain."""
    parser = default_parser()
    plain = [json.loads(JSON_PLAN), STEPS[:6], {"plan": STEPS[:6], "description": "Fetch the cup"}]
    for value in plain:
        assert parser._plain_steps(value) is not None, value
        text = json.dumps(value)
        assert both_ways(text, "json")[0] == both_ways(text, "json")[1]
    # A second plan key hands the plan over, even when the first is null: the general mapping refuses
    # {"plan": null, "steps": [...]} ('plan' must be an array), and the plain path once read "steps".
    for value in ({"plan": None, "steps": STEPS[:1]}, {"plan": STEPS[:1], "steps": None}):
        assert parser._plain_steps(value) is None, value
        text = json.dumps(value)
        assert both_ways(text, "json")[0] == both_ways(text, "json")[1]
    assert isinstance(both_ways(json.dumps({"plan": None, "steps": STEPS[:1]}), "json")[0], ServiceError)
    # A sub-step, a synonym spelled otherwise, or a point hand the plan over.
    for step in ({"substeps": [STEPS[0]]}, {"action": "Pick Up", "target": "cup"}, STEPS[6], STEPS[7]):
        assert parser._plain_steps([step]) is None, step
