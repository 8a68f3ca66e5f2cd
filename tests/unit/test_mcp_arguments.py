"""`tether mcp` holds each tool call's arguments to the tool's schema: a plan's steps one by one,
against their own action's schema, so the check's time grows with the plan's size, not twelvefold per
level of on_failure (the schema's anyOf of every action, as written)."""

from __future__ import annotations

import time
from typing import Any

import pytest
from jsonschema import Draft202012Validator

from schemas.plan import MAX_NESTING, MAX_STEPS
from services.agent.tools import all_tools
from tether.mcpserver import ArgumentCheck

PLAN_TOOL = next(spec for spec in all_tools() if spec.name == "execute_plan")


def nested(depth: int, step: dict[str, Any] | None = None) -> dict[str, Any]:
    """A step whose on_failure holds one step, `depth` levels down."""
    step = step or {"action": "close_gripper"}
    for _ in range(depth):
        step = {"action": "close_gripper", "on_failure": [step]}
    return step


def test_a_plan_as_deep_as_allowed_is_checked_at_once_and_a_deeper_one_refused() -> None:
    """Five levels took 47 s against the whole schema; eight would take hours."""
    check = ArgumentCheck(PLAN_TOOL.parameters)
    started = time.thread_time()
    assert check.problem({"plan": [nested(MAX_NESTING)]}) is None
    assert time.thread_time() - started < 0.5
    deeper = check.problem({"plan": [nested(MAX_NESTING + 1)]})
    assert deeper is not None and f"on_failure nested more than {MAX_NESTING} levels deep" in deeper
    assert "plan/0/on_failure/0" in deeper
    # Far deeper than Python's recursion: an answer, not a RecursionError.
    assert "levels deep" in (check.problem({"plan": [nested(2000)]}) or "")
    # The plan's own maxItems bounds its steps; its on_failure steps count too.
    many = check.problem({"plan": [nested(1)] * (MAX_STEPS // 2 + 1)})
    assert many is not None and f"more than {MAX_STEPS} steps, on_failure steps included" in many


WRONG = [
    {"plan": [{"action": "fly"}]},
    {"plan": [{"action": "navigate_to"}]},  # no target
    {"plan": [{"action": "close_gripper", "target": "cup", "wings": 2}]},
    {"plan": [nested(2, {"action": "say", "text": 3})]},
    {"plan": [{"action": "close_gripper", "on_failure": "later"}]},
    {"plan": [{"action": "close_gripper", "on_failure": ["wave"]}]},
    {"plan": "go"},
    {"plan": [], "colour": "red"},
]
RIGHT = [
    {"plan": [{"action": "close_gripper"}], "description": "grip"},
    {"plan": [nested(2, {"action": "say", "text": "hello"})]},
    {"plan": [{"action": "navigate_to", "target": "kitchen", "on_failure": [{"action": "say", "text": "stuck"}]}]},
]


@pytest.mark.parametrize("arguments", WRONG + RIGHT)
def test_a_shallow_plan_gets_the_verdict_the_whole_schema_gives(arguments: dict[str, Any]) -> None:
    whole = Draft202012Validator(PLAN_TOOL.parameters).is_valid(arguments)
    problem = ArgumentCheck(PLAN_TOOL.parameters).problem(arguments)
    assert (problem is None) == whole, problem
    assert whole == (arguments in RIGHT)


def test_a_wrong_step_is_named_where_it_is() -> None:
    problem = ArgumentCheck(PLAN_TOOL.parameters).problem({"plan": [nested(2, {"action": "fly"})]})
    assert problem is not None and problem.startswith("plan/0/on_failure/0/on_failure/0/action: 'fly' is not one of")
