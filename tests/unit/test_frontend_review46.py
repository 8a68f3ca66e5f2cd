"""Review 46 of the plan front end (parser, resolver, planner, agent tools): each test failed before its fix."""

from __future__ import annotations

import time
from typing import Any

import msgspec
import pytest

from schemas.common import ServiceError
from schemas.plan import Action, Plan, PlanText, Step
from services.agent.tools import all_tools
from services.parser.extract import fenced_blocks
from services.parser.parser import answer as parse_answer
from services.parser.parser import default_parser
from services.parser.vocabulary import load_vocabulary
from services.resolver.resolver import Resolver, answer
from services.worldmodel import WorldModel, load_world


@pytest.fixture(scope="module")
def resolver() -> Resolver:
    return Resolver(WorldModel(load_world("household")))


def plan_of(*steps: dict[str, Any]) -> Plan:
    return Plan(steps=[msgspec.convert(s, Step) for s in steps])


@pytest.mark.parametrize("target", ["operator", "me", "the person"])
def test_detect_of_a_person_is_refused_at_resolve_time_pointing_to_look_at(resolver: Resolver, target: str) -> None:
    # The executor's detect waits for the person among the camera's objects (world/objects), where
    # people never are: the step could only fail, after a search drive.
    reply = answer(resolver, plan_of({"action": "detect", "target": target}))
    assert isinstance(reply, ServiceError), reply
    assert "person" in reply.message and "look_at" in reply.message, reply.message
    assert reply.message.startswith("step 1:")


def test_detect_of_an_object_still_grounds(resolver: Resolver) -> None:
    grounded = resolver.resolve(plan_of({"action": "detect", "target": "blue book"}))
    assert [s.object_id for s in grounded.steps] == ["blue_book"]  # type: ignore[union-attr]


def test_detect_tool_and_vocabulary_say_it_is_for_objects_not_people() -> None:
    summary = load_vocabulary().actions[Action.DETECT].summary
    assert "person" in summary and "look_at" in summary
    detect = next(t for t in all_tools() if t.name == "detect")
    assert "look_at" in detect.description


# Adversarial text within the size limit: each took seconds to minutes of CPU (quadratic regex search).
@pytest.mark.parametrize(
    "text",
    [
        "```" * 40_000,  # no newline after any opening fence: 14 s
        "\n" * 5_000 + "x",  # a run of blank lines, each tried as a YAML plan's or a list's start: 20 s
        " \n" * 5_000 + "pick the cup",
    ],
    ids=["backquotes", "newlines", "blank-lines"],
)
def test_adversarial_text_is_answered_in_linear_time(text: str) -> None:
    started = time.thread_time()
    reply = parse_answer(default_parser(), PlanText(text=text))
    spent = time.thread_time() - started
    assert spent < 1.0, f"an answer took {spent:.2f} s of CPU"
    assert isinstance(reply, ServiceError) or reply.steps


def test_fenced_blocks_still_read_an_unclosed_fence_to_the_end() -> None:
    text = 'Here:\n```json\n[{"action": "stop"}]'
    assert fenced_blocks(text) == [("json", 14, '[{"action": "stop"}]')]
    assert fenced_blocks("```yaml\n- a\n```\nand ```x") == [("yaml", 8, "- a\n")]
    assert fenced_blocks("no newline ```json [1]") == []


def test_a_yaml_fence_body_after_blank_lines_is_still_yaml() -> None:
    reply = parse_answer(default_parser(), PlanText(text="```\n\n\nplan:\n  - action: stop\n```"))
    assert not isinstance(reply, ServiceError), reply
    assert [s.action for s in reply.steps] == [Action.STOP]


@pytest.mark.parametrize("target", ["red cap", "blue cap", "black fan", "cap"])
def test_a_short_word_spelt_one_letter_off_is_another_word_not_a_typo(resolver: Resolver, target: str) -> None:
    # 'red cap' scored 0.86 against 'red cup' and was picked up as the red cup, with a warning only.
    reply = answer(resolver, plan_of({"action": "pick", "target": target}))
    assert isinstance(reply, ServiceError), reply
    assert reply.message.startswith(f"step 1: unknown name {target!r}"), reply.message


@pytest.mark.parametrize(("target", "meant"), [("red cpu", "red_cup"), ("rde cup", "red_cup"), ("red cp", "red_cup")])
def test_a_swapped_or_dropped_letter_in_a_short_word_is_still_a_typo(
    resolver: Resolver, target: str, meant: str
) -> None:
    grounded = resolver.resolve(plan_of({"action": "pick", "target": target}))
    assert grounded.resolutions[0].id == meant and grounded.resolutions[0].via == "fuzzy"
    assert f"{target!r} read as" in grounded.warnings[0]
