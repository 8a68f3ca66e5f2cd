"""Review 41 of the parser: a step field given under two of its names, null fields of an expansion,
steps under two plan keys, and YAML values that are no JSON type named in refusals."""

from __future__ import annotations

import json
from typing import Any

import pytest

from schemas.common import ServiceError
from schemas.plan import Action, PlanText
from services.parser.parser import answer, default_parser, parse


def refusal(text: str, fmt: str = "auto") -> ServiceError:
    reply = answer(default_parser(), PlanText(text=text, format=fmt))  # type: ignore[arg-type]
    assert isinstance(reply, ServiceError), reply
    return reply


def _plan(*steps: dict[str, Any]) -> str:
    return json.dumps({"plan": list(steps)})


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        # The second name used to win: the robot went to the garage.
        (
            {"action": "navigate_to", "target": "kitchen", "goal_name": "garage"},
            "step 1: gives its target twice, as 'target' and 'goal_name', and they differ ('kitchen' and 'garage')",
        ),
        (
            {"action": "pick", "object": "cup", "item": "knife"},
            "gives its target_object twice, as 'object' and 'item'",
        ),
        # 'args' used to replace 'parameters': the direction was lost and the robot turned left.
        (
            {"action": "turn", "parameters": {"angle": "90 degrees", "direction": "right"}, "args": {"speed": 0.5}},
            "step 1: gives its parameters twice, as 'parameters' and 'args', and they differ",
        ),
        (
            {"action": "stop", "on_failure": [{"action": "stop"}], "fallback": [{"action": "say", "target": "x"}]},
            "gives its on_failure twice, as 'on_failure' and 'fallback'",
        ),
        (
            {"substeps": [{"action": "stop"}], "children": [{"action": "wait", "duration": 1}]},
            "gives its substeps twice, as 'substeps' and 'children'",
        ),
        # A name in parameters that differs from the step's was dropped without a word.
        (
            {"action": "pick", "object": "cup", "parameters": {"item": "knife"}},
            "step 1: gives its target_object twice: 'cup', and 'knife' as 'item' in parameters",
        ),
        # Expansions read the fields themselves, and kept the last of each.
        ({"action": "bring", "object": "cup", "item": "knife"}, "gives its target_object twice"),
        (
            {"action": "bring", "object": "cup", "destination": "table", "to": "floor"},
            "gives its target_location twice",
        ),
        ({"action": "bring", "object": "cup", "parameters": {"speed": 1}, "args": {"speed": 0.1}}, "parameters twice"),
        (
            {
                "action": "go_home",
                "on_failure": [{"action": "stop"}],
                "fallback": [{"action": "stop"}, {"action": "stop"}],
            },
            "on_failure twice",
        ),
    ],
)
def test_a_field_given_under_two_of_its_names_that_differ_is_refused(step: dict[str, Any], expected: str) -> None:
    assert expected in refusal(_plan(step)).message


def test_a_field_given_under_two_of_its_names_alike_is_read_once() -> None:
    plan = parse(
        _plan(
            {"action": "navigate_to", "target": "kitchen", "goal_name": " kitchen", "params": None},
            {"action": "pick", "object": "cup", "parameters": {"item": "cup"}, "fallback": None},
            {"action": "bring", "object": "cup", "item": "cup"},
        )
    )
    assert [(s.action, s.target) for s in plan.steps[:2]] == [(Action.NAVIGATE_TO, "kitchen"), (Action.PICK, "cup")]
    assert [(s.action, s.target) for s in plan.steps[2].substeps] == [(Action.PICK, "cup"), (Action.PLACE, "cup")]


def test_a_null_alias_does_not_blank_out_the_field_given() -> None:
    plan = parse(
        _plan({"action": "navigate_to", "target": "hall", "on_failure": [{"action": "stop"}], "fallback": None})
    )
    assert [s.action for s in plan.steps[0].on_failure] == [Action.STOP]


def test_null_fields_of_an_expansion_are_not_given() -> None:
    """Strict-mode models write null for every optional field: null must not replace what the expansion says."""
    plan = parse(
        _plan(
            # The location used to become null, and the object the place to put it on: "place on the cup".
            {"action": "put_back", "target": "cup", "location": None, "description": None},
            {"action": "go_home", "target": None},
            {"action": "dock", "target": None, "parameters": None},
            {"action": "put_back", "object": "cup", "args": {"approach": "top"}, "parameters": None},
            {"action": "bring", "object": "cup", "substeps": None},
        )
    )
    put_back, home, dock, with_args, bring = plan.steps
    assert (put_back.action, put_back.target, put_back.location) == (Action.PLACE, "cup", "where it was found")
    assert (home.action, home.target) == (Action.NAVIGATE_TO, "home")
    assert (dock.action, dock.target) == (Action.NAVIGATE_TO, "dock")
    assert (with_args.location, with_args.params) == ("where it was found", {"approach": "top"})
    assert [s.action for s in bring.substeps] == [Action.PICK, Action.PLACE]


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (
            {"plan": [{"action": "stop"}], "steps": [{"action": "wait", "duration": 1}]},
            "the object holds steps under both 'plan' and 'steps'",
        ),
        ({"plan": [{"action": "stop"}], "Plan": [{"action": "say", "target": "hi"}]}, "under both 'plan' and 'Plan'"),
        (
            {"plan": {"steps": [{"action": "stop"}], "actions": [{"action": "stop"}]}},
            "under both 'steps' and 'actions'",
        ),
    ],
)
def test_steps_under_two_plan_keys_are_refused(value: dict[str, Any], expected: str) -> None:
    # The second array used to be dropped with a warning, and the first run as the whole plan.
    assert expected in refusal(json.dumps(value)).message


@pytest.mark.parametrize(
    ("yaml", "expected"),
    [
        ("plan:\n  - action: wait\n    duration: 2026-01-01\n", "parameter 'duration' must be a number, got a date"),
        ("plan:\n  - action: !!binary aGVsbG8=\n", "'action' must be a string, got binary data"),
        ("plan:\n  - action: say\n    text: !!set {a, b}\n", "parameter 'text' must be text, got a set"),
        ("plan:\n  - action: look_at\n    x: 2026-01-01 10:00:00\n    y: 1\n", "must be a number, got a date and time"),
        ("plan: !!omap [{a: 1}]\n", "step 1: is a pair, not an object"),
    ],
)
def test_yaml_values_of_no_json_type_are_named_in_refusals(yaml: str, expected: str) -> None:
    # They were all "a number": "must be a number, got a number".
    assert expected in refusal(yaml).message


@pytest.mark.parametrize(
    "text",
    [
        '{"action": "navigate_to", "target": "kitchen"}\n{"action": "pick", "target": "cup"}',
        '[{"action": "navigate_to", "target": "kitchen"}]\n[{"action": "pick", "target": "cup"}]',
        '```json\n{"action": "navigate_to", "target": "kitchen"}\n{"action": "pick", "target": "cup"}\n```',
        '{"plan": [{"action": "navigate_to", "target": "kitchen"}]}, {"action": "pick", "target": "cup"}',
    ],
)
def test_a_plan_after_the_first_json_value_is_not_dropped(text: str) -> None:
    # One step per line: only the first was read, the pick dropped without a word.
    assert "conflicting plans" in refusal(text).message


def test_a_step_cut_off_after_the_first_json_value_is_refused() -> None:
    text = '{"action": "navigate_to", "target": "kitchen"}\n{"action": "pick", "tar'
    assert "was the output cut off?" in refusal(text).message


def test_words_after_the_json_plan_are_still_ignored() -> None:
    text = '{"plan": [{"action": "navigate_to", "target": "kitchen"}]}\nThis goes to the kitchen [as asked], see [1].'
    assert [s.action for s in parse(text).steps] == [Action.NAVIGATE_TO]
    same = '{"action": "stop"}\n{"action": "stop"}'
    assert parse(same).warnings == ["2 identical plans found; read once"]
